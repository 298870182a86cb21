"""The broker restarts in the middle of a run: every process reconnects and the federation still finishes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from services.broker.embedded import free_port, start_broker_process, stop_process
from tests.conftest import HOST

pytestmark = pytest.mark.slow


def test_federation_survives_a_broker_restart(tmp_path: Path) -> None:
    port = free_port(HOST)
    broker_log = (tmp_path / "broker.log").open("wb")
    broker, _ = start_broker_process(HOST, port, stdout=broker_log, stderr=subprocess.STDOUT)
    run_dir = tmp_path / "run"
    env = {"FEDRL_ROUND_TIMEOUT": "3", "FEDRL_REPLY_TIMEOUT": "6"}
    launcher = subprocess.Popen(
        [sys.executable, "-m", "deploy.run_local", "--workers", "2", "--seed", "2", "--max-episodes", "600",
         "--round-timeout", "3", "--broker", f"mqtt://{HOST}:{port}", "--run-dir", str(run_dir), "--run-id", "rs"],
        stdout=(tmp_path / "launcher.log").open("wb"), stderr=subprocess.STDOUT, env={**os.environ, **env})
    try:
        metrics = run_dir / "metrics.jsonl"
        deadline = time.monotonic() + 120
        while not metrics.exists() or len(metrics.read_text().splitlines()) < 20:
            assert time.monotonic() < deadline and launcher.poll() is None, (tmp_path / "launcher.log").read_text()
            time.sleep(0.05)
        stop_process(broker)  # the broker goes away mid-run ...
        time.sleep(1.0)
        broker, _ = start_broker_process(HOST, port, stdout=broker_log, stderr=subprocess.STDOUT)  # ... and is back
        assert launcher.wait(timeout=400) == 0, (tmp_path / "launcher.log").read_text()[-3000:]
    finally:
        if launcher.poll() is None:
            launcher.kill()
        stop_process(broker)
        broker_log.close()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert all(w["solved"] for w in summary["workers"]), summary
    logs = "".join(p.read_text() for p in (run_dir / "logs").glob("worker-*.log"))
    assert "lost the broker" in logs  # they did notice, and carried on
