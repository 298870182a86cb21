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

#: The longest tests and groups, longest first (seconds of one test process in ``make test``'s pytest on the 2-core
#: machine under other load, 2026-12-05: the e2e group about 600, the SAC equivalence 186 (400 before it was
#: shortened), test_lab 141 + 106 + 71, the root's resume 60, test_interrupt 62 + 58 + 2 x 24, test_edge_failover
#: 55 + 54 + 47 + 34, the printed resume line 53, the byzantine median 51, the other equivalences 48 and less).
#: A module whose module-scoped fixture is a federation or a recording keeps its tests in one xdist group, so that
#: the fixture is made once (test_edge_failover's reference was made in each of three test processes).
#: Under ``--dist loadgroup`` a test process is handed the tests (a group as one) in the order of collection as it
#: frees up, so a long one collected late ran alone at the end; they run first, then the other slow ones, then the
#: rest (short ones last even out the ends). Only the order changes.
LONGEST_FIRST = (
    "tests/e2e/test_end_to_end.py::",  # with the rest of the xdist group "e2e", which runs where its first test does
    "tests/e2e/test_inprocess_equivalence.py::test_off_policy_learners_in_process_and_over_mqtt_give_the_same_"
    "federation[sac-",
    "tests/deploy/test_lab.py::",
    "tests/chief/test_chief_resume.py::",
    "tests/deploy/test_interrupt.py::",
    "tests/e2e/test_edge_failover.py::",
    "tests/deploy/test_printed_commands.py::",
    "tests/e2e/test_byzantine.py::",
    "tests/e2e/test_inprocess_equivalence.py::",
    "tests/services/test_site_brokers.py::",  # xdist groups of a module fixture, 130 s and 110 s in all
    "tests/services/test_identify.py::",
)


def pytest_configure(config: pytest.Config) -> None:
    """xdist's loadgroup would hand out the groups with the most tests first (--loadscope-reorder); this order
    (pytest_collection_modifyitems) is by length instead."""
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """LONGEST_FIRST first, in its order; then the other slow tests; then the rest (each in collection order)."""

    def rank(item: pytest.Item) -> int:
        for i, prefix in enumerate(LONGEST_FIRST):
            if item.nodeid.startswith(prefix):
                return i
        return len(LONGEST_FIRST) + (item.get_closest_marker("slow") is None)

    items.sort(key=rank)


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
