"""bench.paper's harness on a tiny configuration, its measurements from run records, targets, and the README and
figure generation on a fixture."""

from __future__ import annotations

import json
import os
from dataclasses import asdict
from pathlib import Path
from typing import Any

import pytest

from bench import figures, paper, report
from bench.runs import Job, _modelled_times, _mqtt_times, execute, learning_curve, run_folder_lock
from runtime.records import EpisodeRecord, RoundRecord


def test_tiny_inprocess_benchmark_end_to_end(tmp_path: Path) -> None:
    out, runs = tmp_path / "results", tmp_path / "runs"
    code = paper.main(["--tasks", "CartPole-v0", "--strategies", "independent", "weighted", "--algos", "ppo",
                       "--seeds", "101", "--workers", "2", "--max-episodes", "12", "--jobs", "1", "--references",
                       "single", "--no-cost", "--no-readme", "--out", str(out), "--runs-dir", str(runs)])
    assert code == 0
    index = json.loads((out / "paper.json").read_text())
    assert index["config"]["mode"] == "inprocess" and index["config"]["seeds"]["report"] == [101]
    assert index["config"]["seeds"]["tuning"] == list(paper.TUNING_SEEDS)
    full = json.loads((out / "paper-CartPole-v0.json").read_text())
    assert list(full["learners"]) == ["ppo"] and all(r["algo"] == "ppo" for r in full["runs"])
    rep = {**full, **full["learners"]["ppo"]}
    assert rep["strategies"] == ["independent", "weighted"]
    assert len(rep["runs"]) == 3  # two federations and the single worker
    for run in rep["runs"]:
        assert run["mode"] == "in-process" and run["audit"]["passed"], run.get("audit")
        assert len(run["per_worker"]) == run["workers"]
        for w in run["per_worker"]:
            assert w["episodes"] <= 12 and w["steps"] > 0 and w["steps_per_s"] > 0
            assert 0.0 <= w["wait_share"] < 1.0 and w["own_s"] <= w["wall_s"]
        if not run["finished"]:  # unfinished within M: reported, never dropped
            assert run["last_worker"]["episodes"] is None and run["last_worker"]["episodes_reached"] == 12
        assert run["curve"]["episode"][0] == 1
    s = rep["summary"]["weighted"]
    assert s["runs"] == 1 and s["finished"] + len(s["unfinished_seeds"]) == 1
    assert "weighted" in rep["significance"] and "independent" not in rep["significance"]
    for name in ("fig5-episodes.png", "fig5-steps.png", "fig7-episodes.png", "fig7-steps.png"):
        assert (out / name).stat().st_size > 0
    # --resume reuses every finished run: nothing runs again
    results = paper.run_jobs(paper.plan(["CartPole-v0"], ["weighted"], [101], 2, 12, "inprocess", []), 1, runs,
                             resume=True)
    assert results[0]["run_wall_s"] == next(r for r in rep["runs"] if r["strategy"] == "weighted")["run_wall_s"]
    # another learner into the same folder: PPO's results stay beside it
    code = paper.main(["--tasks", "CartPole-v0", "--strategies", "weighted", "--algos", "sac", "--seeds", "101",
                       "--workers", "2", "--max-episodes", "3", "--jobs", "1", "--references", "--no-cost",
                       "--no-readme", "--out", str(out), "--runs-dir", str(runs)])
    assert code == 0
    both = json.loads((out / "paper-CartPole-v0.json").read_text())
    assert list(both["learners"]) == ["ppo", "sac"] and len(both["runs"]) == 4
    assert both["learners"]["ppo"]["summary"] == rep["summary"]
    assert [r["algo"] for r in both["runs"]] == ["ppo"] * 3 + ["sac"]
    assert list(json.loads((out / "paper.json").read_text())["tasks"]["CartPole-v0"]["learners"]) == ["ppo", "sac"]


