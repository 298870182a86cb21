"""``median``: the coordinate-wise median of the round's gradients, and the paper's soft transfer (Eq. 10-11).

Each coordinate of g_bar is the median of the contributors' values, so as long as fewer than half of them lie, every
coordinate stays within the range of the honest workers' values (Yin et al. 2018). PI plays no part in the mean:
a worker cannot buy influence by claiming progress.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from chief.strategies.base import Aggregate, Arrays, Strategy, coordinatewise
from chief.strategies.weighted import keep_weight


def aggregate(gradients: Mapping[str, Arrays], progress: Mapping[str, float]) -> Aggregate:
    """g_bar[k] = median_n g_n[k] (the mean of the two middle values for an even count)."""
    return Aggregate(gradient=coordinatewise(gradients, lambda stack: np.median(stack, axis=0)), weights=None)


STRATEGY = Strategy(
    name="median",
    summary="coordinate-wise median gradient, soft transfer (Eq. 10-11)",
    aggregate=aggregate,
    keep_weight=keep_weight,
    tolerates=lambda n: (n - 1) // 2,
    robustness="up to (N-1)//2 arbitrary gradients per coordinate (1 of 4); a lying finisher's actor is still "
    "transferred",
)
