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
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch
from gymnasium import spaces
from torch import nn

from worker.adam import Adam
from worker.nets import FromDict, StepGradients, UpdateStats, mlp
from worker.offpolicy import OffPolicyLearner, ReplayBatch
from worker.replay import FiniteTransitions


@dataclass
class DQNConfig(FromDict):
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
        self._validate(positive=("utd_ratio",), at_least_one=("n_step", "replay_size", "target_update_interval"),
                       problems=((self.learning_starts < 0 or self.eps_decay_steps < 0,
                                  "learning_starts and eps_decay_steps must be >= 0"),
                                 (not 0.0 <= self.eps_end <= self.eps_start <= 1.0,
                                  "need 0 <= eps_end <= eps_start <= 1")))


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


class DQNLearner(OffPolicyLearner):
    """One worker's Double DQN: acting (epsilon-greedy), the n-step window into the replay, the TD loss; the replay,
    the schedule and the federation's seams are worker/offpolicy.py's (``seed`` and ``init_seed``: worker/
    federation.py)."""

    ALGO = "dqn"
    CONFIG = DQNConfig
    NETWORKS = ("actor", "critic", "target")
    OPTIMIZERS: ClassVar[dict[str, str]] = {"actor_optimizer": "actor_lr"}
    GRADIENT_DTYPE = np.float64

    def _build(self, obs_dim: int, action_space: spaces.Space) -> None:
        if not isinstance(action_space, spaces.Discrete):
            raise ValueError(f"DQN needs Discrete actions, got {action_space!r} (use sac or ppo)")
        cfg, self.n_actions = self.config, int(action_space.n)
        self.actor = mlp(obs_dim, cfg.hidden_sizes, self.n_actions, cfg.activation, ortho=False, out_gain=1.0)
        self.critic = nn.Module()  # DQN has no critic: nothing of it travels
        self.target = copy.deepcopy(self.actor).requires_grad_(False)
        self.actor_optimizer = Adam(self.actor.parameters(), lr=cfg.actor_lr)
        self.env_steps = self.gradient_steps = 0
        self._finite = FiniteTransitions("DQN")
        self._window: deque[tuple[np.ndarray, int, float]] = deque()  # the open n-step window of this episode

    def _columns(self) -> dict[str, tuple[tuple[int, ...], Any]]:
        """A replay transition: s_t, a_t, R_t^(m), s_{t+m}, terminated, gamma^m."""
        obs = ((int(np.prod(self.obs_shape)),), np.float32)
        return {"obs": obs, "actions": ((), np.int64), "returns": ((), np.float64), "next_obs": obs,
                "terminated": ((), bool), "discounts": ((), np.float64)}

    # -- acting and storing ----------------------------------------------------------------------------------------

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
        that is not finite is refused, counted (``rejected_transitions``) and logged (worker.replay.FiniteTransitions);
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
        self.replay.add(obs=obs, actions=action, returns=ret, next_obs=next_obs, terminated=terminated,
                        discounts=discount)

    # -- updates ------------------------------------------------------------------------------------------------

    def update(self) -> UpdateStats:
        """round(utd_ratio * n) gradient steps for the n transitions stored since the last update (at least one; none
        while the replay holds fewer than ``learning_starts``); records the episode's mean Q-network gradient. Its
        statistics: the mean TD loss (as both losses; no entropy)."""
        batch, steps = self._episode_steps()
        losses = [s.actor_loss for s in steps if s.actor is not None]
        loss = float(np.mean(losses)) if losses else 0.0
        return UpdateStats(actor_loss=loss, critic_loss=loss, entropy=math.nan, **self._statistics(batch, steps))

    def minibatch_gradients(self, batch: ReplayBatch) -> StepGradients:
        """One mini-batch's gradient of the TD loss against the Double DQN target, norm-clipped when configured;
        the actor's (the Q network's), None where not finite and while the replay holds fewer than
        ``learning_starts``; the critic's is empty (there is none)."""
        if not self._learning(batch):
            return StepGradients(critic={}, actor=None, actor_loss=math.nan, critic_loss=math.nan, entropy=math.nan)
        rows = self.replay.sample(batch.n, self.config.batch_size, self.generator)
        obs, next_obs = self._obs_tensor(rows["obs"]), self._obs_tensor(rows["next_obs"])
        actions = torch.from_numpy(rows["actions"])
        returns, discounts = (torch.from_numpy(rows[c]).float() for c in ("returns", "discounts"))
        with torch.no_grad():
            target = double_q_target(returns, discounts, torch.from_numpy(rows["terminated"]), self.actor(next_obs),
                                     self.target(next_obs))
        loss = td_loss(self.actor(obs).gather(1, actions.unsqueeze(-1)).squeeze(-1), target)
        return StepGradients(critic={}, actor=self._gradients(loss, self.actor), actor_loss=loss.item(),
                             critic_loss=loss.item(), entropy=math.nan)

    def apply_step(self, critic: Mapping[str, np.ndarray] | None, actor: Mapping[str, np.ndarray] | None) -> None:
        """One Q-network step with ``actor`` (None or all zeros: none), counting it; every ``target_update_interval``
        steps the target network becomes a copy of the Q network. ``critic`` is ignored (there is none)."""
        del critic
        if not self._step(self.actor, self.actor_optimizer, actor):
            return
        self.gradient_steps += 1
        if self.gradient_steps % self.config.target_update_interval == 0:
            self.target.load_state_dict(self.actor.state_dict())

    # -- persistence beyond the declared names ------------------------------------------------------------------

    def _own_state(self) -> dict[str, Any]:
        return {"counters": torch.tensor([self.env_steps, self.gradient_steps], dtype=torch.int64)}

    def _load_own(self, state: Mapping[str, Any]) -> None:
        self.env_steps, self.gradient_steps = (int(x) for x in state["counters"])

    def load_memory(self, state: Mapping[str, torch.Tensor]) -> None:
        """Replace the replay with ``memory_state()`` output; the open n-step window is not kept (a resumed worker
        starts a new episode)."""
        super().load_memory(state)
        self._window.clear()
