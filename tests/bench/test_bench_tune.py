"""bench.tune: tuning runs take the preset with the overrides, on tuning seeds only."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench import tune
from worker import envs


@pytest.mark.slow
def test_tuning_runs_only_on_tuning_seeds_with_the_overrides(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(envs.ENVS, "CartPole-v0", envs.ENVS["CartPole-v0"])  # restored after the test
    with pytest.raises(SystemExit):
        tune.main(["CartPole-v0", "sync", "--algo", "sac", "--seeds", "101"])
    out = tmp_path / "t.jsonl"
    assert tune.main(["CartPole-v0", "sync", "--algo", "sac", "--seeds", "1", "--workers", "2", "--max-episodes",
                      "2", "--set", "update_epochs=3", "hidden_sizes=(8,)", "--out", str(out)]) == 0
    line = json.loads(out.read_text())
    assert line["set"] == {"update_epochs": 3, "hidden_sizes": [8]} and line["last_worker_episodes"] is None
    assert [w[1] for w in line["per_worker"]] == [2, 2]
    assert envs.env_spec("CartPole-v0").learner_config("sac").hidden_sizes == (8,)
    assert tune.tuned("CartPole-v0", "ppo", {"actor_lr": 1e-4}).actor_lr == 1e-4
