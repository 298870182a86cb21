"""worker/dqn.py: the n-step return and the Double DQN target against hand numbers, the n-step window, learning only
from learning_starts on, refused non-finite transitions, the federation hooks and the state round trip (tiny
networks: every test runs in well under a second)."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
import torch
from gymnasium import spaces

from worker.dqn import DQNConfig, DQNLearner, double_q_target, epsilon, n_step_return, td_loss

OBS = spaces.Box(-1.0, 1.0, (3,), dtype=np.float32)
TINY = {"hidden_sizes": (16,), "batch_size": 8, "learning_starts": 8, "replay_size": 32, "update_epochs": 3,
        "n_step": 3, "gamma": 0.5, "target_update_interval": 2}


def learner(seed: int = 0, **over: object) -> DQNLearner:
    return DQNLearner(OBS, spaces.Discrete(2), DQNConfig(**{**TINY, **over}), seed=seed)  # type: ignore[arg-type]


def play(dqn: DQNLearner, n: int, seed: int = 5, reward: float = 1.0, end_every: int = 7) -> None:
    rng = np.random.default_rng(seed)
    obs = rng.uniform(-1, 1, 3).astype(np.float32)
    for i in range(n):
        nxt = rng.uniform(-1, 1, 3).astype(np.float32)
        dqn.remember(obs, dqn.act(obs), reward, nxt, terminated=i % end_every == end_every - 1, truncated=False)
        obs = nxt


def test_n_step_return_and_double_q_target_by_hand() -> None:
    assert n_step_return([1.0, 2.0, 4.0], 0.5) == (1.0 + 1.0 + 1.0, 0.125)
    online = torch.tensor([[1.0, 3.0], [5.0, 2.0]])  # the online network picks action 1, then action 0
    target = torch.tensor([[10.0, 20.0], [30.0, 40.0]])  # the target network values them: 20 and 30
    y = double_q_target(torch.tensor([1.0, 2.0]), torch.tensor([0.25, 0.5]), torch.tensor([False, True]), online,
                        target)
    assert torch.allclose(y, torch.tensor([1.0 + 0.25 * 20.0, 2.0]))  # a termination cuts the bootstrap
    assert td_loss(torch.tensor([0.0, 3.0]), torch.tensor([0.5, 0.0])).item() == pytest.approx((0.125 + 2.5) / 2)
    cfg = DQNConfig(eps_start=1.0, eps_end=0.1, eps_decay_steps=10)
    assert [epsilon(cfg, s) for s in (0, 5, 10, 50)] == pytest.approx([1.0, 0.55, 0.1, 0.1])


def test_the_window_stores_n_step_transitions_and_flushes_at_the_episode_end() -> None:
    dqn = learner(gamma=0.5, n_step=3)
    obs = [np.full(3, i / 10, np.float32) for i in range(5)]
    for i in range(4):
        dqn.remember(obs[i], 0, 1.0, obs[i + 1], terminated=i == 3, truncated=False)
    replay = dqn.replay  # columns: s_t, a_t, R_t^(m), s_{t+m}, terminated, gamma^m
    assert len(replay) == 4 and dqn.memory_size == 4
    first = replay[0]  # s0, rewards r1 r2 r3, bootstraps from s3 with gamma^3
    assert np.array_equal(first[0], obs[0]) and np.array_equal(first[3], obs[3])
    assert first[2] == pytest.approx(1.75) and first[5] == 0.125 and not first[4]
    last = replay[-1]  # s3: one reward, then the termination
    assert np.array_equal(last[3], obs[4]) and last[2] == 1.0 and last[5] == 0.5 and last[4]


def test_nothing_is_learned_before_learning_starts_and_then_it_learns() -> None:
    dqn = learner(learning_starts=30)
    start = dqn.actor_parameters()
    play(dqn, 20)
    stats = dqn.update()
    assert stats.skipped_steps == 0 and all(np.array_equal(v, start[k]) for k, v in dqn.actor_parameters().items())
    assert all(not g.any() for g in dqn.actor_gradient().values())
    batch = dqn.prepare()
    step = dqn.minibatch_gradients(batch)
    assert step.actor is None and step.critic == {}
    dqn.apply_step({}, {k: np.zeros_like(v) for k, v in start.items()})  # sync's mean of zeros: no step
    assert dqn.gradient_steps == 0 and not dqn.actor_optimizer.state
    play(dqn, 20, seed=6)
    dqn.update()
    assert dqn.gradient_steps > 0 and any(not np.array_equal(v, start[k]) for k, v in dqn.actor_parameters().items())
    assert all(torch.equal(a, b) for a, b in zip(dqn.target.state_dict().values(),
                                                 dqn.actor.state_dict().values(), strict=True)) \
        == (dqn.gradient_steps % 2 == 0)  # a copy every target_update_interval = 2 steps


def test_a_non_finite_transition_never_enters_the_replay() -> None:
    dqn = learner()
    play(dqn, 10)
    size = dqn.memory_size
    dqn.remember(np.zeros(3, np.float32), 0, math.nan, np.zeros(3, np.float32), terminated=True, truncated=False)
    assert dqn.memory_size == size and dqn.rejected_transitions == 1
    assert all(math.isfinite(t) for t in dqn.replay.ordered()["returns"])


def test_the_hooks_and_a_state_round_trip_go_on_bit_for_bit() -> None:
    a = learner(seed=2)
    play(a, 42)  # more than the replay holds; ends with an episode (a resumed worker starts a new one)
    a.update()
    grad = a.actor_gradient()
    assert {k: v.shape for k, v in grad.items()} == a.actor_spec() and a.critic_spec() == {}
    with pytest.raises(ValueError, match="keep_weight"):
        a.blend_actor(a.actor_parameters(), 1.5)
    data = io.BytesIO()
    torch.save({"state": a.state_dict(), "memory": a.memory_state()}, data)
    data.seek(0)
    saved = torch.load(data, weights_only=True)
    b = learner(seed=99)
    b.load_state_dict(saved["state"])
    b.load_memory(saved["memory"])
    play(a, 6, seed=9)
    play(b, 6, seed=9)
    a.update()
    b.update()
    assert all(np.array_equal(v, b.actor_parameters()[k]) for k, v in a.actor_parameters().items())
    with pytest.raises(ValueError, match="Discrete"):
        DQNLearner(OBS, spaces.Box(-1.0, 1.0, (1,)))
