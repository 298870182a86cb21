"""The worker's learners, a registry as the chief's strategies are (chief/strategies). Their names and one-line
descriptions are the wire's (protocol/learners.py); this module maps each name to its module, whose learner subclasses
worker/federation.py's ``FederatedLearner`` (``Learner``) and so has the seams every federation strategy uses:

- acting and storing: ``act``, ``act_greedy``, ``remember`` (the memory, or replay buffer, never leaves the device);
- per-episode strategies: ``update()`` after an episode, then ``actor_gradient()`` goes to the chief, whose answer is
  ``apply_gradient`` (Eq. 9) or ``blend_actor`` (Eq. 11);
- per-step strategies: ``prepare()``, then K times ``minibatch_gradients`` and ``apply_step`` with the chief's mean;
- persistence: ``state_dict``/``load_state_dict``, ``memory_state``/``load_memory``, ``warm_start``, ``save``;
- ``scale_learning_rates``: a warm start's gentle rates (worker/federated.py ``warm_factor``).

``python -m worker.learners`` lists them.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

from protocol import learners
from worker.federation import FederatedLearner

#: The seams of a worker's learner: worker/federation.py's base, which every learner subclasses.
Learner = FederatedLearner


@dataclass(frozen=True)
class LearnerKind:
    """Where a learner lives: ``module`` defines the learner class ``learner``, which declares the rest (its
    configuration dataclass ``CONFIG``, its per-step batch ``BATCH``: worker/federation.py)."""

    name: str
    module: str
    learner: str

    @property
    def learner_class(self) -> type[FederatedLearner]:
        """The class: ``learner_class(obs_space, action_space, config, seed=..., init_seed=...)`` builds a learner."""
        return getattr(importlib.import_module(self.module), self.learner)

    @property
    def config_class(self) -> Any:
        return self.learner_class.CONFIG

    def config_fields(self) -> list[str]:
        return [f.name for f in fields(self.config_class)]


_KINDS: dict[str, LearnerKind] = {
    "ppo": LearnerKind("ppo", "worker.ppo", "PPOLearner"),
    "sac": LearnerKind("sac", "worker.sac", "SACLearner"),
    "dqn": LearnerKind("dqn", "worker.dqn", "DQNLearner"),
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
