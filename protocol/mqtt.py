"""paho-mqtt 2.x connection helper: MQTT 3.1.1, TCP_NODELAY, last will, automatic reconnect and resubscribe.

- **Identity and sessions.** The client id is the given name plus a random part nobody can guess (so nobody can take
  over a process's connection by connecting with its id), stable for the life of the process; the session is
  persistent (not clean), so a broker that keeps sessions queues QoS 1 messages for us while we are away, and paho
  sends our unacknowledged ones again after a reconnect. ``connects`` and ``session_present`` tell whether the broker
  still had our session (the embedded amqtt loses sessions when it restarts).
- **Retained messages are never delivered to handlers**: a retained message is a leftover of an earlier run (or a
  trap). They are counted as rejects (``retained``). The one exception is a route marked ``retain`` in
  protocol/routes.py (the chief's claim of its run, chief/claim.py), whose retained message is the point.
- **Chunking.** With ``max_payload`` set (``FEDRL_MAX_PAYLOAD``, e.g. 131072 for AWS IoT Core's 128 KB cap), a larger
  payload is sent as Chunk messages on the same topic; every connection rejoins chunks before its handlers see them,
  so services never do. Bounded: at most MAX_PARTIAL messages in assembly, each within the codec's payload limit, and
  a partial message expires after CHUNK_TTL seconds.

Handlers run on paho's network thread: keep them short (decode, validate, put on a queue). A handler that raises is
logged and counted; it never kills the network loop.
"""

from __future__ import annotations

import contextlib
import logging
import secrets
import socket
import ssl
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from struct import error as struct_error
from urllib.parse import unquote, urlsplit

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion

from protocol.codec import MAX_PAYLOAD_BYTES, DecodeError, RejectCounter, decode, encode
from protocol.messages import Chunk
from protocol.routes import route_of

log = logging.getLogger(__name__)

Handler = Callable[[str, bytes], None]
DEFAULT_BROKER = "mqtt://127.0.0.1:1883"
#: Keep-alive seconds; sessions are persistent, so the broker queues QoS 1 messages for us while we are away.
KEEPALIVE, CLEAN_SESSION = 15, False
#: Chunk assembly limits: partial messages held at once, and seconds before a partial message is dropped.
MAX_PARTIAL, CHUNK_TTL = 64, 60.0
#: Seconds a clean stop waits for the broker's answers to what it sent last (then it disconnects anyway).
STOP_TIMEOUT = 2.0
#: How often a wait for the broker's CONNACK looks at the caller's stop event (s).
STOP_POLL_S = 0.1
#: Bytes of a Chunk message around its data (msgpack keys, id, counters), kept below max_payload.
CHUNK_OVERHEAD = 160
_CHUNK_SNIFF = b"\xa4kind\xa5chunk"


@dataclass
class _Partial:
    count: int
    total: int
    started: float
    parts: dict[int, bytes] = field(default_factory=dict)


class ChunkAssembler:
    """Rejoins Chunk messages per (topic, id); thread-confined to paho's network thread."""

    def __init__(self, max_partial: int = MAX_PARTIAL, ttl: float = CHUNK_TTL) -> None:
        self.max_partial, self.ttl = max_partial, ttl
        self._partial: dict[tuple[str, str], _Partial] = {}

    def add(self, topic: str, chunk: Chunk, now: float) -> bytes | None:
        """The whole payload once its last chunk arrived, else None; a ValueError for an inconsistent chunk."""
        for key in [k for k, p in self._partial.items() if now - p.started > self.ttl]:
            del self._partial[key]
        if chunk.total > MAX_PAYLOAD_BYTES:
            raise ValueError(f"chunked payload of {chunk.total} bytes exceeds the limit of {MAX_PAYLOAD_BYTES}")
        if chunk.index >= chunk.count:
            raise ValueError(f"chunk {chunk.index} of {chunk.count}")
        key = (topic, chunk.id)
        partial = self._partial.get(key)
        if partial is None:
            if len(self._partial) >= self.max_partial:
                raise ValueError(f"more than {self.max_partial} chunked messages in assembly")
            partial = self._partial[key] = _Partial(chunk.count, chunk.total, now)
        if (partial.count, partial.total) != (chunk.count, chunk.total):
            del self._partial[key]
            raise ValueError("chunks of one message disagree on their count or size")
        partial.parts[chunk.index] = chunk.data
        if sum(len(d) for d in partial.parts.values()) > partial.total:
            del self._partial[key]
            raise ValueError("chunks carry more bytes than announced")
        if len(partial.parts) < partial.count:
            return None
        del self._partial[key]
        payload = b"".join(partial.parts[i] for i in range(partial.count))
        if len(payload) != partial.total:
            raise ValueError(f"rejoined {len(payload)} bytes, {partial.total} announced")
        return payload


