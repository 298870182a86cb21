"""paho-mqtt 2.x connection helper: MQTT 3.1.1, TCP_NODELAY, last will, automatic reconnect and resubscribe.

Handlers run on paho's network thread: keep them short (decode, validate, put on a queue). A handler that raises is
logged and counted; it never kills the network loop.
"""

from __future__ import annotations

import logging
import os
import socket
import ssl
import threading
from collections.abc import Callable
from dataclasses import dataclass
from urllib.parse import unquote, urlsplit

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion

log = logging.getLogger(__name__)

Handler = Callable[[str, bytes], None]
DEFAULT_BROKER = "mqtt://127.0.0.1:1883"


@dataclass(frozen=True)
class BrokerAddress:
    """Where the broker is and how to log in: ``mqtt://[user:pass@]host:port`` or ``mqtts://`` for TLS."""

    host: str
    port: int
    tls: bool = False
    username: str | None = None
    password: str | None = None
    ca_file: str | None = None

    @classmethod
    def parse(
        cls,
        url: str,
        username: str | None = None,
        password: str | None = None,
        ca_file: str | None = None,
    ) -> BrokerAddress:
        """Parse a broker URL; explicit credentials override those in the URL. A bare ``host:port`` is accepted."""
        text = url.strip()
        if "://" not in text:
            text = "mqtt://" + text
        parts = urlsplit(text)
        if parts.scheme not in ("mqtt", "mqtts", "tcp", "ssl"):
            raise ValueError(f"broker URL {url!r}: scheme must be mqtt:// or mqtts://")
        if not parts.hostname:
            raise ValueError(f"broker URL {url!r} has no host")
        tls = parts.scheme in ("mqtts", "ssl")
        try:
            port = parts.port or (8883 if tls else 1883)
        except ValueError as exc:
            raise ValueError(f"broker URL {url!r}: {exc}") from None
        return cls(
            host=parts.hostname,
            port=port,
            tls=tls,
            username=username or (unquote(parts.username) if parts.username else None),
            password=password or (unquote(parts.password) if parts.password else None),
            ca_file=ca_file,
        )

    @classmethod
    def from_env(cls, url: str | None = None) -> BrokerAddress:
        """``url`` (or FEDRL_BROKER) plus FEDRL_MQTT_USERNAME / FEDRL_MQTT_PASSWORD / FEDRL_MQTT_CA_FILE."""
        return cls.parse(
            url or os.environ.get("FEDRL_BROKER", DEFAULT_BROKER),
            username=os.environ.get("FEDRL_MQTT_USERNAME") or None,
            password=os.environ.get("FEDRL_MQTT_PASSWORD") or None,
            ca_file=os.environ.get("FEDRL_MQTT_CA_FILE") or None,
        )

    def __str__(self) -> str:
        return f"{'mqtts' if self.tls else 'mqtt'}://{self.host}:{self.port}"


def _set_nodelay(client: paho.Client, userdata: object, sock: socket.socket) -> None:
    """Nagle + delayed ACK turn a 0.6 ms round trip into 40-90 ms (reference/mqtt.md), so disable Nagle."""
    try:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    except OSError:  # not a TCP socket (e.g. websockets proxy): nothing to tune
        pass


class MqttConnection:
    """One paho client with subscriptions that survive reconnects."""

    def __init__(
        self,
        address: BrokerAddress,
        client_id: str,
        will: tuple[str, bytes] | None = None,
        keepalive: int = 15,
    ) -> None:
        self.address = address
        self.client_id = client_id
        self.connected = threading.Event()
        self.handler_errors = 0
        self._stopping = False
        self._subscriptions: dict[str, tuple[int, Handler]] = {}
        self._lock = threading.Lock()
        self._keepalive = keepalive
        self._client = paho.Client(
            CallbackAPIVersion.VERSION2,
            client_id=client_id,
            protocol=paho.MQTTv311,
            clean_session=True,
            reconnect_on_failure=True,
        )
        self._client.on_socket_open = _set_nodelay
        self._client.on_connect = self._on_connect
        self._client.on_disconnect = self._on_disconnect
        self._client.reconnect_delay_set(min_delay=0.2, max_delay=5)
        self._client.max_queued_messages_set(10_000)
        if will is not None:
            self._client.will_set(will[0], will[1], qos=1, retain=False)
        if address.username:
            self._client.username_pw_set(address.username, address.password)
        if address.tls:
            self._client.tls_set(ca_certs=address.ca_file, cert_reqs=ssl.CERT_REQUIRED)

    # -- lifecycle ---------------------------------------------------------------------------------------------

    def start(self, timeout: float = 10.0) -> MqttConnection:
        """Connect in the background and wait up to ``timeout`` s for the first CONNACK."""
        self._client.connect_async(self.address.host, self.address.port, keepalive=self._keepalive)
        self._client.loop_start()
        if not self.connected.wait(timeout):
            self.stop()
            raise ConnectionError(
                f"could not connect to the MQTT broker at {self.address} within {timeout:.0f} s "
                "(is it running? set FEDRL_BROKER or --broker)"
            )
        return self

    def stop(self) -> None:
        """Disconnect cleanly (no last will) and stop the network thread."""
        self._stopping = True
        try:
            self._client.disconnect()
        finally:
            self._client.loop_stop()
            self.connected.clear()

    def __enter__(self) -> MqttConnection:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- messaging ---------------------------------------------------------------------------------------------

    def subscribe(self, topic_filter: str, handler: Handler, qos: int = 1) -> None:
        """Call ``handler(topic, payload)`` for every message matching the filter, now and after reconnects."""
        with self._lock:
            self._subscriptions[topic_filter] = (qos, handler)
        self._client.message_callback_add(topic_filter, self._wrap(handler))
        if self.connected.is_set():
            self._client.subscribe(topic_filter, qos)

    def unsubscribe(self, topic_filter: str) -> None:
        with self._lock:
            self._subscriptions.pop(topic_filter, None)
        self._client.message_callback_remove(topic_filter)
        if self.connected.is_set():
            self._client.unsubscribe(topic_filter)

    def publish(self, topic: str, payload: bytes, qos: int = 1, retain: bool = False) -> paho.MQTTMessageInfo:
        """Queue a message; QoS 1 messages published while disconnected go out after the reconnect."""
        return self._client.publish(topic, payload, qos=qos, retain=retain)

    # -- paho callbacks ----------------------------------------------------------------------------------------

    def _wrap(self, handler: Handler) -> Callable[[paho.Client, object, paho.MQTTMessage], None]:
        def on_message(client: paho.Client, userdata: object, msg: paho.MQTTMessage) -> None:
            try:
                handler(msg.topic, msg.payload)
            except Exception:
                self.handler_errors += 1
                log.exception("handler for %s failed (handler errors: %d)", msg.topic, self.handler_errors)

        return on_message

    def _on_connect(self, client: paho.Client, userdata: object, flags: object, reason: object, props: object) -> None:
        if getattr(reason, "is_failure", False):
            log.error("broker %s refused the connection: %s", self.address, reason)
            return
        with self._lock:
            subs = list(self._subscriptions.items())
        for topic_filter, (qos, _) in subs:
            client.subscribe(topic_filter, qos)
        log.info("%s connected to %s (%d subscriptions)", self.client_id, self.address, len(subs))
        self.connected.set()

    def _on_disconnect(
        self, client: paho.Client, userdata: object, flags: object, reason: object, props: object
    ) -> None:
        if self.connected.is_set() and not self._stopping:
            log.warning("%s lost the broker at %s (%s); reconnecting", self.client_id, self.address, reason)
        self.connected.clear()
