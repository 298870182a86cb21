"""The broker restarts in the middle of a run. Mosquitto with persistence keeps every session and queued message;
the embedded amqtt loses its sessions, and the processes make up for it (workers send unanswered submissions again
after a reconnect, the chief answers a closed round again). Either way the run ends with the same per-worker result
as without the restart, and nobody waits out a reply timeout."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from chief.audit import audit
from services.broker.embedded import free_port, start_broker_process, stop_process
from tests.conftest import HOST, mosquitto_available, start_mosquitto

pytestmark = pytest.mark.slow

SEED, WORKERS = 2, 2


def per_worker(run_dir: Path) -> list[tuple[str, int, int]]:
    return [(w["id"], w["episodes"], w["steps"]) for w in json.loads((run_dir / "summary.json").read_text())["workers"]]


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> list[tuple[str, int, int]]:
    """The same federation without any restart (in one process: the same logic, the same result)."""
    from deploy.inprocess import run_federation

    run_dir = tmp_path_factory.mktemp("reference") / "run"
    run_federation("CartPole-v0", "weighted", SEED, WORKERS, 600, run_dir, plot=False)
    return per_worker(run_dir)


def federate_through_a_restart(tmp_path: Path, port: int, restart: object) -> Path:
    run_dir = tmp_path / "run"
    launcher = subprocess.Popen(
        [sys.executable, "-m", "deploy.run_local", "--workers", str(WORKERS), "--seed", str(SEED), "--max-episodes",
         "600", "--broker", f"mqtt://{HOST}:{port}", "--run-dir", str(run_dir), "--run-id", "restart"],
        stdout=(tmp_path / "launcher.log").open("wb"), stderr=subprocess.STDOUT,
        env={**os.environ, "FEDRL_RESEND_INTERVAL": "600"})  # only a reconnect may trigger a resend here
    try:
        metrics = run_dir / "metrics.jsonl"
        deadline = time.monotonic() + 300
        while not metrics.exists() or metrics.read_text().count('"type":"round"') < 10:
            assert time.monotonic() < deadline and launcher.poll() is None, (tmp_path / "launcher.log").read_text()
            time.sleep(0.05)
        restart()  # type: ignore[operator]
        assert launcher.wait(timeout=400) == 0, (tmp_path / "launcher.log").read_text()[-3000:]
    finally:
        if launcher.poll() is None:
            launcher.kill()
    return run_dir


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
        stop_process(box[0])
        time.sleep(1.0)
        box[0], _ = start_broker_process(HOST, port, stdout=log, stderr=subprocess.STDOUT)

    try:
        check(federate_through_a_restart(tmp_path, port, restart), reference)
    finally:
        stop_process(box[0])
        log.close()
