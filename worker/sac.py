"""Soft Actor-Critic, a learner of the worker beside PPO (worker/ppo.py) and DQN (worker/dqn.py).

One module covers both kinds of action space:

- Box actions: SAC with a tanh-squashed Gaussian policy, twin Q critics, target critics by Polyak averaging and an
  automatically tuned entropy temperature alpha (Haarnoja et al. 2018, "Soft Actor-Critic Algorithms and
  Applications", arXiv:1812.05905);
- Discrete actions: discrete SAC (Christodoulou 2019, arXiv:1910.07207): a categorical policy, Q networks with one
  output per action, and every expectation over the policy computed exactly as a sum over the actions.

Read it top to bottom: the configuration, the networks (an actor and ONE critic module holding both Q networks), the
pure math (soft state value, soft Q target, the critic loss J_Q, the actor loss J_pi, the temperature loss J(alpha),
the Polyak update) and the learner, which owns the target critic, log alpha and three Adam optimizers; the replay and
the schedule of gradient steps are worker/offpolicy.py's, the federation's seams worker/federation.py's.

What travels: the actor (its per-episode gradient, and its parameters in a transfer); under a per-step strategy also
the gradients of both Q networks (``critic`` = q1 and q2). What never leaves the device: the target critics, the
temperature (log alpha and its optimizer; its step is always local, after the shared critic and actor steps) and the
replay buffer.

Exploration: SAC's acting noise is white (a fresh Gaussian draw each step); ``noise_beta`` > 0 colours it in time
(``colored_noise``), which reaches MountainCarContinuous-v0's goal where white noise does not.
"""


from __future__ import annotations

import copy
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch
from gymnasium import spaces
from torch import nn

from worker.adam import Adam
from worker.nets import FromDict, StepGradients, UpdateStats, action_kind, mlp
from worker.offpolicy import OffPolicyLearner, ReplayBatch
from worker.replay import FiniteTransitions

#: Bounds of the Gaussian's log standard deviation (before the tanh squashing), as is usual for SAC.
LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0


# ----------------------------------------------------------------------------------------------------
# Configuration
# ----------------------------------------------------------------------------------------------------


@dataclass
class SACConfig(FromDict):
    """Hyper-parameters; the defaults are Haarnoja et al.'s (2018) where they give one: two hidden layers of 256 ReLU
    units, Adam 3e-4 for every network and for alpha, gamma 0.99, tau 0.005, batch 256, one gradient step per env step,
    target entropy -dim(A).

    Names shared with ``PPOConfig`` mean the same (hidden_sizes, activation, actor_lr, critic_lr, batch_size,
    update_epochs, gamma, max_grad_norm, obs_scale, reward_scale). ``update_epochs`` is K, the fixed number of
    gradient steps per episode under a per-step federation strategy only; ``update()`` alone takes
    round(utd_ratio * new transitions) steps.

    Target entropy: ``target_entropy`` when given; else -dim(A) for Box actions and ``target_entropy_ratio`` * log|A|
    for Discrete ones (log|A| is the entropy of the uniform policy; Christodoulou uses the ratio 0.98).
    """

    hidden_sizes: tuple[int, ...] = (256, 256)
    activation: str = "relu"  # one of worker.nets.ACTIVATIONS
    actor_lr: float = 3e-4
    critic_lr: float = 3e-4  # both Q networks (one optimizer)
    alpha_lr: float = 3e-4  # the temperature, optimised as log alpha
    gamma: float = 0.99
    tau: float = 0.005  # Polyak averaging of the target critics
    replay_size: int = 100_000  # FIFO replay buffer, across episodes
    batch_size: int = 256
    learning_starts: int = 1000  # transitions in the replay before update() takes its first gradient step
    utd_ratio: float = 1.0  # update-to-data ratio: gradient steps per new env step in update()
    update_epochs: int = 10  # K: gradient steps per episode under a per-step federation strategy
    init_alpha: float = 1.0
    target_entropy: float | None = None  # None: -dim(A) (Box) or target_entropy_ratio * log|A| (Discrete)
    target_entropy_ratio: float = 0.98  # Discrete only, and only when target_entropy is None
    max_grad_norm: float | None = None  # clip each network's gradient norm; None disables
    # Fixed per-dimension input scale, the same on every worker (see PPOConfig.obs_scale).
    obs_scale: tuple[float, ...] | None = None
    reward_scale: float = 1.0  # rewards are multiplied by this for learning (returns are reported unscaled)
    # Box only: the colour of the acting noise, power spectrum 1/f^beta (Eberhard et al. 2023): 0 is SAC's white
    # noise, 1 pink, 2 red; the policy's marginal distribution is the same, only its correlation in time changes.
    noise_beta: float = 0.0
    noise_horizon: int = 1000  # length of one noise sequence (one per episode; a longer episode draws another)

    def __post_init__(self) -> None:
        self._validate(
            positive=("critic_lr", "alpha_lr", "init_alpha", "utd_ratio"), at_least_one=("replay_size",),
            unit=("target_entropy_ratio",),
            problems=((self.learning_starts < 0, "learning_starts must be >= 0"),
                      (not 0.0 < self.tau <= 1.0, "tau must be in (0, 1]"),
                      (self.target_entropy is not None and not math.isfinite(self.target_entropy),
                       "target_entropy must be finite or None"),
                      (not 0.0 <= self.noise_beta <= 4.0, "noise_beta must be in [0, 4]"),
                      (self.noise_horizon < 2, "noise_horizon must be >= 2")))


