"""The worker's learners, a registry as the chief's strategies are (chief/strategies). Their names and one-line
descriptions are the wire's (protocol/learners.py); this module maps each name to its module, whose learner has the
seams every federation strategy uses (``Learner``):

- acting and storing: ``act``, ``act_greedy``, ``remember`` (the memory, or replay buffer, never leaves the device);
- per-episode strategies: ``update()`` after an episode, then ``actor_gradient()`` goes to the chief, whose answer is
  ``apply_gradient`` (Eq. 9) or ``blend_actor`` (Eq. 11);
- per-step strategies: ``prepare()``, then K times ``minibatch_gradients`` and ``apply_step`` with the chief's mean;
- persistence: ``state_dict``/``load_state_dict``, ``memory_state``/``load_memory``, ``warm_start``, ``save``.

``python -m worker.learners`` lists them.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Protocol

from gymnasium import spaces

from protocol import learners


class LearnerConfig(Protocol):
    """What the federation reads of a learner's configuration: K, its mini-batch steps per episode under a per-step
    strategy (the rounds per episode of ``sync``), and the fields a warm start compares."""

    update_epochs: int
    hidden_sizes: tuple[int, ...]
    activation: str
    obs_scale: tuple[float, ...] | None


class Learner(Protocol):
    """The seams of a worker's learner (worker/ppo.py ``PPOLearner`` is the model)."""

    config: Any
    actor: Any
    critic: Any
    STEP: type  # its StepGradients class (worker/nets.py), rebuilt when a worker resumes mid-episode

    def act(self, obs: Any) -> Any: ...
    def act_greedy(self, obs: Any) -> Any: ...
    def remember(self, obs: Any, action: Any, reward: float, next_obs: Any, terminated: bool,
                 truncated: bool) -> None: ...
    def update(self) -> Any: ...
    def prepare(self) -> Any: ...
    def minibatch_gradients(self, batch: Any) -> Any: ...
    def apply_step(self, critic: Mapping[str, Any] | None, actor: Mapping[str, Any] | None) -> None: ...
    def actor_spec(self) -> dict[str, tuple[int, ...]]: ...
    def critic_spec(self) -> dict[str, tuple[int, ...]]: ...
    def actor_parameters(self) -> dict[str, Any]: ...
    def actor_gradient(self) -> dict[str, Any]: ...
    def apply_gradient(self, grad: Mapping[str, Any]) -> None: ...
    def blend_actor(self, params: Mapping[str, Any], keep_weight: float) -> None: ...
    def state_dict(self) -> dict[str, Any]: ...
    def load_state_dict(self, state: Mapping[str, Any]) -> None: ...
    def memory_state(self) -> dict[str, Any]: ...
    def load_memory(self, state: Mapping[str, Any]) -> None: ...
    def warm_start(self, state: Mapping[str, Any]) -> None: ...
    def save(self, path: str | Path, provenance: Mapping[str, Any] | None = None) -> None: ...


@dataclass(frozen=True)
class LearnerKind:
    """Where a learner lives: ``module`` defines the learner class ``learner``, its configuration dataclass
    ``config`` and the per-step batch ``batch`` (rebuilt from ``vars(batch)`` when a worker resumes)."""

    name: str
    module: str
    learner: str
    config: str
    batch: str

    def _attr(self, name: str) -> Any:
        return getattr(importlib.import_module(self.module), name)

    @property
    def learner_class(self) -> type:
        return self._attr(self.learner)

    @property
    def config_class(self) -> Any:
        return self._attr(self.config)

    @property
    def batch_class(self) -> type:
        return self._attr(self.batch)

    def config_fields(self) -> list[str]:
        return [f.name for f in fields(self.config_class)]

    def build(self, obs_space: spaces.Space, action_space: spaces.Space, config: Any, seed: int,
              init_seed: int | None = None) -> Learner:
        return self.learner_class(obs_space, action_space, config, seed=seed, init_seed=init_seed)


_KINDS: dict[str, LearnerKind] = {
    "ppo": LearnerKind("ppo", "worker.ppo", "PPOLearner", "PPOConfig", "Batch"),
    "sac": LearnerKind("sac", "worker.sac", "SACLearner", "SACConfig", "ReplayBatch"),
    "dqn": LearnerKind("dqn", "worker.dqn", "DQNLearner", "DQNConfig", "ReplayBatch"),
}
assert set(_KINDS) == set(learners.LEARNERS), "protocol/learners.py and worker/learners.py name the same learners"


def get(name: str) -> LearnerKind:
    """The learner called ``name``, or a ValueError listing the known ones."""
    return _KINDS[learners.check(name)]


def recorded(state: Mapping[str, Any]) -> str:
    """The learner a saved ``state_dict()`` was made by (models saved before learners had names are PPO's)."""
    algo = state.get("algo", "ppo")
    return algo if isinstance(algo, str) else "ppo"


def main(argv: list[str] | None = None) -> int:
    """``python -m worker.learners``: list the learners."""
    del argv
    for name, summary in learners.LEARNERS.items():
        print(f"{name:<6} {summary}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
