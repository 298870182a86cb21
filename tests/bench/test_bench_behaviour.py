"""bench.behaviour: the grid is make bench-quick's plus make run's federation, and two result files compare run by
run."""

from __future__ import annotations

import json
from pathlib import Path

from bench import behaviour
from bench.paper import QUICK
from chief import strategies


def test_the_grid_is_bench_quick_and_make_run() -> None:
    runs = behaviour.grid()
    assert runs[0] == ("CartPole-v0", "weighted", 1, 2000)
    assert len(runs) == 1 + len(QUICK["tasks"]) * len(strategies.names()) * len(QUICK["seeds"])


def test_two_files_compare_run_by_run(tmp_path: Path) -> None:
    a = {"x": [["w0", 3, 30]], "y": [["w0", 4, 40]]}
    (tmp_path / "a.json").write_text(json.dumps(a))
    (tmp_path / "b.json").write_text(json.dumps({**a, "y": [["w0", 5, 40]], "z": []}))
    assert behaviour.compare(a, a) == [] and behaviour.compare(a, {**a, "y": [["w0", 5, 40]], "z": []}) == ["y", "z"]
    assert behaviour.main(["--compare", str(tmp_path / "a.json"), str(tmp_path / "a.json")]) == 0
    assert behaviour.main(["--compare", str(tmp_path / "a.json"), str(tmp_path / "b.json")]) == 1
