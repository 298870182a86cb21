"""Run amqtt as a broker bound to one interface, and start/stop it as a child process."""

from __future__ import annotations

import asyncio
import logging
import signal
import socket
import subprocess
import sys
import time
from typing import Any

log = logging.getLogger(__name__)


def broker_config(host: str, port: int, max_connections: int = 256) -> dict[str, Any]:
    """amqtt config: one TCP listener, anonymous clients allowed (local use), no $SYS chatter, sessions expire."""
    return {
        "listeners": {"default": {"type": "tcp", "bind": f"{host}:{port}", "max_connections": max_connections}},
        "timeout_disconnect_delay": 2,
        "session_expiry_interval": 600,
        "plugins": {"amqtt.plugins.authentication.AnonymousAuthPlugin": {"allow_anonymous": True}},
    }


async def serve(host: str, port: int, stop: asyncio.Event) -> None:
    """Run the broker until ``stop`` is set."""
    from amqtt.broker import Broker  # the broker extra is only needed by this process

    broker = Broker(broker_config(host, port))
    await broker.start()
    log.info("amqtt broker listening on %s:%d", host, port)
    print(f"broker ready on {host}:{port}", flush=True)
    await stop.wait()
    await broker.shutdown()


def run(host: str, port: int) -> None:
    """Blocking entry point: serve until SIGINT/SIGTERM."""

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        await serve(host, port, stop)

    asyncio.run(main())


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that is free right now on ``host`` (never 1883 unless the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


#: MQTT 3.1.1 CONNECT (clean session, keepalive 60 s, empty client id) and DISCONNECT, for readiness probes.
_PROBE_CONNECT = bytes([0x10, 12, 0, 4]) + b"MQTT" + bytes([4, 0x02, 0, 60, 0, 0])
_PROBE_DISCONNECT = bytes([0xE0, 0])


def broker_answers(host: str, port: int, timeout: float = 1.0) -> bool:
    """True when an MQTT broker on host:port answers a CONNECT with a successful CONNACK."""
    try:
        with socket.create_connection((host, port), timeout=timeout) as sock:
            sock.sendall(_PROBE_CONNECT)
            reply = sock.recv(4)
            sock.sendall(_PROBE_DISCONNECT)
            return len(reply) == 4 and reply[0] == 0x20 and reply[3] == 0
    except OSError:
        return False


def wait_for_port(host: str, port: int, timeout: float = 15.0, proc: subprocess.Popen | None = None) -> None:
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
    host: str = "127.0.0.1", port: int | None = None, **popen: Any
) -> tuple[subprocess.Popen, int]:
    """Start ``python -m services.broker`` on a free (or given) port and wait until it listens."""
    port = port or free_port(host)
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.broker", "--host", host, "--port", str(port), "--log-level", "WARNING"],
        **popen,
    )
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
