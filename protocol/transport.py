"""What a service needs of its connection to the others: the interface that protocol/mqtt.py's MqttConnection and
protocol/memory.py's in-memory connection both satisfy, so the chief and the workers run unchanged over either.

Handlers are called with the topic and the raw payload, on the connection's own delivery thread (paho's network
thread over MQTT); a handler that raises is logged and counted and never stops the delivery.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Protocol

from protocol.codec import RejectCounter

#: ``handler(topic, payload)``, called for every message matching a subscription.
Handler = Callable[[str, bytes], None]


class Published(Protocol):
    """What ``publish`` returns: a handle to wait until the message is on its way."""

    def wait_for_publish(self, timeout: float | None = None) -> None: ...


class Transport(Protocol):
    """A process's connection: publish and subscribe on MQTT topics (filters with ``+`` and ``#``)."""

    #: Set while connected.
    connected: threading.Event
    #: Successful connects so far (more than 1: the connection came back, and what was in flight may be lost).
    connects: int
    #: Where dropped messages (retained, bad chunks) are counted.
    rejects: RejectCounter

    def start(self, timeout: float = 10.0, stop: threading.Event | None = None) -> Transport:
        """Connect within ``timeout`` s (ConnectionError), or give up once ``stop`` is set (protocol.mqtt.Stopped)."""

    def stop(self) -> None: ...

    def subscribe(self, topic_filter: str, handler: Handler, qos: int = 1) -> None: ...

    def unsubscribe(self, topic_filter: str) -> None: ...

    def publish(self, topic: str, payload: bytes, qos: int = 1, retain: bool = False) -> Published: ...


#: How a service gets its connection: ``connect(client_id, will, rejects)``, where ``will`` is the (topic, payload)
#: published for it when it is lost without a clean stop, and ``rejects`` the service's reject counter.
Connect = Callable[[str, "tuple[str, bytes] | None", RejectCounter], Transport]
