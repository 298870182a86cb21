"""``--set KEY=VALUE`` on a federation's launcher reaches every worker's learner (here in process; the launcher of
separate processes hands it on as FEDRL_LEARNER_SET: tests/runtime/test_settings.py), and only there: a run without
it learns with the task's preset."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

import worker.service
from deploy.inprocess import run_federation
from deploy.settings import InprocessSettings
from worker.envs import env_spec


@pytest.fixture
def built(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """The configurations of the learners the workers build to learn with (not their shape probes)."""
    real, configs = worker.service.build_learner_and_env, []

    def build(*args: Any, **kwargs: Any) -> Any:
        env, learner = real(*args, **kwargs)
        if not kwargs.get("spec_only"):
            configs.append(learner.config)
        return env, learner

    monkeypatch.setattr(worker.service, "build_learner_and_env", build)
    return configs


@pytest.mark.parametrize("given", [["entropy_coef=0.05", "hidden_sizes=(16, 16)"], []])
def test_every_worker_learns_with_the_launchers_overrides(given: list[str], built: list[Any], tmp_path: Path) -> None:
    s = InprocessSettings.given(env="CartPole-v0", policy="plain", seed=3, workers=2, max_episodes=2,
                                run_dir=tmp_path / "run", learner_set=given)
    summary = run_federation(s, plot=False, tensorboard_files=False, models=False, tolerate_failures=True)
    assert summary.learner_set == (given or None)  # the run says what it changed
    preset = env_spec("CartPole-v0").learner_config("ppo")
    wanted = (0.05, (16, 16)) if given else (preset.entropy_coef, preset.hidden_sizes)
    assert len(built) == 2 and all((c.entropy_coef, tuple(c.hidden_sizes)) == wanted for c in built)