def test_plan_has_the_learner_dimension_and_each_learners_sb3_reference() -> None:
    jobs = paper.plan(["CartPole-v0", "Pendulum-v1"], ["independent", "sync"], [101, 102], None, 50, "inprocess",
                      ["single", "sb3"], algos=["ppo", "sac"])
    fed = [j for j in jobs if j.kind == "federation"]
    assert len(fed) == 2 * 2 * 2 * 2 and {j.algo for j in fed} == {"ppo", "sac"}
    sb3 = {(j.task, j.algo): j.strategy for j in jobs if j.kind == "sb3"}
    assert sb3 == {("CartPole-v0", "ppo"): "sb3-zoo-ppo", ("CartPole-v0", "sac"): "sb3-zoo-dqn",
                   ("Pendulum-v1", "ppo"): "sb3-zoo-ppo", ("Pendulum-v1", "sac"): "sb3-zoo-sac"}
    assert len({j.name for j in jobs}) == len(jobs)  # a run folder per job
    assert Job("single", "CartPole-v0", "independent", 1, 1, 5).name.endswith("-inprocess")  # PPO's as before
    assert paper.parse_args([]).algos == ["ppo", "sac"] and paper.parse_args(["--quick"]).algos == ["ppo"]


def test_plan_runs_dqn_only_where_actions_are_discrete() -> None:
    jobs = paper.plan(["CartPole-v0", "Pendulum-v1"], ["sync"], [101], None, 50, "inprocess", ["single"],
                      algos=["dqn", "sac"])
    assert sorted({(j.task, j.algo) for j in jobs}) == [("CartPole-v0", "dqn"), ("CartPole-v0", "sac"),
                                                         ("Pendulum-v1", "sac")]


def test_plan_covers_every_strategy_and_the_references() -> None:
    jobs = paper.plan(["CartPole-v0", "qube-local"], ["independent", "weighted"], [101, 102], None, 50, "inprocess",
                      ["single", "sb3"])
    fed = [j for j in jobs if j.kind == "federation"]
    assert len(fed) == 2 * 2 * 2
    assert {j.workers for j in fed if j.task == "qube-local"} == {3}
    assert {j.workers for j in fed if j.task == "CartPole-v0"} == {4}
    assert sum(1 for j in jobs if j.kind == "single") == 4
    assert {j.task for j in jobs if j.kind == "sb3"} == {"CartPole-v0"}  # no zoo entry for the QUBE


def test_registry_strategies_are_the_default() -> None:
    from chief import strategies

    args = paper.parse_args(["--quick"])
    assert args.strategies == strategies.names()
    assert args.seeds == list(paper.QUICK["seeds"]) and args.max_episodes == paper.QUICK["max_episodes"]
    full = paper.parse_args([])
    assert full.seeds == list(paper.REPORT_SEEDS) and not set(full.seeds) & set(paper.TUNING_SEEDS)
    assert full.tasks == list(paper.TASKS)


def test_modelled_times_from_inprocess_timing() -> None:
    timing = {"worker_s": {"w0": [1.0, 1.0], "w1": [2.0, 3.0, 1.0]}, "chief_s": [0.5, 0.5, 0.5]}
    # w0 finished after 2 episodes: rounds last max(1, 2) + 0.5 and max(1, 3) + 0.5 -> 6 s, 2 s its own
    t = _modelled_times("w0", 2, timing)
    assert t["own_s"] == 2.0 and t["wall_s"] == 6.0 and t["wait_share"] == pytest.approx(1 - 2 / 6, abs=1e-4)
    t1 = _modelled_times("w1", 3, timing)
    assert t1["wall_s"] == 2.5 + 3.5 + 1.5 and t1["own_s"] == 6.0


def episode(worker: str, number: int, steps: int, t: float = 0.0, pi: float = 0.0) -> EpisodeRecord:
    return EpisodeRecord(worker=worker, round=number, episode=number, return_=pi, pi=pi, steps=steps, kind="update",
                         t=t)


def test_mqtt_times_from_the_chiefs_clock() -> None:
    episodes = [episode("w0", 1, 10, 1.0), episode("w1", 1, 10, 1.5), episode("w0", 2, 20, 2.6),
                episode("w1", 2, 20, 3.0), episode("w0", 3, 30, 4.0)]
    rounds = [RoundRecord(round=n, episode=n, kind="aggregate", strategy="weighted", contributors=[], t=t)
              for n, t in ((1, 1.6), (2, 3.1), (3, 4.1))]
    t = _mqtt_times("w0", 3, episodes, rounds)
    # own: (2.6 - 1.6) + (4.0 - 3.1) = 1.9 s for 50 steps; waits: (1.6 - 1.0) + (3.1 - 2.6) = 1.1 s
    assert t["own_s"] == pytest.approx(1.9) and t["timed_steps"] == 50
    assert t["wait_share"] == pytest.approx(1.1 / 3.0, abs=1e-4) and t["wall_s"] == pytest.approx(3.0)


