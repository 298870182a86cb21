"""bench.exploration: one untrained SAC learner per noise colour, its goal rate written as JSON."""

from __future__ import annotations

import json
from pathlib import Path

from bench import exploration


def test_each_colour_gets_its_episodes_and_the_report_names_its_command(tmp_path: Path) -> None:
    out = tmp_path / "exploration.json"
    assert exploration.main(["--episodes", "1", "--betas", "0", "1", "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["task"] == "MountainCarContinuous-v0" and report["command"].startswith("python -m bench.exploration")
    assert [row["beta"] for row in report["results"]] == [0.0, 1.0]
    for row in report["results"]:
        assert row["episodes"] == 1 and row["reached_goal"] in (0, 1) and 1 <= row["mean_length"] <= 999
