"""``make run`` against a broker nobody can reach ends at once: one line and exit code 1, no processes started. An
impossible quorum (k > n) ends the same way before anything starts (exit code 2), and so does
a learner that cannot act in the task (DQN on continuous actions), which once left the chief waiting for workers
that had died at their first step."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest


def _closed_port() -> int:
    """A port on 127.0.0.1 with nothing listening (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_an_unreachable_broker_is_one_line_and_exit_1(tmp_path: Path) -> None:
    env = {**os.environ, "FEDRL_BROKER": f"mqtt://127.0.0.1:{_closed_port()}", "FEDRL_RUN_DIR": str(tmp_path / "run")}
    done = subprocess.run([sys.executable, "-m", "deploy.run_local"], env=env, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 1
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "cannot reach the MQTT broker" in lines[0], done.stderr
    # Refused at once, not waited out (no wall-clock bound here: a loaded machine must not fail the suite).
    assert "Connection refused" in lines[0] and "no answer within" not in lines[0], lines[0]
    assert not (tmp_path / "run" / "logs" / "chief.log").exists()


@pytest.mark.parametrize("launcher", ["deploy.run_local", "deploy.inprocess"])
def test_an_impossible_quorum_is_one_line_and_exit_2_before_anything_starts(tmp_path: Path, launcher: str) -> None:
    """k of n with k > n never closes a round, with edges or without: the launcher itself refuses it, before a
    broker, a run folder or a thread exists (not the chief's settings after the embedded broker started)."""
    run_dir = tmp_path / "run"
    done = subprocess.run([sys.executable, "-m", launcher, "--workers", "4", "--edges", "2", "--quorum", "5",
                           "--run-dir", str(run_dir)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "--quorum 5: a round cannot wait for more than its 4 workers" in lines[0], done.stderr
    assert not run_dir.exists()


@pytest.mark.parametrize("launcher", ["deploy.run_local", "deploy.inprocess", "worker", "worker.train_local"])
def test_a_learner_that_cannot_act_in_the_task_is_one_line_and_exit_2(tmp_path: Path, launcher: str) -> None:
    run_dir = tmp_path / "run"
    done = subprocess.run([sys.executable, "-m", launcher, "--algo", "dqn", "--env", "Pendulum-v1"],
                          env={**os.environ, "FEDRL_RUN_DIR": str(run_dir)}, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].endswith(
        "learner 'dqn' needs discrete actions and Pendulum-v1's are continuous; use ppo, sac"), done.stderr
    assert not run_dir.exists()
