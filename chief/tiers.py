"""Edge aggregation: Eq. 8-9 split across edges, as pure functions (docs/explanation/tiered.md).

A strategy whose aggregate is a normalised weighted sum,

    g_bar = sum_n s_n g_n / sum_n s_n        (uniform, sum_n g_n / N, when every s_n is 0)     Eq. 8-9

with an unnormalised share s_n of the worker's progress alone (``Strategy.share``: progress for ``weighted``, 1 for
``plain`` and ``sync``), can be closed in two levels. Each edge forwards one ``Partial`` of its contributors: the
*unnormalised* sum S_e = sum_{n in e} s_n g_n and the share total T_e = sum_{n in e} s_n (an edge whose total is 0
forwards the plain sum instead, flagged ``uniform``). The root divides once, by the federation's total
T = sum_e T_e, so the weights stay normalised over ALL contributors:

    g_bar = sum_{e: T_e > 0} S_e / T       when T > 0 (a uniform edge's shares are all 0: it adds nothing)
    g_bar = sum_e S_e / N                  when T = 0 (every edge is uniform; N = sum_e N_e)

Exactness. The flat chief computes fl32(sum_n fl64(s_n / T) g_n) in float64; an edge sums in float64 too but
forwards S_e as float32 (one update's bytes on the wire), which rounds it by at most u32 = 2^-24 relative; the root
adds the E partials in float64 and divides (E: one per edge, more when an edge sent a late worker's own partial
under a quorum). Both are within (n + E + 2) u64 (u64 = 2^-53) of the exact value, the
tiered one also within u32 sum_e |S_e| / T <= u32 sum_n w_n |g_n|, and each is rounded to float32 once at the end
(half a float32 spacing each). So, coordinate by coordinate,

    |g_tiered - g_flat| <= spacing32(max(|g_tiered|, |g_flat|)) + (u32 + (2n + E + 4) u64) sum_n w_n |g_n|

``tolerance`` is this bound; the audit (chief/audit.py ``tiered-exact``) holds every tiered round to it.

A coordinate-wise median or trimmed mean is no weighted sum (``Strategy.share`` is None): it cannot be split and
runs flat (``decomposable``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from chief import federation
from chief.strategies.base import Strategy, no_gradient

Arrays = Mapping[str, np.ndarray]
#: Unit roundoffs of float32 and float64 (round to nearest).
U32, U64 = 2.0**-24, 2.0**-53


@dataclass(frozen=True)
class Partial:
    """One edge's share of a round's Eq. 9: the unnormalised sum of its contributors' (bounded) gradients, each
    times its share (the plain sum when ``uniform``: its shares were all 0), their share total and their count.
    ``critic`` is the same sum of the critic gradients under a per-step strategy."""

    gradient: dict[str, np.ndarray] | None
    total: float
    count: int
    uniform: bool = False
    critic: dict[str, np.ndarray] | None = None


def decomposable(strategy: Strategy) -> bool:
    """Whether ``strategy``'s aggregate can be closed at the edges (a normalised weighted sum, or nothing shared)."""
    return strategy.share is not None or strategy.aggregate is no_gradient


def edge_quorum(quorum: int, workers: int, behind: int) -> int:
    """k_e, an edge's share of a k-of-n round (docs/explanation/tiered.md): the edge closes its part of a round once
    it misses at most the n - k workers the whole round may miss, k_e = clamp(n_e - (n - k), 1, n_e); 0 (all of
    them) without a quorum. Smaller, the root could not close without a further partial of the edge; larger, one
    straggler behind it would hold back a round the root could close."""
    if not quorum:
        return 0
    if not 1 <= quorum <= workers or not 1 <= behind <= workers:
        raise ValueError(f"a quorum of {quorum} of {workers} workers, {behind} of them behind the edge")
    return min(behind, max(1, behind - (workers - quorum)))


def why_flat(strategy: Strategy) -> str:
    """One line on why a strategy runs flat (for the launchers' note)."""
    return (f"policy {strategy.name!r} is not a weighted sum of the gradients ({strategy.summary.split(',')[0]}): "
            "it needs every contribution in one place, so it runs flat, without edges")


def shares(strategy: Strategy, progress: Mapping[str, float]) -> dict[str, float]:
    """Each contributor's unnormalised share s_n (Eq. 8's numerator)."""
    if strategy.share is None:
        raise ValueError(why_flat(strategy))
    return {w: float(strategy.share(progress[w])) for w in sorted(progress)}


def weights(all_shares: Mapping[str, float]) -> dict[str, float]:
    """Eq. 8: w_n = s_n / sum s, uniform when the sum is 0 (the flat strategies' weights exactly)."""
    return federation.normalised(all_shares)