def split(payload: bytes, max_payload: int) -> list[bytes]:
    """Encoded Chunk messages, each at most ``max_payload`` bytes, that rejoin to ``payload``."""
    size = max_payload - CHUNK_OVERHEAD
    pieces = [payload[i:i + size] for i in range(0, len(payload), size)]
    ident = secrets.token_hex(8)
    return [encode(Chunk(id=ident, index=i, count=len(pieces), total=len(payload), data=piece))
            for i, piece in enumerate(pieces)]


class Stopped(Exception):
    """The process was told to stop before its connection was up (``MqttConnection.start``'s ``stop``)."""


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

    def __str__(self) -> str:
        return f"{'mqtts' if self.tls else 'mqtt'}://{self.host}:{self.port}"


def check_readable(path: str, what: str) -> None:
    """A ValueError naming the file and the reason (missing, permission denied, a folder) unless it can be read;
    processes turn it into one line and exit code 2, as for any bad setting."""
    try:
        with open(path, "rb"):
            pass
    except OSError as err:
        raise ValueError(f"cannot read the {what} {path}: {err.strerror or err}") from None


#: Seconds a start-up check waits for the broker's answer to an MQTT CONNECT (the run has not started yet).
PROBE_TIMEOUT = 10.0
#: Seconds a connection that could not start tries once more, to say why.
STARTUP_PROBE_S = 3.0


def connect_problem(address: BrokerAddress, timeout: float = PROBE_TIMEOUT) -> str | None:
    """Why an MQTT CONNECT to ``address``, with its login and TLS settings, is not accepted within ``timeout``
    seconds, as one line naming the cause (refused login, a listener that is not MQTT, a certificate that does not
    verify, one for another host name, nothing listening), or None once the broker accepted it. A clean session under
    a client id of its own, disconnected at once: it leaves nothing on the broker."""
    answer: list[str | None] = []
    client = paho.Client(CallbackAPIVersion.VERSION2, client_id=f"fedrl-probe-{secrets.token_hex(6)}",
                         protocol=paho.MQTTv311, clean_session=True)
    client.connect_timeout = timeout
    client.on_connect = lambda c, u, flags, rc, props: answer.append(refused_login(address, rc) if rc.is_failure
                                                                      else None)
    client.on_disconnect = lambda c, u, flags, rc, props: answer.append(
        "the listener closed the connection without an MQTT answer (is it an MQTT broker's port? a TLS listener "
        "needs mqtts://)")
    if address.username:
        client.username_pw_set(address.username, address.password)
    try:
        if address.tls:
            if address.ca_file:
                check_readable(address.ca_file, "CA file (FEDRL_MQTT_CA_FILE)")
            client.tls_set(ca_certs=address.ca_file, cert_reqs=ssl.CERT_REQUIRED)
        client.connect(address.host, address.port, keepalive=KEEPALIVE)
    except ssl.SSLCertVerificationError as err:
        why = err.verify_message or str(err)
        if "mismatch" in why.lower():
            return (f"TLS: the broker's certificate is not for host {address.host!r} ({why}); use the host name or "
                    "address it was made for (make-certs.sh <host>)")
        return (f"TLS: the broker's certificate does not verify ({why}); give its CA with FEDRL_MQTT_CA_FILE "
                "(--mqtt-ca-file)")
    except ssl.SSLError as err:
        return f"TLS handshake failed ({err.reason or err}): is it a TLS listener? mqtt:// is plain MQTT"
    except TimeoutError:
        return f"no answer within {timeout:g} s"
    except ValueError as err:  # an unreadable CA file
        return str(err)
    except OSError as err:  # refused, no route, unknown host; reset in the middle of a TLS handshake
        why = err.strerror or type(err).__name__
        if address.tls and isinstance(err, ConnectionResetError):
            return f"TLS handshake failed ({why}): is it a TLS listener? mqtt:// is plain MQTT"
        return why
    deadline = time.monotonic() + timeout
    try:
        while not answer and time.monotonic() < deadline:
            rc = client.loop(timeout=0.1)
            if rc not in (paho.MQTT_ERR_SUCCESS, paho.MQTT_ERR_AGAIN) and not answer:
                answer.append("the listener closed the connection without an MQTT answer (is it an MQTT broker's "
                              "port? a TLS listener needs mqtts://)")
    except (ValueError, TypeError, IndexError, struct_error):  # a reply that is not MQTT, as paho reads it
        answer.append("the listener's answer is not MQTT (is it an MQTT broker's port?)")
    finally:
        if answer and answer[0] is None:
            client.disconnect()
            client.loop(timeout=0.1)
        with contextlib.suppress(OSError):
            sock = client.socket()
            if sock is not None:
                sock.close()
    if not answer:
        return f"it accepts connections but gave no MQTT answer within {timeout:g} s (is it an MQTT broker's port?)"
    return answer[0]


