"""The learner registry (protocol/learners.py, worker/learners.py) and ``--algo`` where a run is decided: the chief
admits only workers of the run's learner, a worker refuses a run of another, a model records its learner and a warm
start or an evaluation of another learner's model is one clear line."""

from __future__ import annotations

from pathlib import Path

import pytest
from gymnasium import spaces
from pydantic import ValidationError

from chief.roster import Roster
from chief.service import ChiefService, Outputs
from chief.settings import ChiefSettings, FederationSettings
from deploy.settings import DockerSettings, InprocessSettings, LocalRunSettings
from protocol import learners as names
from protocol.memory import Hub, MemoryConnection
from protocol.messages import WorkerHello
from protocol.tasks import TASKS
from runtime.model_file import ModelFileError
from worker import learners, model
from worker.episode import build_learner_and_env
from worker.ppo import PPOLearner
from worker.settings import TrainLocalSettings, WorkerSettings, parse_override


def test_the_wire_and_the_worker_name_the_same_learners() -> None:
    assert names.names() == ["ppo", "sac", "dqn"] and names.DEFAULT == "ppo"
    for name in names.names():
        kind = learners.get(name)
        assert kind.name == name and "update_epochs" in kind.config_fields()
    with pytest.raises(ValueError, match="unknown learner 'a2c'; choose one of ppo, sac, dqn"):
        learners.get("a2c")


def test_a_ppo_model_records_its_learner_and_older_ones_are_ppo() -> None:
    learner = PPOLearner(spaces.Box(-1, 1, (4,)), spaces.Discrete(2))
    state = learner.state_dict()
    assert learners.recorded(state) == "ppo"
    del state["algo"]
    assert learners.recorded(state) == "ppo"  # saved before learners had names


def test_roster_admits_only_the_runs_learner() -> None:
    spec = {"net.0.weight": (128, 4)}
    roster = Roster("CartPole-v0", algo="sac")
    assert roster.offer("w0", "CartPole-v0", spec, algo="ppo") == (
        "wrong_algo", "worker runs learner 'ppo', this run 'sac'")
    assert roster.offer("w1", "CartPole-v0", spec, algo="sac") is None
    assert roster.workers == ["w1"]


def test_the_chief_counts_a_hello_of_another_learner_as_refused(tmp_path: Path) -> None:
    hub = Hub()
    chief = ChiefService(ChiefSettings.given(run_id="alg", workers=2, run_dir=tmp_path),
                         connect=lambda cid, will, rejects: MemoryConnection(hub, cid, will, rejects),
                         outputs=Outputs(state=False, tensorboard=False, plot=False, progress=False))
    spec = {"net.0.weight": (128, 4)}
    assert chief.roster.algo == "ppo"
    assert not chief._register(WorkerHello(worker_id="w0", env_id="CartPole-v0", actor_spec=spec, algo="sac"))
    assert not chief._register(WorkerHello(worker_id="w1", env_id="CartPole-v0", actor_spec=spec, algo="dqn"))
    assert chief._register(WorkerHello(worker_id="w2", env_id="CartPole-v0", actor_spec=spec))
    assert chief.rejects.as_dict().get("wrong_algo") == 2


@pytest.mark.parametrize("env_id", ["CartPole-v0", "Pendulum-v1"])
def test_each_learner_builds_for_discrete_and_continuous_tasks(env_id: str) -> None:
    for name in names.names():
        if name == "dqn" and env_id == "Pendulum-v1":
            with pytest.raises(ValueError, match="DQN needs Discrete actions"):
                build_learner_and_env(env_id, seed=3, device_noise=0.0, algo=name)
            continue
        env, learner = build_learner_and_env(env_id, seed=3, device_noise=0.0, algo=name)
        obs, _ = env.reset(seed=3)
        action = learner.act(obs)
        assert env.action_space.contains(action) or env_id == "Pendulum-v1"  # Box actions may be raw (the env clips)
        assert learner.actor_spec() and (learner.critic_spec() or name == "dqn")  # DQN has no critic
        assert learners.recorded(learner.state_dict()) == name
        env.close()


