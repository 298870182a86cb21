"""An in-memory stand-in for the MQTT broker: the services of a federation in one process talk through a Hub.

Each MemoryConnection has the interface of protocol/mqtt.py's MqttConnection (protocol.transport.Transport), so the
chief and the workers run unchanged over it (deploy/inprocess.py). What it keeps of MQTT:

- topic filters with ``+`` (one level) and ``#`` (the rest, including none), matched as a broker does (a wildcard in
  the first level does not match a ``$`` topic);
- payloads are bytes, copied as they are sent, so every message goes through the codec as over the wire;
- each connection gets the messages of its subscriptions in the order the hub routed them, once per message, and
  calls every matching handler on its own delivery thread (as paho does on its network thread); a handler that
  raises is logged and counted in ``handler_errors`` and the delivery goes on;
- a connection closed without a clean ``stop`` (``drop``) has its last will published to the others.

What it leaves out: QoS (nothing is lost), retained messages (none are kept), sessions, chunking and sizes.

A hub is passed by value (``Hub.connect``, deploy/inprocess.py) or chosen by address: ``memory://<name>`` is the hub
of that name in this process (made at its first connection), so services whose settings name the same address talk
through one hub, as over ``mqtt://`` they talk through one broker (protocol.transport.connector).
"""

from __future__ import annotations

import logging
import queue
import threading

from protocol.codec import RejectCounter
from protocol.transport import Connect, Handler

log = logging.getLogger(__name__)


def check_filter(topic_filter: str) -> None:
    """A ValueError unless ``topic_filter`` is a valid MQTT filter (``+`` and ``#`` fill a level; ``#`` is last)."""
    levels = topic_filter.split("/")
    for i, level in enumerate(levels):
        if ("+" in level or "#" in level) and len(level) > 1:
            raise ValueError(f"topic filter {topic_filter!r}: a wildcard must fill its level")
        if level == "#" and i != len(levels) - 1:
            raise ValueError(f"topic filter {topic_filter!r}: '#' must be the last level")
    if not topic_filter:
        raise ValueError("empty topic filter")


def matches(topic_filter: str, topic: str) -> bool:
    """Whether ``topic`` matches ``topic_filter`` under MQTT's rules."""
    wanted, levels = topic_filter.split("/"), topic.split("/")
    if topic.startswith("$") and wanted[0] in ("+", "#"):
        return False
    for i, part in enumerate(wanted):
        if part == "#":
            return True
        if i >= len(levels) or (part != "+" and part != levels[i]):
            return False
    return len(wanted) == len(levels)


class _Sent:
    """What ``publish`` returns: the hub routed the message before ``publish`` returned."""

    def wait_for_publish(self, timeout: float | None = None) -> None:
        return None


