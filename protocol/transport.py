"""What a service needs of its connection to the others: the interface that protocol/mqtt.py's MqttConnection and
protocol/memory.py's in-memory connection both satisfy, so the chief and the workers run unchanged over either, and
the one factory of connections, :func:`connector`.

A service takes a :data:`Connect` by value (the chief, an edge, a worker, the bridge, the dashboard): by default
``connector`` of its settings' broker address (MqttSettings.connector), in process ``Hub.connect`` of
protocol/memory.py. The address chooses the transport: ``mqtt://`` or ``mqtts://`` a broker, ``memory://<name>`` the
in-memory hub of that name in this process. Adding a transport is one module whose connection satisfies
:class:`Transport` and whose ``connector(address)`` makes its Connect, and its scheme's line in :data:`TRANSPORTS`.

Handlers are called with the topic and the raw payload, on the connection's own delivery thread (paho's network
thread over MQTT); a handler that raises is logged and counted and never stops the delivery.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Protocol

from protocol.codec import RejectCounter
from protocol.mqtt import BrokerAddress, MqttConnection

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

    @property
    def session_present(self) -> bool:
        """Whether the broker still held this connection's session at its last connect (False: what was published
        for it while it was away is gone; a transport without sessions says False)."""

    def start(self, timeout: float = 10.0, stop: threading.Event | None = None) -> Transport:
        """Connect within ``timeout`` s (ConnectionError), or give up once ``stop`` is set (protocol.mqtt.Stopped)."""

    def stop(self) -> None: ...

    def subscribe(self, topic_filter: str, handler: Handler, qos: int = 1) -> None: ...

    def unsubscribe(self, topic_filter: str) -> None: ...

    def publish(self, topic: str, payload: bytes, qos: int = 1, retain: bool = False) -> Published: ...


class Connect(Protocol):
    """How a service gets its connection (not yet started): ``connect(client_id, will, rejects)``, where ``will`` is
    the (topic, payload) published for it when it is lost without a clean stop, and ``rejects`` the service's reject
    counter (None: the connection's own)."""

    def __call__(self, client_id: str, will: tuple[str, bytes] | None = None,
                 rejects: RejectCounter | None = None) -> Transport: ...


#: The transports besides MQTT, by the scheme of their address: the module whose ``connector(address)`` makes the
#: Connect.
def _memory(address: str) -> Connect:
    """memory://<name>: the in-memory hub of that name in this process (imported when chosen: it imports this)."""
    from protocol import memory

    return memory.connector(address)


#: A transport's scheme -> the maker of its Connect from an address; MQTT (``mqtt://``, ``mqtts://``) is the default.
TRANSPORTS: dict[str, Callable[[str], Connect]] = {
    "memory": _memory,
}


def transport_of(address: str) -> Callable[[str], Connect] | None:
    """The maker of the Connect of the transport an address names by its scheme (TRANSPORTS); None for MQTT."""
    return TRANSPORTS.get(address.split("://", 1)[0]) if "://" in address else None


def connector(address: str | BrokerAddress, max_payload: int | None = None, username: str | None = None,
              password: str | None = None, ca_file: str | None = None) -> Connect:
    """The Connect of ``address``, the one place a service's connection is made: a transport of TRANSPORTS by its
    scheme, else MQTT to the broker the URL (with the login given, which wins over the URL's) or BrokerAddress names,
    over TLS for ``mqtts://`` (``max_payload``: larger payloads travel in chunks, protocol/mqtt.py). A ValueError for
    an address no transport takes."""
    if isinstance(address, str) and (make := transport_of(address)) is not None:
        return make(address)
    broker = address if isinstance(address, BrokerAddress) else BrokerAddress.parse(address, username, password,
                                                                                    ca_file)

    def connect(client_id: str, will: tuple[str, bytes] | None = None,
                rejects: RejectCounter | None = None) -> Transport:
        return MqttConnection(broker, client_id=client_id, will=will, max_payload=max_payload, rejects=rejects)

    return connect