# ----------------------------------------------------------------------------------------------------
# Exploration noise
# ----------------------------------------------------------------------------------------------------


def colored_noise(beta: float, shape: tuple[int, ...], generator: torch.Generator) -> torch.Tensor:
    """Gaussian noise of unit variance along the last axis (length T), power spectral density proportional to
    1/f^beta (Eberhard et al. 2023, "Pink Noise Is All You Need", ICLR; generated in the frequency domain as in
    Timmer and Koenig 1995). Frequencies below 1/T get the power of 1/T, so the sequence has no unbounded drift.

    Each Fourier coefficient k of the real signal is s_k (a_k + i b_k) with a_k, b_k ~ N(0, 1) and s_k = f_k^(-beta/2);
    the zero and (even T) Nyquist coefficients are real, with twice the variance, so that beta = 0 is white. The
    inverse transform x_t = (1/T) sum_k X_k e^(2 pi i k t / T) then has Var x_t = (2 s_0^2 + 4 sum_mid s_k^2 + 2 s_N^2)
    / T^2 for every t, which the result is divided by."""
    length = shape[-1]
    freqs = torch.fft.rfftfreq(length, dtype=torch.float64).clamp(min=1.0 / length)
    s = freqs ** (-beta / 2.0)
    real = torch.randn((*shape[:-1], s.numel()), generator=generator, dtype=torch.float64)
    imag = torch.randn((*shape[:-1], s.numel()), generator=generator, dtype=torch.float64)
    edges = [0] + ([s.numel() - 1] if length % 2 == 0 else [])
    imag[..., edges] = 0.0
    real[..., edges] *= math.sqrt(2.0)
    x = torch.fft.irfft(torch.complex(real * s, imag * s), n=length)
    power = 4.0 * (s**2).sum() - 2.0 * (s[edges] ** 2).sum()
    return (x / (power.sqrt() / length)).to(torch.float32)


# ----------------------------------------------------------------------------------------------------
# Networks
# ----------------------------------------------------------------------------------------------------