def refused_login(address: BrokerAddress, reason: object) -> str:
    """The cause of a CONNACK that refused the connection, as one line."""
    who = f" of user {address.username!r}" if address.username else " (no user name given)"
    return (f"the broker refused the login{who}: {reason} (check FEDRL_MQTT_USERNAME and FEDRL_MQTT_PASSWORD, or the "
            "user's line in the broker's password file)")


def _set_nodelay(client: paho.Client, userdata: object, sock: paho.SocketLike) -> None:
    """Nagle + delayed ACK turn a 0.6 ms round trip into 40-90 ms (measured on loopback; mosquitto
    issues #433, #1526, #1616), so disable Nagle."""
    if not isinstance(sock, socket.socket):  # e.g. paho's websocket wrapper: nothing to tune
        return
    try:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    except OSError:  # not a TCP socket (e.g. websockets proxy): nothing to tune
        pass


def _retained_by_contract(topic: str) -> bool:
    """Whether the contract (protocol/routes.py) retains messages on ``topic``: then a retained one is delivered."""
    route = route_of(topic)
    return route is not None and route.retain


class MqttConnection:
    """One paho client with subscriptions that survive reconnects."""

    def __init__(
        self,
        address: BrokerAddress,
        client_id: str,
        will: tuple[str, bytes] | None = None,
        keepalive: int = KEEPALIVE,
        max_payload: int | None = None,
        rejects: RejectCounter | None = None,
    ) -> None:
        self.address = address
        self.client_id = f"{client_id}-{secrets.token_hex(6)}"  # the part nobody can guess
        self.connected = threading.Event()
        self._answered = threading.Event()  # the first CONNACK came, accepting or refusing
        self._refused: str | None = None  # why the broker refused the first CONNECT
        self.connects = 0  # successful CONNACKs so far (more than 1: we reconnected)
        self.session_present = False  # whether the broker still had our session at the last CONNACK
        self.handler_errors = 0
        self.max_payload = max_payload
        self.rejects = rejects or RejectCounter(log)
        self._assembler = ChunkAssembler()
        self._stopping = False
        self._subscriptions: dict[str, tuple[int, Handler]] = {}
        self._lock = threading.Lock()
        self._keepalive = keepalive
        self._client = paho.Client(
            CallbackAPIVersion.VERSION2,
            client_id=self.client_id,
            protocol=paho.MQTTv311,
            clean_session=CLEAN_SESSION,
            reconnect_on_failure=True,
        )
        self._client.on_socket_open = _set_nodelay
        self._client.on_connect = self._on_connect
        self._client.on_disconnect = self._on_disconnect
        self._client.reconnect_delay_set(min_delay=0.2, max_delay=5)  # type: ignore[arg-type]  # paho says int; any seconds do
        self._client.max_queued_messages_set(10_000)
        if will is not None:
            route = route_of(will[0])  # a status topic of the contract; QoS 1 for any other (tests)
            self._client.will_set(will[0], will[1], qos=route.qos if route else 1, retain=False)
        if address.username:
            self._client.username_pw_set(address.username, address.password)
        if address.tls:
            if address.ca_file:
                check_readable(address.ca_file, "CA file (FEDRL_MQTT_CA_FILE)")
            self._client.tls_set(ca_certs=address.ca_file, cert_reqs=ssl.CERT_REQUIRED)

    # -- lifecycle ---------------------------------------------------------------------------------------------

    def start(self, timeout: float = 10.0, stop: threading.Event | None = None) -> MqttConnection:
        """Connect in the background and wait up to ``timeout`` s for the first CONNACK; :class:`Stopped` as soon
        as ``stop`` is set meanwhile (a signal while the broker cannot be reached)."""
        self._client.connect_async(self.address.host, self.address.port, keepalive=self._keepalive)
        self._client.loop_start()
        deadline = time.monotonic() + timeout
        while not self._answered.wait(max(0.0, min(STOP_POLL_S, deadline - time.monotonic()))):
            if stop is not None and stop.is_set():
                self.stop()
                raise Stopped(f"stopped while connecting to the MQTT broker at {self.address}")
            if time.monotonic() >= deadline:
                break
        if self._refused is not None:  # a refused login does not get better by retrying: say so at once
            self.stop()
            raise ConnectionError(f"could not connect to the MQTT broker at {self.address}: {self._refused}")
        if not self.connected.wait(0):
            self.stop()
            # Why, as the launchers' start-up check says it (a refused login, TLS, not MQTT...), in one more try.
            why = connect_problem(self.address, timeout=STARTUP_PROBE_S) or "it answered only now"
            raise ConnectionError(f"could not connect to the MQTT broker at {self.address} within {timeout:.0f} s: "
                                  f"{why} (set FEDRL_BROKER or --broker)")
        return self

    def stop(self, timeout: float = STOP_TIMEOUT) -> None:
        """Disconnect cleanly (no last will) and stop the network thread. The session is persistent, but this
        client id is never used again: its subscriptions go first, so the broker queues nothing more for it. Waits
        up to ``timeout`` s for the broker to acknowledge them and every QoS 1 publish before the DISCONNECT."""
        self._stopping = True
        try:
            if self.connected.is_set():
                self._drain(timeout)
            self._client.disconnect()
        finally:
            self._client.loop_stop()
            self.connected.clear()

    def _drain(self, timeout: float) -> None:
        """Unsubscribe everything, then wait until nothing is left to send and the broker has answered every
        UNSUBSCRIBE and QoS 1 PUBLISH. paho closes the socket as soon as it has written the DISCONNECT; closing
        with an answer still unread (an UNSUBACK on its way) sends a TCP reset, and a broker drops what it had not
        read yet on a reset, the DISCONNECT included, so it published the last will."""
        acked: set[int] = set()

        def on_unsubscribe(client: paho.Client, userdata: object, mid: int, *rest: object) -> None:
            acked.add(mid)

        self._client.on_unsubscribe = on_unsubscribe
        with self._lock:
            filters = list(self._subscriptions)
        sent = []
        for topic_filter in filters:  # sent before the DISCONNECT, on the same connection
            rc, mid = self._client.unsubscribe(topic_filter)
            if rc == paho.MQTT_ERR_SUCCESS and mid is not None:
                sent.append(mid)
        deadline = time.monotonic() + timeout
        while self.connected.is_set():  # paho has no public count of unacknowledged publishes: _out_messages
            if acked.issuperset(sent) and not self._client._out_messages and not self._client.want_write():
                return
            if time.monotonic() > deadline:
                log.warning("%s: the broker did not answer within %.1f s; disconnecting anyway", self.client_id,
                            timeout)
                return
            time.sleep(0.005)

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
        """Queue a message (as chunks when it exceeds ``max_payload``); QoS 1 messages published while disconnected
        go out after the reconnect. The returned info is the last chunk's."""
        if self.max_payload is None or len(payload) <= self.max_payload:
            return self._client.publish(topic, payload, qos=qos, retain=retain)
        info = None
        for piece in split(payload, self.max_payload):
            info = self._client.publish(topic, piece, qos=qos, retain=retain)
        assert info is not None
        return info

    # -- paho callbacks ----------------------------------------------------------------------------------------

    def _wrap(self, handler: Handler) -> Callable[[paho.Client, object, paho.MQTTMessage], None]:
        def on_message(client: paho.Client, userdata: object, msg: paho.MQTTMessage) -> None:
            try:
                if msg.retain and not _retained_by_contract(msg.topic):
                    self.rejects.reject(msg.topic, "retained", "a retained message (left on the broker earlier)")
                    return
                payload = bytes(msg.payload)  # paho reads bytes, and bytes() of bytes is the same object
                if _CHUNK_SNIFF in payload[:48]:
                    try:
                        whole = self._assembler.add(msg.topic, decode(payload, Chunk), time.monotonic())
                    except (DecodeError, ValueError) as err:
                        self.rejects.reject(msg.topic, "bad_chunk", str(err))
                        return
                    if whole is None:
                        return
                    payload = whole
                handler(msg.topic, payload)
            except Exception:
                self.handler_errors += 1
                log.exception("handler for %s failed (handler errors: %d)", msg.topic, self.handler_errors)

        return on_message

    def _on_connect(self, client: paho.Client, userdata: object, flags: object, reason: object, props: object) -> None:
        if getattr(reason, "is_failure", False):
            log.error("broker %s refused the connection: %s", self.address, reason)
            if self.connects == 0 and not self._answered.is_set():
                self._refused = refused_login(self.address, reason)
                self._answered.set()
            return
        with self._lock:
            subs = list(self._subscriptions.items())
        for topic_filter, (qos, _) in subs:
            client.subscribe(topic_filter, qos)
        self.session_present = bool(getattr(flags, "session_present", False))
        self.connects += 1
        log.info("%s connected to %s (%d subscriptions, %s)", self.client_id, self.address, len(subs),
                 "session resumed" if self.session_present else "new session")
        self.connected.set()
        self._answered.set()

    def _on_disconnect(
        self, client: paho.Client, userdata: object, flags: object, reason: object, props: object
    ) -> None:
        if self.connected.is_set() and not self._stopping:
            log.warning("%s lost the broker at %s (%s); reconnecting", self.client_id, self.address, reason)
        self.connected.clear()
