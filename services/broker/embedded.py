"""Run amqtt as a broker bound to one interface, and start/stop it as a child process.

Hardened for a shared machine: with a password file only listed users connect (argon2 hashes, amqtt's FileAuthPlugin),
with an ACL file each user publishes and subscribes only where it may (TopicAccessControlListPlugin), and every
packet above ``max_packet_size`` closes its connection before its body is read (amqtt has no such limit of its own;
Mosquitto's ``max_packet_size`` does the same), and a topic with a NUL character, or a published topic with a
wildcard, is refused (services/broker/topic_guard.py). Sessions are kept for reconnecting clients, but not across a
restart of this broker (amqtt keeps them in memory): clients then find their session gone and send again what is
unanswered (protocol/mqtt.py, worker/service.py).
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import secrets
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from protocol.topics import ROOT_EDGE
from runtime.cli import STOP_SIGNALS
from runtime.settings import to_env
from services.broker.settings import MAX_PACKET_SIZE, BrokerSettings

log = logging.getLogger(__name__)


class PacketTooLarge(Exception):
    """A client announced a packet above the limit: its connection is closed."""


def broker_config(host: str, port: int, max_connections: int = 256, password_file: Path | None = None,
                  acl: dict[str, dict[str, list[str]]] | None = None) -> dict[str, Any]:
    """amqtt config: one TCP listener, no $SYS chatter, sessions expire; topics with NUL and published wildcards
    refused (services/broker/topic_guard.py); anonymous clients unless a password file is given; topic ACLs
    (``{"publish": {user: [filters]}, "subscribe": {...}}``) when given."""
    plugins: dict[str, Any] = {"services.broker.topic_guard.TopicGuardPlugin": {}}
    if password_file is None:
        plugins["amqtt.plugins.authentication.AnonymousAuthPlugin"] = {"allow_anonymous": True}
    else:
        plugins["amqtt.plugins.authentication.FileAuthPlugin"] = {"password_file": str(password_file)}
    if acl is not None:
        plugins["amqtt.plugins.topic_checking.TopicAccessControlListPlugin"] = {
            "publish_acl": acl.get("publish", {}), "acl": acl.get("subscribe", {})}
    return {
        "listeners": {"default": {"type": "tcp", "bind": f"{host}:{port}", "max_connections": max_connections}},
        "timeout_disconnect_delay": 2,
        "session_expiry_interval": 600,
        "plugins": plugins,
    }


class SnapshotSubscriptions(dict[str, list[Any]]):
    """amqtt's subscriptions (topic filter -> [(session, qos)]), walked as a snapshot.

    amqtt 0.12 awaits each subscriber's topic check while it walks its live subscriptions to broadcast a message, and
    when a client subscribed or left meanwhile, the walk raised and the message was dropped for everyone not reached
    yet (tests/services/test_broker_churn.py). A walk over this dict goes over a copy, each subscriber list included.
    """

    def __iter__(self) -> Iterator[str]:
        return iter(list(super().keys()))

    def items(self) -> list[tuple[str, list[Any]]]:  # type: ignore[override]
        return [(topic, list(subscribers)) for topic, subscribers in super().items()]


class ExpectedTimeouts(logging.Filter):
    """One warning line with a count for each acknowledgement a stalled client did not send in time.

    amqtt waits 5 s for a PUBACK (PUBREC, PUBCOMP) from a subscriber, logs a warning of its own when none came, then
    logs the failed delivery task with a traceback ("Task failed and will be skipped"). That is expected of a client
    that stalls (a worker in a long update, a paused process) and amqtt goes on: this filter turns the traceback
    into one warning line with the count so far and drops amqtt's own warning, which said the same."""

    def __init__(self) -> None:
        super().__init__()
        self.count = 0

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        if isinstance(exc, TimeoutError) and str(exc).startswith("Timeout waiting for"):
            self.count += 1
            record.msg, record.args = "a client did not acknowledge in time (%s): %d such timeouts so far", (
                str(exc)[len("Timeout waiting for "):], self.count)
            record.levelno, record.levelname = logging.WARNING, "WARNING"
            record.exc_info, record.exc_text, record.stack_info = None, None, None
            return True
        return not (isinstance(record.msg, str) and record.msg.startswith("Timeout waiting for"))


#: amqtt's loggers that report an acknowledgement timeout (the delivery task's, the protocol handler's).
TIMEOUT_LOGGERS = ("amqtt.broker", "amqtt.mqtt.protocol.handler")


