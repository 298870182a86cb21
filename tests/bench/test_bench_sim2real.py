"""bench.sim2real: the table's arithmetic on made-up runs, and one real smoke-sized federation of lab rigs whose
last rig carries the figures the table reports."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench import sim2real


def run(setting: str, seed: int, episodes: int | None, steps: int | None, rig_min: float | None) -> dict:
    return {"setting": setting, "seed": seed, "finished": episodes is not None, "episodes": episodes,
            "balance_steps": steps, "rig_min": rig_min, "idle_min": 0.5, "wall_min": 1.0, "run_dir": "x",
            "rig_wall_ratio": None if episodes is None else 1.1}


def test_the_table_takes_medians_counts_unfinished_runs_as_worse_and_checks_the_targets() -> None:
    runs = [run("randomised", 101, 10, 25_000, 3.0), run("randomised", 102, 12, 29_000, 3.5),
            run("randomised", 103, None, None, None), run("scratch", 101, 100, 40_000, 9.0)]
    t = sim2real.table(runs)
    assert t["randomised"]["runs"] == 3 and t["randomised"]["finished"] == 2
    assert t["randomised"]["episodes"]["median"] == 12 and t["randomised"]["episodes"]["unfinished"] == 1
    assert t["randomised"]["targets_met"] == {"episodes": True, "balance_steps": True, "rig_min": True,
                                              "rig_wall_ratio": True}
    assert t["scratch"]["targets_met"] == {"balance_steps": False}


@pytest.mark.slow
def test_a_lab_federation_reports_its_last_rig(tmp_path: Path) -> None:
    folder = tmp_path / "scratch"
    summary = sim2real.federate(folder, 101, 2, {"rig_profile": "lab"})
    r = sim2real.last_rig(summary, folder)
    assert r["finished"] is False and r["episodes"] is None and r["idle_min"] is not None
    assert summary.last_rig is not None and summary.last_rig.rig_s > 0 and r["run_dir"] == str(folder)
    again = sim2real.federate(folder, 101, 2, {"rig_profile": "lab"})  # reused, not run again
    assert again.wall_s == summary.wall_s


def test_the_report_is_the_table_of_the_json_and_replaces_only_its_block(tmp_path: Path) -> None:
    runs = [run("scratch", 101, 200, 34_000, 30.0), run("scratch", 102, None, None, None),
            run("randomised", 101, 12, 29_000, 3.5), run("randomised", 102, 14, 30_500, 4.5)]
    runs[1] |= {"end_reason": "aborted: every unfinished worker offline", "unsolved": {"w0": "failed"}}
    result = {"config": {"rigs": 3, "policy": "plain", "seeds": [101, 102], "pretrain_seed": 1, "date": "2026-12-02",
                         "cores": 2, "load_average": [3.0, 3.0, 3.0]}, "wall_s": 600.0, "table": sim2real.table(runs),
              "runs": runs,
              "pretrains": {"randomised": {"finished": True, "episodes": 147, "rig_min": 20.0, "balance_min": 5.0,
                                           "reset_min": 15.0, "wall_min": 9.5},
                            "ideal": {"finished": False}},
              "zero_shot": {"randomised": {"rigs": 10, "balanced_to_end": 9}},
              "disturbed_trials": [{"rigs": 1, "balanced_to_end": 1, "largest_pulse_of_stall": 0.2},
                                   {"rigs": 1, "balanced_to_end": 0, "largest_pulse_of_stall": 0.12}],
              "reference_trials": {"rigs": 2, "balanced_to_end": 1, "median_largest_pulse_of_stall": 0.175},
              "realtime": [{"seed": 101, "finished": True, "measured_ratio": 1.16, "episodes": 19,
                            "balance_steps": 44_427, "rig_min": 6.237, "missed_actions": 0.0094},
                           {"seed": 102, "finished": False}]}
    text = sim2real.report(result, "sim2real.json")
    assert "| from scratch | 1/2 | not reached (1 of 2 runs unfinished) |" in text  # the unfinished run is worse
    assert "| warm start: randomised pretrain (`lab`, +-20%) | 2/2 | 13 [12.5 to 13.5] |" in text
    assert "episodes **missed**" in text and "balance_steps **missed**" in text  # 13 > 12 and 29,750 <= 30,000 met
    assert "balanced to the end on 9 of 10 unseen `lab` rigs (in distribution)" in text
    assert "1 of 2 balanced to the end" in text
    assert "median largest pulse survived was 20% of stall" in text and "**Clock `lockstep`**" in text
    assert "`ideal` pretrain: did not finish: no model; no zero-shot test." in text
    assert ("`randomised` pretrain: finished at episode 147, its last rig after 20.0 rig minutes: 5.0 balancing, "
            "15.0 in swing-up resets (9.5 wall minutes here)") in text
    assert "LQR restricted to the same three actions on the same unseen rigs: 1 of 2 balanced" in text
    assert "sweep 18% of stall" in text
    assert ("seeds 101, 102): 1 of 2 finished; wall-clock over the slowest rig's rig time 1.16 (median; 1.16 to "
            "1.16); last rig per seed: 101: episode 19, 44,427 balance steps, 6.2 rig min, 0.9% of actions late; "
            "102: unfinished.") in text
    assert "What the randomised pretrain saves" not in text  # scratch's median is an unfinished run: no ratio
    finished = sim2real.table([run("scratch", 101, 200, 34_000, 30.0), run("randomised", 101, 12, 29_000, 4.0)])
    assert "falls from 30.0 minutes from scratch to 4.0 warm-started (13%)" in (sim2real._saving(finished) or "")
    assert ("- Unfinished: from scratch, lockstep clock, seed 102: aborted: every unfinished worker offline "
            "(w0 failed).") in text
    json_path = tmp_path / "sim2real.json"
    json_path.write_text(json.dumps(result))
    page = tmp_path / "page.md"
    page.write_text(f"before\n{sim2real.BEGIN}\nold table\n{sim2real.END}\nafter\n")
    sim2real.write_report(json_path, [page])
    table = sim2real.report(result, str(json_path))
    assert page.read_text() == f"before\n{sim2real.BEGIN}\n{table}\n{sim2real.END}\nafter\n"


def test_the_reference_controller_is_the_bridges_lqr_as_bang_bang() -> None:
    from rpi_bridge.reset import ResetController
    from worker.qube_env import ACTIONS

    for obs in ([0.0, 0.0, 0.0, 0.0], [0.05, 0.0, 0.0, 0.0], [-0.05, 0.0, 0.0, 0.0], [0.0, 0.0, 0.3, 1.0]):
        u = ResetController().hold_command(obs[2], obs[0], obs[3], obs[1])
        assert ACTIONS[sim2real.lqr_action(obs)] == (60 if u > 0 else -60 if u < 0 else 0)
    assert ACTIONS[sim2real.lqr_action([0.05, 0.0, 0.0, 0.0])] != ACTIONS[sim2real.lqr_action([-0.05, 0.0, 0.0, 0.0])]


def test_another_learner_or_action_set_writes_its_own_file_and_runs_only_the_settings_asked() -> None:
    assert sim2real.Setup().results_name(quick=False) == "sim2real.json"  # the table's, as before
    assert sim2real.Setup().results_name(quick=True) == "sim2real-quick.json"
    assert sim2real.Setup("sac", "sync", "voltage").results_name(quick=False) == "sim2real-sac-sync-voltage.json"
    assert sim2real.Setup(qube_actions="levels").results_name(quick=True) == "sim2real-ppo-plain-levels-quick.json"
    assert sim2real.Setup().paper_actions and not sim2real.Setup(qube_actions="voltage").paper_actions
    args = sim2real.parse(["--algo", "sac", "--policy", "sync", "--qube-actions", "voltage", "--settings", "scratch"])
    assert args.settings == ["scratch"] and args.runs_dir.name == "sac-sync-voltage"
    assert sim2real.parse([]).settings == list(sim2real.SETTINGS) == ["scratch", "ideal", "randomised"]
    assert sim2real.parse([]).runs_dir.name == "ppo-plain"
    with pytest.raises(SystemExit):
        sim2real.parse(["--settings", "nowhere"])
