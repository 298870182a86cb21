"""bench.sim2real: the table's arithmetic on made-up runs, and one real smoke-sized federation of lab rigs whose
last rig carries the figures the table reports."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench import sim2real


def run(setting: str, seed: int, episodes: int | None, steps: int | None, rig_min: float | None) -> dict:
    return {"setting": setting, "seed": seed, "finished": episodes is not None, "episodes": episodes,
            "balance_steps": steps, "rig_min": rig_min, "idle_min": 0.5, "wall_min": 1.0, "run_dir": "x"}


def test_the_table_takes_medians_counts_unfinished_runs_as_worse_and_checks_the_targets() -> None:
    runs = [run("randomised", 101, 10, 25_000, 3.0), run("randomised", 102, 12, 29_000, 3.5),
            run("randomised", 103, None, None, None), run("scratch", 101, 100, 40_000, 9.0)]
    t = sim2real.table(runs)
    assert t["randomised"]["runs"] == 3 and t["randomised"]["finished"] == 2
    assert t["randomised"]["episodes"]["median"] == 12 and t["randomised"]["episodes"]["unfinished"] == 1
    assert t["randomised"]["targets_met"] == {"episodes": True, "balance_steps": True, "rig_min": True}
    assert t["scratch"]["targets_met"] == {"balance_steps": False}


@pytest.mark.slow
def test_a_lab_federation_reports_its_last_rig(tmp_path: Path) -> None:
    summary = sim2real.federate(tmp_path / "scratch", 101, 2, {"rig_profile": "lab"})
    r = sim2real.last_rig(summary)
    assert r["finished"] is False and r["episodes"] is None and r["idle_min"] is not None
    assert summary["last_rig"]["rig_s"] > 0 and summary["run_dir"] == str(tmp_path / "scratch")
    again = sim2real.federate(tmp_path / "scratch", 101, 2, {"rig_profile": "lab"})  # reused, not run again
    assert again["wall_s"] == summary["wall_s"]
