"""worker.ppo: the paper's PPO math against hand numbers, the learner's federation hooks, reproducibility."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from gymnasium import spaces

from protocol.messages import ChiefAggregate
from protocol.tensors import pack_arrays
from worker.envs import make_env
from worker.federated import Algorithm2
from worker.ppo import PPOConfig, PPOLearner, clipped_surrogate_loss, compute_gae, value_loss
from worker.train_local import train

torch.set_num_threads(1)

CARTPOLE_OBS = spaces.Box(-np.inf, np.inf, (4,), np.float32)
PENDULUM_OBS = spaces.Box(-8.0, 8.0, (3,), np.float32)
TORQUE = spaces.Box(-2.0, 2.0, (1,), np.float32)


def fill(learner: PPOLearner, n: int, seed: int = 0, episode_len: int = 50) -> None:
    """Remember ``n`` synthetic transitions: episodes of ``episode_len`` steps ending in a termination."""
    rng = np.random.default_rng(seed)
    obs = rng.normal(size=learner.obs_shape).astype(np.float32)
    for t in range(n):
        action = learner.act(obs)
        next_obs = rng.normal(size=learner.obs_shape).astype(np.float32)
        terminated = (t + 1) % episode_len == 0
        learner.remember(obs, action, float(rng.normal()), next_obs, terminated, False)
        obs = rng.normal(size=learner.obs_shape).astype(np.float32) if terminated else next_obs


def actor_state(learner: PPOLearner) -> dict[str, np.ndarray]:
    return learner.actor_parameters()


def assert_same(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    assert a.keys() == b.keys()
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


# -- Eq. 2: GAE ---------------------------------------------------------------------------------------------


def test_gae_hand_computed_with_termination_and_truncation() -> None:
    # gamma = lam = 0.5, so gamma * lam = 0.25. Two episodes in the memory:
    #   t0: r=1, V(s0)=0.5, V(s1)=1.0                       delta0 = 1 + 0.5*1.0 - 0.5 = 1.0
    #   t1: r=3, V(s1)=1.0, terminated (V(s2') would be 2.0, ignored: next value 0)
    #                                                        delta1 = 3 + 0 - 1.0 = 2.0
    #   t2: r=0, V(s2)=1.0, V(s3)=2.0 (new episode)          delta2 = 0 + 0.5*2.0 - 1.0 = 0.0
    #   t3: r=1, V(s3)=2.0, truncated: bootstrap V(s4)=4.0   delta3 = 1 + 0.5*4.0 - 2.0 = 1.0
    # Backwards, resetting after each episode end:
    #   A3 = 1.0;  A2 = 0.0 + 0.25*1.0 = 0.25;  A1 = 2.0 (terminated: no A2 term);  A0 = 1.0 + 0.25*2.0 = 1.5
    # returns = A + V = [2.0, 3.0, 1.25, 3.0]
    adv, ret = compute_gae(
        rewards=np.array([1.0, 3.0, 0.0, 1.0]),
        values=np.array([0.5, 1.0, 1.0, 2.0]),
        next_values=np.array([1.0, 2.0, 2.0, 4.0]),
        terminated=np.array([False, True, False, False]),
        episode_end=np.array([False, True, False, True]),
        gamma=0.5,
        lam=0.5,
    )
    np.testing.assert_allclose(adv, [1.5, 2.0, 0.25, 1.0])
    np.testing.assert_allclose(ret, [2.0, 3.0, 1.25, 3.0])


def test_gae_lambda_zero_gives_eq3_td_target() -> None:
    # lam = 0: A_t = delta_t and the return is r + gamma * V(s') (Eq. 3's target): 1 + 0.9 * 2 = 2.8
    adv, ret = compute_gae(np.array([1.0]), np.array([0.5]), np.array([2.0]), np.array([False]),
                           np.array([True]), gamma=0.9, lam=0.0)
    np.testing.assert_allclose(ret, [2.8])
    np.testing.assert_allclose(adv, [2.3])


# -- Eq. 6 and Eq. 3 ----------------------------------------------------------------------------------------


def test_clipped_surrogate_hand_numbers_and_gradients() -> None:
    # eps = 0.2, old log-prob 0, so ratio = exp(new_logp):
    #   ratio 1.1, A=+2 (inside):          min(2.2, 2.2)  =  2.2  gradient flows
    #   ratio 1.5, A=+1 (above 1+eps):     min(1.5, 1.2)  =  1.2  clipped, no gradient
    #   ratio 0.5, A=-1 (below 1-eps):     min(-0.5, -0.8) = -0.8  clipped, no gradient
    #   ratio 1.5, A=-1 (above, A < 0):    min(-1.5, -1.2) = -1.5  unclipped term, gradient flows
    #   ratio 0.5, A=+1 (below, A > 0):    min(0.5, 0.8)  =  0.5  unclipped term, gradient flows
    # L^CLIP = (2.2 + 1.2 - 0.8 - 1.5 + 0.5) / 5 = 0.32, loss = -0.32
    ratios = torch.tensor([1.1, 1.5, 0.5, 1.5, 0.5], dtype=torch.float64)
    new_logp = ratios.log().requires_grad_(True)
    advantages = torch.tensor([2.0, 1.0, -1.0, -1.0, 1.0], dtype=torch.float64)
    loss = clipped_surrogate_loss(new_logp, torch.zeros(5, dtype=torch.float64), advantages, clip=0.2)
    assert loss.item() == pytest.approx(-0.32)
    loss.backward()
    # d(-L)/d logp_i = -(1/5) * ratio_i * A_i where the unclipped term is the minimum, else 0
    np.testing.assert_allclose(new_logp.grad.numpy(), [-0.44, 0.0, 0.0, 0.3, -0.1], atol=1e-12)


def test_value_loss_variants() -> None:
    # errors 1, 0, -2: L1 = 3/3 = 1; MSE = (1 + 0 + 4)/3; Huber(delta 1) = (0.5 + 0 + 1.5)/3
    values, targets = torch.tensor([1.0, 2.0, 3.0]), torch.tensor([2.0, 2.0, 1.0])
    assert value_loss(values, targets, "l1").item() == pytest.approx(1.0)
    assert value_loss(values, targets, "mse").item() == pytest.approx(5 / 3)
    assert value_loss(values, targets, "huber").item() == pytest.approx(2 / 3)
    with pytest.raises(ValueError):
        value_loss(values, targets, "l2")


def test_config_defaults_are_the_papers_and_validation() -> None:
    cfg = PPOConfig()
    assert (cfg.hidden_sizes, cfg.actor_lr, cfg.critic_lr) == ((128, 128, 128), 1e-3, 1e-3)
    assert (cfg.memory_size, cfg.batch_size, cfg.update_epochs, cfg.gae_lambda) == (400, 128, 10, 0.99)
    assert cfg.value_loss == "l1" and cfg.clip_epsilon == 0.2
    with pytest.raises(ValueError, match="clip_epsilon"):
        PPOConfig(clip_epsilon=0.0)
    with pytest.raises(ValueError, match="value_loss"):
        PPOConfig(value_loss="l2")


# -- actors -------------------------------------------------------------------------------------------------


def test_categorical_actor_actions_and_log_probs() -> None:
    learner = PPOLearner(CARTPOLE_OBS, spaces.Discrete(2), seed=0)
    obs = np.zeros(4, np.float32)
    actions = {int(learner.act(obs)) for _ in range(50)}
    assert actions == {0, 1}
    assert isinstance(learner.act(obs), np.integer) and learner.act_greedy(obs) in (0, 1)
    batch = torch.zeros(2, 4)
    logp0, ent = learner.actor.log_prob_entropy(batch, torch.tensor([0, 0]))
    logp1, _ = learner.actor.log_prob_entropy(batch, torch.tensor([1, 1]))
    assert torch.all(logp0 <= 0) and torch.allclose(logp0.exp() + logp1.exp(), torch.ones(2))
    assert torch.all(ent > 0) and torch.all(ent <= math.log(2) + 1e-6)


def test_gaussian_actor_raw_samples_and_log_probs() -> None:
    learner = PPOLearner(PENDULUM_OBS, TORQUE, PPOConfig(log_std_init=1.5), seed=0)
    obs = np.zeros(3, np.float32)
    samples = np.array([learner.act(obs) for _ in range(200)])
    assert samples.shape == (200, 1) and samples.dtype == np.float32
    assert np.abs(samples).max() > 2.0  # raw samples: not clipped to the space (the env does that)
    assert learner.act_greedy(obs).shape == (1,)
    # initial mean is ~0 (head gain 0.01, zero bias), std = e^1.5: compare with the Normal density
    mean = learner.actor(torch.zeros(1, 3))[0, 0].item()
    logp, ent = learner.actor.log_prob_entropy(torch.zeros(1, 3), torch.tensor([[0.7]]))
    std = math.exp(1.5)
    expected = -((0.7 - mean) ** 2) / (2 * std**2) - math.log(std) - 0.5 * math.log(2 * math.pi)
    assert logp.item() == pytest.approx(expected, rel=1e-5)
    assert ent.item() == pytest.approx(0.5 + 0.5 * math.log(2 * math.pi) + 1.5, rel=1e-5)
    assert "log_std" in learner.actor_spec()


# -- the learner --------------------------------------------------------------------------------------------


def test_fifo_memory_caps_at_400() -> None:
    learner = PPOLearner(CARTPOLE_OBS, spaces.Discrete(2), seed=0)
    for t in range(450):
        learner.remember(np.full(4, t, np.float32), 0, 1.0, np.full(4, t + 1, np.float32), False, False)
    assert len(learner.memory) == 400
    assert learner.memory[0][0][0] == 50.0 and learner.memory[-1][0][0] == 449.0  # the oldest 50 dropped out


def test_seeded_learners_are_reproducible() -> None:
    def run(seed: int) -> dict[str, np.ndarray]:
        learner = PPOLearner(CARTPOLE_OBS, spaces.Discrete(2), seed=seed)
        fill(learner, 300)
        learner.update()
        critic = {f"critic.{k}": v.numpy() for k, v in learner.critic.state_dict().items()}
        return actor_state(learner) | critic

    torch.manual_seed(123)  # the global RNG must not matter
    first = run(7)
    torch.manual_seed(456)
    assert_same(first, run(7))
    assert not np.array_equal(first["net.0.weight"], run(8)["net.0.weight"])


def test_update_and_episode_gradient_is_the_mean_of_the_k_actor_gradients() -> None:
    learner = PPOLearner(PENDULUM_OBS, TORQUE, PPOConfig(update_epochs=3, batch_size=32), seed=1)
    with pytest.raises(RuntimeError):
        learner.actor_gradient()
    fill(learner, 100)
    captured: list[dict[str, torch.Tensor]] = []
    step = learner.actor_optimizer.step

    def spy_step(*args, **kwargs):  # records each applied actor gradient
        captured.append({n: p.grad.clone() for n, p in learner.actor.named_parameters()})
        return step(*args, **kwargs)

    learner.actor_optimizer.step = spy_step
    stats = learner.update()
    assert len(captured) == 3 and stats.memory_size == 100 and stats.skipped_steps == 0
    assert all(math.isfinite(v) for v in (stats.actor_loss, stats.critic_loss, stats.entropy))
    grad = learner.actor_gradient()
    assert {k: v.shape for k, v in grad.items()} == learner.actor_spec()
    for name, g in grad.items():
        assert g.dtype == np.float32
        np.testing.assert_allclose(g, sum(c[name] for c in captured).numpy() / 3, rtol=1e-5, atol=1e-7)


def test_apply_gradient_takes_one_adam_step() -> None:
    learner = PPOLearner(CARTPOLE_OBS, spaces.Discrete(2), seed=0)
    before = actor_state(learner)
    learner.apply_gradient({k: np.ones(s, np.float32) for k, s in learner.actor_spec().items()})
    # Adam's first step with a constant gradient moves every parameter by -lr (bias-corrected m / sqrt(v) = 1)
    for name, value in actor_state(learner).items():
        np.testing.assert_allclose(value, before[name] - 1e-3, atol=1e-6)


def test_blend_rejects_a_keep_weight_outside_0_1_without_changing_anything() -> None:
    learner = PPOLearner(PENDULUM_OBS, TORQUE, seed=0)
    before = actor_state(learner)
    good = {k: np.zeros(s, np.float32) for k, s in learner.actor_spec().items()}
    for keep in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="keep_weight"):
            learner.blend_actor(good, keep)
    assert_same(before, actor_state(learner))


def test_an_answer_that_does_not_fit_the_actor_is_refused_without_changing_anything() -> None:
    """The worker checks the chief's tensors against its networks where they come in (Algorithm2.apply); the
    learner's API takes the arrays as they are."""
    env = make_env("Pendulum-v1", seed=0)
    learner = PPOLearner(PENDULUM_OBS, TORQUE, seed=0)
    algo = Algorithm2("w0", env, learner, tc=-400.0, seed=0)
    algo.play()  # an episode and its PPO update
    before = actor_state(learner)
    steps = [float(state["step"]) for state in learner.actor_optimizer.state.values()]
    spec = learner.actor_spec()
    first = next(iter(spec))
    good = {k: np.zeros(s, np.float32) for k, s in spec.items()}
    missing = {k: v for k, v in good.items() if k != first}
    for bad, what in ((good | {first: np.zeros((3, 3), np.float32)}, "shape"), (missing, first),
                      (good | {"extra": np.zeros(1, np.float32)}, "extra")):
        answer = ChiefAggregate(round=1, episode=1, gradient=pack_arrays(bad), weights={"w0": 1.0},
                                contributors=("w0",))
        assert algo.apply(answer) is None
        assert algo.receipt is not None and algo.receipt.applied == "missed"
        assert algo.refused_answer is not None and what in algo.refused_answer, algo.refused_answer
        assert_same(before, actor_state(learner))
    assert [float(state["step"]) for state in learner.actor_optimizer.state.values()] == steps  # no Adam step
    env.close()


