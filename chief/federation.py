"""The federation math every strategy shares, as pure functions over numpy arrays (paper Section IV, sign-safe).

The paper's Eq. 8 (w_n = PI_n / sum PI) and Eq. 10 (w_T = PI / TC) assume non-negative returns. On Acrobot and
Pendulum (negative returns) they give the worse worker the larger weight and a w_T above 1. We use each worker's
progress on its env's own scale instead; with R_floor = 0 this is the paper's formula exactly:

    progress_n = clip((PI_n - R_floor) / (TC - R_floor), 0, 1)
    w_n        = progress_n / sum(progress)        (uniform when the sum is 0)     Eq. 8
    g_bar      = sum_n w_n g_n                                                      Eq. 9
    w_T        = progress_n                                                         Eq. 10
    theta      = w_T theta + (1 - w_T) theta_bar                                    Eq. 11

Which weights a round uses is the strategy's decision (chief/strategies/); ``weighted`` is the formula above.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

Arrays = Mapping[str, np.ndarray]


def progress(pi: float, tc: float, r_floor: float) -> float:
    """How far a worker is from the floor to the termination condition, in [0, 1]."""
    if not tc > r_floor:
        raise ValueError(f"termination condition {tc} must be above the return floor {r_floor}")
    if not math.isfinite(pi):
        raise ValueError(f"performance index must be finite, got {pi}")
    # Plain floats, not np.clip: a root calls this for each of 1,024 contributions a round (the same value).
    return min(max((float(pi) - r_floor) / (tc - r_floor), 0.0), 1.0)


def normalised(shares: Mapping[str, float]) -> dict[str, float]:
    """Eq. 8: w_n = s_n / sum(s), in sorted worker order, uniform when the sum is 0."""
    ids = sorted(shares)
    total = sum(shares[i] for i in ids)
    if total <= 0.0:
        return {i: 1.0 / len(ids) for i in ids}
    return {i: shares[i] / total for i in ids}


def weighted_sum(gradients: Mapping[str, Arrays], weights: Mapping[str, float]) -> dict[str, np.ndarray]:
    """Eq. 9: g_bar = sum_n w_n g_n, tensor by tensor in float64 (all gradients must share names and shapes)."""
    if not gradients:
        raise ValueError("no gradients to aggregate")
    ids = sorted(gradients)
    if set(ids) != set(weights):
        raise ValueError(f"weights given for {sorted(weights)} but gradients for {ids}")
    names = list(gradients[ids[0]])
    out: dict[str, np.ndarray] = {}
    for name in names:
        acc = np.zeros_like(np.asarray(gradients[ids[0]][name], dtype=np.float64))
        for i in ids:
            g = np.asarray(gradients[i][name], dtype=np.float64)
            if g.shape != acc.shape:
                raise ValueError(f"gradient {name} of worker {i} has shape {g.shape}, expected {acc.shape}")
            acc += weights[i] * g
        out[name] = acc.astype(np.float32)
    return out


def best_mature(pis: Mapping[str, float]) -> str:
    """Several workers finished in one round: the best PI is transferred (ties: smallest id)."""
    if not pis:
        raise ValueError("no finished worker")
    return min(pis, key=lambda i: (-pis[i], i))