def test_learning_curve_holds_a_finished_workers_pi() -> None:
    recs = [episode("w0", 1, 5, pi=10.0), episode("w1", 1, 7, pi=20.0), episode("w1", 2, 9, pi=30.0)]
    c = learning_curve(recs)
    assert c == {"episode": [1, 2], "pi": [15.0, 20.0], "steps": [6.0, 10.5]}


# -- fixture: a small results folder, no training -----------------------------------------------------------------


def _run(kind: str, strategy: str, seed: int, eps: int | None, m: int = 200) -> dict[str, Any]:
    n = 4 if kind == "federation" else 1
    reached = eps or m
    curve = {"episode": [1, reached], "pi": [20.0, 196.0 if eps else 90.0], "steps": [20.0, reached * 150.0]}
    if kind == "sb3":
        return {"kind": "sb3", "task": "CartPole-v0", "strategy": "sb3-zoo-ppo", "seed": seed, "workers": 1,
                "finished": eps is not None, "episodes": eps or 500, "steps": (eps or 500) * 90, "zoo_entry":
                "CartPole-v1", "n_envs": 8, "mode": "in-process", "job": Job("sb3", "CartPole-v0", "sb3-zoo-ppo",
                                                                              seed, 1, 0).__dict__}
    workers = [{"id": f"w{i}", "solved": eps is not None, "episodes": reached - i, "steps": (reached - i) * 150,
                "own_s": 1.0, "wall_s": 2.0, "wait_share": 0.5, "steps_per_s": 3000.0, "time_basis": "modelled"}
               for i in range(n)]
    return {"kind": kind, "task": "CartPole-v0", "strategy": strategy, "seed": seed, "workers": n,
            "max_episodes": m, "mode": "in-process", "finished": eps is not None, "end_reason": "x", "rounds": reached,
            "last_worker": {"episodes": eps, "steps": eps * 150 if eps else None, "wall_s": 2.0 if eps else None,
                            "episodes_reached": reached, "steps_reached": reached * 150},
            "first_worker_episodes": (eps - 3) if eps else None, "solved_workers": n if eps else 0,
            "total_steps": 1000, "per_worker": workers, "audit": {"passed": True, "detail": "ok"}, "curve": curve}


def fixture_results(out: Path, old_format: bool = False) -> dict[str, Any]:
    seeds = [101, 102, 103, 104]
    runs = [_run("federation", "independent", s, e) for s, e in zip(seeds, [80, 90, None, 120], strict=True)]
    runs += [_run("federation", "weighted", s, e) for s, e in zip(seeds, [30, 35, 38, 40], strict=True)]
    runs += [_run("single", "independent", s, e) for s, e in zip(seeds, [60, 70, 65, None], strict=True)]
    runs += [_run("sb3", "sb3-zoo-ppo", s, e) for s, e in zip(seeds, [150, 140, 160, 155], strict=True)]
    cfg = {"variant": "quick", "mode": "inprocess", "strategies": ["independent", "weighted"],
           "tasks": ["CartPole-v0"], "seeds": paper.seeds_block(seeds), "workers": None, "max_episodes": 200,
           "command": "python -m bench.paper --quick", "machine": {"cores": 2}, "wall_s": 12.0,
           "finished_at": "2026-01-01T00:00:00+00:00"}
    rep = paper.task_report("CartPole-v0", runs, cfg)
    if old_format:  # as bench.paper wrote it before learners were a dimension: PPO's alone, at the top level
        block = rep.pop("learners")["ppo"]
        rep.update({k: v for k, v in block.items() if k not in ("algo", "config")})
    out.mkdir(parents=True, exist_ok=True)
    (out / "paper-CartPole-v0.json").write_text(json.dumps({"config": cfg, **rep}))
    from bench.cost import bytes_per_round, growth

    cost = {"bytes": {"CartPole-v0": bytes_per_round("CartPole-v0", (4, 16))},
            "chief": {"task": "CartPole-v0", "strategy": "weighted", "rounds_per_point": 3, "skipped": [],
                      "points": [{"broker": b, "workers": n, "round_s": {"median": 0.01 * n, "p90": 0.02 * n}}
                                 for b in ("mosquitto", "amqtt") for n in (4, 16)],
                      "growth": {b: growth({4: 0.04, 16: 0.16}) for b in ("mosquitto", "amqtt")}},
            "workers": {"CartPole-v0": {"federation": {"steps_per_s": {"n": 1, "median": 3000.0, "q1": 2900.0,
                                                                       "q3": 3100.0}, "wait_share": {
                "n": 1, "median": 0.5, "q1": 0.4, "q3": 0.6}, "time_basis": ["modelled"]}}}}
    index = {"config": cfg, "tasks": {"CartPole-v0": {k: v for k, v in rep.items() if k != "runs"}}, "cost": cost}
    (out / "paper.json").write_text(json.dumps(index))
    return index


