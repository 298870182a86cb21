"""End to end: chief + 2 PPO workers as separate processes over a real broker learn CartPole-v0."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow


def federate(tmp_path: Path, name: str, broker: str | None, seed: int = 3, policy: str = "weighted") -> dict:
    run_dir = tmp_path / name
    argv = [sys.executable, "-m", "deploy.run_local", "--workers", "2", "--env", "CartPole-v0", "--policy", policy,
            "--seed", str(seed), "--max-episodes", "600", "--run-dir", str(run_dir), "--run-id", name]
    if broker:
        argv += ["--broker", broker]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "all workers solved" in proc.stdout
    summary = json.loads((run_dir / "summary.json").read_text())
    assert (run_dir / "learning_curve.png").stat().st_size > 1000
    assert sorted(p.name for p in (run_dir / "models").iterdir()) == ["w0.pt", "w1.pt"]
    metrics = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert {m["worker"] for m in metrics if m["type"] == "episode"} == {"w0", "w1"}
    return summary


@pytest.fixture(scope="module")
def embedded_run(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """One federation over the embedded amqtt broker, shared by the tests below."""
    return federate(tmp_path_factory.mktemp("e2e"), "amqtt", broker=None)


def test_two_workers_learn_cartpole_over_the_embedded_broker(embedded_run: dict) -> None:
    summary = embedded_run
    assert summary["env"] == "CartPole-v0" and summary["policy"] == "weighted" and summary["seed"] == 3
    assert all(w["solved"] for w in summary["workers"])
    assert summary["episodes_to_all_solved"] == max(w["episodes"] for w in summary["workers"]) <= 600
    assert summary["rejected_messages"] == {} and summary["wall_s"] > 0


def test_same_wiring_over_mosquitto_gives_the_same_result(
    embedded_run: dict, mosquitto_broker: str, tmp_path: Path
) -> None:
    # Same seed on another broker: the federation is deterministic, so every worker solves at the same episode.
    again = federate(tmp_path, "mosquitto", broker=mosquitto_broker)
    assert again["broker"] == mosquitto_broker
    episodes = [(w["id"], w["episodes"]) for w in again["workers"]]
    assert episodes == [(w["id"], w["episodes"]) for w in embedded_run["workers"]]
    assert all(w["solved"] for w in again["workers"])
