"""Bounded staleness (RunStart.max_staleness S): a worker plays on with up to S of its rounds unanswered, applies the
answers in round order as they come, and the audit checks which answer each worker applied and when; S = 0 is the
federation as before, and a per-step strategy refuses S > 0 with one line."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

from chief.audit import AuditFailure, audit
from chief.report import MetricsLog, run_summary, write_summary
from chief.rounds import RoundKeeper, Submission
from chief.service import ChiefService, Outputs
from chief.settings import ChiefSettings
from protocol.messages import ChiefAggregate
from protocol.rigtime import model_idle
from protocol.tasks import PI_WINDOW, performance_index, task, worker_seed
from protocol.tensors import answer_digest, pack_arrays
from runtime.records import RunSummary
from tests.federations import run_in_threads
from worker import service as worker_service
from worker.episode import build_learner_and_env
from worker.federated import Algorithm2
from worker.service import WorkerService
from worker.settings import WorkerSettings

# -- the worker's pure core -----------------------------------------------------------------------------------


def algorithm(staleness: int) -> Algorithm2:
    env, learner = build_learner_and_env("CartPole-v0", seed=5, device_noise=0.0)
    return Algorithm2("w0", env, learner, tc=195.0, seed=5, max_staleness=staleness)


def aggregate(algo: Algorithm2, round_: int, value: float) -> ChiefAggregate:
    grads = {k: np.full(shape, value, np.float32) for k, shape in algo.actor_spec.items()}
    return ChiefAggregate(round=round_, episode=round_, gradient=pack_arrays(grads), weights={"w0": 1.0},
                          contributors=("w0",))


def test_a_worker_plays_on_with_up_to_s_rounds_owed_and_applies_answers_in_order() -> None:
    algo = algorithm(1)
    first = algo.play()
    assert first.receipt is None and algo.owed == [1] and not algo.waits  # S = 1: episode 2 may start
    algo.play()
    assert algo.owed == [1, 2] and algo.waits  # two owed: it must wait for round 1's answer
    a1, a2 = aggregate(algo, 1, 0.01), aggregate(algo, 2, 0.02)
    assert algo.take({2: a2}) == []  # round 2's answer waits for round 1's
    assert algo.take({1: a1, 2: a2}) == [1, 2] and algo.owed == [] and not algo.waits
    third = algo.play()
    assert third.receipt is not None and third.receipt.round == 2 and third.receipt.episode == 3
    assert [(r.round, r.episode, r.applied) for r in third.earlier_receipts] == [(1, 3, "aggregate")]
    assert third.receipt.digest == answer_digest(a2.gradient, None)
    fourth = algo.play()  # nothing applied since: no receipt is reported twice
    assert fourth.earlier_receipts == () and fourth.receipt is None


def test_a_worker_gives_up_its_oldest_owed_answer() -> None:
    algo = algorithm(1)
    algo.play()
    algo.play()
    assert algo.give_up() == 1 and algo.owed == [2]
    assert algo.play().receipt is not None and algo.receipt is not None and algo.receipt.applied == "missed"


def test_without_staleness_every_answer_is_waited_for() -> None:
    algo = algorithm(0)
    algo.play()
    assert algo.waits
    assert algo.apply(aggregate(algo, 1, 0.0)) is None and not algo.waits
    assert algo.play().receipt.episode == 2  # type: ignore[union-attr]


def test_a_per_step_run_has_no_staleness() -> None:
    with pytest.raises(ValueError, match="one round per episode"):
        env, learner = build_learner_and_env("CartPole-v0", seed=5, device_noise=0.0)
        from protocol.rounds import RoundShape
        Algorithm2("w0", env, learner, 195.0, 5, shape=RoundShape(per_episode=10), max_staleness=1)
    with pytest.raises(ValueError, match="staleness"):
        RoundKeeper(["w0"], "sync", task("CartPole-v0"), 10, 30.0, shape=RoundShape(per_episode=10), max_staleness=1)


def test_staleness_with_sync_is_one_line_and_exit_2(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    from deploy.inprocess import main

    assert main(["--policy", "sync", "--max-staleness", "1", "--run-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--max-staleness 1" in err and "sync" in err


# -- the idle model --------------------------------------------------------------------------------------------


def test_the_idle_model_waits_only_for_the_round_s_back() -> None:
    rounds = [{"fast": 1.0, "slow": 3.0}] * 3
    assert model_idle(rounds) == {"fast": 6.0, "slow": 0.0}  # S = 0: 2 s per round
    # S = 1: the fast rig waits only for the answer to its round before the last. The slow rig closes the rounds
    # at 3, 6, 9; the fast one is ready at 1 (no gate yet), at 2 (waits for round 1's close at 3: 1 s), at 4
    # (waits for round 2's at 6: 2 s).
    assert model_idle(rounds, staleness=1) == {"fast": 3.0, "slow": 0.0}


# -- the audit -------------------------------------------------------------------------------------------------

WORKERS, EPISODES = ("w0", "w1", "w2"), 10


def simulate_stale(run_dir: Path) -> None:
    """The real RoundKeeper under S = 1: w0 and w1 submit two episodes ahead of the slow w2, which then closes two
    rounds at once; each worker reports, with its next submission, every answer that came (several at once)."""
    keeper = RoundKeeper(list(WORKERS), "plain", task("CartPole-v0"), max_episodes=EPISODES, round_timeout=30.0,
                         actor_spec={"g": (2,)}, max_staleness=1)
    returns: dict[str, list[float]] = {w: [] for w in WORKERS}
    came: dict[str, list[dict[str, Any]]] = {w: [] for w in WORKERS}  # answers come, not reported yet
    metrics = MetricsLog(run_dir)

    def submit(w: str, episode: int) -> None:
        returns[w].append(20.0 + episode)
        receipts = [{**r, "episode": episode} for r in came[w]]
        came[w] = []
        verdict = keeper.submit(Submission(
            w, episode, performance_index(returns[w]), returns[w][-1], recent_returns=tuple(returns[w][-PI_WINDOW:]),
            steps=20, gradient={"g": np.array([episode, 1.0], np.float32)},
            receipt=receipts[-1] if receipts else None, earlier_receipts=tuple(receipts[:-1])), now=float(episode))
        assert verdict.status == "accepted", verdict.detail
        metrics.episode(verdict.record(float(episode)))
        for outcome in verdict.outcomes:
            metrics.round({**outcome.record(), "t": float(episode)})
            for x in WORKERS:
                came[x].append({"round": outcome.round, "applied": outcome.kind, "digest": outcome.digest})

    for first in range(1, EPISODES + 1, 2):
        for w in ("w0", "w1"):
            submit(w, first)
            submit(w, first + 1)
        submit("w2", first)
        submit("w2", first + 1)
    metrics.close()
    write_summary(run_dir, run_summary(keeper, keeper.done_reason or "", run_id="stale", seed=0))


@pytest.fixture(scope="module")
def stale_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    run_dir = tmp_path_factory.mktemp("stale") / "run"
    simulate_stale(run_dir)
    return run_dir


def lines_of(run_dir: Path) -> list[dict[str, Any]]:
    return [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]


def test_a_stale_federation_passes_the_audit(stale_run: Path) -> None:
    report = audit(stale_run)
    assert report.rounds == EPISODES and report.staleness == 1
    assert any(x.get("earlier_receipts") for x in lines_of(stale_run))  # two answers applied at once


def doctor_order(lines: list[dict[str, Any]]) -> None:
    """w0 reports round 1's and round 2's answers as applied the other way round."""
    e = next(x for x in lines if x.get("worker") == "w0" and x.get("earlier_receipts"))
    e["receipt"], e["earlier_receipts"] = e["earlier_receipts"][0], [e["receipt"]]


def doctor_episode(lines: list[dict[str, Any]]) -> None:
    """w1 says it applied an answer before a later episode than the one whose submission reports it."""
    e = next(x for x in lines if x.get("worker") == "w1" and x.get("receipt"))
    e["receipt"]["episode"] += 1


def doctor_too_stale(lines: list[dict[str, Any]]) -> None:
    """w0 moves round 1's receipt from its episode-3 submission to its episode-4 one: 3 rounds behind."""
    e3 = next(x for x in lines if x.get("worker") == "w0" and x.get("episode") == 3)
    e4 = next(x for x in lines if x.get("worker") == "w0" and x.get("episode") == 4)
    moved = e3.pop("earlier_receipts")
    e4["earlier_receipts"] = [{**moved[0], "episode": 4}]
    e4["receipt"] = {**e3["receipt"], "episode": 4}
    e3["receipt"] = None