def test_misfit_says_what_building_the_learner_finds() -> None:
    """protocol/learners.py misfit (torch-free, for the launchers) against the learners themselves, on every task
    whose env this process can make (qube drives a rig over MQTT: qube-local has its spaces)."""
    for env_id, spec in TASKS.items():
        assert spec.discrete is not None, f"{env_id} must say whether its actions are discrete"
        made = "qube-local" if env_id == "qube" else env_id
        for name in names.names():
            problem = names.misfit(name, env_id)
            try:
                env, _ = build_learner_and_env(made, seed=3, device_noise=0.0, algo=name)
                env.close()
            except ValueError:
                assert problem is not None, (name, env_id)
            else:
                assert problem is None, (name, env_id)
    assert names.misfit("dqn", "an-extension-task") is None  # a registered task that does not say: not refused


@pytest.mark.parametrize("settings", [ChiefSettings, FederationSettings, LocalRunSettings, InprocessSettings,
                                      DockerSettings, WorkerSettings, TrainLocalSettings])
def test_every_settings_refuse_dqn_on_continuous_actions(settings: type, tmp_path: Path) -> None:
    needed = {"run_dir": tmp_path} if settings is InprocessSettings else {}
    with pytest.raises(ValidationError, match="learner 'dqn' needs discrete actions and MountainCarContinuous-v0's"):
        settings.given(env="MountainCarContinuous-v0", algo="dqn", **needed)
    assert settings.given(env="Acrobot-v1", algo="dqn", **needed).algo == "dqn"


def test_a_model_of_another_learner_is_one_line(tmp_path: Path) -> None:
    _, sac = build_learner_and_env("CartPole-v0", seed=0, device_noise=0.0, algo="sac")
    path = tmp_path / "w0.pt"
    sac.save(path)
    state = model.load_state(path)
    _, ppo = build_learner_and_env("CartPole-v0", seed=0, device_noise=0.0)
    with pytest.raises(ModelFileError, match=r"was made by learner sac, not ppo \(give --algo sac\)"):
        model.check_fits(state, ppo, "CartPole-v0", path)
    model.check_fits(state, sac, "CartPole-v0", path, "sac")
    with pytest.raises(ModelFileError, match="made by learner sac, not ppo"):
        model.open_init_model(path, "CartPole-v0")
    init, _ = model.open_init_model(path, "CartPole-v0", algo="sac")
    assert init.file == path


def test_overrides_are_the_chosen_learners_fields() -> None:
    assert parse_override("tau=0.01", "sac") == ("tau", 0.01)
    with pytest.raises(ValueError, match="KEY one of"):
        parse_override("tau=0.01", "ppo")
    s = TrainLocalSettings.given(algo="sac", learner_set=["utd_ratio=0.5"])
    assert s.learner_overrides() == {"utd_ratio": 0.5}


@pytest.mark.parametrize(("algo", "policy"), [("sac", "weighted"), ("sac", "sync"), ("dqn", "weighted"),
                                             ("dqn", "sync")])
def test_an_off_policy_federation_shares_and_audits(algo: str, policy: str, tmp_path: Path) -> None:
    """SAC and DQN workers federate under a per-episode and the per-step strategy: every round an aggregate of both
    workers (K = update_epochs rounds per episode under sync; DQN's critic is empty), the summary names the learner
    and the audit passes."""
    import json

    from chief.audit import audit
    from deploy.inprocess import run_federation
    from worker.envs import env_spec

    summary = run_federation(InprocessSettings.given(env="CartPole-v0", policy=policy, seed=1, workers=2,
                             max_episodes=2, run_dir=tmp_path, algo=algo), plot=False, tensorboard_files=False,
                             models=False)
    assert summary.algo == algo
    per_episode = env_spec("CartPole-v0").learner_config(algo).update_epochs if policy == "sync" else 1
    assert summary.rounds == 2 * per_episode
    rounds = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()
              if json.loads(line)["type"] == "round"]
    assert len(rounds) == 2 * per_episode
    assert all(r["kind"] == "aggregate" and r["contributors"] == ["w0", "w1"] for r in rounds)
    audit(tmp_path)
