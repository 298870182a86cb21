"""The broker restarts in the middle of a run. Mosquitto with persistence keeps every session and queued message;
the embedded amqtt loses its sessions, and the processes make up for it (workers send unanswered submissions again
after a reconnect, the chief answers a closed round again). Either way the run ends with the same per-worker result
as without the restart, and nobody waits out a reply timeout."""

from __future__ import annotations

import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from chief.audit import audit
from services.broker.embedded import free_port, start_broker_process, stop_process
from tests.conftest import HOST, mosquitto_available, start_mosquitto
from tests.federations import federate_through, per_worker

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("test_broker_restart")]  # the reference is made once

SEED, WORKERS = 2, 2


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> list[tuple[str, int, int]]:
    """The same federation without any restart (in one process: the same logic, the same result)."""
    from deploy.inprocess import run_federation
    from deploy.settings import InprocessSettings

    run_dir = tmp_path_factory.mktemp("reference") / "run"
    run_federation(InprocessSettings.given(env="CartPole-v0", policy="weighted", seed=SEED, workers=WORKERS,
                   max_episodes=600, run_dir=run_dir), plot=False)
    return per_worker(run_dir)


def federate_through_a_restart(tmp_path: Path, port: int, restart: Callable[[], None]) -> Path:
    return federate_through(
        tmp_path, restart, ["--workers", str(WORKERS), "--seed", str(SEED), "--max-episodes", "600", "--broker",
                            f"mqtt://{HOST}:{port}"],
        {"FEDRL_RESEND_INTERVAL": "600"}, name="restart")  # only a reconnect may trigger a resend here


def check(run_dir: Path, reference: list[tuple[str, int, int]]) -> str:
    assert per_worker(run_dir) == reference
    audit(run_dir)
    logs = "".join(p.read_text() for p in (run_dir / "logs").glob("*.log"))
    assert "lost the broker" in logs  # they did notice
    assert "going on alone" not in logs  # and nobody waited out a reply timeout
    return logs


@pytest.mark.skipif(not mosquitto_available(), reason="mosquitto is not installed (apt-get install mosquitto)")
def test_mosquitto_with_persistence_loses_nothing(tmp_path: Path, reference: list[tuple[str, int, int]]) -> None:
    proc, port = start_mosquitto(tmp_path, persistence=True)
    box = [proc]

    def restart() -> None:
        stop_process(box[0])  # SIGTERM: Mosquitto saves its sessions and queued messages ...
        time.sleep(1.0)
        box[0], _ = start_mosquitto(tmp_path, port=port, persistence=True)  # ... and is back with them

    try:
        logs = check(federate_through_a_restart(tmp_path, port, restart), reference)
    finally:
        stop_process(box[0])
    assert "session resumed" in logs


def test_the_embedded_broker_loses_sessions_and_nothing_is_lost(tmp_path: Path,
                                                               reference: list[tuple[str, int, int]]) -> None:
    port = free_port(HOST)
    log = (tmp_path / "broker.log").open("wb")
    box = [start_broker_process(HOST, port, stdout=log, stderr=subprocess.STDOUT)[0]]

    def restart() -> None:
        # SIGKILL, not SIGTERM: amqtt's graceful shutdown closes its sessions one by one and routes messages
        # meanwhile, so on a busy machine the run could end inside it and nobody would lose the broker.
        box[0].kill()
        box[0].wait()
        time.sleep(1.0)
        box[0], _ = start_broker_process(HOST, port, stdout=log, stderr=subprocess.STDOUT)

    try:
        check(federate_through_a_restart(tmp_path, port, restart), reference)
    finally:
        stop_process(box[0])
        log.close()
