"""The federation's seams of a learner, written once (``FederatedLearner``): the episode gradient that the chief
aggregates (paper Eq. 8-9), the actor's spec, parameters, blend (Eq. 11) and step, and persistence, declared by name.

A learner (worker/ppo.py, worker/sac.py, worker/dqn.py) subclasses it and declares:

- ``ALGO`` (its registry name, worker/learners.py), ``CONFIG`` (its configuration dataclass) and ``BATCH`` (what its
  ``prepare`` returns, rebuilt from ``vars(batch)`` when a worker resumes);
- ``NETWORKS``: its attributes that a model holds and a warm start takes (modules, or tensors such as SAC's log
  alpha), by name; ``OPTIMIZERS``: each optimizer's attribute and the configuration field of its learning rate;
- ``MEMORY``: the attribute of its memory (a ``worker.replay.Replay`` of the columns ``_columns`` declares: by default
  s, a, r, s' and the episode's flags) and the configuration field of its capacity;
- ``STEP``: its ``StepGradients`` class, when its steps report more than the common statistics;
- ``GRADIENT_DTYPE``: the precision the episode gradient is summed in; ``SKIP_ZERO_STEPS``: whether an optimizer
  step with all-zero gradients (no worker had one) is skipped, so that Adam's moments stay as they are.

The base's ``__init__`` takes the spaces, then the learner's ``_build`` builds ``actor``, ``critic``, the optimizers and
whatever else it names (the base then makes the generator and the memory); the learner writes its own acting (``act``,
and ``_to_env`` for the greedy action ``actor.greedy`` gives), ``remember``, ``prepare``, ``minibatch_gradients`` (with
``_gradients``), ``apply_step`` (with ``_step``) and ``update`` (with ``_steps``, the loop that records the episode
gradient, and ``_statistics``). ``_own_state``/``_load_own`` carry what it saves beyond the declared names.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from gymnasium import spaces
from torch import nn

from protocol.tensors import NORM_LIMIT, l2_norm
from worker.adam import Adam
from worker.nets import StepGradients, blend, seeded, tensors
from worker.replay import Replay


class FederatedLearner:
    """The seams every federation strategy uses, over the attributes a learner declares (see the module).

    A learner is built as ``Learner(obs_space, action_space, config, seed=..., init_seed=...)``. ``seed`` fixes all
    of its randomness (network init, acting, mini-batch draws, the samples inside its losses: a private
    ``torch.Generator``, the global RNGs are left alone), so the same seed and the same transitions give the same
    parameters. ``init_seed``, when given, seeds only the network init: federated workers share it, so that they
    start from the same networks (as clients of federated learning start from one global model) and the shared
    gradient (Eq. 9) and the parameter blend (Eq. 11) act on aligned parameters.
    """

    ALGO: ClassVar[str]
    CONFIG: ClassVar[Any]
    NETWORKS: ClassVar[tuple[str, ...]]
    OPTIMIZERS: ClassVar[dict[str, str]]
    BATCH: ClassVar[type]
    STEP: ClassVar[type[StepGradients]] = StepGradients
    GRADIENT_DTYPE: ClassVar[type[np.floating]] = np.float32
    SKIP_ZERO_STEPS: ClassVar[bool] = False
    #: The memory (worker/replay.py) that never leaves the device: its attribute, and the configuration field of its
    #: capacity.
    MEMORY: ClassVar[tuple[str, str]] = ("replay", "replay_size")

    actor: Any  # an nn.Module, of the learner's own class
    critic: Any
    actor_optimizer: Adam
    _episode_gradient: dict[str, np.ndarray] | None = None

    # -- building: the observations, the networks, the memory -----------------------------------------------------

    def __init__(self, obs_space: spaces.Space, action_space: spaces.Space, config: Any = None, seed: int = 0,
                 init_seed: int | None = None) -> None:
        """Take the spaces (observations must be a Box; ``config.obs_scale``, when given, one entry per dimension; a
        ``CONFIG()`` when no config), ``_build`` the learner with its networks drawn from ``init_seed`` (else ``seed``),
        then the generator of everything else from ``seed`` and an empty memory."""
        self.config = config if config is not None else self.CONFIG()
        if not isinstance(obs_space, spaces.Box):
            raise ValueError(f"unsupported observation space {obs_space!r}: use a Box")
        self.obs_shape = tuple(obs_space.shape)
        obs_dim = int(np.prod(self.obs_shape))
        scale = self.config.obs_scale
        if scale is not None and len(scale) != obs_dim:
            raise ValueError(f"obs_scale has {len(scale)} entries for observations of shape {self.obs_shape}")
        self._obs_scale = None if scale is None else torch.tensor(scale, dtype=torch.float32).reshape(self.obs_shape)
        with seeded(seed if init_seed is None else init_seed):
            self._build(obs_dim, action_space)
        self.generator = torch.Generator().manual_seed(seed + 1_000_003)
        self.load_memory({})

    def _build(self, obs_dim: int, action_space: spaces.Space) -> None:
        """The learner's networks (``obs_dim`` inputs; their initial weights from the init seed), its optimizers and
        whatever else it keeps."""
        raise NotImplementedError

    def _obs_tensor(self, obs: Any) -> torch.Tensor:
        """The networks' input of one observation or a batch: float32, times ``obs_scale``, flat per sample."""
        x = torch.as_tensor(np.asarray(obs, dtype=np.float32)).reshape(-1, *self.obs_shape)
        if self._obs_scale is not None:
            x = x * self._obs_scale
        return self._normalized(x).flatten(1)

    def _normalized(self, x: torch.Tensor) -> torch.Tensor:
        """A learner's own normalisation of its scaled inputs (PPO's running statistics); none by default."""
        return x

    # -- the episode's gradient steps -----------------------------------------------------------------------------

    def _steps(self, batch: Any, n: int) -> list[StepGradients]:
        """``n`` gradient steps (``minibatch_gradients`` then ``apply_step`` with its own gradients), recording the
        episode gradient g_theta^n sent to the chief (Eq. 8-9): the mean of the steps' applied actor gradients (after
        clipping; zeros after no step). The paper says "the last gradient"; the mean over the episode estimates the
        same direction with less mini-batch noise. Returns the steps, for the learner's statistics."""
        grad_sum = {name: np.zeros(tuple(p.shape), self.GRADIENT_DTYPE) for name, p in self.actor.named_parameters()}
        steps, actor_steps = [], 0
        for _ in range(n):
            step = self.minibatch_gradients(batch)
            self.apply_step(step.critic, step.actor)
            steps.append(step)
            if step.actor is not None:
                actor_steps += 1
                for name, g in step.actor.items():
                    grad_sum[name] += g
        self._episode_gradient = {name: (g / max(actor_steps, 1)).astype(np.float32) for name, g in grad_sum.items()}
        return steps

    @staticmethod
    def _statistics(batch: Any, steps: list[StepGradients], means: tuple[str, ...] = ()) -> dict[str, Any]:
        """An update's statistics every learner has: the memory's size when ``batch`` was prepared, the critic and actor
        steps skipped because a loss or gradient was not finite, and the mean over the steps of each statistic
        ``means`` names (zeros after none)."""
        totals = dict.fromkeys(means, 0.0)
        for step in steps:
            for key in totals:
                totals[key] += getattr(step, key)
        return {**{key: value / max(len(steps), 1) for key, value in totals.items()}, "memory_size": batch.n,
                "skipped_steps": sum((s.critic is None) + (s.actor is None) for s in steps)}

    def _gradients(self, loss: torch.Tensor, net: nn.Module) -> dict[str, np.ndarray] | None:
        """The gradient of ``loss`` with respect to ``net``'s parameters only (torch.autograd.grad: nothing is
        accumulated in any .grad), norm-clipped when configured; None when the loss or a gradient is not finite, or
        its norm exceeds the protocol's NORM_LIMIT (so a numerical blow-up never reaches the parameters or the chief,
        which refuses such a gradient: a refused update would leave its round waiting for this worker)."""
        if not torch.isfinite(loss):
            return None
        named = list(net.named_parameters())
        raw = torch.autograd.grad(loss, [p for _, p in named], allow_unused=True)
        grads = [torch.zeros_like(p) if g is None else g.detach() for (_, p), g in zip(named, raw, strict=True)]
        if self.config.max_grad_norm is not None:
            total = torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in grads]))
            coef = torch.clamp(self.config.max_grad_norm / (total + 1e-6), max=1.0)
            grads = [g * coef for g in grads]
        out = {name: g.numpy().astype(np.float32, copy=True) for (name, _), g in zip(named, grads, strict=True)}
        return out if l2_norm(out) <= NORM_LIMIT else None  # inf when a value is not finite

    # -- what each learner writes: acting, its memory, its update -------------------------------------------------

    @torch.no_grad()
    def act(self, obs: Any) -> Any:
        """Sample a_t ~ pi_theta(.|s_t) (``actor.sample``, with the learner's generator), in the environment's
        units."""
        return self._to_env(self.actor.sample(self._obs_tensor(obs), self.generator)[0])

    @torch.no_grad()
    def act_greedy(self, obs: Any) -> Any:
        """The deterministic action (``actor.greedy``: arg-max or the Gaussian's mean), for evaluation."""
        return self._to_env(self.actor.greedy(self._obs_tensor(obs))[0])

    def _to_env(self, action: torch.Tensor) -> Any:
        """One of the actor's actions as the environment takes it."""
        raise NotImplementedError

    def remember(self, obs: Any, action: Any, reward: float, next_obs: Any, terminated: bool,
                 truncated: bool) -> None:
        raise NotImplementedError

    def update(self) -> Any:
        raise NotImplementedError

    def prepare(self) -> Any:
        raise NotImplementedError

    def minibatch_gradients(self, batch: Any) -> StepGradients:
        raise NotImplementedError

    def apply_step(self, critic: Mapping[str, np.ndarray] | None, actor: Mapping[str, np.ndarray] | None) -> None:
        raise NotImplementedError

    def _columns(self) -> dict[str, tuple[tuple[int, ...], Any]]:
        """The memory's columns, name -> (shape, dtype) of one transition's value; by default s_t, a_t (an index, or
        the flat vector of a Box action), r_{t+1}, s_{t+1} and the episode's flags."""
        obs = (self.obs_shape, np.float32)
        actions = ((), np.int64) if self.actor.discrete else ((self.actor.action_dim,), np.float32)
        return {"obs": obs, "actions": actions, "rewards": ((), np.float64), "next_obs": obs,
                "terminated": ((), bool), "truncated": ((), bool)}

    def memory_state(self) -> dict[str, torch.Tensor]:
        """The memory (which spans episodes) as tensors, oldest first, with ``pending`` (transitions not yet used by an
        update), for a worker's resumable state (worker/resume.py); ``load_memory`` restores it exactly."""
        memory: Replay = getattr(self, self.MEMORY[0])
        return memory.state()

    def load_memory(self, state: Mapping[str, torch.Tensor]) -> None:
        """Replace the memory with ``memory_state()`` output (its newest transitions, as many as the capacity; ``{}``:
        empty)."""
        name, capacity = self.MEMORY
        memory = Replay(getattr(self.config, capacity), self._columns())
        memory.load(state)
        setattr(self, name, memory)

    def _step(self, net: nn.Module, optimizer: Adam, grads: Mapping[str, np.ndarray] | None) -> bool:
        """One optimizer step of ``net`` with ``grads``; none (False) for None, or all zeros when SKIP_ZERO_STEPS."""
        if grads is None or (self.SKIP_ZERO_STEPS and not any(np.any(g) for g in grads.values())):
            return False
        optimizer.zero_grad()
        for name, g in tensors(grads, net).items():
            net.get_parameter(name).grad = g
        optimizer.step()
        optimizer.zero_grad()
        return True

    # -- the actor, as the chief sees it ----------------------------------------------------------------------------

    def actor_spec(self) -> dict[str, tuple[int, ...]]:
        """Names and shapes of the actor's parameters (``actor.named_parameters()`` order)."""
        return {name: tuple(p.shape) for name, p in self.actor.named_parameters()}

    def critic_spec(self) -> dict[str, tuple[int, ...]]:
        """Names and shapes of the critic's parameters (empty for a learner without one)."""
        return {name: tuple(p.shape) for name, p in self.critic.named_parameters()}

    def actor_parameters(self) -> dict[str, np.ndarray]:
        """A float32 copy of theta."""
        return {name: p.detach().numpy().astype(np.float32, copy=True) for name, p in self.actor.named_parameters()}

    def actor_gradient(self) -> dict[str, np.ndarray]:
        """g_theta^n of the last ``update()`` (float32; see ``_steps``)."""
        if self._episode_gradient is None:
            raise RuntimeError("no actor gradient yet: call update() first")
        return {name: g.copy() for name, g in self._episode_gradient.items()}

    def apply_gradient(self, grad: Mapping[str, np.ndarray]) -> None:
        """Algorithm 2, "update pi_theta with the received g_bar": one actor-optimizer (Adam) step with ``grad``
        (nothing else: no critic, temperature or target step)."""
        self._step(self.actor, self.actor_optimizer, grad)

    def blend_actor(self, params: Mapping[str, Any], keep_weight: float) -> None:
        """Eq. 11 in place: theta = w_T * theta + (1 - w_T) * theta_bar, with w_T = ``keep_weight`` in [0, 1]. Only the
        actor is blended (critics, targets, temperature and observation statistics stay the worker's own). A
        ValueError for a weight outside [0, 1], before anything changed."""
        blend(self.actor, params, keep_weight)

    # -- persistence, declared by name ------------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """The learner's name, config, declared networks and optimizers, RNG state and its own extras (not the memory:
        ``memory_state``)."""
        state: dict[str, Any] = {"algo": self.ALGO, "config": asdict(self.config)}
        for name in self.NETWORKS:
            value = getattr(self, name)
            state[name] = value.detach().clone() if isinstance(value, torch.Tensor) else value.state_dict()
        for name in self.OPTIMIZERS:
            state[name] = getattr(self, name).state_dict()
        return {**state, "generator": self.generator.get_state(), **self._own_state()}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore ``state_dict()`` output (a ValueError for another learner's or another architecture's)."""
        if state.get("algo", "ppo") != self.ALGO:
            raise ValueError(f"not a {self.ALGO.upper()} checkpoint (algo {state.get('algo')!r})")
        config = self.CONFIG.from_dict(state["config"])
        theirs, ours = ([c.hidden_sizes, c.activation] for c in (config, self.config))
        if theirs != ours:
            raise ValueError(f"checkpoint architecture {theirs} does not match {ours}")
        self._load_networks(state)
        for name in self.OPTIMIZERS:
            getattr(self, name).load_state_dict(state[name])
        self.generator.set_state(state["generator"])
        self._load_own(state)
        self.config = config
        self.load_memory(self.memory_state())  # fit the memory to the saved configuration

    def _load_networks(self, state: Mapping[str, Any]) -> None:
        for name in self.NETWORKS:
            value = getattr(self, name)
            if isinstance(value, torch.Tensor):
                with torch.no_grad():
                    value.copy_(state[name])
            else:
                value.load_state_dict(state[name])

    def warm_start(self, state: Mapping[str, Any]) -> None:
        """Start from another learner's ``state_dict()`` (``--init-model``): its declared networks and its optimizers'
        Adam moments with this learner's learning rates, so that fine-tuning goes on where the model's training
        stopped. Not taken: its configuration (the caller checked the architecture is the same) and its sampling RNG
        (each worker keeps its own seed's)."""
        self._load_networks(state)
        for name, lr in self.OPTIMIZERS.items():
            if name in state:
                optimizer = getattr(self, name)
                optimizer.load_state_dict(state[name])
                for group in optimizer.param_groups:
                    group["lr"] = getattr(self.config, lr)

    def temper(self, temperature: float) -> None:
        """The policy at ``temperature`` (0 < T <= 1) from now on, at a warm start (--warm-temperature); a learner
        without one (protocol/learners.py ``TEMPERED``) refuses it."""
        raise ValueError(f"{self.ALGO} has no policy temperature to set")

    def scale_learning_rates(self, factor: float) -> None:
        """Every optimizer's learning rate at ``factor`` times its configured one (``OPTIMIZERS``); the Adam moments
        are kept (a warm start's gentle rates, worker/federated.py ``warm_factor``)."""
        for name, lr in self.OPTIMIZERS.items():
            for group in getattr(self, name).param_groups:
                group["lr"] = factor * getattr(self.config, lr)

    def _own_state(self) -> dict[str, Any]:
        """What ``state_dict`` saves beyond the declared names."""
        return {}

    def _load_own(self, state: Mapping[str, Any]) -> None:
        """Restore ``_own_state``."""

    def save(self, path: str | Path, provenance: Mapping[str, Any] | None = None) -> None:
        """``state_dict()`` to ``path``, with the model's ``provenance`` (worker/model.py) when given."""
        state = self.state_dict()
        if provenance is not None:
            state["provenance"] = dict(provenance)
        torch.save(state, Path(path))

    def load(self, path: str | Path) -> None:
        self.load_state_dict(torch.load(Path(path), weights_only=True))
