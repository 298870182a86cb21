"""bench.behaviour: the grid is make run's federation, make bench-quick's and the off-policy learners' short runs, and
two result files compare run by run."""

from __future__ import annotations

import json
from pathlib import Path

from bench import behaviour
from bench.paper import QUICK
from chief import strategies


def test_the_grid_is_make_run_bench_quick_and_the_off_policy_learners() -> None:
    runs = behaviour.grid()
    assert runs[0] == ("CartPole-v0", "weighted", 1, 2000, "ppo") and runs[0].name == "CartPole-v0-weighted-s1"
    ppo = 1 + len(QUICK["tasks"]) * len(strategies.names()) * len(QUICK["seeds"])
    assert len(runs) == ppo + 8 and {r.algo for r in runs[:ppo]} == {"ppo"}
    assert {(r.algo, r.task, r.strategy) for r in runs[ppo:]} == {
        (algo, task, strategy) for algo, task in (("sac", "Pendulum-v1"), ("sac", "MountainCarContinuous-v0"),
                                                  ("dqn", "CartPole-v0"), ("dqn", "Acrobot-v1"))
        for strategy in ("sync", "independent")}
    assert runs[-1].name == "dqn-Acrobot-v1-independent-s101"


def test_two_files_compare_run_by_run(tmp_path: Path) -> None:
    a = {"x": [["w0", 3, 30]], "y": [["w0", 4, 40]]}
    (tmp_path / "a.json").write_text(json.dumps(a))
    (tmp_path / "b.json").write_text(json.dumps({**a, "y": [["w0", 5, 40]], "z": []}))
    assert behaviour.compare(a, a) == [] and behaviour.compare(a, {**a, "y": [["w0", 5, 40]], "z": []}) == ["y", "z"]
    assert behaviour.main(["--compare", str(tmp_path / "a.json"), str(tmp_path / "a.json")]) == 0
    assert behaviour.main(["--compare", str(tmp_path / "a.json"), str(tmp_path / "b.json")]) == 1
