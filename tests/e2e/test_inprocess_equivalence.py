"""One implementation, two transports: the in-process runner (deploy/inprocess.py, the services on the in-memory
hub) and the same services over a real MQTT broker (real sockets) give, for one seed, the same per-worker episodes
and steps and the same records (every submission and every round: weights, contributors, digests; not the times)
under every strategy. The benchmarks' numbers come from the in-process runs: this is what makes them the system's."""

from __future__ import annotations

import subprocess
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import pytest

from chief import strategies
from chief.audit import audit
from services.broker.embedded import start_broker_process, stop_process
from tests.federations import all_records, over_mqtt, per_worker_final

pytestmark = pytest.mark.slow

ENV, SEED, WORKERS, EPISODES = "CartPole-v0", 101, 2, 30  # w0 finishes at 28 under weighted


@pytest.fixture(scope="module")
def broker(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """One embedded amqtt broker for every run of this module (each run has its own run id)."""
    log = (tmp_path_factory.mktemp("broker") / "amqtt.log").open("wb")
    proc, port = start_broker_process("127.0.0.1", stdout=log, stderr=subprocess.STDOUT)
    try:
        yield f"mqtt://127.0.0.1:{port}"
    finally:
        stop_process(proc)
        log.close()


@pytest.mark.parametrize("policy", strategies.names())
def test_in_process_and_over_mqtt_give_the_same_federation(broker: str, tmp_path: Path, policy: str) -> None:
    from deploy.inprocess import run_federation
    from deploy.settings import InprocessSettings

    over_mqtt(broker, f"eq-{policy}", tmp_path / "mqtt", ENV, policy, SEED, WORKERS, EPISODES)
    summary = run_federation(InprocessSettings.given(env=ENV, policy=policy, seed=SEED, workers=WORKERS,
                             max_episodes=EPISODES, run_dir=tmp_path / "inprocess"), plot=False,
                             tensorboard_files=False)
    assert summary.mode == "in-process"
    assert per_worker_final(tmp_path / "inprocess") == per_worker_final(tmp_path / "mqtt")
    subs, rounds = all_records(tmp_path / "inprocess")
    assert (subs, rounds) == all_records(tmp_path / "mqtt")
    assert len(rounds) == summary.rounds > 0
    assert audit(tmp_path / "inprocess").transfers == audit(tmp_path / "mqtt").transfers


#: Off-policy learners (worker/sac.py, worker/dqn.py) on their presets' tasks: (learner, task, strategy, seed, M).
#: SAC on Pendulum-v1 under weighted, seed 103, with CHEAPER's learner: w0 solves at 20 and hands its actor to w1,
#: which plays on to M = 21.
OFF_POLICY = [("sac", "Pendulum-v1", "weighted", 103, 21), ("dqn", "CartPole-v0", "sync", 101, 2),
              ("dqn", "Acrobot-v1", "median", 101, 3)]
#: Fields of a learner's preset replaced for these runs (in this process, which runs both federations' workers). SAC
#: on Pendulum-v1: one gradient step per env step instead of the preset's two, learning rates 2e-3 instead of 1e-3.
#: The same equivalence, with a transfer, in about half the gradient steps: the preset (seed 102, w0 solving at 16,
#: M = 18) took 400 s of the suite's busiest test process.
CHEAPER = {"sac": {"utd_ratio": 1.0, "actor_lr": 2e-3, "critic_lr": 2e-3}}


@pytest.mark.parametrize(("algo", "env", "policy", "seed", "episodes"), OFF_POLICY)
def test_off_policy_learners_in_process_and_over_mqtt_give_the_same_federation(
    broker: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, algo: str, env: str, policy: str, seed: int,
    episodes: int
) -> None:
    """The learner travels with the run (ChiefSettings.algo, WorkerSettings.algo): over MQTT the same records as
    in process, the per-step rounds of sync, and a soft transfer of a SAC actor that the audit checks."""
    from deploy.inprocess import run_federation
    from deploy.settings import InprocessSettings
    from worker import envs
    from worker.envs import env_spec

    if algo in CHEAPER:
        spec = env_spec(env)
        monkeypatch.setitem(envs.ENVS, env, replace(spec, presets={**spec.presets,
                                                                   algo: spec.learner_config(algo, **CHEAPER[algo])}))
    over_mqtt(broker, f"eq-{algo}-{policy}", tmp_path / "mqtt", env, policy, seed, WORKERS, episodes, algo=algo)
    summary = run_federation(InprocessSettings.given(env=env, policy=policy, seed=seed, workers=WORKERS,
                             max_episodes=episodes, run_dir=tmp_path / "inprocess", algo=algo), plot=False,
                             tensorboard_files=False)
    assert summary.algo == algo
    assert per_worker_final(tmp_path / "inprocess") == per_worker_final(tmp_path / "mqtt")
    subs, rounds = all_records(tmp_path / "inprocess")
    assert (subs, rounds) == all_records(tmp_path / "mqtt")
    if policy == "sync":
        assert len(rounds) == episodes * env_spec(env).learner_config(algo).update_epochs
    else:  # every round an aggregate of both workers until the first finisher hands over its actor
        first = min((r["round"] for r in rounds if r["kind"] == "transfer"), default=episodes + 1)
        assert all(r["kind"] == "aggregate" and len(r["contributors"]) == WORKERS for r in rounds
                   if r["round"] < first)
    reports = audit(tmp_path / "inprocess"), audit(tmp_path / "mqtt")
    assert reports[0].transfers == reports[1].transfers == (1 if algo == "sac" else 0)
    if algo == "sac":
        transfer = next(r for r in rounds if r["kind"] == "transfer")
        assert transfer["finished"] == ["w0"] and list(transfer["keep_weights"]) == ["w1"]
