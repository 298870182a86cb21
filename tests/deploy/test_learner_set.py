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


def test_a_launched_runs_summary_says_what_its_workers_learner_replaced(tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """deploy.run_local's chief never sees the workers' settings: the launcher adds ``learner_set`` to its summary."""
    from deploy import run_local
    from runtime.records import RunSummary
    from tests.deploy.test_printed_commands import solved_run

    monkeypatch.setenv("FEDRL_ENV_FILE", "/dev/null")
    given = ["entropy_coef=0.05", "hidden_sizes=(16, 16)"]
    for learner_set in (given, []):
        run_dir = tmp_path / f"run{len(learner_set)}"
        flags = [word for text in learner_set for word in ("--set", text)]
        s = run_local.load(["--run-id", "r1", "--run-dir", str(run_dir), *flags])
        solved_run(run_dir, s)
        assert run_local.report(s, 0, 1.0) == 0
        assert RunSummary.read(run_dir).learner_set == (learner_set or None)


def test_the_docker_launcher_hands_its_workers_the_overrides() -> None:
    from deploy.settings import DockerSettings
    from worker.settings import WorkerSettings

    s = DockerSettings.given(learner_set=["entropy_coef=0.05"])
    worker = s.child(WorkerSettings, inherit=False, broker="mqtt://127.0.0.1:1", run_id="r1", worker_id="w0")
    assert worker.learner_overrides() == {"entropy_coef": 0.05}
