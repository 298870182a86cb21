"""``plain``: the authors' earlier federation policy (paper Section II, ref. [16]): the uniform mean of the round's
gradients, and a hard transfer (a recipient replaces its actor with the mature one)."""

from __future__ import annotations

from collections.abc import Mapping

from chief import federation
from chief.strategies.base import Aggregate, Arrays, Strategy


def aggregate(gradients: Mapping[str, Arrays], progress: Mapping[str, float]) -> Aggregate:
    """Eq. 9 with w_n = 1 / N."""
    weights = {w: 1.0 / len(gradients) for w in sorted(gradients)}
    return Aggregate(gradient=federation.weighted_sum(gradients, weights), weights=weights)


def keep_weight(progress: float) -> float:
    """Hard transfer: w_T = 0, so Eq. 11 gives theta = theta_bar."""
    return 0.0


STRATEGY = Strategy(
    name="plain",
    summary="uniform mean gradient, hard transfer (the authors' earlier work)",
    aggregate=aggregate,
    keep_weight=keep_weight,
    tolerates=lambda n: 0,
    robustness="a linear mean: one worker's gradient can move g_bar anywhere",
    share=lambda progress: 1.0,
)