def test_statistics_and_target_on_the_fixture(tmp_path: Path) -> None:
    index = fixture_results(tmp_path)
    rep = index["tasks"]["CartPole-v0"]["learners"]["ppo"]
    ind, wtd = rep["summary"]["independent"], rep["summary"]["weighted"]
    assert ind["last_worker_episodes"]["median"] == 105.0  # 80 90 120 and one unfinished (ranked worst)
    assert ind["unfinished_seeds"] == [103] and wtd["last_worker_episodes"]["median"] == 36.5
    test = rep["significance"]["weighted"]["episodes"]
    assert test["p"] == pytest.approx(2 / 70) and test["significant"] and test["direction"] == "fewer"
    target = rep["target"]
    assert target["best_strategy"] == "weighted" and target["met"] and target["half_of_independent"]
    assert not target["comparable"]  # 4 seeds, not the 10 the target is for
    assert rep["references"]["single"]["finished"] == 3 and rep["references"]["sb3"]["zoo_entry"] == "CartPole-v1"


@pytest.mark.parametrize(("median", "independent", "significant", "half"), [
    (40, 100, True, True), (60, 100, True, False), (40, 100, False, False),
    (40, None, True, True),  # independent's median is past M = 80: more than twice 40
    (56, None, True, None),  # past 80, but not known to be past 112: the runs cannot tell
    (56, None, False, False), (None, None, True, False)])
def test_half_of_independent_is_claimed_only_where_the_runs_show_it(
        median: float | None, independent: float | None, significant: bool, half: bool | None) -> None:
    assert paper.half_of(median, independent, 80, significant) is half


@pytest.mark.parametrize("old_format", [False, True])
def test_figures_and_readme_from_the_fixture(tmp_path: Path, old_format: bool) -> None:
    index = fixture_results(tmp_path, old_format)
    paths = figures.draw_all(figures.load_reports(tmp_path), tmp_path)
    assert all(p.stat().st_size > 1000 for p in paths)
    readme, page = tmp_path / "README.md", tmp_path / "docs" / "results.md"
    readme.write_text(f"# x\n\nbefore\n\n{report.BEGIN}\nstale text\n{report.END}\n\nafter\n")
    assert report.main(["--results", str(tmp_path), "--readme", str(readme), "--docs", str(page),
                        "--links-from", str(tmp_path)]) == 0
    head = readme.read_text()
    assert "stale text" not in head and head.startswith("# x\n\nbefore") and head.rstrip().endswith("after")
    assert "| CartPole-v0 | `ppo` | 4 | 195 |" in head and "| 36.5 (4/4) |" in head
    assert "[`paper.json`](paper.json)" in head
    assert "| `weighted` | 36.5 [33.75-38.5] |" not in head  # the full tables are on the docs page only
    text = page.read_text()
    assert text.startswith(report.PAGE_HEAD) and "| `weighted` | 36.5 [33.75-38.5] |" in text
    assert "**p = 0.0286, fewer**" in text and "| 1 worker of ours alone | 67.5 [63.75-unfinished] |" in text
    assert "`independent` seeds 103" in text and "[`fig7-episodes.png`](fig7-episodes.png)" in text
    assert "t ~ N^1.00" in text and "| CartPole-v0 | `ppo` | <= 40 episodes | `weighted`: 36.5 episodes" in text
    assert "| SB3 PPO, zoo `CartPole-v1` (8 envs) |" in text and "learner `ppo`" in text
    again = report.markdown(index, tmp_path, tmp_path)
    assert again in text and "## Quick variant: CartPole-v0, 4 seeds, M = 200" in text  # the same block again
    with pytest.raises(ValueError):
        report.replace_block("no markers", "x")


