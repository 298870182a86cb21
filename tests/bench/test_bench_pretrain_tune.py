"""bench.pretrain_tune: tuning runs of deploy.lab's pretrain never touch a report seed, and a run stopped before its end
still has its learning curve read."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench import pretrain_tune


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
    w0 = line["curve"]["w0"]
    assert w0["episodes"] == 60 and w0["first_full_return"] == 30 and w0["last_pi"] == 60.0
    assert w0["pi"] == {25: 25.0, 50: 50.0} and w0["entropy"] == {25: 0.04, 50: 0.02}
