"""bench.matrix: its cells, what it finds wrong in a run folder, and a real slice of it over Mosquitto."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from bench import matrix
from bench.matrix import Cell
from runtime.records import RunSummary


def test_the_matrix_has_every_strategy_of_every_fitting_pair_and_each_misfit_once_per_mode() -> None:
    todo = matrix.cells(["CartPole-v0", "Pendulum-v1"], ["ppo", "dqn"], ["sync", "weighted"], ["mqtt", "inprocess"])
    assert len(todo) == (2 * 2 + 2 + 1) * 2  # CartPole: both learners; Pendulum: PPO, and DQN's refusal
    assert Cell("Pendulum-v1", "dqn", "-", "mqtt") in todo and Cell("Pendulum-v1", "dqn", "sync", "mqtt") not in todo
    assert Cell("qube-local", "sac", "sync", "mqtt").env == "qube"  # rigs behind the broker
    assert Cell("qube-local", "sac", "sync", "inprocess").env == "qube-local"


def worker(worker_id: str, episodes: int) -> dict[str, Any]:
    return {"id": worker_id, "index": int(worker_id[1:]), "episodes": episodes, "solved": False,
            "steps": 100 * episodes, "state": "stopped"}


def summary(**changes: Any) -> RunSummary:
    base = {"env": "Acrobot-v1", "algo": "sac", "policy": "sync", "rounds": 6, "rounds_per_episode": 3,
            "rejected_messages": {"malformed": 0}, "tc": -100.0, "r_floor": -500.0, "max_episodes": 2,
            "total_steps": 400, "end_reason": "reached the maximum of 2 episodes",
            "workers": [worker("w0", 2), worker("w1", 2)]}
    return RunSummary.model_validate({**base, **changes})


def test_a_run_that_did_what_its_cell_says_has_no_problems() -> None:
    assert matrix.problems(Cell("Acrobot-v1", "sac", "sync", "mqtt"), summary(), True, "", 2) == []


@pytest.mark.parametrize(("changes", "audit", "found"), [
    ({"algo": "ppo"}, True, "the run says env, learner, strategy = ('Acrobot-v1', 'ppo', 'sync')"),
    ({"workers": [worker("w0", 2), worker("w1", 1)]}, True, "workers that played fewer than M = 2 episodes: {'w1': 1}"),
    ({"rounds": 5}, True, "5 rounds for 2 episodes of 3 rounds"),
    ({"rejected_messages": {"late": 1}}, True, "refused messages: {'late': 1}"),
    ({}, False, "audit failed: broken"),
])
def test_what_a_cell_finds_wrong(changes: dict[str, Any], audit: bool, found: str) -> None:
    assert matrix.problems(Cell("Acrobot-v1", "sac", "sync", "mqtt"), summary(**changes), audit, "broken", 2) == [found]


@pytest.mark.slow
def test_a_slice_runs_over_mosquitto_and_a_misfit_is_refused(mosquitto_broker: str, tmp_path: Path) -> None:
    out = tmp_path / "matrix.json"
    code = matrix.main(["--tasks", "CartPole-v0", "Pendulum-v1", "--algos", "dqn", "--strategies", "weighted",
                        "--modes", "mqtt", "--broker", mosquitto_broker, "--runs-dir", str(tmp_path / "runs"),
                        "--out", str(out)])
    report = json.loads(out.read_text())
    assert code == 0 and report["passed"] == report["cells"] == 2, report["failed"]
    ran, refused = report["rows"]
    assert (ran["task"], ran["strategy"], ran["episodes"], ran["rounds"]) == ("CartPole-v0", "weighted",
                                                                              {"w0": 2, "w1": 2}, 2)
    assert (refused["task"], refused["exit_code"]) == ("Pendulum-v1", 2)
    assert report["command"].startswith("python -m bench.matrix --tasks CartPole-v0")
