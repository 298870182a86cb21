"""What the off-policy learners (worker/sac.py, worker/dqn.py) share beyond the federation's seams, as
Stable-Baselines3's OffPolicyAlgorithm: the replay buffer (worker/replay.py) and its persistence, the per-episode
schedule of gradient steps (round(utd_ratio * new transitions), none before ``learning_starts``; a fixed K =
``update_epochs`` under a per-step strategy), and the gradient of a loss with respect to one network.

A learner declares its replay's columns (``_columns``) and writes its acting, ``remember``, ``minibatch_gradients``,
``apply_step`` and the statistics of its ``update``. Its configuration has ``replay_size``, ``batch_size``,
``learning_starts``, ``utd_ratio``, ``update_epochs`` and ``max_grad_norm``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

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

    def _columns(self) -> dict[str, tuple[tuple[int, ...], Any]]:
        """The replay's columns: name -> (shape, dtype) of one transition's value."""
        raise NotImplementedError

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

    def _gradients(self, loss: torch.Tensor, net: nn.Module) -> dict[str, np.ndarray] | None:
        """The gradient of ``loss`` with respect to ``net``'s parameters only (torch.autograd.grad: nothing is
        accumulated in any .grad), norm-clipped when configured; None when the loss or a gradient is not finite."""
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
        if not all(bool(np.isfinite(g).all()) for g in out.values()):
            return None
        return out

    def memory_state(self) -> dict[str, torch.Tensor]:
        """The replay as tensors, oldest first, with ``pending`` (transitions not yet used by an update), for a
        worker's resumable state (worker/resume.py); ``load_memory`` restores it exactly."""
        return self.replay.state()

    def load_memory(self, state: Mapping[str, torch.Tensor]) -> None:
        """Replace the replay with ``memory_state()`` output (the newest ``replay_size`` of it)."""
        self.replay = Replay(self.config.replay_size, self._columns())
        self.replay.load(state)

    def _resized(self, old: Any) -> None:
        if self.config.replay_size != old.replay_size:
            self.replay = self.replay.resized(self.config.replay_size)