def _sum(gradients: Mapping[str, Arrays], scale: Mapping[str, float]) -> dict[str, np.ndarray]:
    """sum_n scale_n g_n in float64, in sorted worker order."""
    ids = sorted(gradients)
    out: dict[str, np.ndarray] = {}
    for name in gradients[ids[0]]:
        acc = np.zeros(np.shape(gradients[ids[0]][name]), np.float64)
        for i in ids:
            acc += scale[i] * np.asarray(gradients[i][name], np.float64)
        out[name] = acc
    return out


def partial(strategy: Strategy, gradients: Mapping[str, Arrays], progress: Mapping[str, float],
            critics: Mapping[str, Arrays] | None = None) -> Partial:
    """An edge's Partial of its contributors' gradients (float32 on the wire); an empty one without sharing."""
    if not gradients or strategy.aggregate is no_gradient:
        return Partial(None, 0.0, len(gradients))
    s = shares(strategy, {w: progress[w] for w in gradients})
    total, uniform = share_total(s)
    scale = {w: 1.0 for w in s} if uniform else s

    def f32(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        return {k: v.astype(np.float32) for k, v in arrays.items()}

    return Partial(f32(_sum(gradients, scale)), total, len(gradients), uniform,
                   f32(_sum(critics, scale)) if critics else None)


def share_total(all_shares: Mapping[str, float]) -> tuple[float, bool]:
    """A partial's (T_e, uniform): the sum of its shares in sorted worker order, and whether it is 0 (the partial
    then carries the plain sum, its total 0)."""
    total = sum(all_shares[w] for w in sorted(all_shares))
    return (0.0, True) if total <= 0.0 else (total, False)


def expected_totals(strategy: Strategy, progress: Mapping[str, float]) -> tuple[float, int, bool]:
    """(total, count, uniform) of the Partial an edge sends for learners of this progress (what ``partial`` gives):
    the audit holds an edge's records to its partial with it."""
    if not progress or strategy.aggregate is no_gradient:
        return 0.0, len(progress), False
    total, uniform = share_total(shares(strategy, progress))
    return total, len(progress), uniform


def combine(partials: Sequence[Partial]) -> tuple[dict[str, np.ndarray] | None, dict[str, np.ndarray] | None]:
    """The root's Eq. 9 from the edges' Partials, in the given (canonical) order: (actor g_bar, critic g_bar)."""
    total = sum(p.total for p in partials)
    count = sum(p.count for p in partials)
    used = [p for p in partials if p.gradient is not None and (total <= 0.0 or not p.uniform)]
    if not used:
        return None, None
    divisor = total if total > 0.0 else float(count)

    def mean(which: str) -> dict[str, np.ndarray] | None:
        parts = [getattr(p, which) for p in used]
        if any(x is None for x in parts):
            return None
        out: dict[str, np.ndarray] = {}
        for name in parts[0]:
            acc = np.zeros(np.shape(parts[0][name]), np.float64)
            for x in parts:
                acc += np.asarray(x[name], np.float64)
            out[name] = (acc / divisor).astype(np.float32)
        return out

    return mean("gradient"), mean("critic")


def tolerance(gradients: Mapping[str, Arrays], w: Mapping[str, float], edges: int,
              flat: Arrays, tiered: Arrays) -> dict[str, np.ndarray]:
    """The module docstring's bound on |g_tiered - g_flat|, coordinate by coordinate."""
    n = len(gradients)
    factor = U32 + (2 * n + edges + 4) * U64
    out: dict[str, np.ndarray] = {}
    for name, g in flat.items():
        mass = np.zeros(np.shape(g), np.float64)
        for i in sorted(gradients):
            mass += w[i] * np.abs(np.asarray(gradients[i][name], np.float64))
        top = np.maximum(np.abs(np.asarray(g, np.float32)), np.abs(np.asarray(tiered[name], np.float32)))
        out[name] = np.spacing(top).astype(np.float64) + factor * mass
    return out


def excess(gradients: Mapping[str, Arrays], w: Mapping[str, float], edges: int, flat: Arrays,
           tiered: Arrays) -> float:
    """The largest |g_tiered - g_flat| / tolerance over every coordinate (<= 1: within the bound)."""
    if set(flat) != set(tiered):
        return float("inf")
    bound = tolerance(gradients, w, edges, flat, tiered)
    worst = 0.0
    for name in flat:
        diff = np.abs(np.asarray(tiered[name], np.float64) - np.asarray(flat[name], np.float64))
        if diff.shape != bound[name].shape:
            return float("inf")
        worst = max(worst, float(np.max(diff / bound[name], initial=0.0)))
    return worst
