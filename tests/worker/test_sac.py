"""worker/sac.py: the pure math, seeding, the replay and state round trip, the per-step seams and the federation
hooks, for Box and Discrete actions (tiny networks: every test runs in well under a second)."""

from __future__ import annotations

import copy
import io
import math

import numpy as np
import pytest
import torch
from gymnasium import spaces

from worker.sac import (
    SACConfig,
    SACLearner,
    colored_noise,
    polyak_update,
    soft_q_target,
    soft_state_value,
    temperature_loss,
)

OBS = spaces.Box(-1.0, 1.0, (3,), dtype=np.float32)
SPACES = {"box": spaces.Box(-2.0, 2.0, (1,), dtype=np.float32), "discrete": spaces.Discrete(3)}
TINY = {"hidden_sizes": (16,), "batch_size": 8, "learning_starts": 8, "replay_size": 32, "update_epochs": 3}


def learner(kind: str, seed: int = 0, **over: object) -> SACLearner:
    return SACLearner(OBS, SPACES[kind], SACConfig(**{**TINY, **over}), seed=seed)  # type: ignore[arg-type]


def fill(sac: SACLearner, n: int, seed: int = 5, reward: float = 1.0) -> None:
    rng = np.random.default_rng(seed)
    obs = rng.uniform(-1, 1, 3).astype(np.float32)
    for i in range(n):
        nxt = rng.uniform(-1, 1, 3).astype(np.float32)
        sac.remember(obs, sac.act(obs), reward, nxt, terminated=i % 7 == 6, truncated=False)
        obs = nxt


def params(sac: SACLearner) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in [*sac.actor.state_dict().items(), *sac.critic.state_dict().items()]}