class Hub:
    """The in-memory broker: routes every published message to the connections subscribed to its topic."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._clients: list[MemoryConnection] = []

    def connect(self, client_id: str, will: tuple[str, bytes] | None = None,
                rejects: RejectCounter | None = None) -> MemoryConnection:
        """A new connection to this hub (protocol.transport.Connect), not yet started."""
        return MemoryConnection(self, client_id, will, rejects)

    def _attach(self, client: MemoryConnection) -> None:
        with self._lock:
            self._clients.append(client)

    def _detach(self, client: MemoryConnection) -> None:
        with self._lock:
            if client in self._clients:
                self._clients.remove(client)

    def route(self, topic: str, payload: bytes) -> None:
        """Hand the message to every attached connection with a matching subscription (one total order)."""
        if "+" in topic or "#" in topic or not topic:
            raise ValueError(f"cannot publish on {topic!r}: not a topic name")
        with self._lock:
            for client in self._clients:
                if client.wants(topic):
                    client._enqueue(topic, payload)


SCHEME = "memory://"
_NAMED: dict[str, Hub] = {}
_NAMED_LOCK = threading.Lock()


def connector(address: str) -> Connect:
    """The Connect of ``memory://<name>``: connections to the hub of that name in this process (protocol.transport's
    factory calls it); a ValueError for an address that names no hub."""
    name = address.removeprefix(SCHEME)
    if not address.startswith(SCHEME) or not name or "/" in name or "@" in name:
        raise ValueError(f"in-memory address {address!r}: use memory://<name> (a name without '/' or '@')")

    def connect(client_id: str, will: tuple[str, bytes] | None = None,
                rejects: RejectCounter | None = None) -> MemoryConnection:
        with _NAMED_LOCK:
            hub = _NAMED.setdefault(name, Hub())
        return hub.connect(client_id, will, rejects)

    return connect


class MemoryConnection:
    """One service's connection to a Hub (protocol.transport.Transport)."""

    def __init__(self, hub: Hub, client_id: str, will: tuple[str, bytes] | None = None,
                 rejects: RejectCounter | None = None) -> None:
        self.hub = hub
        self.client_id = client_id
        self.will = will
        self.connected = threading.Event()
        self.connects = 0
        self.session_present = False
        self.handler_errors = 0
        self.rejects = rejects or RejectCounter(log)
        self._subscriptions: dict[str, Handler] = {}
        self._lock = threading.Lock()
        self._inbox: queue.Queue[tuple[str, bytes] | None] = queue.Queue()
        self._thread: threading.Thread | None = None

    def start(self, timeout: float = 10.0, stop: threading.Event | None = None) -> MemoryConnection:
        """Attach to the hub and start the delivery thread (at once: ``timeout`` and ``stop`` are for a broker)."""
        if self.connected.is_set():
            return self
        self._thread = threading.Thread(target=self._deliver, name=f"memory-{self.client_id}", daemon=True)
        self._thread.start()
        self.hub._attach(self)
        self.connects += 1
        self.connected.set()
        return self

    def stop(self) -> None:
        """Leave cleanly (no last will): nothing more is delivered, pending messages are dropped."""
        self._close()

    def drop(self) -> None:
        """Leave as a lost connection does: the hub publishes the last will to the others."""
        was_connected = self.connected.is_set()
        self._close()
        if was_connected and self.will is not None:
            self.hub.route(*self.will)

    def _close(self) -> None:
        with self._lock:
            self._subscriptions.clear()
        self.hub._detach(self)
        self.connected.clear()
        thread = self._thread
        if thread is not None:
            self._inbox.put(None)
            if thread is not threading.current_thread():
                thread.join(timeout=5)
            self._thread = None

    def __enter__(self) -> MemoryConnection:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def subscribe(self, topic_filter: str, handler: Handler, qos: int = 1) -> None:
        """Call ``handler(topic, payload)`` for every message matching the filter (QoS is ignored)."""
        check_filter(topic_filter)
        with self._lock:
            self._subscriptions[topic_filter] = handler

    def unsubscribe(self, topic_filter: str) -> None:
        with self._lock:
            self._subscriptions.pop(topic_filter, None)

    def publish(self, topic: str, payload: bytes, qos: int = 1, retain: bool = False) -> _Sent:
        """Route a copy of the payload to the subscribers; dropped (and logged) while not connected."""
        if not isinstance(payload, (bytes, bytearray, memoryview)):
            raise TypeError(f"payload must be bytes, not {type(payload).__name__}")
        if not self.connected.is_set():
            log.debug("%s is not connected: dropped a message on %s", self.client_id, topic)
            return _Sent()
        self.hub.route(topic, bytes(payload))
        return _Sent()

    # -- delivery ----------------------------------------------------------------------------------------------

    def wants(self, topic: str) -> bool:
        with self._lock:
            return any(matches(f, topic) for f in self._subscriptions)

    def _enqueue(self, topic: str, payload: bytes) -> None:
        self._inbox.put((topic, payload))

    def _deliver(self) -> None:
        while (item := self._inbox.get()) is not None:
            topic, payload = item
            with self._lock:
                handlers = [h for f, h in self._subscriptions.items() if matches(f, topic)]
            for handler in handlers:
                try:
                    handler(topic, payload)
                except Exception:
                    self.handler_errors += 1
                    log.exception("handler for %s failed (handler errors: %d)", topic, self.handler_errors)
