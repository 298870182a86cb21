"""A worker process killed mid-run: its last will takes it out of the rounds, the others finish, the chief reports."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow


def spawn(module: str, *args: str, log: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen([sys.executable, "-m", module, *args], stdout=log.open("wb"), stderr=subprocess.STDOUT,
                            env=env)


def episodes_logged(metrics: Path, worker: str) -> int:
    if not metrics.exists():
        return 0
    return sum(1 for line in metrics.read_text().splitlines() if f'"worker":"{worker}"' in line)


def test_killed_worker_is_dropped_and_the_run_still_ends(amqtt_broker: str, tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    common = ["--broker", amqtt_broker, "--run-id", "kill", "--env", "CartPole-v0"]
    chief = spawn("chief", *common, "--workers", "2", "--max-episodes", "600", "--run-dir", str(run_dir),
                  "--round-timeout", "5", "--idle-timeout", "3", log=tmp_path / "chief.log")
    w0 = spawn("worker", *common, "--id", "w0", log=tmp_path / "w0.log")
    w1 = spawn("worker", *common, "--id", "w1", log=tmp_path / "w1.log")
    try:
        deadline = time.monotonic() + 120
        while episodes_logged(run_dir / "metrics.jsonl", "w1") < 5:
            assert time.monotonic() < deadline, (tmp_path / "chief.log").read_text()
            time.sleep(0.05)
        w1.send_signal(signal.SIGKILL)  # dies mid-run without a word: only the broker's last will tells
        assert chief.wait(timeout=300) == 4, (tmp_path / "chief.log").read_text()  # aborted: exit 4
        assert w0.wait(timeout=30) == 0
    finally:
        for p in (chief, w0, w1):
            if p.poll() is None:
                p.kill()
    summary = json.loads((run_dir / "summary.json").read_text())
    states = {w["id"]: (w["solved"], w["state"]) for w in summary["workers"]}
    assert states == {"w0": (True, "finished"), "w1": (False, "offline")}
    assert summary["episodes_to_all_solved"] is None
    assert "offline" in summary["end_reason"]
    assert "worker w1 is offline" in (tmp_path / "chief.log").read_text()
