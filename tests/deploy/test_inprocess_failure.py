"""A worker that fails in process (its env raises, as a rig that cannot reset does) leaves the federation: the
others learn on to their result, and the run then ends as aborted with its summary, instead of waiting forever for
a worker nothing will restart."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import pytest

import worker.episode
from chief.audit import audit
from deploy.inprocess import run_federation
from deploy.settings import InprocessSettings
from protocol.tasks import worker_seed

ENV, POLICY, SEED, WORKERS, EPISODES = "CartPole-v0", "plain", 5, 3, 300
BROKEN = 1  # worker w1's env fails at the reset of its episode FAIL_AT
FAIL_AT = 4


class FailingReset(gym.Wrapper):
    """An env whose reset raises from its ``fail_at``-th call on (a rig that can no longer swing up)."""

    def __init__(self, env: gym.Env, fail_at: int) -> None:
        super().__init__(env)
        self.resets, self.fail_at = 0, fail_at

    def reset(self, **kwargs: Any) -> Any:
        self.resets += 1
        if self.resets >= self.fail_at:
            raise RuntimeError("the rig could not reset")
        return self.env.reset(**kwargs)


@pytest.fixture
def broken_worker(monkeypatch: pytest.MonkeyPatch) -> None:
    real = worker.episode.make_env

    def make_env(env_id: str, seed: int, *args: Any, **kwargs: Any) -> gym.Env:
        env = real(env_id, seed, *args, **kwargs)
        return FailingReset(env, FAIL_AT) if seed == worker_seed(SEED, BROKEN) else env

    monkeypatch.setattr(worker.episode, "make_env", make_env)


@pytest.mark.slow
def test_a_failed_worker_ends_the_run_as_aborted_once_the_others_are_done(broken_worker: None, tmp_path: Path
                                                                          ) -> None:
    run_dir = tmp_path / "run"
    summary = run_federation(InprocessSettings.given(env=ENV, policy=POLICY, seed=SEED, workers=WORKERS,
                             max_episodes=EPISODES, run_dir=run_dir), plot=False, tensorboard_files=False,
                             tolerate_failures=True)
    by_id = {w.id: w for w in summary.workers}
    assert not by_id["w1"].solved and by_id["w1"].episodes == FAIL_AT - 1 and by_id["w1"].state == "offline"
    assert by_id["w0"].solved and by_id["w2"].solved  # the others learned on to their end
    assert summary.end_reason.startswith("aborted") and summary.episodes_to_all_solved is None
    audit(run_dir)


@pytest.mark.slow
def test_a_gradient_step_past_the_protocols_norm_limit_is_skipped_and_the_run_goes_on(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """An honest learner whose gradient blows up past NORM_LIMIT (a PPO policy whose entropy collapsed: seen in a QUBE
    pretrain at round 550) skips that step, as it skips a non-finite one. Sent, the chief refuses it, and a lockstep
    round without timeouts waits for that worker forever (the pretrain hung)."""
    import json

    from worker.federation import FederatedLearner

    real = FederatedLearner._gradients
    calls = {"n": 0, "blown": 0}

    def blowing_up(self: FederatedLearner, loss: Any, net: Any) -> Any:
        calls["n"] += 1
        if calls["n"] % 7 == 0:  # now and then, a finite loss whose gradient is far past the limit
            calls["blown"] += 1
            loss = loss * 1e12
        return real(self, loss, net)

    monkeypatch.setattr(FederatedLearner, "_gradients", blowing_up)
    run_dir = tmp_path / "run"
    summary = run_federation(InprocessSettings.given(env=ENV, policy=POLICY, seed=SEED, workers=2, max_episodes=6,
                                                     run_dir=run_dir), plot=False, tensorboard_files=False)
    assert calls["blown"] > 3 and summary.end_reason.startswith("reached the maximum")
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert not [r for r in records if r["type"] == "refused"]
    audit(run_dir)
