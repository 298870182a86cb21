"""bench.stragglers: each pair's quorum run is compared with its own baseline, whatever order the pair ran in."""

from __future__ import annotations

from bench.stragglers import pair_slowdowns


def test_each_pair_is_its_own_comparison() -> None:
    runs = [{"name": "baseline", "pair": 0, "s_per_round": 1.0}, {"name": "quorum", "pair": 0, "s_per_round": 1.1},
            {"name": "quorum", "pair": 1, "s_per_round": 2.0}, {"name": "baseline", "pair": 1, "s_per_round": 2.5},
            {"name": "unbounded", "pair": 0, "s_per_round": 9.0}]
    assert pair_slowdowns(runs) == [10.0, -20.0]
