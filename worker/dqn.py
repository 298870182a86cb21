"""Double DQN with n-step returns, a third learner beside PPO (worker/ppo.py) and SAC (worker/sac.py), with the same
seams (worker/learners.py ``Learner``). Discrete actions only.

Read it top to bottom: the configuration, the pure math, the learner. The math:

- the n-step return (Sutton and Barto 2018, "Reinforcement Learning: An Introduction", Eq. 7.1; multi-step DQN as in
  Hessel et al. 2018, "Rainbow", arXiv:1710.02298, Section 3): R_t^(n) = sum_{k=0}^{m-1} gamma^k r_{t+k+1}, with
  m = n, or fewer when the episode ends first;
- the Double DQN target (van Hasselt, Guez and Silver 2016, "Deep Reinforcement Learning with Double Q-learning",
  Eq. 4, with the n-step return): y = R_t^(n) + gamma^m (1 - terminated) Q_target(s_{t+m}, argmax_a Q(s_{t+m}, a)):
  the online network chooses the action, the target network values it; only a termination cuts the bootstrap;
- the loss: the Huber loss of Q(s_t, a_t) - y (Mnih et al. 2015, "Human-level control through deep reinforcement
  learning": the error term clipped to [-1, 1], which is the Huber loss's gradient).

What travels: the Q network is the federation's "actor" (the policy is its arg-max): its per-episode gradient
(Eq. 8-9), its parameters in a transfer (Eq. 11), and its step gradients under ``sync``. There is no critic (an
empty module). What never leaves the device: the replay buffer, the target network (a copy of the Q network every
``target_update_interval`` gradient steps; under ``sync`` every worker takes the same steps, so the copies agree) and
the exploration schedule.
"""

from __future__ import annotations

import copy
import math
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from torch import nn

from worker.adam import Adam
from worker.ppo import (
    _GLOBAL_RNG,
    StepGradients,
    UpdateStats,
    _tensors,
    blend,
    mlp,
    network_fields,
    save_model,
    take_optimizers,
)
from worker.sac import FiniteTransitions, SACBatch

#: A replay transition: s_t, a_t, R_t^(m), s_{t+m}, terminated, gamma^m.
Transition = tuple[np.ndarray, int, float, np.ndarray, bool, float]
__all__ = ["DQNConfig", "DQNLearner", "SACBatch", "double_q_target", "n_step_return", "td_loss"]


@dataclass
class DQNConfig:
    """Hyper-parameters. ``actor_lr`` is the Q network's learning rate (the Q network is the federation's actor);
    ``update_epochs`` is K, the gradient steps per episode under a per-step strategy; ``update()`` alone takes
    round(utd_ratio * new transitions). Exploration: epsilon falls linearly from ``eps_start`` to ``eps_end`` over
    the first ``eps_decay_steps`` env steps of the worker."""

    hidden_sizes: tuple[int, ...] = (128, 128)
    activation: str = "relu"
    actor_lr: float = 1e-3
    gamma: float = 0.99
    n_step: int = 3
    replay_size: int = 50_000
    batch_size: int = 64
    learning_starts: int = 500
    utd_ratio: float = 1.0
    update_epochs: int = 10
    target_update_interval: int = 250  # gradient steps between copies of the Q network into the target network
    eps_start: float = 1.0
    eps_end: float = 0.05
    eps_decay_steps: int = 5000
    max_grad_norm: float | None = 10.0
    obs_scale: tuple[float, ...] | None = None
    reward_scale: float = 1.0

    def __post_init__(self) -> None:
        self.hidden_sizes, self.obs_scale, problems = network_fields(self.hidden_sizes, self.activation,
                                                                     self.obs_scale)
        for name in ("actor_lr", "reward_scale", "utd_ratio"):
            if not (getattr(self, name) > 0 and math.isfinite(getattr(self, name))):
                problems.append(f"{name} must be finite and > 0")
        for name in ("n_step", "replay_size", "batch_size", "update_epochs", "target_update_interval"):
            if getattr(self, name) < 1:
                problems.append(f"{name} must be >= 1")
        if self.learning_starts < 0 or self.eps_decay_steps < 0:
            problems.append("learning_starts and eps_decay_steps must be >= 0")
        if not (0.0 <= self.gamma <= 1.0 and 0.0 <= self.eps_end <= self.eps_start <= 1.0):
            problems.append("need gamma in [0, 1] and 0 <= eps_end <= eps_start <= 1")
        if self.max_grad_norm is not None and not self.max_grad_norm > 0:
            problems.append("max_grad_norm must be > 0 or None")
        if problems:
            raise ValueError("invalid DQNConfig: " + "; ".join(problems))

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> DQNConfig:
        """Build from ``asdict(config)``; unknown keys are an error."""
        unknown = set(values) - {f.name for f in fields(cls)}
        if unknown:
            raise ValueError(f"unknown DQNConfig keys: {sorted(unknown)}")
        return cls(**dict(values))