def test_a_new_learner_merges_into_an_old_ppo_only_report(tmp_path: Path) -> None:
    fixture_results(tmp_path, old_format=True)
    old = json.loads((tmp_path / "paper-CartPole-v0.json").read_text())
    assert "learners" not in old
    sac_run = {**_run("federation", "sync", 101, 20), "algo": "sac"}
    cfg = {**old["config"], "algos": ["sac"], "strategies": ["sync"], "command": "python -m bench.paper --algos sac"}
    merged = paper.merge_task(old, paper.task_report("CartPole-v0", [sac_run], cfg))
    assert list(merged["learners"]) == ["ppo", "sac"] and len(merged["runs"]) == len(old["runs"]) + 1
    assert merged["learners"]["ppo"]["summary"] == old["summary"]
    assert merged["learners"]["ppo"]["config"]["command"] == "python -m bench.paper --quick"
    assert merged["learners"]["sac"]["target"]["target"] == {"episodes": 15}
    dqn_run = {**_run("federation", "sync", 101, 20), "algo": "dqn"}
    dqn = paper.task_report("CartPole-v0", [dqn_run], {**cfg, "algos": ["dqn"]})
    assert dqn["learners"]["dqn"]["target"]["target"] == {"episodes": 15}


def test_a_run_folder_being_written_by_another_process_is_refused_and_left_alone(tmp_path: Path) -> None:
    """Two benchmark processes over the same seeds and runs folder once clobbered a run's metrics.jsonl (its audit
    then failed): the second one now reports the job as an error and leaves the folder to the first."""
    job = Job("federation", "CartPole-v0", "weighted", 1, 2, 3)
    folder = tmp_path / job.name
    folder.mkdir()
    (folder / "metrics.jsonl").write_text("the first process's records\n")
    with run_folder_lock(tmp_path, job.name):  # held as another process would hold it (flock is per open file)
        result = execute(job, tmp_path)
    assert result["finished"] is False and "being written by another process" in result["error"]
    assert str(os.getpid()) in result["error"]
    assert (folder / "metrics.jsonl").read_text() == "the first process's records\n"
    with run_folder_lock(tmp_path, job.name):  # released when its holder is done
        pass


def test_resume_reuses_only_what_this_code_made(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    """A result made by other code (its fingerprint differs) runs again; one from before results carried a
    fingerprint is reused and counted; one made by this code is reused."""
    from bench import runs as bench_runs

    jobs = paper.plan(["CartPole-v0"], ["weighted"], [101, 102, 103], 2, 12, "inprocess", [])
    here = bench_runs.code_fingerprint("federation")
    old = [{"job": asdict(jobs[0]), "code": here, "made": "before"},
           {"job": asdict(jobs[1]), "code": "0" * 16, "made": "before"},
           {"job": asdict(jobs[2]), "made": "before"}]
    (tmp_path / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in old))
    ran: list[int] = []

    def fake(job: Job, runs_dir: Path) -> dict:
        ran.append(job.seed)
        return {"job": asdict(job), "code": here, "made": "now", "task": job.task, "kind": job.kind,
                "strategy": job.strategy, "seed": job.seed, "finished": False, "end_reason": "fake", "last_worker": {},
                "audit": {"passed": True}}

    monkeypatch.setattr(paper, "execute", fake)
    results = paper.run_jobs(jobs, 1, tmp_path, resume=True)
    assert ran == [102] and [r["made"] for r in results] == ["before", "now", "before"]
    assert "1 of them made by other code before; 1 reused without a code fingerprint" in capsys.readouterr().out
    again = paper.run_jobs(jobs, 1, tmp_path, resume=True)  # the new result, last in the file, is the one reused
    assert ran == [102] and [r["made"] for r in again] == ["before", "now", "before"]