@pytest.mark.parametrize(("doctor", "invariant"), [(doctor_order, "staleness"), (doctor_episode, "staleness"),
                                                   (doctor_too_stale, "delivery")])
def test_a_doctored_stale_record_fails(stale_run: Path, tmp_path: Path, doctor: Any, invariant: str) -> None:
    run_dir = tmp_path / "doctored"
    shutil.copytree(stale_run, run_dir)
    lines = lines_of(run_dir)
    doctor(lines)
    (run_dir / "metrics.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))
    with pytest.raises(AuditFailure) as failure:
        audit(run_dir)
    assert failure.value.invariant == invariant, str(failure.value)


def test_a_stale_run_claimed_as_lockstep_fails(stale_run: Path, tmp_path: Path) -> None:
    """The same records under summary.json's max_staleness 0: the workers were behind more than allowed."""
    run_dir = tmp_path / "claimed"
    shutil.copytree(stale_run, run_dir)
    summary = json.loads((run_dir / "summary.json").read_text())
    (run_dir / "summary.json").write_text(json.dumps({**summary, "max_staleness": 0}))
    with pytest.raises(AuditFailure) as failure:
        audit(run_dir)
    assert failure.value.invariant in ("delivery", "staleness")


# -- over a real broker, and in process --------------------------------------------------------------------------

ENV, SEED, MQTT_EPISODES, SLOW_S = "CartPole-v0", 7, 6, 0.4


class SlowReset(gym.Wrapper):
    """A device whose every reset takes SLOW_S wall seconds (a rig's slow swing-up)."""

    def reset(self, **kwargs: Any) -> Any:
        time.sleep(SLOW_S)
        return self.env.reset(**kwargs)


def slow_worker_1(monkeypatch: pytest.MonkeyPatch) -> None:
    """Worker index 1 of the run (seed worker_seed(SEED, 1)) gets a slow reset."""
    build = worker_service.build_learner_and_env

    def slowed(env_id: str, seed: int, *args: Any, **kwargs: Any) -> Any:
        env, learner = build(env_id, seed, *args, **kwargs)
        return (SlowReset(env) if seed == worker_seed(SEED, 1) else env), learner

    monkeypatch.setattr(worker_service, "build_learner_and_env", slowed)


def over_mqtt(url: str, run_dir: Path, staleness: int) -> None:
    run_id = f"stale-{staleness}"
    chief = ChiefService(ChiefSettings.given(broker=url, run_id=run_id, workers=2, env=ENV, policy="plain",
                                             seed=SEED, max_episodes=MQTT_EPISODES, round_timeout=600.0,
                                             run_dir=run_dir, max_staleness=staleness),
                         outputs=Outputs(tensorboard=False, plot=False, progress=False))
    services = [chief] + [WorkerService(WorkerSettings.given(broker=url, run_id=run_id, worker_id=f"w{i}", env=ENV))
                          for i in range(2)]
    run_in_threads([s.run for s in services], timeout=300)


def played_on(run_dir: Path, worker: str) -> list[int]:
    """The rounds r for which ``worker``'s submission for r + 1 was counted before round r closed."""
    seen: set[int] = set()
    out = []
    for x in lines_of(run_dir):
        if x["type"] == "episode" and x["worker"] == worker:
            seen.add(x["round"])
        elif x["type"] == "round" and x["round"] + 1 in seen:
            out.append(x["round"])
    return out


@pytest.mark.slow
def test_over_a_broker_a_worker_plays_on_while_anothers_round_is_open(
    any_broker: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    slow_worker_1(monkeypatch)
    over_mqtt(any_broker, tmp_path / "mqtt", staleness=1)
    assert played_on(tmp_path / "mqtt", "w0")  # w0 went on while w1 (slow) held the round open
    assert not played_on(tmp_path / "mqtt", "w1")
    report = audit(tmp_path / "mqtt")
    assert report.staleness == 1 and report.rounds == MQTT_EPISODES
    idle = {w["id"]: w for w in json.loads((tmp_path / "mqtt" / "summary.json").read_text())["workers"]}
    assert idle["w0"]["episodes"] == idle["w1"]["episodes"] == MQTT_EPISODES


@pytest.mark.slow
def test_in_process_and_over_mqtt_keep_the_same_invariants_under_staleness(
    amqtt_broker: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Under S > 0 which answer a worker has when it starts an episode depends on when the answer arrives, so the
    two transports need not give the same gradients; what must agree is the federation's shape: the same rounds,
    the same episodes per worker, every answer applied in order within S rounds (both audits pass)."""
    from deploy.inprocess import run_federation
    from deploy.settings import InprocessSettings

    slow_worker_1(monkeypatch)
    over_mqtt(amqtt_broker, tmp_path / "mqtt", staleness=1)
    summary = run_federation(InprocessSettings.given(env=ENV, policy="plain", seed=SEED, workers=2,
                             max_episodes=MQTT_EPISODES, run_dir=tmp_path / "inprocess", max_staleness=1), plot=False,
                             tensorboard_files=False, models=False)
    mqtt = RunSummary.read(tmp_path / "mqtt")
    assert [(w.id, w.episodes) for w in summary.workers] == [(w.id, w.episodes) for w in mqtt.workers]
    assert summary.max_staleness == mqtt.max_staleness == 1
    a, b = audit(tmp_path / "inprocess"), audit(tmp_path / "mqtt")
    assert (a.rounds, a.submissions, a.staleness) == (b.rounds, b.submissions, b.staleness)
    assert played_on(tmp_path / "inprocess", "w0")