def quiet_expected_timeouts() -> ExpectedTimeouts:
    """Install one :class:`ExpectedTimeouts` on amqtt's loggers (again: the same one)."""
    loggers = [logging.getLogger(name) for name in TIMEOUT_LOGGERS]
    found = [f for f in loggers[0].filters if isinstance(f, ExpectedTimeouts)]
    timeouts = found[0] if found else ExpectedTimeouts()
    for logger in loggers:
        if timeouts not in logger.filters:
            logger.addFilter(timeouts)
    return timeouts


def install_packet_limit(max_bytes: int) -> None:
    """Make amqtt close a connection whose next packet announces more than ``max_bytes`` (before reading it)."""
    from amqtt.mqtt.packet import MQTTFixedHeader

    original = MQTTFixedHeader.from_stream.__func__
    if getattr(original, "_fedrl_limit", None) is not None:
        original = original._fedrl_original

    async def from_stream(cls: type, reader: Any) -> Any:
        header = await original(cls, reader)
        if header is not None and header.remaining_length > max_bytes:
            log.warning("closing a connection that announced a %d-byte packet (limit %d)", header.remaining_length,
                        max_bytes)
            raise PacketTooLarge(f"{header.remaining_length} bytes")
        return header

    from_stream._fedrl_limit = max_bytes  # type: ignore[attr-defined]
    from_stream._fedrl_original = original  # type: ignore[attr-defined]
    MQTTFixedHeader.from_stream = classmethod(from_stream)


async def serve(host: str, port: int, stop: asyncio.Event, password_file: Path | None = None,
                acl: dict[str, dict[str, list[str]]] | None = None, max_packet_size: int = MAX_PACKET_SIZE) -> None:
    """Run the broker until ``stop`` is set."""
    from amqtt.broker import Broker  # the broker extra is only needed by this process

    from services.broker.topic_guard import install_wildcard_close

    install_packet_limit(max_packet_size)
    install_wildcard_close()
    quiet_expected_timeouts()
    broker = Broker(broker_config(host, port, password_file=password_file, acl=acl))
    broker._subscriptions = SnapshotSubscriptions(broker._subscriptions)  # amqtt walks them while it awaits
    await broker.start()
    log.info("amqtt broker listening on %s:%d", host, port)
    print(f"broker ready on {host}:{port}", flush=True)
    await stop.wait()
    await broker.shutdown()


def run(host: str, port: int, password_file: Path | None = None, acl_file: Path | None = None,
        max_packet_size: int = MAX_PACKET_SIZE) -> None:
    """Blocking entry point: serve until SIGINT/SIGTERM."""
    acl = json.loads(acl_file.read_text(encoding="utf-8")) if acl_file is not None else None

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in STOP_SIGNALS:
            loop.add_signal_handler(sig, stop.set)
        await serve(host, port, stop, password_file=password_file, acl=acl, max_packet_size=max_packet_size)

    asyncio.run(main())


@dataclass(frozen=True)
class Credentials:
    """Per-run users of an embedded broker: ``users`` maps a name to its password (kept in memory and handed to
    the processes through their environment); the folder holds the argon2 password file and the ACL."""

    folder: Path
    users: dict[str, str]

    @property
    def password_file(self) -> Path:
        return self.folder / "passwd"

    @property
    def acl_file(self) -> Path:
        return self.folder / "acl.json"

    def login(self, user: str) -> dict[str, str]:
        """The MQTT settings (``mqtt_username``, ``mqtt_password``) of one process."""
        return {"mqtt_username": user, "mqtt_password": self.users[user]}


def run_acl(run_id: str, workers: list[str], rigs: dict[str, str], edges: dict[str, str] | None = None
            ) -> dict[str, dict[str, list[str]]]:
    """Who may publish and subscribe where in one run: the chief on its topics, each worker on its own (and its
    rig's action and reset), each rig on its own, and a read-only observer (the dashboard). In a tiered run
    (``edges``: worker -> its edge chief) each edge on its own topics, reading the chief's and the workers'; each
    worker reads the edges' too (any edge's: a stand-in's, chief/failover.py); the chief publishes as its own edge
    (ROOT_EDGE: standing in for a dead edge whose site has no live edge left, whose workers read the chief's
    topics)."""
    run = f"fedrl/{run_id}"
    edges = edges or {}
    publish: dict[str, list[str]] = {"chief": [f"{run}/chief/#", f"{run}/claim", f"{run}/edge/{ROOT_EDGE}/#"],
                                     "observer": []}
    subscribe: dict[str, list[str]] = {"chief": [f"{run}/worker/#", f"{run}/claim", f"{run}/edge/+/partial",
                                                 f"{run}/edge/+/status"],
                                       "observer": [f"{run}/#", "qube/#"]}
    for e in sorted(set(edges.values())):
        publish[e] = [f"{run}/edge/{e}/#"]
        subscribe[e] = [f"{run}/chief/#", f"{run}/worker/#"]
    for w in workers:
        rig = rigs.get(w)
        commands = [f"qube/{rig}/{leaf}" for leaf in ("action", "reset", "identify")] if rig else []
        publish[w] = [f"{run}/worker/{w}/#", *commands]
        # Behind an edge: any edge's (a dead edge's stand-in passes the answers on), and the root's own.
        answers = [f"{run}/edge/+/chief/#", f"{run}/chief/#"] if w in edges else [f"{run}/chief/#"]
        subscribe[w] = answers + ([f"qube/{rig}/#"] if rig else [])
    for rig in rigs.values():
        publish[rig] = [f"qube/{rig}/#"]
        subscribe[rig] = [f"qube/{rig}/#"]
    return {"publish": publish, "subscribe": subscribe}