def same(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_the_soft_target_bootstraps_through_a_truncation_but_not_a_termination() -> None:
    r, v = torch.tensor([1.0, 1.0]), torch.tensor([10.0, 10.0])
    assert soft_q_target(r, v, torch.tensor([False, True]), 0.9).tolist() == [10.0, 1.0]


def test_the_discrete_soft_value_is_the_exact_expectation() -> None:
    q1, q2 = torch.tensor([[1.0, 4.0]]), torch.tensor([[2.0, 3.0]])
    probs = torch.tensor([[0.25, 0.75]])
    value = soft_state_value(q1, q2, probs.log(), 0.5, probs)
    expected = 0.25 * (1.0 - 0.5 * math.log(0.25)) + 0.75 * (3.0 - 0.5 * math.log(0.75))
    assert value.item() == pytest.approx(expected)


def test_the_temperature_grows_while_the_entropy_is_below_its_target() -> None:
    log_alpha = torch.zeros((), requires_grad=True)
    temperature_loss(log_alpha, torch.tensor([2.0]), target_entropy=-1.0).backward()  # entropy -2 < target -1
    assert log_alpha.grad is not None and log_alpha.grad.item() < 0  # gradient descent raises log alpha
    log_alpha.grad = None
    temperature_loss(log_alpha, torch.tensor([0.5]), target_entropy=-1.0).backward()  # entropy -0.5 > target -1
    assert log_alpha.grad is not None and log_alpha.grad.item() > 0


def test_polyak_moves_the_target_by_tau() -> None:
    target, source = [torch.zeros(2)], [torch.ones(2)]
    polyak_update(target, source, 0.25)
    assert target[0].tolist() == [0.25, 0.25]


def test_an_invalid_config_is_one_error_listing_every_problem() -> None:
    with pytest.raises(ValueError, match=r"invalid SACConfig: .*tau.*"):
        SACConfig(tau=2.0)
    with pytest.raises(ValueError, match="unknown SACConfig keys"):
        SACConfig.from_dict({"clip_epsilon": 0.2})


@pytest.mark.parametrize("kind", SPACES)
def test_the_same_seed_and_transitions_give_the_same_parameters_and_the_global_rng_is_untouched(kind: str) -> None:
    torch.manual_seed(123)
    before = torch.random.get_rng_state()
    a, b = learner(kind, seed=4), learner(kind, seed=4)
    for sac in (a, b):
        fill(sac, 20)
        stats = sac.update()
        assert stats.memory_size == 20 and stats.skipped_steps == 0
    assert same(params(a), params(b))
    assert torch.equal(torch.random.get_rng_state(), before)
    assert not same(params(a), params(learner(kind, seed=5)))


@pytest.mark.parametrize("kind", SPACES)
def test_nothing_is_learned_before_learning_starts(kind: str) -> None:
    sac = learner(kind, learning_starts=30)
    start = params(sac)
    fill(sac, 20)
    sac.update()
    assert same(params(sac), start)
    assert all(not g.any() for g in sac.actor_gradient().values())  # zeros: nothing to share yet


@pytest.mark.parametrize("kind", SPACES)
def test_a_learner_restored_from_its_state_and_replay_goes_on_bit_for_bit(kind: str) -> None:
    a = learner(kind, seed=2)
    fill(a, 40)  # more than the replay holds: the oldest transitions have dropped out
    a.update()
    fill(a, 5, seed=9)
    data = io.BytesIO()
    torch.save({"state": a.state_dict(), "memory": a.memory_state()}, data)  # through a file, as a worker saves
    data.seek(0)
    saved = torch.load(data, weights_only=True)
    b = learner(kind, seed=99)
    b.load_state_dict(saved["state"])
    b.load_memory(saved["memory"])
    a.update()
    b.update()
    assert same(params(a), params(b))


@pytest.mark.parametrize("kind", SPACES)
def test_a_per_step_episode_with_its_own_gradients_steps_each_network(kind: str) -> None:
    sac = learner(kind, seed=3)
    fill(sac, 20)
    twin = copy.deepcopy(sac)
    batch = sac.prepare()
    for _ in range(sac.config.update_epochs):
        step = sac.minibatch_gradients(batch)
        assert step.actor is not None and step.critic is not None
        assert set(step.actor) == set(sac.actor_spec()) and set(step.critic) == set(sac.critic_spec())
        sac.apply_step(step.critic, step.actor)
    assert not same(params(sac), params(twin))
    # the shared mean of identical workers is each one's own step: a twin applying the same gradients agrees
    batch2 = twin.prepare()
    for _ in range(twin.config.update_epochs):
        step = twin.minibatch_gradients(batch2)
        twin.apply_step(step.critic, step.actor)
    assert same(params(sac), params(twin))


@pytest.mark.parametrize("kind", SPACES)
def test_the_federation_hooks(kind: str) -> None:
    sac = learner(kind)
    with pytest.raises(RuntimeError):
        sac.actor_gradient()
    fill(sac, 20)
    sac.update()
    grad = sac.actor_gradient()
    assert {k: v.shape for k, v in grad.items()} == sac.actor_spec()
    before = sac.actor_parameters()
    sac.apply_gradient(grad)
    assert any(not np.array_equal(before[k], v) for k, v in sac.actor_parameters().items())
    other = {k: np.zeros_like(v) for k, v in before.items()}
    with pytest.raises(ValueError, match="keep_weight"):
        sac.blend_actor(other, 1.5)
    theta = sac.actor_parameters()
    sac.blend_actor(other, 0.25)  # Eq. 11: 0.25 theta + 0.75 * 0
    for k, v in sac.actor_parameters().items():
        np.testing.assert_allclose(v, 0.25 * theta[k], rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("kind", SPACES)
def test_actions_fit_the_space(kind: str) -> None:
    sac = learner(kind)
    obs = np.zeros(3, np.float32)
    for action in (sac.act(obs), sac.act_greedy(obs)):
        assert SPACES[kind].contains(action)


@pytest.mark.parametrize("length", [999, 1000])
def test_coloured_noise_has_unit_variance_and_its_colour_sets_the_correlation_in_time(length: int) -> None:
    lag1 = {}
    for beta in (0.0, 1.0, 2.0):
        x = colored_noise(beta, (400, length), torch.Generator().manual_seed(0))
        assert x.shape == (400, length) and x.dtype == torch.float32
        assert abs(float(x.var()) - 1.0) < 0.05  # the marginal is the policy's N(0, 1) whatever the colour
        lag1[beta] = float((x[:, 1:] * x[:, :-1]).mean() / x.var())
    assert abs(lag1[0.0]) < 0.02 and 0.7 < lag1[1.0] < 0.85 and lag1[2.0] > 0.99  # white, pink (~0.78), red
    again = colored_noise(1.0, (400, length), torch.Generator().manual_seed(0))
    assert torch.equal(again, colored_noise(1.0, (400, length), torch.Generator().manual_seed(0)))


def test_coloured_acting_noise_is_correlated_within_an_episode_and_redrawn_for_the_next() -> None:
    obs = np.zeros(3, np.float32)
    white, pink = learner("box", seed=4), learner("box", seed=4, noise_beta=1.0, noise_horizon=64)
    twin = torch.Generator().set_state(white.generator.get_state())
    with torch.no_grad():
        mean, std = white.actor.gaussian(white._obs_tensor(obs))
    expected = 2.0 * torch.tanh(mean + std * torch.randn(mean.shape, generator=twin))  # the Box is [-2, 2]
    assert float(white.act(obs)[0]) == pytest.approx(float(expected[0, 0]), abs=1e-6)  # beta 0: a fresh draw a step

    def episode(sac: SACLearner, n: int) -> np.ndarray:
        acts = np.array([float(sac.act(obs)[0]) for _ in range(n)])
        sac.remember(obs, acts[-1:].astype(np.float32), 0.0, obs, terminated=False, truncated=True)
        return acts

    corr = {name: np.corrcoef(a[1:], a[:-1])[0, 1]
            for name, a in (("white", episode(white, 200)), ("pink", episode(pink, 200)))}
    assert abs(corr["white"]) < 0.2 and corr["pink"] > 0.4  # 200 actions outlast one 64-step sequence: redrawn
    first, second = episode(pink, 20), episode(pink, 20)
    assert not np.allclose(first, second)  # a truncation ends the sequence: the next episode has its own noise
    assert all(SPACES["box"].contains(np.float32([a])) for a in first)


@pytest.mark.parametrize("bad", ["reward", "obs", "next_obs", "action"])
def test_a_non_finite_transition_never_enters_the_replay(bad: str) -> None:
    """A NaN in the replay would poison every mini-batch that draws it: remember refuses it and counts it."""
    sac = learner("box")
    fill(sac, 10)
    good = dict(obs=np.zeros(3, np.float32), action=np.zeros(1, np.float32), reward=0.5,
                next_obs=np.zeros(3, np.float32))
    nan = {"reward": math.nan, "action": np.array([math.nan], np.float32)}.get(bad, np.full(3, math.nan, np.float32))
    sac.remember(**{**good, bad: nan}, terminated=False, truncated=False)  # type: ignore[arg-type]
    assert sac.memory_size == 10 and sac.rejected_transitions == 1
    assert all(torch.isfinite(v).all() for k, v in sac.memory_state().items() if k != "pending")
    fill(sac, 5, seed=7)
    stats = sac.update()
    assert stats.gradient_steps > 0 and stats.skipped_steps == 0
    assert all(torch.isfinite(p).all() for p in [*sac.critic.parameters(), *sac.actor.parameters()])


def test_an_episode_of_only_non_finite_rewards_takes_no_step() -> None:
    sac = learner("box", learning_starts=0)
    start = params(sac)
    fill(sac, 20, reward=float("nan"))
    assert sac.memory_size == 0 and sac.rejected_transitions == 20
    assert sac.update().gradient_steps == 0
    assert same(params(sac), start)


@pytest.mark.parametrize("kind", SPACES)
def test_per_step_rounds_before_learning_starts_step_nothing(kind: str) -> None:
    """Under ``sync`` the K rounds of an episode come whatever the replay holds: before ``learning_starts`` each
    worker shares zeros, and the chief's mean of zeros (or no answer, its own None) moves no network, no Adam state,
    no target critic and no temperature."""
    sac = learner(kind, learning_starts=30)
    fill(sac, 20)
    start, target, alpha = params(sac), copy.deepcopy(sac.target_critic.state_dict()), sac.alpha
    batch = sac.prepare()
    for _ in range(sac.config.update_epochs):
        step = sac.minibatch_gradients(batch)
        assert step.actor is None and step.critic is None
        zeros = ({k: np.zeros(s, np.float32) for k, s in sac.critic_spec().items()},
                 {k: np.zeros(s, np.float32) for k, s in sac.actor_spec().items()})
        sac.apply_step(*zeros)  # the chief's mean when every worker shared zeros
        sac.apply_step(step.critic, step.actor)  # no answer: the worker's own step
    assert same(params(sac), start) and same(sac.target_critic.state_dict(), target) and sac.alpha == alpha
    assert not sac.actor_optimizer.state and not sac.critic_optimizer.state
    fill(sac, 10)
    step = sac.minibatch_gradients(sac.prepare())  # 30 transitions: learning starts
    assert step.actor is not None and step.critic is not None