class SACActor(nn.Module):
    """pi_theta(a|s): Categorical over logits (Discrete), or a tanh-squashed diagonal Gaussian (Box) whose mean and
    state-dependent log standard deviation are the two halves of the MLP's output. Box actions are in [-1, 1]; the
    learner scales them to the action space's bounds."""

    def __init__(self, obs_dim: int, action_space: spaces.Space, config: SACConfig) -> None:
        super().__init__()
        self.discrete, self.action_shape, self.action_dim = action_kind(action_space)
        if isinstance(action_space, spaces.Box) and not np.isfinite([action_space.low, action_space.high]).all():
            raise ValueError(f"SAC needs finite Box bounds to squash actions into, got {action_space!r}")
        out_dim = self.action_dim if self.discrete else 2 * self.action_dim
        self.net = mlp(obs_dim, config.hidden_sizes, out_dim, config.activation, ortho=False, out_gain=1.0)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Logits (Discrete, shape (batch, |A|)) or mean and log std concatenated (Box, (batch, 2 dim(A)))."""
        return self.net(obs)

    def log_probs(self, obs: torch.Tensor) -> torch.Tensor:
        """Discrete: log pi(a|s) of every action, shape (batch, |A|)."""
        return torch.log_softmax(self(obs), dim=-1)

    def gaussian(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Box: the pre-squash Gaussian's mean and standard deviation."""
        mean, log_std = self(obs).chunk(2, dim=-1)
        return mean, log_std.clamp(LOG_STD_MIN, LOG_STD_MAX).exp()

    def rsample(self, obs: torch.Tensor, generator: torch.Generator, eps: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """Box: a reparameterised sample a = tanh(mean + std * eps) in [-1, 1] and its log-density log pi(a|s),
        with the tanh change of variables: log N(u) - sum log(1 - tanh(u)^2). ``eps`` is drawn with ``generator``
        unless given (coloured acting noise)."""
        mean, std = self.gaussian(obs)
        if eps is None:
            eps = torch.randn(mean.shape, generator=generator, dtype=mean.dtype)
        u = mean + std * eps
        log_normal = torch.distributions.Normal(mean, std).log_prob(u).sum(-1)
        # log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u)), stable for large |u|
        log_det = (2.0 * (math.log(2.0) - u - nn.functional.softplus(-2.0 * u))).sum(-1)
        return torch.tanh(u), log_normal - log_det

    def sample(self, obs: torch.Tensor, generator: torch.Generator, eps: torch.Tensor | None = None) -> torch.Tensor:
        """Draw actions with ``generator``: action indices (Discrete) or squashed actions in [-1, 1] (Box); a Box
        action takes the standard normal ``eps`` when given (coloured noise) instead of a fresh draw."""
        if self.discrete:
            return torch.multinomial(torch.softmax(self(obs), dim=-1), 1, generator=generator).squeeze(-1)
        return self.rsample(obs, generator, eps)[0]

    def greedy(self, obs: torch.Tensor) -> torch.Tensor:
        """The deterministic action: arg-max logit, or tanh of the Gaussian mean."""
        if self.discrete:
            return self(obs).argmax(dim=-1)
        return torch.tanh(self.gaussian(obs)[0])


class QNetwork(nn.Module):
    """Q_phi(s, a): an MLP of (s, a) with one output (Box), or of s with one output per action (Discrete)."""

    def __init__(self, obs_dim: int, action_dim: int, discrete: bool, config: SACConfig) -> None:
        super().__init__()
        self.discrete = discrete
        in_dim, out_dim = (obs_dim, action_dim) if discrete else (obs_dim + action_dim, 1)
        self.net = mlp(in_dim, config.hidden_sizes, out_dim, config.activation, ortho=False, out_gain=1.0)

    def forward(self, obs: torch.Tensor, actions: torch.Tensor | None = None) -> torch.Tensor:
        """Discrete: Q of every action, (batch, |A|), or of ``actions`` (indices), (batch,). Box: Q(s, a), (batch,)."""
        if self.discrete:
            q = self.net(obs)
            return q if actions is None else q.gather(1, actions.long().unsqueeze(-1)).squeeze(-1)
        if actions is None:
            raise ValueError("a Box Q network needs the actions")
        return self.net(torch.cat([obs, actions], dim=-1)).squeeze(-1)


class TwinQ(nn.Module):
    """The critic: the two Q networks ``q1`` and ``q2`` in one module (one optimizer, one parameter namespace)."""

    def __init__(self, obs_dim: int, action_dim: int, discrete: bool, config: SACConfig) -> None:
        super().__init__()
        self.q1 = QNetwork(obs_dim, action_dim, discrete, config)
        self.q2 = QNetwork(obs_dim, action_dim, discrete, config)

    def forward(self, obs: torch.Tensor, actions: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        return self.q1(obs, actions), self.q2(obs, actions)


# ----------------------------------------------------------------------------------------------------
# The math as pure functions
# ----------------------------------------------------------------------------------------------------


def soft_state_value(
    q1: torch.Tensor, q2: torch.Tensor, log_pi: torch.Tensor, alpha: float | torch.Tensor,
    probs: torch.Tensor | None = None,
) -> torch.Tensor:
    """The soft state value V(s) = E_{a~pi}[min(Q1, Q2)(s, a) - alpha log pi(a|s)], per state.

    Box (``probs`` None): a one-sample estimate, all inputs of shape (batch,) at a sampled a ~ pi(.|s).
    Discrete (``probs`` = pi(.|s), shape (batch, |A|) like q1, q2 and log_pi): the exact sum over the actions."""
    inner = torch.min(q1, q2) - alpha * log_pi
    return inner if probs is None else (probs * inner).sum(-1)


def soft_q_target(
    rewards: torch.Tensor, next_value: torch.Tensor, terminated: torch.Tensor, gamma: float
) -> torch.Tensor:
    """The soft Q target y = r + gamma (1 - terminated) V_target(s'), with V_target from ``soft_state_value`` over
    the target critics. Only a termination cuts the bootstrap: after a truncation (time limit) s' still has a value."""
    return rewards + gamma * (1.0 - terminated.to(rewards.dtype)) * next_value


def critic_loss(q1: torch.Tensor, q2: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """J_Q of both Q networks: mean 0.5 (Q1(s, a) - y)^2 + mean 0.5 (Q2(s, a) - y)^2 (``target`` y is a constant)."""
    target = target.detach()
    return 0.5 * (q1 - target).square().mean() + 0.5 * (q2 - target).square().mean()


def actor_loss(
    q1: torch.Tensor, q2: torch.Tensor, log_pi: torch.Tensor, alpha: float | torch.Tensor,
    probs: torch.Tensor | None = None,
) -> torch.Tensor:
    """J_pi = E_s[E_{a~pi}[alpha log pi(a|s) - min(Q1, Q2)(s, a)]] = -mean soft_state_value (same argument shapes).

    Box: a reparameterised sample, the gradient flows through the actions into Q. Discrete: the exact expectation;
    pass the Q values detached, the gradient flows through ``probs`` and ``log_pi``."""
    return -soft_state_value(q1, q2, log_pi, alpha, probs).mean()


def temperature_loss(log_alpha: torch.Tensor, log_pi: torch.Tensor, target_entropy: float) -> torch.Tensor:
    """J(alpha) = E[-alpha (log pi(a|s) + H_target)], optimised over log alpha (the usual parameterisation: same sign
    of gradient, alpha stays positive). ``log_pi``: per-sample log pi(a|s) (Box) or -entropy of pi(.|s) (Discrete,
    the exact expectation), a constant here. alpha grows while the policy's entropy is below the target."""
    return -(log_alpha * (log_pi.detach() + target_entropy)).mean()


@torch.no_grad()
def polyak_update(target: Iterable[torch.Tensor], source: Iterable[torch.Tensor], tau: float) -> None:
    """In place, pairwise: target = (1 - tau) target + tau source (the target critics' slow average)."""
    for t, s in zip(target, source, strict=True):
        t.mul_(1.0 - tau).add_(s, alpha=tau)


# ----------------------------------------------------------------------------------------------------
# The learner
# ----------------------------------------------------------------------------------------------------


@dataclass
class SACUpdateStats(UpdateStats):
    """Means over the gradient steps of one ``update()`` (zeros when it took none). actor_loss is J_pi, critic_loss
    J_Q, entropy the policy's mean entropy estimate."""

    alpha: float = 0.0  # the temperature after the update
    gradient_steps: int = 0


class SACLearner(OffPolicyLearner):
    """One worker's SAC: acting, the soft actor-critic losses, the temperature and the target critics; the replay,
    the schedule and the federation's seams are worker/offpolicy.py's (``seed`` and ``init_seed``: worker/
    federation.py). The target critic starts as a copy of the critic."""

    ALGO = "sac"
    CONFIG = SACConfig
    NETWORKS = ("actor", "critic", "target_critic", "log_alpha")
    OPTIMIZERS: ClassVar[dict[str, str]] = {"actor_optimizer": "actor_lr", "critic_optimizer": "critic_lr",
                                            "alpha_optimizer": "alpha_lr"}

    def _build(self, obs_dim: int, action_space: spaces.Space) -> None:
        cfg = self.config
        self.actor = SACActor(obs_dim, action_space, cfg)
        self.critic = TwinQ(obs_dim, self.actor.action_dim, self.actor.discrete, cfg)
        self.target_critic = copy.deepcopy(self.critic).requires_grad_(False)
        if isinstance(action_space, spaces.Box):
            low, high = action_space.low.astype(np.float64), action_space.high.astype(np.float64)
            self._action_center, self._action_half = (high + low) / 2.0, (high - low) / 2.0
        self.log_alpha = torch.tensor(math.log(cfg.init_alpha), dtype=torch.float32, requires_grad=True)
        self.actor_optimizer = Adam(self.actor.parameters(), lr=cfg.actor_lr)
        self.critic_optimizer = Adam(self.critic.parameters(), lr=cfg.critic_lr)
        self.alpha_optimizer = Adam([self.log_alpha], lr=cfg.alpha_lr)
        # the latest mini-batch's mean log pi estimate, for the temperature step of apply_step
        self._alpha_term: torch.Tensor | None = None
        self._finite = FiniteTransitions("SAC")
        self._noise: torch.Tensor | None = None  # this episode's coloured noise, shape (dim(A), noise_horizon)
        self._noise_pos = 0

    @property
    def target_entropy(self) -> float:
        """H_target: the configured value, or -dim(A) (Box) / target_entropy_ratio * log|A| (Discrete)."""
        if self.config.target_entropy is not None:
            return float(self.config.target_entropy)
        if self.actor.discrete:
            return self.config.target_entropy_ratio * math.log(self.actor.action_dim)
        return -float(self.actor.action_dim)

    @property
    def alpha(self) -> float:
        return float(self.log_alpha.detach().exp())

    # -- acting --------------------------------------------------------------------------------------------

    def _to_env(self, action: torch.Tensor) -> Any:
        if self.actor.discrete:
            return np.int64(action.item())
        scaled = self._action_center + self._action_half * action.double().numpy().reshape(self.actor.action_shape)
        return scaled.astype(np.float32)

    def _next_eps(self) -> torch.Tensor | None:
        """The standard normal noise of this step when the acting noise is coloured (None: white, drawn by
        ``sample``). A sequence is drawn at an episode's first action, and again if the episode outlasts it."""
        if self.actor.discrete or self.config.noise_beta == 0.0:
            return None
        if self._noise is None or self._noise_pos >= self._noise.shape[-1]:
            self._noise = colored_noise(self.config.noise_beta, (self.actor.action_dim, self.config.noise_horizon),
                                        self.generator)
            self._noise_pos = 0
        eps = self._noise[:, self._noise_pos]
        self._noise_pos += 1
        return eps

    @torch.no_grad()
    def act(self, obs: Any) -> Any:
        """Sample a_t ~ pi_theta(.|s_t): a numpy int64 (Discrete) or a float32 array within the Box bounds."""
        return self._to_env(self.actor.sample(self._obs_tensor(obs), self.generator, self._next_eps())[0])

    def remember(
        self, obs: Any, action: Any, reward: float, next_obs: Any, terminated: bool, truncated: bool
    ) -> None:
        """Store <s_t, a_t, r_{t+1}, s_{t+1}> and the episode flags in the FIFO replay (the oldest drops out when it
        is full). Box actions come in env units and are stored rescaled to [-1, 1] (clipped), the actor's range.

        A transition with a value that is not finite (reward, observations or action) is refused, counted in
        ``rejected_transitions`` and logged (FiniteTransitions)."""
        if terminated or truncated:
            self._noise = None  # the next episode draws its own noise sequence
        if not self._finite.admit(reward, obs, next_obs, action):
            return
        if self.actor.discrete:
            stored: Any = int(action)
        else:
            a = np.asarray(action, dtype=np.float64).reshape(-1)
            stored = np.clip((a - self._action_center.reshape(-1)) / self._action_half.reshape(-1), -1.0, 1.0)
        self.replay.add(obs=np.asarray(obs, dtype=np.float32).reshape(self.obs_shape),
                        next_obs=np.asarray(next_obs, dtype=np.float32).reshape(self.obs_shape), actions=stored,
                        rewards=float(reward), terminated=bool(terminated), truncated=bool(truncated))

    # -- the update after an episode --------------------------------------------------------------------------

    def update(self) -> SACUpdateStats:
        """round(utd_ratio * n) gradient steps for the n transitions remembered since the last update (worker/
        offpolicy.py), each: a twin soft Q critic step, an actor step, a temperature step and the Polyak update of the
        target critics. Also records the episode's actor gradient (see ``actor_gradient``)."""
        batch, steps = self._episode_steps()
        return SACUpdateStats(**self._statistics(batch, steps, ("actor_loss", "critic_loss", "entropy")),
                              alpha=self.alpha, gradient_steps=len(steps))

    def minibatch_gradients(self, batch: ReplayBatch) -> StepGradients:
        """One random mini-batch from the replay: the critic's gradient of J_Q (both Q networks, against the soft Q
        target of the target critics) and the actor's of J_pi (with the critic's current parameters), each after
        optional norm clipping; None where the loss or a gradient is not finite, and both None (losses NaN) while the
        replay holds fewer than ``learning_starts`` transitions. Nothing is applied: ``apply_step`` does that (with
        these, or with a federation's mean of them)."""
        cfg = self.config
        if not self._learning(batch):  # no gradients yet: shared as zeros, and a step of zeros is none
            self._alpha_term = None
            return StepGradients(critic=None, actor=None, actor_loss=math.nan, critic_loss=math.nan, entropy=math.nan)
        rows = self.replay.sample(batch.n, cfg.batch_size, self.generator)
        obs, next_obs = self._obs_tensor(rows["obs"]), self._obs_tensor(rows["next_obs"])
        actions, terminated = torch.from_numpy(rows["actions"]), torch.from_numpy(rows["terminated"])
        rewards = torch.from_numpy(rows["rewards"] * cfg.reward_scale).float()
        alpha = self.log_alpha.detach().exp()
        discrete = self.actor.discrete
        with torch.no_grad():
            if discrete:
                next_log_pi = self.actor.log_probs(next_obs)
                nq1, nq2 = self.target_critic(next_obs)
                next_v = soft_state_value(nq1, nq2, next_log_pi, alpha, next_log_pi.exp())
            else:
                next_a, next_log_pi = self.actor.rsample(next_obs, self.generator)
                nq1, nq2 = self.target_critic(next_obs, next_a)
                next_v = soft_state_value(nq1, nq2, next_log_pi, alpha)
            target = soft_q_target(rewards, next_v, terminated, cfg.gamma)
        q1, q2 = self.critic(obs, actions)
        c_loss = critic_loss(q1, q2, target)
        critic_grad = self._gradients(c_loss, self.critic)

        if discrete:
            log_pi = self.actor.log_probs(obs)
            probs = log_pi.exp()
            with torch.no_grad():
                aq1, aq2 = self.critic(obs)
            a_loss = actor_loss(aq1, aq2, log_pi, alpha, probs)
            log_pi_per_state = (probs * log_pi).sum(-1).detach()  # -entropy, exact
        else:
            new_a, log_pi = self.actor.rsample(obs, self.generator)
            aq1, aq2 = self.critic(obs, new_a)
            a_loss = actor_loss(aq1, aq2, log_pi, alpha)
            log_pi_per_state = log_pi.detach()  # one-sample estimate of -entropy
        actor_grad = self._gradients(a_loss, self.actor)
        self._alpha_term = log_pi_per_state.mean()
        return StepGradients(critic=critic_grad, actor=actor_grad, actor_loss=a_loss.item(),
                             critic_loss=c_loss.item(), entropy=-self._alpha_term.item())

    def apply_step(self, critic: Mapping[str, np.ndarray] | None, actor: Mapping[str, np.ndarray] | None) -> None:
        """One critic-optimizer step and one actor-optimizer step with the given gradients (None or all zeros: that
        network is not stepped), then the local steps: the temperature (J(alpha), from the latest
        ``minibatch_gradients``' log pi estimate, none before ``learning_starts``) and, after a critic step, the
        Polyak update of the target critics."""
        stepped = self._step(self.critic, self.critic_optimizer, critic)
        self._step(self.actor, self.actor_optimizer, actor)
        if self._alpha_term is not None and torch.isfinite(self._alpha_term):
            self.alpha_optimizer.zero_grad()
            temperature_loss(self.log_alpha, self._alpha_term, self.target_entropy).backward()
            self.alpha_optimizer.step()
            self.alpha_optimizer.zero_grad()
        if stepped:
            polyak_update(self.target_critic.parameters(), self.critic.parameters(), self.config.tau)

    # -- persistence beyond the declared names ------------------------------------------------------------------

    def _own_state(self) -> dict[str, Any]:
        return {"alpha_term": None if self._alpha_term is None else self._alpha_term.clone()}

    def _load_own(self, state: Mapping[str, Any]) -> None:
        term = state.get("alpha_term")
        self._alpha_term = None if term is None else term.clone()
