"""Shared fixtures: real MQTT brokers on free loopback ports (embedded amqtt always, Mosquitto where installed)."""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.broker.embedded import free_port, start_broker_process, stop_process, wait_for_port

HOST = "127.0.0.1"

# Hermetic settings: no developer's ./.env (docker compose reads one too) reaches the processes the tests start.
os.environ["FEDRL_ENV_FILE"] = os.devnull


@pytest.fixture
def amqtt_broker(tmp_path: Path) -> Iterator[str]:
    """``python -m services.broker`` on a free port; yields its mqtt:// URL."""
    log = (tmp_path / "amqtt.log").open("wb")
    proc, port = start_broker_process(HOST, stdout=log, stderr=subprocess.STDOUT)
    try:
        yield f"mqtt://{HOST}:{port}"
    finally:
        stop_process(proc)
        log.close()


def start_mosquitto(tmp_path: Path, port: int | None = None, max_packet_size: int = 4259840,
                    persistence: bool = False) -> tuple[subprocess.Popen, int]:
    """Mosquitto with TCP_NODELAY and a packet limit (the codec's 4 MiB plus headers) on a free loopback port; with
    ``persistence`` it keeps sessions and queued messages across a restart (in a folder of the test)."""
    binary = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    port = port or free_port(HOST)
    conf = tmp_path / f"mosquitto-{port}.conf"
    store = f"persistence true\npersistence_location {tmp_path}/\nautosave_interval 1\n" if persistence else (
        "persistence false\n")
    if os.geteuid() == 0:
        store += "user root\n"  # as root, Mosquitto would switch to its own user, who cannot write the test's folder
    conf.write_text(
        f"listener {port} {HOST}\nallow_anonymous true\nset_tcp_nodelay true\nmax_packet_size {max_packet_size}\n"
        f"{store}log_dest stderr\n"
    )
    log = (tmp_path / f"mosquitto-{port}.log").open("wb")
    proc = subprocess.Popen([binary, "-c", str(conf)], stdout=log, stderr=subprocess.STDOUT)
    wait_for_port(HOST, port, proc=proc)
    return proc, port


def mosquitto_available() -> bool:
    return shutil.which("mosquitto") is not None or Path("/usr/sbin/mosquitto").exists()


@pytest.fixture
def mosquitto_broker(tmp_path: Path) -> Iterator[str]:
    """A Mosquitto started by the test on a free port (skipped, with the reason, where it is not installed)."""
    if not mosquitto_available():
        pytest.skip("mosquitto is not installed (apt-get install mosquitto)")
    proc, port = start_mosquitto(tmp_path)
    try:
        yield f"mqtt://{HOST}:{port}"
    finally:
        stop_process(proc)


@pytest.fixture(params=["amqtt", "mosquitto"])
def any_broker(request: pytest.FixtureRequest) -> str:
    """Each test using it runs once against each broker."""
    return request.getfixturevalue(f"{request.param}_broker")
