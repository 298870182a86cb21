"""``trimmed``: a coordinate-wise trimmed mean of the round's gradients, and the paper's soft transfer (Eq. 10-11).

Per coordinate, the ``trim(n)`` largest and ``trim(n)`` smallest values are dropped and the rest averaged. Unlike a
fraction that rounds down to nothing at small N (Flower's FedTrimmedAvg with beta 0.2 trims nothing at N = 4), it
always trims at least one value per tail once there are three contributors. At N = 4 it equals the median; from
N = 5 on it averages more values than the median does.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from chief.strategies.base import Aggregate, Arrays, Strategy, coordinatewise
from chief.strategies.weighted import keep_weight

#: Share of contributors dropped per tail (at least one from three contributors on).
TRIM_FRACTION = 0.25


def trim(n: int) -> int:
    """Values dropped per tail at n contributors: max(1, floor(0.25 n)) for n >= 3, else 0 (nothing to trim)."""
    return max(1, int(TRIM_FRACTION * n)) if n >= 3 else 0


def trimmed_mean(stack: np.ndarray) -> np.ndarray:
    """Mean over axis 0 after dropping the trim(n) smallest and largest values of each coordinate."""
    k = trim(stack.shape[0])
    ordered = np.sort(stack, axis=0)
    return ordered[k: stack.shape[0] - k].mean(axis=0)


def aggregate(gradients: Mapping[str, Arrays], progress: Mapping[str, float]) -> Aggregate:
    return Aggregate(gradient=coordinatewise(gradients, trimmed_mean), weights=None)


STRATEGY = Strategy(
    name="trimmed",
    summary="coordinate-wise trimmed mean gradient (drops max(1, N/4) per tail from N = 3), soft transfer",
    aggregate=aggregate,
    keep_weight=keep_weight,
    tolerates=trim,
    robustness="up to max(1, N//4) arbitrary gradients per coordinate from N = 3 (1 of 4), none at N <= 2; "
    "a lying finisher's actor is still transferred",
)