def test_blend_actor_eq11_with_keep_quarter() -> None:
    learner = PPOLearner(CARTPOLE_OBS, spaces.Discrete(2), seed=0)
    mature = PPOLearner(CARTPOLE_OBS, spaces.Discrete(2), seed=1).actor_parameters()
    theta = actor_state(learner)
    learner.blend_actor(mature, keep_weight=0.25)  # theta = 0.25 * theta + 0.75 * theta_bar
    for name, value in actor_state(learner).items():
        np.testing.assert_allclose(value, 0.25 * theta[name] + 0.75 * mature[name], rtol=1e-6, atol=1e-7)
    # a worked scalar: 0.25 * 4 + 0.75 * 8 = 7
    ones = {k: np.full(s, 4.0, np.float32) for k, s in learner.actor_spec().items()}
    eights = {k: np.full(s, 8.0, np.float32) for k, s in learner.actor_spec().items()}
    learner.blend_actor(ones, 0.0)
    learner.blend_actor(eights, 0.25)
    assert all(np.all(v == 7.0) for v in actor_state(learner).values())


def test_save_and_load_roundtrip(tmp_path) -> None:
    learner = PPOLearner(PENDULUM_OBS, TORQUE, PPOConfig(normalize_obs=True), seed=3)
    fill(learner, 200)
    learner.update()
    path = tmp_path / "learner.pt"
    learner.save(path)
    other = PPOLearner(PENDULUM_OBS, TORQUE, PPOConfig(normalize_obs=True), seed=99)
    other.load(path)
    assert_same(actor_state(learner), actor_state(other))
    torch.testing.assert_close(other.obs_norm.mean, learner.obs_norm.mean)
    obs = np.ones(3, np.float32)
    np.testing.assert_array_equal(learner.act(obs), other.act(obs))  # the sampling generator is restored too
    with pytest.raises(ValueError, match="architecture"):
        PPOLearner(PENDULUM_OBS, TORQUE, PPOConfig(hidden_sizes=(64, 64)), seed=0).load(path)


