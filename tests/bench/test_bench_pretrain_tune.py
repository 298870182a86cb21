"""bench.pretrain_tune: tuning runs of deploy.lab's pretrain never touch a report seed, and a run stopped before its end
still has its learning curve read."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench import pretrain_tune
from tests.bench.test_bench_unidentified import identified_rig


@pytest.mark.parametrize("seed", [501, 510, 601, 606, 1])
def test_a_report_seed_is_refused_before_anything_runs(seed: int, tmp_path: Path) -> None:
    with pytest.raises(SystemExit):
        pretrain_tune.main([str(seed), "--runs-dir", str(tmp_path / "runs"), "--out", str(tmp_path / "out.jsonl")])
    assert not (tmp_path / "runs").exists() and not (tmp_path / "out.jsonl").exists()


def test_the_curve_of_a_run_stopped_before_its_end(tmp_path: Path) -> None:
    rows = [{"type": "episode", "worker": "w0", "episode": k, "return": 2450.0 if k == 30 else 10.0, "pi": float(k),
             "stats": {"entropy": 1.0 / k}} for k in range(1, 61)]
    rows.insert(5, {"type": "round", "round": 1})
    (tmp_path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    line = pretrain_tune.line_of(tmp_path, 701, "levels", {"actor_lr": 1e-3}, None)
    assert not line["finished"] and line["last_worker_episodes"] is None
    assert line["ease_in"] == pretrain_tune.EASE_IN  # the default of run and of the command line
    w0 = line["curve"]["w0"]
    assert w0["episodes"] == 60 and w0["first_full_return"] == 30 and w0["last_pi"] == 60.0
    assert w0["pi"] == {25: 25.0, 50: 50.0} and w0["entropy"] == {25: 0.04, 50: 0.02}


@pytest.mark.parametrize("seed", [701, 709, 521, 540])
def test_the_tuning_seeds_are_this_tools_and_bench_labs_tuning_labs(seed: int) -> None:
    assert seed in pretrain_tune.TUNING_SEEDS


def test_an_attempt_runs_with_the_seed_deploy_lab_gives_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from deploy import inprocess

    given: dict[str, object] = {}
    folder = tmp_path / "s527" / "identified"
    folder.mkdir(parents=True)
    for i in range(pretrain_tune.RIGS):
        (folder / f"rig{i}.json").write_text(identified_rig().to_json())
    monkeypatch.setattr(pretrain_tune, "identified", lambda seed, runs: folder)
    monkeypatch.setattr(inprocess, "run_federation", lambda s, **_: given.update(seed=s.seed, run_dir=s.run_dir))
    run_dir = pretrain_tune.run(527, "paper", {}, 5, tmp_path, attempt=2)
    assert given == {"seed": 527 + 10_000, "run_dir": run_dir} and run_dir.name == "s527-paper-attempt2"
