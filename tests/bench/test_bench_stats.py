"""bench.stats on data whose answers are worked out by hand."""

from __future__ import annotations

import math

import pytest

from bench import stats


def test_spread_is_median_and_inclusive_quartiles() -> None:
    s = stats.spread([10, 1, 4, 7])  # sorted 1 4 7 10: quartile positions 0.75, 1.5, 2.25
    assert s == {"n": 4, "median": 5.5, "q1": 3.25, "q3": 7.75, "min": 1.0, "max": 10.0}
    assert stats.spread([3])["q1"] == stats.spread([3])["q3"] == 3.0
    assert stats.spread([])["median"] is None


def test_unfinished_runs_count_as_worst_in_the_spread() -> None:
    s = stats.spread_censored([30, None, 10, 20, None])  # 10 20 30 inf inf
    assert s["median"] == 30 and s["q1"] == 20 and s["q3"] is None and s["unfinished"] == 2
    assert s["min"] == 10 and s["max"] is None


def test_u_counts_pairs_with_ties_as_halves() -> None:
    assert stats.u_statistic([1, 2], [3, 4]) == 0.0
    assert stats.u_statistic([3, 4], [1, 2]) == 4.0
    assert stats.u_statistic([2, 3], [2, 1]) == 3.5  # 2>1, 3>2, 3>1, 2=2 half


def test_exact_p_values_by_hand() -> None:
    # Complete separation of 3 against 3: 2 of the C(6,3) = 20 splits are as extreme (U = 0 or 9).
    r = stats.mann_whitney([1, 2, 3], [4, 5, 6])
    assert r["u"] == 0.0 and r["p"] == pytest.approx(2 / 20) and r["p_x_smaller"] == 1.0
    assert r["method"].startswith("exact")
    # 4 against 4, fully separated: 2 / C(8,4) = 2/70.
    assert stats.mann_whitney([1, 2, 3, 4], [5, 6, 7, 8])["p"] == pytest.approx(2 / 70)
    # Identical samples: every split is at least as extreme, p = 1.
    assert stats.mann_whitney([5, 5], [5, 5])["p"] == 1.0


def test_exact_p_value_with_ties_by_enumeration() -> None:
    # x = (1, 2), y = (2, 3): U_x = 0.5 (one tie). The 6 splits of the pooled (1, 2, 2, 3) give
    # mid-ranks 1, 2.5, 2.5, 4, so U = 0.5, 0.5, 2, 2, 3.5, 3.5 for the group taken as x; |U - 2| >= 1.5 holds
    # for 4 of them.
    r = stats.mann_whitney([1, 2], [2, 3])
    assert r["u"] == 0.5 and r["p"] == pytest.approx(4 / 6)


def test_unfinished_ranked_worse_than_any_finished() -> None:
    m = 100
    # The candidate finished every run, the baseline none: complete separation, p = 2 / C(6, 3) = 0.1.
    r = stats.compare([10, 20, 30], [None, None, None], worse_than=m + 1)
    assert r["p"] == pytest.approx(0.1) and r["direction"] == "fewer" and not r["significant"]
    with pytest.raises(ValueError):
        stats.ranked([200, None], worse_than=101)


def test_significant_with_enough_seeds() -> None:
    r = stats.compare(list(range(1, 11)), list(range(11, 21)), worse_than=1000)
    assert r["significant"] and r["direction"] == "fewer"
    assert r["p"] == pytest.approx(2 / math.comb(20, 10))
    slower = stats.compare(list(range(11, 21)), list(range(1, 11)), worse_than=1000)
    assert slower["significant"] and slower["direction"] == "more"


def test_monte_carlo_when_exact_is_too_big() -> None:
    x, y = list(range(0, 30, 2)), list(range(1, 31, 2))  # 15 against 15: C(30,15) splits, too many
    r = stats.mann_whitney(x, y)
    assert r["method"].startswith("Monte Carlo") and 0.5 < r["p"] <= 1.0
