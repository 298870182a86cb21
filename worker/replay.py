"""The learners' memory, which never leaves the device: a FIFO ring of transitions in named numpy columns (PPO's
trajectory memory, the replay buffer of SAC and DQN), and the guard that keeps a non-finite transition out of a
replay."""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

log = logging.getLogger("worker")


class Replay:
    """``capacity`` transitions, each a value per column (``columns``: name -> (shape, dtype) of one value); when full,
    the oldest is overwritten. Logical index 0 is the oldest transition. ``pending`` counts those added since the
    learner last took them into an update."""

    def __init__(self, capacity: int, columns: Mapping[str, tuple[tuple[int, ...], Any]]) -> None:
        self.columns = dict(columns)
        self.capacity, self.pos, self.size, self.pending = capacity, 0, 0, 0
        self.data = {name: np.zeros((capacity, *shape), dtype=dtype) for name, (shape, dtype) in self.columns.items()}

    def __len__(self) -> int:
        return self.size

    def __getitem__(self, i: int) -> tuple[Any, ...]:
        """The ``i``-th oldest transition, its values in the columns' order."""
        position = self.order()[i]
        return tuple(column[position] for column in self.data.values())

    def ordered(self) -> dict[str, np.ndarray]:
        """Every column, oldest first."""
        order = self.order()
        return {name: column[order] for name, column in self.data.items()}

    def add(self, **values: Any) -> None:
        """Store one transition (a value for every column)."""
        for name, value in values.items():
            self.data[name][self.pos] = value
        self.pos = (self.pos + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)
        self.pending += 1

    def order(self) -> np.ndarray:
        """Physical positions of the stored transitions, oldest first."""
        start = self.pos if self.size == self.capacity else 0
        return (start + np.arange(self.size)) % self.capacity

    def sample(self, n: int, batch_size: int, generator: torch.Generator) -> dict[str, np.ndarray]:
        """``batch_size`` transitions drawn uniformly, with replacement, from the oldest ``n`` (the replay as the
        learner's ``prepare`` saw it; each column an array)."""
        logical = torch.randint(0, min(n, self.size), (batch_size,), generator=generator).numpy()
        idx = self.order()[logical]
        return {name: column[idx] for name, column in self.data.items()}

    def state(self) -> dict[str, torch.Tensor]:
        """The transitions as tensors, oldest first, with ``pending`` (empty when there are none)."""
        if self.size == 0:
            return {}
        return {**{name: torch.from_numpy(column) for name, column in self.ordered().items()},
                "pending": torch.tensor(self.pending, dtype=torch.int64)}

    def load(self, state: Mapping[str, torch.Tensor]) -> None:
        """Replace the transitions with ``state()`` output (its newest ``capacity``)."""
        self.pos = self.size = self.pending = 0
        n = len(state[next(iter(self.columns))]) if state else 0
        if n == 0:
            return
        m = min(n, self.capacity)
        for name, (shape, _) in self.columns.items():
            self.data[name][:m] = state[name][n - m:].numpy().reshape(m, *shape)
        self.size, self.pos = m, m % self.capacity
        self.pending = min(int(state.get("pending", 0)), m)


class FiniteTransitions:
    """Keeps a transition with a value that is not finite out of a learner's replay: in it, it would poison every
    mini-batch that draws it, for as long as it stays. Counts what it refuses (``refused``) and logs the first, then
    every 100th."""

    def __init__(self, learner: str) -> None:
        self.learner = learner
        self.refused = 0

    def admit(self, reward: float, *arrays: Any) -> bool:
        """Whether the reward and every value of ``arrays`` are finite (else the transition is counted and logged)."""
        if math.isfinite(reward) and all(bool(np.isfinite(np.asarray(a, dtype=np.float64)).all()) for a in arrays):
            return True
        self.refused += 1
        if self.refused == 1 or self.refused % 100 == 0:
            log.warning("%s refused a transition with a non-finite value (%d so far): not in the replay",
                        self.learner, self.refused)
        return False
