"""A tiered root's MetricsLog notes an edge's record as the records of its contributions (chief/report.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

from chief.report import MetricsLog
from protocol.messages import Contribution, Played
from runtime.records import EdgeRecord

DIGEST = "0123456789abcdef"


def contributions(rig: bool, step: bool) -> list[Contribution]:
    out = []
    for i in range(6):
        played = Played(life=f"{i:08x}", episodes=3 + i, steps=60 + i) if i % 3 else None
        out.append(Contribution(f"w{i}", 3, 1 if step and i == 5 else 0, 10.0 + i, 12.0 + i, 20 + i, DIGEST, played,
                                (100 + i, 1.5, 2.0, None) if rig and i % 2 else None))
    return out


@pytest.mark.parametrize(("rig", "step"), [(False, False), (True, False), (False, True)])
def test_an_edge_record_is_noted_as_its_contributions_records(tmp_path: Path, rig: bool, step: bool) -> None:
    """Noted whole (without building its records, when none is a step or carries rig time) or as its records one
    by one: the same PI curves, played and counted totals and rig times."""
    record = EdgeRecord(edge="e0", round=3, episode=3, contributions=contributions(rig, step), total=4.0, count=6,
                        matures=["w2"], t=1.5)
    whole, apart = MetricsLog(tmp_path / "whole"), MetricsLog(tmp_path / "apart")
    for _ in range(2):
        whole.edge(record)
        for sub in record.submissions():
            apart.episode(sub)
    assert whole.curves == apart.curves and whole.curves
    assert whole.played == apart.played and whole.played
    assert whole.rigs() == apart.rigs() and bool(whole.rigs()) == rig
    whole.close()
    apart.close()