def make_credentials(folder: Path, run_id: str, workers: list[str], rigs: dict[str, str] | None = None,
                     edges: dict[str, str] | None = None) -> Credentials:
    """Random passwords for the chief, each worker, rig and edge chief (``edges``: worker -> edge) and an observer,
    written as an argon2 password file and an ACL into ``folder`` (created, private)."""
    from pwdlib import PasswordHash
    from pwdlib.hashers.argon2 import Argon2Hasher

    rigs = rigs or {}
    folder.mkdir(parents=True, exist_ok=True)
    folder.chmod(0o700)
    users = {name: secrets.token_urlsafe(24) for name in ["chief", "observer", *workers, *rigs.values(),
                                                         *sorted(set((edges or {}).values()))]}
    hasher = PasswordHash((Argon2Hasher(),))
    creds = Credentials(folder, users)
    creds.password_file.write_text("".join(f"{u}:{hasher.hash(p)}\n" for u, p in users.items()), encoding="utf-8")
    creds.password_file.chmod(0o600)
    creds.acl_file.write_text(json.dumps(run_acl(run_id, workers, rigs, edges), indent=2), encoding="utf-8")
    return creds


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that is free right now on ``host`` (never 1883 unless the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


#: MQTT 3.1.1 CONNECT (clean session, keepalive 60 s, empty client id) and DISCONNECT, for readiness probes.
_PROBE_CONNECT = bytes([0x10, 12, 0, 4]) + b"MQTT" + bytes([4, 0x02, 0, 60, 0, 0])
_PROBE_DISCONNECT = bytes([0xE0, 0])


def broker_answers(host: str, port: int, timeout: float = 1.0) -> bool:
    """True when an MQTT broker on host:port answers a CONNECT with a CONNACK (accepting it or not)."""
    try:
        with socket.create_connection((host, port), timeout=timeout) as sock:
            sock.sendall(_PROBE_CONNECT)
            reply = sock.recv(4)
            sock.sendall(_PROBE_DISCONNECT)
            return len(reply) == 4 and reply[0] == 0x20  # any CONNACK: "not authorized" also means it is up
    except OSError:
        return False


def wait_for_port(host: str, port: int, timeout: float = 60.0, proc: subprocess.Popen | None = None) -> None:
    """Block until an MQTT broker answers on host:port; raise with a clear reason otherwise."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(f"broker process exited with code {proc.returncode} before listening on {host}:{port}")
        if broker_answers(host, port):
            return
        time.sleep(0.05)
    raise TimeoutError(f"no MQTT broker answering on {host}:{port} after {timeout:.0f} s")


def start_broker_process(
    host: str = "127.0.0.1", port: int | None = None, credentials: Credentials | None = None, **popen: Any
) -> tuple[subprocess.Popen, int]:
    """Start ``python -m services.broker`` on a free (or given) port and wait until it listens."""
    port = port or free_port(host)
    settings = BrokerSettings(broker_host=host, broker_port=port, log_level="WARNING",
                              broker_password_file=credentials.password_file if credentials else None,
                              broker_acl_file=credentials.acl_file if credentials else None)
    env = {**popen.pop("env", os.environ), **to_env(settings)}
    proc = subprocess.Popen([sys.executable, "-m", "services.broker"], env=env, **popen)
    try:
        wait_for_port(host, port, proc=proc)
    except Exception:
        proc.kill()
        raise
    return proc, port


def stop_process(proc: subprocess.Popen, timeout: float = 10.0) -> int:
    """SIGTERM, then SIGKILL after ``timeout`` s; returns the exit code."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode
