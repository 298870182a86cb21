"""``weighted``: the paper's federation policy (Section IV), sign-safe: contributions weighted by progress
(Eq. 8-9) and a soft transfer that keeps as much of a recipient's own actor as its progress (Eq. 10-11)."""

from __future__ import annotations

from collections.abc import Mapping

from chief import federation
from chief.strategies.base import Aggregate, Arrays, Strategy


def contribution_weights(progress: Mapping[str, float]) -> dict[str, float]:
    """Eq. 8: w_n = progress_n / sum(progress), uniform when every worker is at the floor."""
    return federation.normalised(progress)


def aggregate(gradients: Mapping[str, Arrays], progress: Mapping[str, float]) -> Aggregate:
    """Eq. 9: g_bar = sum_n w_n g_n with the Eq. 8 weights."""
    weights = contribution_weights({w: progress[w] for w in gradients})
    return Aggregate(gradient=federation.weighted_sum(gradients, weights), weights=weights)


def share(progress: float) -> float:
    """Eq. 8's numerator, s_n = progress_n (what an edge sums before the root divides, chief/tiers.py)."""
    return progress


def keep_weight(progress: float) -> float:
    """Eq. 10: w_T = progress (PI / TC when the return floor is 0)."""
    return progress


STRATEGY = Strategy(
    name="weighted",
    summary="progress-weighted mean gradient (Eq. 8-9), soft transfer w_T = progress (Eq. 10-11): the paper's",
    aggregate=aggregate,
    keep_weight=keep_weight,
    tolerates=lambda n: 0,
    robustness="a linear mean: one worker's gradient (or a worker claiming full progress) can move g_bar anywhere",
    share=share,
)
