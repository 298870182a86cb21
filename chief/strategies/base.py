"""What a federation strategy is: its decisions as pure functions over numpy arrays, plus what it promises.

A strategy decides two things of Algorithm 1 (paper Section IV):

- ``aggregate(gradients, progress)``: the round's shared gradient g_bar from the contributors' actor gradients, and
  the contribution weight of each (Eq. 8-9 for the linear rules; ``None`` for a rule that is not a weighted sum);
- ``keep_weight(progress)``: w_T, how much of its own actor a recipient keeps when a mature actor arrives (Eq. 10);
  ``None`` when the strategy transfers nothing;
- ``share(progress)``: for the linear rules, a contributor's unnormalised Eq. 8 weight, which lets edges close
  their part of a round (chief/tiers.py);
- ``rounds(K)``: the run's round shape (protocol/rounds.py) for workers taking K PPO mini-batch steps per episode:
  one round per episode (the paper: each worker runs its K PPO steps and submits the episode's mean actor gradient,
  ``one_per_episode``) or one per mini-batch step (K rounds per episode: each step's actor and critic gradients are
  aggregated and every worker applies the aggregate before its next step, ``one_per_step``).

``progress`` is each worker's sign-safe progress in [0, 1] (chief/federation.py), computed by the round state
machine from the PIs it accepted. One module per strategy in this package registers one ``Strategy``; nothing else
in the code base names strategies (the CLI choices, RunStart's validation and the README table come from here).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from protocol.rounds import PER_EPISODE, RoundShape

Arrays = Mapping[str, np.ndarray]


@dataclass(frozen=True)
class Aggregate:
    """One round's shared gradient and, for weighted sums, each contributor's weight (summing to 1)."""

    gradient: dict[str, np.ndarray] | None
    weights: dict[str, float] | None


def one_per_episode(update_steps: int) -> RoundShape:
    """The paper's rounds: one per episode, whatever K (a round shares the episode's actor gradient)."""
    return PER_EPISODE


@dataclass(frozen=True)
class Strategy:
    """A federation strategy: pure decisions plus the facts the docs and the audit need."""

    name: str
    summary: str
    aggregate: Callable[[Mapping[str, Arrays], Mapping[str, float]], Aggregate]
    keep_weight: Callable[[float], float | None]
    #: How many of n workers may send arbitrary gradients without taking over a coordinate of g_bar.
    tolerates: Callable[[int], int]
    #: One line on what it tolerates and what it does not, for the README table.
    robustness: str
    #: The round shape for workers taking K PPO steps per episode (ValueError when this strategy cannot run with K).
    rounds: Callable[[int], RoundShape] = one_per_episode
    #: A worker that finished keeps playing and sharing (without transferring anything) until every worker has
    #: finished; its own solve episode stays the one it finished at.
    finishers_help: bool = False
    #: Whether a worker's gradient reaches anyone else. False (``independent``): the chief neither bounds nor
    #: aggregates what it is sent, so an honest outlier of a worker learning alone is never scaled or logged.
    shares: bool = True
    #: s_n, a contributor's unnormalised weight from its progress alone, when ``aggregate`` is Eq. 9's normalised
    #: sum g_bar = sum s_n g_n / sum s_n (uniform when every s_n is 0): then edges can close their workers' part of
    #: a round (chief/tiers.py). None: not a weighted sum (a median), which runs flat.
    share: Callable[[float], float] | None = None

    @property
    def allows_staleness(self) -> bool:
        """Whether workers may play on with rounds unanswered (RunStart.max_staleness > 0): only with one round per
        episode. A per-step strategy's workers must apply each step's mean before computing the next step."""
        return self.rounds is one_per_episode


def one_per_step(update_steps: int) -> RoundShape:
    """K rounds per episode, one per PPO mini-batch step (a round shares that step's actor and critic gradients)."""
    if update_steps < 2:
        raise ValueError(f"sharing every mini-batch step needs workers whose PPO takes at least 2 steps per episode, "
                         f"not {update_steps}")
    return RoundShape(per_episode=update_steps)


def no_gradient(gradients: Mapping[str, Arrays], progress: Mapping[str, float]) -> Aggregate:
    """Nothing is shared (the ``independent`` baseline)."""
    return Aggregate(gradient=None, weights=None)


def coordinatewise(gradients: Mapping[str, Arrays], rule: Callable[[np.ndarray], np.ndarray]) -> dict[str, np.ndarray]:
    """Apply ``rule`` (stacked contributions, axis 0 = worker -> one array) to each named tensor.

    Contributions are stacked in float64 in sorted worker order; the result is float32 like every actor tensor.
    """
    if not gradients:
        raise ValueError("no gradients to aggregate")
    ids = sorted(gradients)
    names = sorted(gradients[ids[0]])
    out: dict[str, np.ndarray] = {}
    for name in names:
        shapes = {np.shape(gradients[i][name]) for i in ids}
        if len(shapes) != 1:
            raise ValueError(f"gradient {name} has different shapes across workers: {sorted(shapes)}")
        stack = np.stack([np.asarray(gradients[i][name], dtype=np.float64) for i in ids])
        out[name] = rule(stack).astype(np.float32)
    return out
