"""Shared fixtures: real MQTT brokers on free loopback ports (embedded amqtt always, Mosquitto where installed)."""

from __future__ import annotations

import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.broker import mosquitto
from services.broker.embedded import start_broker_process, stop_process
from services.broker.settings import MAX_PACKET_SIZE
from tests import federations

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


def start_mosquitto(tmp_path: Path, port: int | None = None, persistence: bool = False,
                    max_packet_size: int | None = MAX_PACKET_SIZE) -> tuple[subprocess.Popen, int]:
    """Mosquitto on a free loopback port, its files in the test's folder (services/broker/mosquitto.py)."""
    return mosquitto.start(tmp_path, port=port, max_packet_size=max_packet_size, persistence=persistence)


mosquitto_available = mosquitto.available


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


@pytest.fixture(scope="session")
def runs(tmp_path_factory: pytest.TempPathFactory) -> federations.Runs:
    """The 4-worker federation of each strategy over the embedded amqtt broker (tests/federations.py), made on first
    use and shared by every test that compares against it; those tests carry ``pytest.mark.xdist_group("e2e")``."""
    return federations.Runs(tmp_path_factory.mktemp("e2e"))