# ----------------------------------------------------------------------------------------------------
# The math as pure functions
# ----------------------------------------------------------------------------------------------------


def n_step_return(rewards: Sequence[float], gamma: float) -> tuple[float, float]:
    """(R, gamma^m) of the m = len(rewards) rewards r_{t+1} .. r_{t+m}: R = sum_k gamma^k r_{t+k+1} (Sutton and Barto
    Eq. 7.1), and the discount of the bootstrap from s_{t+m}."""
    ret = sum(gamma ** k * r for k, r in enumerate(rewards))
    return float(ret), float(gamma ** len(rewards))


def double_q_target(returns: torch.Tensor, discounts: torch.Tensor, terminated: torch.Tensor,
                    next_q_online: torch.Tensor, next_q_target: torch.Tensor) -> torch.Tensor:
    """y = R + gamma^m (1 - terminated) Q_target(s', argmax_a Q_online(s', a)) (van Hasselt et al. 2016, Eq. 4, with
    n-step returns); ``next_q_*`` of shape (batch, |A|), the others (batch,)."""
    best = next_q_online.argmax(dim=-1, keepdim=True)
    bootstrap = next_q_target.gather(1, best).squeeze(-1)
    return returns + discounts * (1.0 - terminated.to(returns.dtype)) * bootstrap


