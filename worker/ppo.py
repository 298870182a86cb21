"""Actor-Critic PPO as the paper's workers run it (Section III, Eq. 1-7; Algorithm 2's inner loop).

Read it top to bottom: the configuration (Section V-A), the networks (separate actor and critic MLPs), the
pure math (GAE Eq. 2, critic loss Eq. 3, clipped surrogate Eq. 6) and the learner, which owns the trajectory
memory, the two Adam optimizers (Eq. 4 and 7), ``prepare()``, ``minibatch_gradients()`` and ``apply_step()`` (the K
steps of ``update()`` one at a time, for strategies that share every mini-batch step's gradients). The federation's
seams (the episode gradient g_theta^n, Eq. 9's step, Eq. 11's blend, persistence) are worker/federation.py's.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch
from gymnasium import spaces
from torch import nn

from worker.adam import Adam
from worker.federation import FederatedLearner
from worker.nets import FromDict, StepGradients, action_kind, mlp
from worker.nets import UpdateStats as CommonStats
from worker.replay import Replay

VALUE_LOSSES = ("l1", "huber", "mse")


# ----------------------------------------------------------------------------------------------------
# Configuration
# ----------------------------------------------------------------------------------------------------


@dataclass
class PPOConfig(FromDict):
    """Hyper-parameters; the defaults are the paper's (Section V-A) where it gives one.

    Paper: actor and critic are separate MLPs with three hidden layers of 128 units, Adam with learning rate
    1e-3 for both, a trajectory memory of 400 transitions (FIFO: when full, the oldest transition drops out),
    mini-batch size U = 128, K = 10 optimisation steps per episode, GAE parameter lambda = 0.99.

    Not given by the paper (our choices, from the authors' code and CleanRL): gamma 0.99, entropy coefficient
    0.01, tanh activation, orthogonal init, advantage normalisation per mini-batch.

    The paper prints a clipping parameter of 0.9. That cannot be a PPO clip range: the ratio would be allowed
    to move in [0.1, 1.9], which is almost no trust region. The authors' code used 0.2 (0.1 in their CartPole
    sample), as does the PPO paper, so 0.2 is the default here.
    """

    hidden_sizes: tuple[int, ...] = (128, 128, 128)
    activation: str = "tanh"  # one of worker.nets.ACTIVATIONS
    ortho_init: bool = True  # orthogonal weights (gain sqrt 2; policy head 0.01, value head 1), zero biases
    actor_lr: float = 1e-3  # eta_theta, Eq. 7
    critic_lr: float = 1e-3  # eta_mu, Eq. 4
    memory_size: int = 400  # trajectory memory, FIFO across episodes
    batch_size: int = 128  # U
    update_epochs: int = 10  # K: critic + actor steps per episode
    gamma: float = 0.99
    gae_lambda: float = 0.99  # the paper's "GAE parameter"
    clip_epsilon: float = 0.2  # epsilon of Eq. 6 (the paper's printed 0.9 is not a clip range, see above)
    entropy_coef: float = 0.01
    value_loss: str = "l1"  # "l1" = Eq. 3 (absolute TD error); "huber" or "mse" as alternatives
    normalize_advantages: bool = True  # per mini-batch
    max_grad_norm: float | None = None  # clip each network's gradient norm; None disables
    log_std_init: float = 0.0  # initial log standard deviation of the Gaussian policy (Box actions)
    normalize_obs: bool = False  # running mean/std of the observations (per worker: see obs_scale)
    # Fixed per-dimension input scale, the same on every worker. Unlike the running statistics of normalize_obs,
    # which differ between workers, it keeps a transferred actor (Eq. 11) meaningful on its recipient.
    obs_scale: tuple[float, ...] | None = None
    reward_scale: float = 1.0  # rewards are multiplied by this for learning (returns are reported unscaled)

    def __post_init__(self) -> None:
        self._validate(positive=("critic_lr", "clip_epsilon"), at_least_one=("memory_size",), unit=("gae_lambda",),
                       problems=((self.value_loss not in VALUE_LOSSES, f"value_loss must be one of {VALUE_LOSSES}"),
                                 (self.entropy_coef < 0, "entropy_coef must be >= 0")))


# ----------------------------------------------------------------------------------------------------
# Networks
# ----------------------------------------------------------------------------------------------------


class Actor(nn.Module):
    """pi_theta(a|s): Categorical over logits for Discrete spaces, diagonal Gaussian for Box spaces.

    The Gaussian's log standard deviation is a state-independent parameter (``log_std``), shared with the
    chief like every other actor parameter. Samples are raw (unclipped); the environment clips Box actions.
    """

    def __init__(self, obs_dim: int, action_space: spaces.Space, config: PPOConfig) -> None:
        super().__init__()
        self.discrete, self.action_shape, self.action_dim = action_kind(action_space)
        cfg = config
        self.net = mlp(obs_dim, cfg.hidden_sizes, self.action_dim, cfg.activation, cfg.ortho_init, out_gain=0.01)
        if not self.discrete:
            self.log_std = nn.Parameter(torch.full((self.action_dim,), float(config.log_std_init)))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Logits (Discrete) or the Gaussian mean (Box), shape (batch, action_dim)."""
        return self.net(obs)

    def sample(self, obs: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """Draw actions with ``generator`` (torch.distributions' own sample() cannot take one)."""
        out = self(obs)
        if self.discrete:
            return torch.multinomial(torch.softmax(out, dim=-1), 1, generator=generator).squeeze(-1)
        noise = torch.randn(out.shape, generator=generator, dtype=out.dtype)
        return out + self.log_std.exp() * noise

    def greedy(self, obs: torch.Tensor) -> torch.Tensor:
        """The most likely action: arg-max logit, or the Gaussian mean."""
        out = self(obs)
        return out.argmax(dim=-1) if self.discrete else out

    @torch.no_grad()
    def temper(self, temperature: float) -> None:
        """pi at temperature T from now on: the logits divided by T (the output layer's weights and bias scaled by
        1/T), or the Gaussian's standard deviation times T (log_std + log T). The greedy action stays the same, and
        pi stays this network, which PPO goes on learning as before (the ratio of Eq. 1 compares the tempered policy
        with itself)."""
        if not 0 < temperature <= 1:
            raise ValueError(f"a policy temperature must be in (0, 1], not {temperature}")
        if self.discrete:
            out = self.net[-1]
            assert isinstance(out, nn.Linear)
            out.weight.div_(temperature)
            out.bias.div_(temperature)
        else:
            self.log_std.add_(math.log(temperature))

    def log_prob_entropy(self, obs: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """log pi_theta(a_t|s_t) and the policy entropy per sample."""
        out = self(obs)
        if self.discrete:
            dist: torch.distributions.Distribution = torch.distributions.Categorical(logits=out)
        else:
            normal = torch.distributions.Normal(out, self.log_std.exp().expand_as(out))
            dist = torch.distributions.Independent(normal, 1)
        return dist.log_prob(actions), dist.entropy()


class Critic(nn.Module):
    """V_mu(s): a separate MLP with a single output (Section V-A)."""

    def __init__(self, obs_dim: int, config: PPOConfig) -> None:
        super().__init__()
        self.net = mlp(obs_dim, config.hidden_sizes, 1, config.activation, config.ortho_init, out_gain=1.0)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.net(obs).squeeze(-1)


class RunningObsNorm(nn.Module):
    """Running mean and variance of observations (parallel-variance update); ``normalize`` clips to +-10."""

    mean: torch.Tensor  # buffers (saved with the state dict), registered in __init__
    var: torch.Tensor
    count: torch.Tensor

    def __init__(self, shape: tuple[int, ...], clip: float = 10.0) -> None:
        super().__init__()
        self.clip = clip
        self.register_buffer("mean", torch.zeros(shape, dtype=torch.float64))
        self.register_buffer("var", torch.ones(shape, dtype=torch.float64))
        self.register_buffer("count", torch.tensor(1e-4, dtype=torch.float64))

    def update(self, batch: torch.Tensor) -> None:
        batch = batch.to(torch.float64).reshape(-1, *self.mean.shape)
        n = batch.shape[0]
        b_mean, b_var = batch.mean(0), batch.var(0, unbiased=False)
        delta, total = b_mean - self.mean, self.count + n
        m2 = self.var * self.count + b_var * n + delta.square() * self.count * n / total
        self.mean += delta * n / total
        self.var.copy_(m2 / total)
        self.count.copy_(total)

    def normalize(self, obs: torch.Tensor) -> torch.Tensor:
        z = (obs.to(torch.float64) - self.mean) / torch.sqrt(self.var + 1e-8)
        return z.clamp(-self.clip, self.clip).to(torch.float32)


# ----------------------------------------------------------------------------------------------------
# The math of Section III as pure functions
# ----------------------------------------------------------------------------------------------------


def compute_gae(
    rewards: np.ndarray,
    values: np.ndarray,
    next_values: np.ndarray,
    terminated: np.ndarray,
    episode_end: np.ndarray,
    gamma: float,
    lam: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Generalised advantage estimates, Eq. 2, over a time-ordered memory; returns (advantages, returns).

    delta_t = r_t + gamma * V(s_{t+1}) * (1 - terminated_t) - V(s_t)
    A_t     = delta_t + gamma * lam * (1 - end_t) * A_{t+1}
    returns = A_t + V(s_t)          (the lambda-return; with lam = 0 it is Eq. 3's TD target r + gamma V(s'))

    ``terminated``: the episode ended in a terminal state, so the value after it is 0. ``episode_end``: the
    recursion stops after t (termination, truncation, or the memory is not contiguous after t, e.g. its last
    entry). On truncation the value of s_{t+1} is still bootstrapped through ``next_values``. Eq. 2 writes the
    sum up to the mini-batch end U; we sum to the end of each episode in the memory, which is the GAE of [32].
    """
    r = np.asarray(rewards, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    v_next = np.asarray(next_values, dtype=np.float64)
    term = np.asarray(terminated, dtype=bool)
    end = np.asarray(episode_end, dtype=bool) | term
    if not r.shape == v.shape == v_next.shape == term.shape == end.shape or r.ndim != 1:
        raise ValueError("compute_gae: all inputs must be 1-D arrays of the same length")
    deltas = r + gamma * v_next * (~term) - v
    advantages = np.zeros_like(r)
    running = 0.0
    for t in reversed(range(len(r))):
        running = deltas[t] + gamma * lam * (0.0 if end[t] else running)
        advantages[t] = running
    return advantages, advantages + v


def clipped_surrogate_loss(
    new_logp: torch.Tensor, old_logp: torch.Tensor, advantages: torch.Tensor, clip: float
) -> torch.Tensor:
    """-L^CLIP, Eq. 6, as the loss to minimise (Eq. 7).

    r_t = pi_theta(a|s) / pi_theta_old(a|s);  L^CLIP = mean(min(r_t A_t, clip(r_t, 1-eps, 1+eps) A_t)).
    """
    ratio = torch.exp(new_logp - old_logp)
    unclipped = ratio * advantages
    clipped = torch.clamp(ratio, 1.0 - clip, 1.0 + clip) * advantages
    return -torch.min(unclipped, clipped).mean()


def value_loss(values: torch.Tensor, targets: torch.Tensor, kind: str = "l1") -> torch.Tensor:
    """L^V, Eq. 3: mean |V_target - V_mu(s)| ("l1"); "huber" (smooth L1, delta 1) and "mse" as options."""
    if kind == "l1":
        return (targets - values).abs().mean()
    if kind == "huber":
        return nn.functional.smooth_l1_loss(values, targets)
    if kind == "mse":
        return (targets - values).square().mean()
    raise ValueError(f"value loss must be one of {VALUE_LOSSES}, not {kind!r}")


# ----------------------------------------------------------------------------------------------------
# The learner
# ----------------------------------------------------------------------------------------------------


@dataclass
class Batch:
    """theta_old's view of the trajectory memory (``PPOLearner.prepare``): inputs, actions, their old
    log-probabilities, GAE advantages and returns (Eq. 2)."""

    n: int
    obs: torch.Tensor
    actions: torch.Tensor
    old_logp: torch.Tensor
    advantages: torch.Tensor
    returns: torch.Tensor


@dataclass
class PPOStepGradients(StepGradients):
    """One mini-batch step's gradients and statistics, with PPO's own: the ratio's spread (see ``UpdateStats``)."""

    approx_kl: float = math.nan
    clip_fraction: float = math.nan


@dataclass
class UpdateStats(CommonStats):
    """Means over the K mini-batch steps of one ``update()``: actor_loss is -L^CLIP - entropy_coef * entropy,
    critic_loss L^V (Eq. 3, or the configured alternative); and PPO's own statistics."""

    approx_kl: float = math.nan  # mean (r - 1) - log r, an estimate of KL(pi_old || pi)
    clip_fraction: float = math.nan  # share of samples whose ratio left [1-eps, 1+eps]


class PPOLearner(FederatedLearner):
    """One worker's Actor-Critic PPO: acting, the trajectory memory, Algorithm 2's update (``seed`` and
    ``init_seed``: worker/federation.py)."""

    ALGO = "ppo"
    CONFIG = PPOConfig
    NETWORKS = ("actor", "critic", "obs_norm")
    OPTIMIZERS: ClassVar[dict[str, str]] = {"actor_optimizer": "actor_lr", "critic_optimizer": "critic_lr"}
    BATCH = Batch
    STEP = PPOStepGradients
    MEMORY = ("memory", "memory_size")
    memory: Replay  # trajectory memory: (s_t, a_t, r_{t+1}, s_{t+1}, terminated, truncated), oldest first

    def _build(self, obs_dim: int, action_space: spaces.Space) -> None:
        self.actor = Actor(obs_dim, action_space, self.config)
        self.critic = Critic(obs_dim, self.config)
        self.obs_norm = RunningObsNorm(self.obs_shape)
        self.actor_optimizer = Adam(self.actor.parameters(), lr=self.config.actor_lr)
        self.critic_optimizer = Adam(self.critic.parameters(), lr=self.config.critic_lr)

    # -- acting --------------------------------------------------------------------------------------------

    def _normalized(self, x: torch.Tensor) -> torch.Tensor:
        return self.obs_norm.normalize(x) if self.config.normalize_obs else x

    def temper(self, temperature: float) -> None:
        """A warm start's policy temperature (``Actor.temper``)."""
        self.actor.temper(temperature)

    def _to_env(self, action: torch.Tensor) -> Any:
        """A numpy int (Discrete) or a raw float32 array (Box, not clipped: the environment clips)."""
        if self.actor.discrete:
            return np.int64(action.item())
        return action.reshape(self.actor.action_shape).numpy().astype(np.float32)

    def remember(
        self, obs: Any, action: Any, reward: float, next_obs: Any, terminated: bool, truncated: bool
    ) -> None:
        """Store <s_t, a_t, r_{t+1}, s_{t+1}> (plus the episode flags) in the FIFO trajectory memory."""
        obs_arr = np.asarray(obs, dtype=np.float32).reshape(self.obs_shape).copy()
        stored = int(action) if self.actor.discrete else np.asarray(action, np.float32).reshape(-1)
        self.memory.add(obs=obs_arr, actions=stored, rewards=float(reward),
                        next_obs=np.asarray(next_obs, dtype=np.float32).reshape(self.obs_shape),
                        terminated=bool(terminated), truncated=bool(truncated))
        if self.config.normalize_obs:
            self.obs_norm.update(torch.from_numpy(obs_arr))

    # -- Algorithm 2: the update after an episode ---------------------------------------------------------

    def update(self) -> UpdateStats:
        """theta_old <- theta, then K times: a random mini-batch of U from memory, a critic step (Eq. 3-4)
        and an actor step (Eq. 6-7). Also records the episode's actor gradient (see ``actor_gradient``)."""
        batch = self.prepare()
        steps = self._steps(batch, self.config.update_epochs)
        means = ("actor_loss", "critic_loss", "entropy", "approx_kl", "clip_fraction")
        return UpdateStats(**self._statistics(batch, steps, means))

    def prepare(self) -> Batch:
        """theta_old <- theta: the whole memory's inputs, log-probs under the current actor, GAE advantages and
        returns under the current critic (Eq. 2). The K mini-batch steps of an update draw from it."""
        cfg = self.config
        n = len(self.memory)
        if n == 0:
            raise ValueError("update() needs transitions in the memory: call remember() first")
        m = self.memory.ordered()
        obs, next_obs = self._obs_tensor(m["obs"]), self._obs_tensor(m["next_obs"])
        actions = torch.from_numpy(m["actions"])
        terminated = m["terminated"]
        episode_end = terminated | m["truncated"]
        if n > 1:  # a gap between consecutive transitions (an episode cut short by the caller) also ends one
            gap = m["next_obs"][:-1].reshape(n - 1, -1) != m["obs"][1:].reshape(n - 1, -1)
            episode_end[:-1] |= gap.any(axis=1)
        episode_end[-1] = True  # nothing follows the newest transition yet
        with torch.no_grad():
            old_logp, _ = self.actor.log_prob_entropy(obs, actions)
            values = self.critic(obs).numpy()
            next_values = self.critic(next_obs).numpy()
        advantages, returns = compute_gae(m["rewards"] * cfg.reward_scale, values, next_values, terminated, episode_end,
                                          cfg.gamma, cfg.gae_lambda)
        return Batch(n=n, obs=obs, actions=actions, old_logp=old_logp,
                     advantages=torch.as_tensor(advantages, dtype=torch.float32),
                     returns=torch.as_tensor(returns, dtype=torch.float32))

    def minibatch_gradients(self, batch: Batch) -> PPOStepGradients:
        """One random mini-batch of U: the critic's gradient of L^V (Eq. 3) and the actor's of -L^CLIP (Eq. 6,
        with the entropy bonus), each after optional norm clipping; None where the loss or a gradient is not
        finite. Nothing is applied: ``apply_step`` does that (with these, or with a federation's mean of them)."""
        cfg = self.config
        idx = torch.randperm(batch.n, generator=self.generator)[: cfg.batch_size]
        critic_loss = value_loss(self.critic(batch.obs[idx]), batch.returns[idx], cfg.value_loss)
        critic_grad = self._gradients(critic_loss, self.critic)
        new_logp, entropy = self.actor.log_prob_entropy(batch.obs[idx], batch.actions[idx])
        adv = batch.advantages[idx]
        if cfg.normalize_advantages and len(idx) > 1:
            adv = (adv - adv.mean()) / (adv.std() + 1e-8)
        surrogate = clipped_surrogate_loss(new_logp, batch.old_logp[idx], adv, cfg.clip_epsilon)
        actor_loss = surrogate - cfg.entropy_coef * entropy.mean()
        actor_grad = self._gradients(actor_loss, self.actor)
        with torch.no_grad():
            log_ratio = new_logp - batch.old_logp[idx]
            ratio = log_ratio.exp()
            approx_kl = float(((ratio - 1) - log_ratio).mean())
            clip_fraction = float(((ratio - 1).abs() > cfg.clip_epsilon).float().mean())
        return PPOStepGradients(critic=critic_grad, actor=actor_grad, actor_loss=actor_loss.item(),
                             critic_loss=critic_loss.item(), entropy=entropy.mean().item(), approx_kl=approx_kl,
                             clip_fraction=clip_fraction)

    def apply_step(self, critic: Mapping[str, np.ndarray] | None, actor: Mapping[str, np.ndarray] | None) -> None:
        """One critic-optimizer step (Eq. 4) and one actor-optimizer step (Eq. 7) with the given gradients; a
        network whose gradient is None is not stepped."""
        self._step(self.critic, self.critic_optimizer, critic)
        self._step(self.actor, self.actor_optimizer, actor)
