"""A worker's resumable state (worker/resume.py): saved mid-run and taken up by a new process's Algorithm 2, the run
goes on exactly as if it had never stopped; a state of another run, chief session, task or network is refused."""

from __future__ import annotations

from pathlib import Path

import pytest

from protocol.messages import ChiefAggregate, MatureParams, RunStart, WorkerUpdate
from protocol.rounds import PER_EPISODE, RoundShape
from protocol.tensors import digest
from worker import resume
from worker.episode import build_learner_and_env
from worker.federated import Algorithm2

ENV, SEED = "CartPole-v0", 1001
START = RunStart(run_id="r1", env_id=ENV, policy="weighted", seed=1, max_episodes=100, tc=195.0, r_floor=0.0,
                 workers=("w0",), session="s1", epoch=1, first_episode=5)


def algorithm(shape: RoundShape = PER_EPISODE) -> Algorithm2:
    env, learner = build_learner_and_env(ENV, seed=SEED, device_noise=1.0, init_seed=1)
    return Algorithm2("w0", env, learner, 195.0, SEED, shape=shape)


def identity(algo: Algorithm2, **changes: object) -> resume.Identity:
    fields = {"run_id": "r1", "worker_id": "w0", "env": ENV, "actor_spec": algo.actor_spec,
              "critic_spec": algo.learner.critic_spec(), **changes}
    return resume.Identity(**fields)  # type: ignore[arg-type]


def answer(algo: Algorithm2, sub: WorkerUpdate) -> ChiefAggregate:
    """The chief's answer of a one-worker federation: the worker's own gradients."""
    return ChiefAggregate(round=algo.round, episode=algo.episode, step=algo.step, gradient=sub.gradient,
                          critic_gradient=sub.critic_gradient, weights={"w0": 1.0}, contributors=("w0",))


def go_on(algo: Algorithm2, sub: WorkerUpdate | MatureParams | None, episodes: int) -> list[tuple]:
    """Answer ``sub`` (and the rest of its episode), then play ``episodes`` more; what each submission said."""
    seen: list[tuple] = []
    for _ in range(episodes + 1):
        sub = algo.play() if sub is None else sub
        while isinstance(sub, WorkerUpdate):
            seen.append((sub.episode, sub.step, sub.episode_return, sub.pi, digest(sub.gradient),
                         sub.receipt and sub.receipt.model_dump()))
            sub = algo.apply(answer(algo, sub))
    return seen


@pytest.mark.parametrize("per_step", [False, True])
def test_a_taken_up_state_goes_on_exactly(tmp_path: Path, per_step: bool) -> None:
    shape = RoundShape(per_episode=algorithm().learner.config.update_epochs) if per_step else PER_EPISODE
    before = algorithm(shape)
    go_on(before, None, 3)
    pending = before.play()
    assert isinstance(pending, WorkerUpdate)
    if per_step:  # stopped in the middle of an episode's rounds
        pending = before.apply(answer(before, pending))
        assert isinstance(pending, WorkerUpdate) and pending.step == 1
    path = resume.state_file(tmp_path, "r1", "w0")
    resume.save(path, identity(before), START, 0, before.state(), pending, {1, 2, 3})
    uninterrupted = go_on(before, pending, 4)

    after = algorithm(shape)  # a new process: fresh networks, fresh RNGs
    resumed = resume.load(path, identity(after), START)
    after.restore(resumed.algorithm)
    assert resumed.pending == pending and resumed.answered == {1, 2, 3}
    assert go_on(after, resumed.pending, 4) == uninterrupted
    resume.discard(path)
    assert not path.exists()


@pytest.mark.parametrize(("change", "says"), [
    ({"run_id": "r2"}, "run_id 'r1'"),
    ({"env": "Acrobot-v1"}, "env 'CartPole-v0'"),
    ({"actor_spec": {"net.0.weight": (3, 4)}}, "actor_spec"),
])
def test_a_state_of_another_run_or_network_is_refused(tmp_path: Path, change: dict, says: str) -> None:
    algo = algorithm()
    path = resume.state_file(tmp_path, "r1", "w0")
    resume.save(path, identity(algo), START, 0, algo.state(), None, set())
    with pytest.raises(resume.UnfitState, match=says):
        resume.load(path, identity(algo, **change), START)


@pytest.mark.parametrize(("session", "epoch"), [("s2", 1), ("s1", 0)])
def test_a_state_of_another_chief_session_or_a_later_epoch_is_refused(tmp_path: Path, session: str,
                                                                      epoch: int) -> None:
    algo = algorithm()
    path = resume.state_file(tmp_path, "r1", "w0")
    resume.save(path, identity(algo), START, 0, algo.state(), None, set())
    with pytest.raises(resume.UnfitState, match="not this run's last interruption"):
        resume.load(path, identity(algo), START.model_copy(update={"session": session, "epoch": epoch}))


def test_an_unreadable_state_is_refused(tmp_path: Path) -> None:
    path = resume.state_file(tmp_path, "r1", "w0")
    path.write_bytes(b"not a state")
    with pytest.raises(resume.UnfitState, match="not a readable worker state"):
        resume.load(path, identity(algorithm()), START)


def test_a_worker_joining_later_without_a_state_says_it_restarted() -> None:
    env, learner = build_learner_and_env(ENV, seed=SEED, device_noise=1.0, init_seed=1)
    algo = Algorithm2("w0", env, learner, 195.0, SEED, first_episode=5)
    sub = algo.play()
    assert sub.receipt is not None and sub.receipt.model_dump() == {"round": 4, "applied": "restarted", "digest": "",
                                                                   "keep": None, "episode": None}


def test_a_worker_whose_state_does_not_fit_refuses_to_start(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """The whole worker: a state saved in another chief session is one clear line and exit 7, and it stays on disk."""
    import threading
    import time

    from protocol import topics
    from protocol.codec import encode
    from protocol.memory import Hub
    from worker.service import EXIT_UNFIT_STATE, WorkerService
    from worker.settings import WorkerSettings

    algo = algorithm()
    path = resume.state_file(tmp_path, "r1", "w0")
    resume.save(path, identity(algo), START, 0, algo.state(), None, set())
    hub = Hub()
    svc = WorkerService(WorkerSettings.given(run_id="r1", worker_id="w0", state_dir=tmp_path), connect=hub.connect)
    chief = hub.connect("chief").start()
    codes: list[int] = []
    worker = threading.Thread(target=lambda: codes.append(svc.run()))
    worker.start()
    try:
        deadline = time.monotonic() + 60
        while worker.is_alive() and time.monotonic() < deadline:
            chief.publish(topics.chief("r1", topics.START), encode(START.model_copy(update={"session": "s2"})))
            worker.join(timeout=0.2)
    finally:
        chief.stop()
    assert codes == [EXIT_UNFIT_STATE] and path.exists()
    [line] = [r.getMessage() for r in caplog.records if "refusing to start" in r.getMessage()]
    assert "session 's1'" in line and "session 's2'" in line