def test_short_learning_run_cartpole_reaches_tc() -> None:
    """The paper's configuration learns CartPole-v0 (PI >= 195) quickly; seed 1 takes 27 episodes."""
    returns = train("CartPole-v0", seed=1, max_episodes=150)
    assert len(returns) < 150 and np.mean(returns[-10:]) >= 195


def test_init_seed_gives_federated_workers_the_same_networks_but_their_own_sampling() -> None:
    a = PPOLearner(CARTPOLE_OBS, spaces.Discrete(2), seed=1000, init_seed=1)
    b = PPOLearner(CARTPOLE_OBS, spaces.Discrete(2), seed=1001, init_seed=1)
    assert_same(actor_state(a), actor_state(b))
    obs = np.zeros(4, np.float32)
    assert [int(a.act(obs)) for _ in range(40)] != [int(b.act(obs)) for _ in range(40)]


def test_obs_scale_multiplies_the_input_and_is_validated() -> None:
    scaled = PPOLearner(CARTPOLE_OBS, spaces.Discrete(2), PPOConfig(obs_scale=(2.0, 1.0, 1.0, 0.5)), seed=3)
    plain = PPOLearner(CARTPOLE_OBS, spaces.Discrete(2), seed=3)
    obs = np.array([0.1, 0.2, 0.3, 0.4], np.float32)
    torch.testing.assert_close(scaled._obs_tensor(obs), plain._obs_tensor(obs * np.array([2.0, 1.0, 1.0, 0.5])))
    with pytest.raises(ValueError, match="obs_scale has 3 entries"):
        PPOLearner(CARTPOLE_OBS, spaces.Discrete(2), PPOConfig(obs_scale=(1.0, 1.0, 1.0)))
    with pytest.raises(ValueError, match="obs_scale"):
        PPOConfig(obs_scale=(1.0, 0.0))