def td_loss(q: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The mean Huber loss of Q(s, a) - y (``target`` is a constant; Mnih et al. 2015's clipped error)."""
    return nn.functional.smooth_l1_loss(q, target.detach())


def epsilon(config: DQNConfig, env_steps: int) -> float:
    """The exploration rate after ``env_steps``: linear from eps_start to eps_end over eps_decay_steps."""
    if config.eps_decay_steps == 0:
        return config.eps_end
    share = min(1.0, env_steps / config.eps_decay_steps)
    return config.eps_start + share * (config.eps_end - config.eps_start)


# ----------------------------------------------------------------------------------------------------
# The learner
# ----------------------------------------------------------------------------------------------------


class DQNLearner:
    """One worker's Double DQN: acting (epsilon-greedy), the n-step replay, the per-episode update and the federation
    hooks, as ``SACLearner`` (``seed``: init, exploration and mini-batch draws; ``init_seed``: the init alone)."""

    def __init__(self, obs_space: spaces.Space, action_space: spaces.Space, config: DQNConfig | None = None,
                 seed: int = 0, init_seed: int | None = None) -> None:
        if not isinstance(obs_space, spaces.Box):
            raise ValueError(f"unsupported observation space {obs_space!r}: use a Box")
        if not isinstance(action_space, spaces.Discrete):
            raise ValueError(f"DQN needs Discrete actions, got {action_space!r} (use sac or ppo)")
        self.config = cfg = config if config is not None else DQNConfig()
        self.obs_space, self.action_space = obs_space, action_space
        self.obs_shape = tuple(obs_space.shape)
        obs_dim, self.n_actions = int(np.prod(self.obs_shape)), int(action_space.n)
        if cfg.obs_scale is not None and len(cfg.obs_scale) != obs_dim:
            raise ValueError(f"obs_scale has {len(cfg.obs_scale)} entries for observations of shape {self.obs_shape}")
        with _GLOBAL_RNG, torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed if init_seed is None else init_seed)
            self.actor = mlp(obs_dim, cfg.hidden_sizes, self.n_actions, cfg.activation, ortho=False, out_gain=1.0)
        self.critic = nn.Module()  # DQN has no critic: nothing of it travels
        self.target = copy.deepcopy(self.actor).requires_grad_(False)
        self.actor_optimizer = Adam(self.actor.parameters(), lr=cfg.actor_lr)
        self.generator = torch.Generator().manual_seed(seed + 1_000_003)
        self.env_steps = self.gradient_steps = 0
        self._finite = FiniteTransitions("DQN")
        self._window: deque[tuple[np.ndarray, int, float]] = deque()  # the open n-step window of this episode
        self._replay: list[Transition] = []  # a ring of replay_size: the oldest is overwritten when it is full
        self._pos = 0
        self._pending = 0
        self._episode_gradient: dict[str, np.ndarray] | None = None

    # -- acting and storing ----------------------------------------------------------------------------------------

    @property
    def rejected_transitions(self) -> int:
        """Transitions ``remember`` refused because a value was not finite."""
        return self._finite.refused

    def _obs_tensor(self, obs: Any) -> torch.Tensor:
        x = torch.as_tensor(np.asarray(obs, dtype=np.float32)).reshape(-1, int(np.prod(self.obs_shape)))
        return x if self.config.obs_scale is None else x * torch.tensor(self.config.obs_scale)

    @torch.no_grad()
    def act(self, obs: Any) -> Any:
        """Epsilon-greedy: a uniform action with probability epsilon(env steps), else the arg-max of Q."""
        if float(torch.rand((), generator=self.generator)) < epsilon(self.config, self.env_steps):
            return np.int64(torch.randint(self.n_actions, (), generator=self.generator).item())
        return self.act_greedy(obs)

    @torch.no_grad()
    def act_greedy(self, obs: Any) -> Any:
        return np.int64(self.actor(self._obs_tensor(obs)).argmax(dim=-1)[0].item())

    def remember(self, obs: Any, action: Any, reward: float, next_obs: Any, terminated: bool,
                 truncated: bool) -> None:
        """Add the step to the episode's n-step window; a full window (or the episode's end, for every step left in
        it) becomes a replay transition <s_t, a_t, R_t^(m), s_{t+m}, terminated, gamma^m>. A transition with a value
        that is not finite is refused, counted (``rejected_transitions``) and logged (worker.sac.FiniteTransitions);
        it ends the window, and the steps still in it are dropped with it (their returns would run through it)."""
        self.env_steps += 1
        if not self._finite.admit(reward, obs, next_obs, action):
            self._window.clear()
            return
        self._window.append((np.asarray(obs, dtype=np.float32).reshape(-1), int(action),
                             float(reward) * self.config.reward_scale))
        nxt = np.asarray(next_obs, dtype=np.float32).reshape(-1)
        if len(self._window) == self.config.n_step:
            self._emit(nxt, False)
        if terminated or truncated:
            while self._window:
                self._emit(nxt, bool(terminated))

    def _emit(self, next_obs: np.ndarray, terminated: bool) -> None:
        ret, discount = n_step_return([r for _, _, r in self._window], self.config.gamma)
        obs, action, _ = self._window.popleft()
        self._store((obs, action, ret, next_obs, terminated, discount))
        self._pending += 1

    def _store(self, transition: Transition) -> None:
        if len(self._replay) < self.config.replay_size:
            self._replay.append(transition)
        else:
            self._replay[self._pos] = transition
            self._pos = (self._pos + 1) % self.config.replay_size

    def _ordered(self) -> list[Transition]:
        """The replay, oldest first."""
        return self._replay[self._pos:] + self._replay[:self._pos]

    @property
    def memory_size(self) -> int:
        return len(self._replay)

    # -- updates ------------------------------------------------------------------------------------------------

    def update(self) -> UpdateStats:
        """round(utd_ratio * n) gradient steps for the n transitions stored since the last update (at least one; none
        while the replay holds fewer than ``learning_starts``); records the episode's mean Q-network gradient."""
        new, batch = self._pending, self.prepare()
        steps = 0 if batch.n < max(self.config.learning_starts, 1) else max(1, round(self.config.utd_ratio * new))
        grad_sum = {name: np.zeros(p.shape, np.float64) for name, p in self.actor.named_parameters()}
        losses, taken = [], 0
        for _ in range(steps):
            step = self.minibatch_gradients(batch)
            self.apply_step(step.critic, step.actor)
            if step.actor is not None:
                taken += 1
                losses.append(step.actor_loss)
                for name, g in step.actor.items():
                    grad_sum[name] += g
        self._episode_gradient = {k: (g / max(taken, 1)).astype(np.float32) for k, g in grad_sum.items()}
        loss = float(np.mean(losses)) if losses else 0.0
        return UpdateStats(actor_loss=loss, critic_loss=loss, entropy=math.nan, approx_kl=math.nan,
                           clip_fraction=math.nan, memory_size=batch.n, skipped_steps=steps - taken)

    def prepare(self) -> SACBatch:
        """The K steps of this episode draw from the replay as it is now (no step below ``learning_starts``)."""
        self._pending = 0
        return SACBatch(n=len(self._replay), steps=self.config.update_epochs)

    def minibatch_gradients(self, batch: SACBatch) -> StepGradients:
        """One mini-batch's gradient of the TD loss against the Double DQN target, norm-clipped when configured;
        the actor's (the Q network's), None where not finite and while the replay holds fewer than
        ``learning_starts``; the critic's is empty (there is none)."""
        cfg = self.config
        if batch.n < max(cfg.learning_starts, 1):
            return StepGradients(critic={}, actor=None, actor_loss=math.nan, critic_loss=math.nan,
                                 entropy=math.nan, approx_kl=math.nan, clip_fraction=math.nan)
        idx = torch.randint(0, min(batch.n, len(self._replay)), (cfg.batch_size,), generator=self.generator)
        size = len(self._replay)
        rows = [self._replay[(self._pos + i) % size] for i in idx.tolist()]  # logical index i: the i-th oldest
        obs = self._obs_tensor(np.stack([r[0] for r in rows]))
        next_obs = self._obs_tensor(np.stack([r[3] for r in rows]))
        actions = torch.tensor([r[1] for r in rows])
        returns, discounts = (torch.tensor([r[i] for r in rows], dtype=torch.float32) for i in (2, 5))
        with torch.no_grad():
            target = double_q_target(returns, discounts, torch.tensor([r[4] for r in rows]), self.actor(next_obs),
                                     self.target(next_obs))
        loss = td_loss(self.actor(obs).gather(1, actions.unsqueeze(-1)).squeeze(-1), target)
        grads = None
        if torch.isfinite(loss):
            named = list(self.actor.named_parameters())
            raw = torch.autograd.grad(loss, [p for _, p in named])
            if cfg.max_grad_norm is not None:
                total = torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in raw]))
                raw = tuple(g * torch.clamp(cfg.max_grad_norm / (total + 1e-6), max=1.0) for g in raw)
            grads = {n: g.numpy().astype(np.float32, copy=True) for (n, _), g in zip(named, raw, strict=True)}
            if not all(bool(np.isfinite(g).all()) for g in grads.values()):
                grads = None
        return StepGradients(critic={}, actor=grads, actor_loss=loss.item(), critic_loss=loss.item(),
                             entropy=math.nan, approx_kl=math.nan, clip_fraction=math.nan)

    def apply_step(self, critic: Mapping[str, np.ndarray] | None, actor: Mapping[str, np.ndarray] | None) -> None:
        """One Q-network step with ``actor`` (None or all zeros: none), counting it; every ``target_update_interval``
        steps the target network becomes a copy of the Q network. ``critic`` is ignored (there is none)."""
        del critic
        if actor is None or not any(np.any(g) for g in actor.values()):
            return
        self.apply_gradient(actor)
        self.gradient_steps += 1
        if self.gradient_steps % self.config.target_update_interval == 0:
            self.target.load_state_dict(self.actor.state_dict())

    # -- federation hooks ---------------------------------------------------------------------------------------

    def actor_spec(self) -> dict[str, tuple[int, ...]]:
        return {name: tuple(p.shape) for name, p in self.actor.named_parameters()}

    def critic_spec(self) -> dict[str, tuple[int, ...]]:
        return {}

    def actor_parameters(self) -> dict[str, np.ndarray]:
        return {name: p.detach().numpy().astype(np.float32, copy=True) for name, p in self.actor.named_parameters()}

    def actor_gradient(self) -> dict[str, np.ndarray]:
        """The last ``update()``'s mean Q-network gradient (zeros after no step)."""
        if self._episode_gradient is None:
            raise RuntimeError("no actor gradient yet: call update() first")
        return {name: g.copy() for name, g in self._episode_gradient.items()}

    def apply_gradient(self, grad: Mapping[str, np.ndarray]) -> None:
        """One Adam step of the Q network with ``grad`` (Algorithm 2's g_bar); nothing for all zeros."""
        if not any(np.any(g) for g in grad.values()):
            return
        self.actor_optimizer.zero_grad()
        for name, g in _tensors(grad, self.actor).items():
            self.actor.get_parameter(name).grad = g
        self.actor_optimizer.step()
        self.actor_optimizer.zero_grad()

    @torch.no_grad()
    def blend_actor(self, params: Mapping[str, Any], keep_weight: float) -> None:
        """Eq. 11 on the Q network: theta = w_T theta + (1 - w_T) theta_bar (the target network stays)."""
        blend(self.actor, params, keep_weight)

    # -- persistence --------------------------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Networks, optimizer, counters, RNG state and config; not the replay (``memory_state``)."""
        return {"algo": "dqn", "config": asdict(self.config), "actor": self.actor.state_dict(),
                "critic": {}, "target": self.target.state_dict(),
                "actor_optimizer": self.actor_optimizer.state_dict(), "generator": self.generator.get_state(),
                "counters": torch.tensor([self.env_steps, self.gradient_steps], dtype=torch.int64)}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        if state.get("algo") != "dqn":
            raise ValueError(f"not a DQN checkpoint (algo {state.get('algo')!r})")
        config = DQNConfig.from_dict(state["config"])
        if (config.hidden_sizes, config.activation) != (self.config.hidden_sizes, self.config.activation):
            raise ValueError("checkpoint architecture does not match")
        self.warm_start(state)
        self.generator.set_state(state["generator"])
        self.env_steps, self.gradient_steps = (int(x) for x in state["counters"])
        kept = self._ordered()[-config.replay_size:]
        self.config = config
        self._replay, self._pos = kept, 0

    def memory_state(self) -> dict[str, torch.Tensor]:
        """The replay (oldest first), with ``pending``; the open n-step window is not kept (a resumed worker starts
        a new episode)."""
        if not self._replay:
            return {}
        obs, actions, returns, next_obs, terminated, discounts = zip(*self._ordered(), strict=True)
        return {"obs": torch.from_numpy(np.stack(obs)), "actions": torch.tensor(actions),
                "returns": torch.tensor(returns, dtype=torch.float64), "next_obs": torch.from_numpy(np.stack(next_obs)),
                "terminated": torch.tensor(terminated), "discounts": torch.tensor(discounts, dtype=torch.float64),
                "pending": torch.tensor(self._pending)}

    def load_memory(self, state: Mapping[str, torch.Tensor]) -> None:
        self._replay, self._pos = [], 0
        self._window.clear()
        n = len(state["actions"]) if state else 0
        for i in range(n):
            self._store((state["obs"][i].numpy().copy(), int(state["actions"][i]), float(state["returns"][i]),
                                 state["next_obs"][i].numpy().copy(), bool(state["terminated"][i]),
                                 float(state["discounts"][i])))
        self._pending = min(int(state["pending"]), len(self._replay)) if n else 0

    def warm_start(self, state: Mapping[str, Any]) -> None:
        """Another DQN model's Q network, target network and Adam moments (this learner's learning rate)."""
        self.actor.load_state_dict(state["actor"])
        self.target.load_state_dict(state["target"])
        take_optimizers(state, (("actor_optimizer", self.actor_optimizer, self.config.actor_lr),))

    def save(self, path: str | Path, provenance: Mapping[str, Any] | None = None) -> None:
        save_model(self.state_dict(), path, provenance)
