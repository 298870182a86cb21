"""Statistics for the benchmark: median and interquartile range, and a two-sided Mann-Whitney U test of each strategy
against a baseline.

Unfinished runs are kept: for ranking, a run that did not finish within M counts as worse than every finished run
(its episodes as M + 1, its steps as one more than the largest value in the comparison), and unfinished runs tie
with each other. The p-value is scipy's exact p-value of U (``scipy.stats.mannwhitneyu(method="exact")``: over every
split of the pooled values into two groups of the original sizes, ties included; two-sided as scipy defines it,
twice the smaller one-sided p-value, which with ties can be larger than the share of splits whose U lies at least as
far from n m / 2 as the observed one) where there are at most
``EXACT_LIMIT`` splits, otherwise a Monte Carlo estimate from ``RESAMPLES`` random splits with a fixed seed; the
method is reported with each result.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.stats import mannwhitneyu, rankdata

#: Significance level for "significant" (two-sided).
ALPHA = 0.05
#: Most splits enumerated for the exact permutation p-value (C(20, 10) = 184,756 for 10 seeds against 10).
EXACT_LIMIT = 200_000
RESAMPLES = 20_000


def spread(values: Sequence[float]) -> dict[str, float | int | None]:
    """Median, quartiles (inclusive method: the quartiles of the values themselves), min, max and n."""
    vals = sorted(float(v) for v in values)
    if not vals:
        return {"n": 0, "median": None, "q1": None, "q3": None, "min": None, "max": None}
    out = {"median": _quantile(vals, 0.5), "q1": _quantile(vals, 0.25), "q3": _quantile(vals, 0.75), "min": vals[0],
           "max": vals[-1]}
    return {"n": len(vals), **{k: v if math.isinf(v) else round(v, 6) for k, v in out.items()}}


def _quantile(sorted_vals: list[float], q: float) -> float:
    """Linear interpolation between the closest ranks (numpy's default, statistics' "inclusive"); exact positions
    take the value itself, so an infinite neighbour does not turn it into NaN."""
    pos = q * (len(sorted_vals) - 1)
    lo = math.floor(pos)
    frac = pos - lo
    if frac == 0:
        return sorted_vals[lo]
    low, high = sorted_vals[lo], sorted_vals[lo + 1]
    return high if math.isinf(high) else low + frac * (high - low)


def ranked(values: Sequence[float | None], worse_than: float) -> list[float]:
    """Values for ranking: ``None`` (unfinished) becomes ``worse_than``, which must exceed every finished value."""
    finished = [v for v in values if v is not None]
    if finished and max(finished) >= worse_than:
        raise ValueError(f"the value for unfinished runs ({worse_than}) must exceed every finished one")
    return [worse_than if v is None else float(v) for v in values]


def u_statistic(x: Sequence[float], y: Sequence[float]) -> float:
    """Mann-Whitney U of ``x``: the number of pairs (x_i, y_j) with x_i > y_j, ties counting one half."""
    xa, ya = np.asarray(x, float)[:, None], np.asarray(y, float)[None, :]
    return float((xa > ya).sum() + 0.5 * (xa == ya).sum())


def mann_whitney(x: Sequence[float], y: Sequence[float]) -> dict[str, Any]:
    """Two-sided Mann-Whitney U test of ``x`` against ``y`` (exact permutation p-value where feasible).

    Returns U (of ``x``), the p-value, the method and the common-language effect size P(x < y) + P(x = y) / 2:
    the chance that a run of ``x`` needs fewer (episodes, steps) than a run of ``y``.
    """
    x, y = [float(v) for v in x], [float(v) for v in y]
    n, m = len(x), len(y)
    if n == 0 or m == 0:
        return {"u": None, "p": None, "method": "no data", "p_x_smaller": None}
    u = u_statistic(x, y)
    splits = math.comb(n + m, n)
    if splits <= EXACT_LIMIT:
        p = float(mannwhitneyu(x, y, alternative="two-sided", method="exact").pvalue)
        method = f"exact permutation ({splits} splits)"
    else:
        rng = np.random.default_rng(20211)
        groups = np.stack([rng.permutation(n + m)[:n] for _ in range(RESAMPLES)])
        us = rankdata(x + y)[groups].sum(axis=1) - n * (n + 1) / 2.0  # U of each split's x, via mid-ranks
        p = min(1.0, 2.0 * float(min(np.mean(us <= u + 1e-9), np.mean(us >= u - 1e-9))))
        method = f"Monte Carlo permutation ({RESAMPLES} splits, seed 20211)"
    return {"u": u, "p": p, "method": method, "p_x_smaller": 1.0 - u / (n * m)}


def compare(candidate: Sequence[float | None], baseline: Sequence[float | None], worse_than: float) -> dict[str, Any]:
    """A strategy's runs against the baseline's (``None`` = unfinished, ranked as ``worse_than``).

    ``significant`` is p < ALPHA (two-sided); ``direction`` says which needed fewer (by the effect size).
    """
    result = mann_whitney(ranked(candidate, worse_than), ranked(baseline, worse_than))
    p, effect = result["p"], result["p_x_smaller"]
    result["significant"] = p is not None and p < ALPHA
    result["direction"] = (None if effect is None else "fewer" if effect > 0.5 else "more" if effect < 0.5
                           else "equal")
    return result


def spread_censored(values: Sequence[float | None]) -> dict[str, float | int | None]:
    """``spread`` over every run, an unfinished one (``None``) counting as worse than any finished one.

    A statistic that falls on unfinished runs is ``None``; ``unfinished`` counts them.
    """
    vals = [math.inf if v is None else float(v) for v in values]
    out = spread(vals)
    for key in ("median", "q1", "q3", "min", "max"):
        if out[key] is not None and not math.isfinite(out[key]):  # type: ignore[arg-type]
            out[key] = None
    out["unfinished"] = sum(1 for v in values if v is None)
    return out
