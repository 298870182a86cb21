"""The QUBE task's action sets (protocol/qube.py ACTION_SETS): what each action sends to the motor, the spaces the
learners see, which learners fit which set, and that a model carries its set so a warm start or an evaluation with
another one is refused in one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from gymnasium import spaces
from pydantic import ValidationError

from deploy.settings import InprocessSettings, LocalRunSettings
from protocol import qube
from protocol.learners import misfit
from rpi_bridge.control import ControlConfig
from runtime.model_file import ModelFileError
from worker import model
from worker.envs import make_env
from worker.episode import build_learner_and_env
from worker.evaluate import EvalError, evaluate
from worker.settings import TrainLocalSettings, WorkerSettings


def test_the_paper_set_is_the_default_and_every_set_stays_inside_the_bridges_clip() -> None:
    assert qube.action_set(None).levels == (-60, 0, 60)
    for actions in qube.ACTION_SETS.values():
        assert actions.limit <= ControlConfig().max_command
        assert actions.levels is None or max(map(abs, actions.levels)) == actions.limit
    voltage = qube.action_set("voltage")
    assert [voltage.command(a) for a in (-1.0, -0.5, 0.0, 0.2, 1.0, 7.0, float("nan"))] == [-150, -75, 0, 30, 150,
                                                                                            150, 0]
    assert voltage.command(np.array([0.5], dtype=np.float32)) == 75
    assert qube.action_set("levels").command(8) == 150
    with pytest.raises(ValueError, match="unknown QUBE action set 'loud'; choose one of paper, levels, voltage"):
        qube.action_set("loud")


@pytest.mark.parametrize(("name", "space"), [("paper", spaces.Discrete(3)), ("levels", spaces.Discrete(9)),
                                             ("voltage", spaces.Box(-1.0, 1.0, (1,), np.float32))])
def test_each_set_gives_its_space_in_process_and_over_mqtt(name: str, space: spaces.Space) -> None:
    local = make_env("qube-local", 1000, rig_profile="lab", qube_actions=name)
    assert local.action_space == space
    assert make_env("qube", 0, probe=True, qube_actions=name).action_space == space
    local.reset(seed=0)
    _, reward, *_ = local.step(local.action_space.sample())
    assert reward == 1.0  # the hand-over state is inside the band: one step of any action keeps it there


def test_dqn_is_refused_continuous_voltage_and_every_learner_takes_the_levels(tmp_path: Path) -> None:
    assert misfit("dqn", "qube-local", "voltage") == ("learner 'dqn' needs discrete actions and qube-local's are "
                                                      "continuous with --qube-actions voltage; use ppo, sac")
    assert all(misfit(a, t, s) is None for a in ("ppo", "sac", "dqn") for t in ("qube", "qube-local")
               for s in ("paper", "levels"))
    for settings in (WorkerSettings, TrainLocalSettings, LocalRunSettings, InprocessSettings):
        needed = {"run_dir": tmp_path} if settings is InprocessSettings else {}
        with pytest.raises(ValidationError, match="with --qube-actions voltage"):
            settings.given(env="qube-local", algo="dqn", qube_actions="voltage", **needed)
        assert settings.given(env="qube-local", algo="sac", qube_actions="voltage", **needed).qube_actions == "voltage"
    worker = WorkerSettings.given(env="qube-local", qube_actions="levels", rig_profile="lab")
    assert worker.env_options() == {"rig_profile": "lab", "qube_actions": "levels"}
    assert WorkerSettings.given(env="qube-local").env_options() == {}  # the paper's: nothing to pass


def test_a_model_carries_its_action_set(tmp_path: Path) -> None:
    options = {"qube_actions": "levels"}
    _, learner = build_learner_and_env("qube-local", seed=0, device_noise=0.0, spec_only=True, env_options=options)
    path = tmp_path / "w0.pt"
    learner.save(path, model.provenance("qube-local", options, 1000, 1, 10, 100, None))
    state = model.load_state(path)
    assert model.recorded_actions(state) == "levels"
    with pytest.raises(ModelFileError, match=r"made with the QUBE action set levels, not paper \(give --qube-actions "
                                             r"levels\)"):
        model.open_init_model(path, "qube-local")
    init, _ = model.open_init_model(path, "qube-local", qube_actions="levels")
    assert init.file == path
    result = evaluate(path, "qube-local", episodes=1, rig_profile="lab")  # built with the model's own set
    assert len(result.returns) == 1
    _, paper = build_learner_and_env("qube-local", seed=0, device_noise=0.0, spec_only=True)
    old = tmp_path / "old.pt"
    paper.save(old, {"task": "qube-local"})  # saved before models recorded their action set: the paper's
    assert model.recorded_actions(model.load_state(old)) == "paper"
    with pytest.raises(EvalError, match="another action set"):
        from worker.evaluate import robustness

        robustness(path, "qube-local", "lab", rigs=1)
