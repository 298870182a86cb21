"""What the off-policy learners (worker/sac.py, worker/dqn.py) share beyond the federation's seams, as
Stable-Baselines3's OffPolicyAlgorithm: the replay buffer (worker/replay.py, saved as the federation's ``MEMORY``)
and the per-episode schedule of gradient steps (round(utd_ratio * new transitions), none before ``learning_starts``; a
fixed K = ``update_epochs`` under a per-step strategy).

A learner declares its replay's columns (``_columns``, unless the default's) and writes its acting, ``remember``,
``minibatch_gradients``, ``apply_step`` and the statistics of its ``update``. Its configuration has ``replay_size``,
``batch_size``, ``learning_starts``, ``utd_ratio``, ``update_epochs`` and ``max_grad_norm``.
"""

from __future__ import annotations

from dataclasses import dataclass

from worker.federation import FederatedLearner
from worker.nets import StepGradients
from worker.replay import FiniteTransitions, Replay


@dataclass
class ReplayBatch:
    """What ``prepare()`` fixes for the K per-step rounds of an episode: ``n``, the number of transitions in the
    replay then (each step draws its mini-batch from those), and ``steps`` = K. Plain ints, so ``vars(batch)`` can be
    saved with torch.save and rebuilt with ``ReplayBatch(**d)``."""

    n: int
    steps: int


class OffPolicyLearner(FederatedLearner):
    """The replay and the schedule of an off-policy learner (see the module)."""

    BATCH = ReplayBatch
    SKIP_ZERO_STEPS = True  # sync's mean of zeros (every worker before learning_starts) is no step
    replay: Replay
    _finite: FiniteTransitions

    @property
    def rejected_transitions(self) -> int:
        """Transitions ``remember`` refused because a value was not finite (they never entered the replay)."""
        return self._finite.refused

    @property
    def memory_size(self) -> int:
        """Transitions in the replay."""
        return len(self.replay)

    def prepare(self) -> ReplayBatch:
        """The K = ``update_epochs`` steps of this episode draw from the replay as it is now (they take no step while
        it holds fewer than ``learning_starts``). The new transitions count as used."""
        self.replay.pending = 0
        return ReplayBatch(n=len(self.replay), steps=self.config.update_epochs)

    def _learning(self, batch: ReplayBatch) -> bool:
        """Whether the replay held ``learning_starts`` transitions (at least one) when ``batch`` was prepared."""
        return batch.n >= max(self.config.learning_starts, 1)

    def _episode_steps(self) -> tuple[ReplayBatch, list[StepGradients]]:
        """``update()``'s gradient steps: round(utd_ratio * n) for the n transitions stored since the last update (at
        least one; none while the replay holds fewer than ``learning_starts``), recording the episode gradient."""
        new, batch = self.replay.pending, self.prepare()
        n = max(1, round(self.config.utd_ratio * new)) if self._learning(batch) else 0
        return batch, self._steps(batch, n)
