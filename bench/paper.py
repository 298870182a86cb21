"""``python -m bench.paper`` (``make bench``): the paper's Section V experiment, with statistics, references and cost.

Every task (the four gymnasium tasks with 4 workers, the simulated QUBE with 3 rigs) under every strategy of the
registry (chief/strategies/, found automatically), for every learner (``--algos``: tasks x learners x strategies x
seeds; each result keeps its learner), on base seeds never used for tuning. Each run is the same chief
and worker logic as ``make run``: in process by default (deploy.inprocess), or ``--mode mqtt`` (deploy.run_local:
embedded broker, chief and workers as separate processes; ``qube-local`` then becomes ``qube``, rigs over MQTT).
Runs go ``--jobs`` at a time (default: the number of cores), each single-threaded.

In the same run, per learner: one worker of ours alone (``independent``, 1 worker) and Stable-Baselines3 with its
zoo hyperparameters (bench/sb3_ref.py: PPO beside our PPO; SAC, or DQN on discrete actions, beside our SAC), on the
same seeds and under the same stop rule; and the cost benchmark (bench/cost.py). Results: ``<out>/paper.json``
(configuration, per task and learner the median [IQR] of the last worker's episodes and steps, the rank tests against
the same learner's ``independent``, the references, the project's targets) and ``<out>/paper-<task>.json`` (the same
plus every run; a learner measured by an earlier invocation into the same folder keeps its results there), figures
``fig5-*.png`` and ``fig7-*.png``, ``cost.json``; finally docs/results.md and the README's results table
(bench/report.py). Run folders go to ``bench/results/runs/<variant>/`` (not committed); ``--resume`` reuses the
results of runs already there.

``--quick`` (``make bench-quick``) is a reduced variant for a 2-core machine in under 15 minutes: see QUICK.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import os
import platform
import sys
import time
from collections.abc import Iterable
from concurrent.futures import FIRST_COMPLETED, Future, wait
from pathlib import Path
from typing import Any

from bench import stats
from bench.output import command
from bench.runs import BASELINE, Job, algo_of, code_fingerprint, execute, learner_blocks, outcome, process_pool
from chief import strategies as registry
from protocol import learners
from protocol.qube import PERIOD_S
from protocol.tasks import TASKS as TASK_SPECS

TASKS = ("CartPole-v0", "Acrobot-v1", "MountainCarContinuous-v0", "Pendulum-v1", "qube-local")
#: Base seeds reported: never used for tuning (their worker seeds are seed*1000 + i, i.e. 101000-110003).
REPORT_SEEDS = tuple(range(101, 111))
#: Base seeds used while tuning and checking: worker/envs.py's presets (single workers on seeds 1-10 and on the
#: worker seeds 1000-1003, 2000-2003, 3000-3003 of base seeds 1-3), the earlier per-policy comparisons and the
#: README's earlier tables (1-5), the end-to-end tests (1-3). Never reported here.
TUNING_SEEDS = tuple(range(1, 13))
#: The learners of ``make bench`` by default: PPO and SAC run every task; DQN (discrete actions only) on request.
BENCH_ALGOS = ("ppo", "sac")
DEFAULT_M = 2000

#: The project's targets per learner, for the last worker to finish (of 4; of 3 rigs), median over 10 report seeds,
#: in episodes.
TARGETS: dict[str, dict[str, dict[str, float]]] = {
    "ppo": {
        "CartPole-v0": {"episodes": 40},
        "Acrobot-v1": {"episodes": 60},
        "MountainCarContinuous-v0": {"episodes": 20, "solved_share": 0.9},
        "Pendulum-v1": {"episodes": 100},
        "qube-local": {"balance_s": 240.0},  # 4 min of simulated balance time per rig (steps of 7 ms)
        "qube": {"balance_s": 240.0},
    },
    "sac": {  # the targets of an off-policy learner's sample efficiency
        "CartPole-v0": {"episodes": 15},
        "Acrobot-v1": {"episodes": 15},
        "MountainCarContinuous-v0": {"episodes": 12, "solved_share": 0.9},
        "Pendulum-v1": {"episodes": 20},
        "qube-local": {"balance_s": 210.0},  # 30,000 balance steps of 7 ms per rig, from scratch
        "qube": {"balance_s": 210.0},
    },
    "dqn": {  # the same off-policy targets, on the discrete tasks (DQN has no continuous actions)
        "CartPole-v0": {"episodes": 15},
        "Acrobot-v1": {"episodes": 15},
        "qube-local": {"balance_s": 210.0},
        "qube": {"balance_s": 210.0},
    },
}

#: The quick variant (make bench-quick), for under 15 minutes on the 2-core VM. What it leaves out: MountainCar-
#: Continuous-v0, Pendulum-v1 and the QUBE (the slow tasks), seeds 104-110, episodes past 300 (a run still learning
#: then is unfinished), SB3 on Acrobot (16 envs, about 50k steps per run), most rounds of the chief load benchmark,
#: and the 64-worker in-process scaling run (bench.cost.worker_scaling).
QUICK: dict[str, Any] = {"tasks": ("CartPole-v0", "Acrobot-v1"), "seeds": (101, 102, 103), "max_episodes": 300,
                         "sb3_tasks": ("CartPole-v0",), "cost_rounds": 6, "cost_workers": (4, 16, 64),
                         "scaling_workers": (4, 16), "scaling_rounds": 10}
#: The full variant's worker scaling runs (bench.cost.worker_scaling): CartPole-v0 for 30 rounds with 4, 16, 64.
FULL_SCALING: dict[str, Any] = {"scaling_workers": (4, 16, 64), "scaling_rounds": 30}
#: Relative cost of a run, to start the longest first.
_COST = {"qube-local": 20.0, "qube": 20.0, "Pendulum-v1": 8.0, "MountainCarContinuous-v0": 2.0}


def default_workers(task: str) -> int:
    return 3 if task.startswith("qube") else 4


def plan(tasks: Iterable[str], strategy_names: Iterable[str], seeds: Iterable[int], workers: int | None,
         max_episodes: int, mode: str, references: Iterable[str], sb3_tasks: Iterable[str] | None = None,
         algos: Iterable[str] = (learners.DEFAULT,)) -> list[Job]:
    """Every run of the experiment, per task and learner: federations, then the references. A learner that cannot
    act in a task's action space (DQN on a continuous one, protocol/learners.py misfit) runs nothing there."""
    from bench import sb3_ref

    jobs: list[Job] = []
    refs = set(references)
    for task in tasks:
        n = workers or default_workers(task)
        for algo in (a for a in algos if learners.misfit(a, task) is None):
            sb3 = sb3_ref.reference(algo, task) if sb3_tasks is None or task in sb3_tasks else None
            for seed in seeds:
                jobs += [Job("federation", task, s, seed, n, max_episodes, mode, algo) for s in strategy_names]
                if "single" in refs:
                    jobs.append(Job("single", task, BASELINE, seed, 1, max_episodes, mode, algo))
                if "sb3" in refs and sb3 is not None:
                    jobs.append(Job("sb3", task, sb3_ref.label(sb3), seed, 1, 0, "inprocess", algo))
    return jobs


def run_jobs(jobs: list[Job], parallel: int, runs_dir: Path, resume: bool = False) -> list[dict[str, Any]]:
    """Run every job, ``parallel`` at a time (1: in this process); results in the jobs' order. Each result is also
    appended to ``runs_dir/results.jsonl`` as it comes. ``resume`` reuses those of the same jobs made by the same
    code (bench.runs.code_fingerprint); one made by other code runs again, and one from before results carried a
    fingerprint is reused and counted (the report says how many)."""
    runs_dir.mkdir(parents=True, exist_ok=True)
    log_path = runs_dir / "results.jsonl"
    latest: dict[tuple[Any, ...], dict[str, Any]] = {}  # each job's last result without an error
    if resume and log_path.exists():
        for rec in map(json.loads, log_path.read_text().splitlines()):
            if "error" not in rec:
                latest[Job(**rec["job"]).key] = rec
    done = {key: rec for key, rec in latest.items()  # made by this code, or before results carried a fingerprint
            if rec.get("code") in (None, code_fingerprint(rec["job"]["kind"]))}
    other_code = latest.keys() - done.keys()
    todo = [j for j in jobs if j.key not in done]
    todo.sort(key=lambda j: -_COST.get(j.task, 1.0) * (1 if j.kind == "federation" else 0.5))
    stale = sum(1 for j in todo if j.key in other_code)
    unstamped = sum(1 for j in jobs if j.key in done and "code" not in done[j.key])
    print(f"{len(jobs)} runs, {len(jobs) - len(todo)} reused, {len(todo)} to run, {parallel} at a time"
          + (f"; {stale} of them made by other code before" if stale else "")
          + (f"; {unstamped} reused without a code fingerprint (made before results carried one)" if unstamped
             else ""), flush=True)
    t0 = time.monotonic()
    with log_path.open("a") as log:
        def record(result: dict[str, Any]) -> None:
            done[Job(**result["job"]).key] = result
            log.write(json.dumps(result) + "\n")
            log.flush()
            count = sum(1 for j in jobs if j.key in done)
            print(f"[{time.monotonic() - t0:7.1f}s] {count}/{len(jobs)} {_line(result)}", flush=True)

        if parallel <= 1:
            for job in todo:
                record(execute(job, runs_dir))
        else:
            with process_pool(parallel) as pool:
                pending: set[Future] = {pool.submit(execute, job, runs_dir) for job in todo}
                while pending:
                    finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for future in finished:
                        record(future.result())
    return [done[j.key] for j in jobs]


def _line(r: dict[str, Any]) -> str:
    head = f"{r['task']} {r['kind']} {r['strategy']} s{r['seed']}"
    if "error" in r:
        return f"{head}: ERROR {r['error']}"
    if r["kind"] == "sb3":
        what = f"solved at episode {r['episodes']} ({r['steps']} steps)" if r["finished"] else "unfinished"
    else:
        last = r["last_worker"]
        what = (f"last worker at episode {last['episodes']} ({last['steps']} steps)" if r["finished"]
                else f"unfinished ({r['end_reason']})")
        what += "" if r["audit"]["passed"] else f"; AUDIT FAILED {r['audit']['detail']}"
    return f"{head}: {what} [{r.get('run_wall_s', 0):.0f} s]"


# -- aggregation ----------------------------------------------------------------------------------------------


def summarize(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Median [IQR] of the last worker's episodes and steps over every run (unfinished ranked worst), and more."""
    eps = [outcome(r)[0] for r in runs]
    steps = [outcome(r)[1] for r in runs]
    fed = [r for r in runs if r.get("kind") != "sb3" and "error" not in r]
    workers = [w for r in fed for w in r["per_worker"]]
    out: dict[str, Any] = {
        "runs": len(runs), "finished": sum(1 for e in eps if e is not None),
        "unfinished_seeds": [r["seed"] for r, e in zip(runs, eps, strict=True) if e is None],
        "errors": {str(r["seed"]): r["error"] for r in runs if "error" in r},
        "last_worker_episodes": stats.spread_censored(eps), "last_worker_steps": stats.spread_censored(steps),
        "per_seed": {str(r["seed"]): {"episodes": e, "steps": s} for r, e, s in zip(runs, eps, steps, strict=True)},
        "modes": sorted({r.get("mode", "?") for r in runs if "error" not in r}),
    }
    if fed:
        out["audits_passed"] = sum(1 for r in fed if r["audit"]["passed"])
        out["first_worker_episodes"] = stats.spread([r["first_worker_episodes"] for r in fed
                                                     if r["first_worker_episodes"] is not None])
        out["last_worker_wall_s"] = stats.spread([r["last_worker"]["wall_s"] for r in fed
                                                  if r["last_worker"]["wall_s"] is not None])
        out["steps_per_s"] = stats.spread([w["steps_per_s"] for w in workers if w.get("steps_per_s")])
        out["wait_share"] = stats.spread([w["wait_share"] for w in workers if w.get("wait_share") is not None])
        out["time_basis"] = sorted({w.get("time_basis", "?") for w in workers})
    return out


def significance(by_strategy: dict[str, list[dict[str, Any]]], max_episodes: int) -> dict[str, Any]:
    """Each strategy against BASELINE: two-sided Mann-Whitney U on the last worker's episodes and steps, runs
    paired by nothing (independent samples), unfinished runs ranked as worse than any finished one."""
    if BASELINE not in by_strategy:
        return {}
    base = by_strategy[BASELINE]
    out = {}
    for name, runs in by_strategy.items():
        if name == BASELINE:
            continue
        eps_x, eps_y = [outcome(r)[0] for r in runs], [outcome(r)[0] for r in base]
        st_x, st_y = [outcome(r)[1] for r in runs], [outcome(r)[1] for r in base]
        worst_steps = 1 + max([s for s in st_x + st_y if s is not None], default=0)
        out[name] = {"episodes": stats.compare(eps_x, eps_y, max_episodes + 1),
                     "steps": stats.compare(st_x, st_y, worst_steps)}
    return out


def evaluate_target(task: str, summary: dict[str, dict[str, Any]], tests: dict[str, Any], workers: int,
                    seeds: list[int], algo: str = learners.DEFAULT, *, max_episodes: int) -> dict[str, Any]:
    """The project's target for this task and learner: the best strategy's median against it, and against half of the
    same learner's independent."""
    target = TARGETS.get(algo, {}).get(task)
    if target is None or not summary:
        return {}

    def key(name: str) -> float:
        med = summary[name]["last_worker_episodes"]["median"]
        return math.inf if med is None else med

    best = min(summary, key=key)
    s = summary[best]
    med_eps, med_steps = s["last_worker_episodes"]["median"], s["last_worker_steps"]["median"]
    result: dict[str, Any] = {"target": target, "best_strategy": best, "median_episodes": med_eps,
                              "median_steps": med_steps,
                              "comparable": workers == default_workers(task) and len(seeds) >= 10}
    if "episodes" in target:
        result["met"] = med_eps is not None and med_eps <= target["episodes"]
    else:
        balance = None if med_steps is None else med_steps * PERIOD_S
        result["median_balance_s"] = balance
        result["met"] = balance is not None and balance <= target["balance_s"]
    if "solved_share" in target:
        share = s["finished"] / s["runs"] if s["runs"] else 0.0
        result["solved_share"] = share
        result["met"] = result["met"] and share >= target["solved_share"]
    base = summary.get(BASELINE, {}).get("last_worker_episodes", {}).get("median")
    test = tests.get(best, {}).get("episodes", {})
    result["independent_median_episodes"] = base
    result["half_of_independent"] = None if BASELINE not in summary else half_of(  # None: independent not run
        med_eps, base, max_episodes, bool(test.get("significant")) and test.get("direction") == "fewer")
    return result


def half_of(median: float | None, independent: float | None, max_episodes: int, significant: bool) -> bool | None:
    """Whether a median of ``median`` episodes is at most half of ``independent``'s, and significantly fewer; None
    when the runs cannot tell: ``independent``'s median is unfinished (past M episodes, by how much unknown) and
    ``median`` is above M / 2."""
    if median is None or not significant:
        return False
    if independent is not None:
        return median <= 0.5 * independent
    return True if median <= 0.5 * max_episodes else None


def learner_report(task: str, mine: list[dict[str, Any]], cfg: dict[str, Any], algo: str) -> dict[str, Any]:
    """One learner on one task: summaries per strategy, tests against its own ``independent``, references, target."""
    fed = [r for r in mine if r["kind"] == "federation"]
    names = [s for s in cfg["strategies"] if any(r["strategy"] == s for r in fed)]
    by_strategy = {s: [r for r in fed if r["strategy"] == s] for s in names}
    summary = {s: summarize(runs) for s, runs in by_strategy.items()}
    tests = significance(by_strategy, cfg["max_episodes"])
    workers = fed[0]["workers"] if fed else (cfg["workers"] or default_workers(task))
    refs = {}
    for kind in ("single", "sb3"):
        runs = [r for r in mine if r["kind"] == kind]
        if runs:
            refs[kind] = summarize(runs)
            if kind == "sb3":
                for key in ("zoo_entry", "n_envs", "strategy"):
                    refs[kind][key] = next((r[key] for r in runs if key in r), None)
    return {"algo": algo, "config": cfg, "workers": workers, "max_episodes": cfg["max_episodes"],
            "seeds": cfg["seeds"], "strategies": names, "summary": summary, "significance": tests,
            "references": refs, "target": evaluate_target(task, summary, tests, workers, cfg["seeds"]["report"], algo,
                                                     max_episodes=cfg["max_episodes"])}


def task_report(task: str, results: list[dict[str, Any]], cfg: dict[str, Any]) -> dict[str, Any]:
    """Everything about one task: per learner (``learners``) summaries per strategy, tests, references and target;
    and every run. The top-level ``workers``, ``max_episodes`` and ``seeds`` are those of the first learner."""
    mine = [r for r in results if r["task"] == task]
    algos = [a for a in cfg.get("algos", [learners.DEFAULT]) if any(algo_of(r) == a for r in mine)]
    blocks = {a: learner_report(task, [r for r in mine if algo_of(r) == a], cfg, a) for a in algos}
    first = next(iter(blocks.values()), {"workers": cfg["workers"] or default_workers(task)})
    return {"task": task, "tc": TASK_SPECS[task].tc, "workers": first["workers"],
            "max_episodes": cfg["max_episodes"], "mode": cfg["mode"], "seeds": cfg["seeds"], "learners": blocks,
            "runs": mine}


def merge_task(old: dict[str, Any], new: dict[str, Any]) -> dict[str, Any]:
    """``new``, keeping ``old``'s learners that ``new`` did not measure (their blocks, configuration and runs)."""
    kept = {a: {"config": old.get("config"), **b} if "config" not in b and old.get("config") else b
            for a, b in learner_blocks(old).items() if a not in new["learners"]}
    if not kept:
        return new
    runs = [r for r in old.get("runs", []) if algo_of(r) in kept]
    return {**new, "learners": {**kept, **new["learners"]}, "runs": runs + new.get("runs", [])}


# -- command line -----------------------------------------------------------------------------------------------


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    names = registry.names()
    parser = argparse.ArgumentParser(prog="python -m bench.paper", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the reduced variant (make bench-quick): " + ", ".join(
        f"{k}={v}" for k, v in QUICK.items()))
    parser.add_argument("--tasks", nargs="+", choices=sorted(TASK_SPECS), help=f"default: {' '.join(TASKS)}")
    parser.add_argument("--strategies", nargs="+", choices=names, help="default: every registered one")
    parser.add_argument("--algos", nargs="+", choices=learners.names(),
                        help=f"the workers' learners (default: {' '.join(BENCH_ALGOS)}; --quick: {learners.DEFAULT})"),
    parser.add_argument("--seeds", nargs="+", type=int, help="base seeds (default 101-110, never used for tuning)")
    parser.add_argument("--workers", type=int, help="workers per federation (default 4; 3 rigs for the QUBE)")
    parser.add_argument("--max-episodes", type=int, help=f"M, the most rounds a run takes (default {DEFAULT_M})")
    parser.add_argument("--mode", choices=["inprocess", "mqtt"], default="inprocess",
                        help="inprocess (default): deploy.inprocess; mqtt: deploy.run_local, as make run")
    parser.add_argument("--jobs", type=int, help="runs at a time (default: cores for inprocess, 1 for mqtt)")
    parser.add_argument("--references", nargs="*", default=["single", "sb3"], choices=["single", "sb3"],
                        help="reference runs on the same seeds (default: single sb3)")
    parser.add_argument("--no-cost", action="store_true", help="skip the cost benchmark (bench/cost.py)")
    parser.add_argument("--no-readme", action="store_true", help="do not rewrite docs/results.md and the README table")
    parser.add_argument("--resume", action="store_true", help="reuse results of runs already in the runs folder")
    parser.add_argument("--out", type=Path, help="results folder (default bench/results, or bench/results/quick)")
    parser.add_argument("--runs-dir", type=Path, help="run folders (default bench/results/runs/<full|quick>)")
    args = parser.parse_args(argv)
    quick = args.quick
    args.tasks = args.tasks or list(QUICK["tasks"] if quick else TASKS)
    if args.mode == "inprocess" and "qube" in args.tasks:
        parser.error("the in-process mode has no MQTT rigs: use qube-local (or --mode mqtt)")
    if args.mode == "mqtt":
        args.tasks = ["qube" if t == "qube-local" else t for t in args.tasks]
    args.strategies = args.strategies or names
    args.algos = args.algos or ([learners.DEFAULT] if quick else list(BENCH_ALGOS))
    args.seeds = args.seeds or list(QUICK["seeds"] if quick else REPORT_SEEDS)
    args.max_episodes = args.max_episodes or (QUICK["max_episodes"] if quick else DEFAULT_M)
    args.jobs = args.jobs or ((os.cpu_count() or 1) if args.mode == "inprocess" else 1)
    args.out = args.out or (Path("bench/results/quick") if quick else Path("bench/results"))
    args.runs_dir = args.runs_dir or Path("bench/results/runs") / ("quick" if quick else "full")
    return args


def seeds_block(seeds: list[int]) -> dict[str, Any]:
    return {"report": list(seeds), "tuning": list(TUNING_SEEDS),
            "report_seeds_used_for_tuning": sorted(set(seeds) & set(TUNING_SEEDS)),
            "note": "report seeds are base seeds; worker i of a run uses seed*1000 + i. The tuning seeds were used "
                    "for worker/envs.py's presets (single workers on seeds 1-10 and on 1000-1003, 2000-2003, "
                    "3000-3003, the worker seeds of base seeds 1-3), the earlier per-policy comparisons, the README's "
                    "earlier tables and the end-to-end tests."}


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    started = time.monotonic()
    cfg = {"variant": "quick" if args.quick else "full", "mode": args.mode, "strategies": args.strategies,
           "algos": args.algos,
           "tasks": args.tasks, "seeds": seeds_block(args.seeds), "workers": args.workers,
           "max_episodes": args.max_episodes, "jobs": args.jobs, "references": args.references,
           "baseline": BASELINE, "command": command("bench.paper", argv),
           "machine": {"cores": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()}}
    if cfg["seeds"]["report_seeds_used_for_tuning"]:
        print(f"WARNING: seeds {cfg['seeds']['report_seeds_used_for_tuning']} were used for tuning", file=sys.stderr)
    for task, algo, why in ((t, a, learners.misfit(a, t)) for t in args.tasks for a in args.algos):
        if why:
            print(f"skipping {algo} on {task}: {why}", flush=True)
    jobs = plan(args.tasks, args.strategies, args.seeds, args.workers, args.max_episodes, args.mode,
                args.references, QUICK["sb3_tasks"] if args.quick else None, args.algos)
    results = run_jobs(jobs, args.jobs, args.runs_dir, resume=args.resume)
    cfg["runs_wall_s"] = round(time.monotonic() - started, 1)
    cfg["unfingerprinted"] = sum(1 for r in results if "code" not in r)  # reused, made before results carried one
    args.out.mkdir(parents=True, exist_ok=True)
    reports = {task: task_report(task, results, cfg) for task in args.tasks}
    for task, rep in reports.items():
        path = args.out / f"paper-{task}.json"
        if path.exists():  # another learner's results of this task, from an earlier invocation, stay
            reports[task] = rep = merge_task(json.loads(path.read_text()), rep)
        path.write_text(json.dumps({"config": cfg, **rep}, indent=1) + "\n")
    cost = None
    if not args.no_cost:
        from bench import cost as cost_bench

        scaling = QUICK if args.quick else FULL_SCALING
        cost = cost_bench.run_all(args.out, rounds=QUICK["cost_rounds"] if args.quick else cost_bench.ROUNDS,
                                  worker_counts=QUICK["cost_workers"] if args.quick else cost_bench.WORKER_COUNTS,
                                  paper_reports=reports, scaling_rounds=scaling["scaling_rounds"],
                                  scaling_workers=scaling["scaling_workers"], runs_dir=args.runs_dir)
    cfg["wall_s"] = round(time.monotonic() - started, 1)
    cfg["finished_at"] = dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")
    index: dict[str, Any] = {
        "config": cfg, "tasks": {t: {k: v for k, v in rep.items() if k != "runs"} for t, rep in reports.items()},
        "cost": cost}
    previous = args.out / "paper.json"
    if previous.exists():
        # Tasks measured by an earlier invocation into the same folder (e.g. with another M or other seeds) stay,
        # each with its own configuration in paper-<task>.json; so does the cost benchmark when skipped now.
        old = json.loads(previous.read_text())
        kept = {t: rep for t, rep in old.get("tasks", {}).items() if t not in index["tasks"]}
        index["tasks"] = {**kept, **index["tasks"]}
        if cost is None:
            index["cost"] = old.get("cost")
        if kept:
            cfg["earlier_tasks"] = sorted(kept)
    (args.out / "paper.json").write_text(json.dumps(index, indent=1) + "\n")
    from bench import figures, report

    figures.draw_all(figures.load_reports(args.out), args.out)
    print(report.markdown(index, args.out))
    if not args.no_readme:
        folders = list(dict.fromkeys([args.out, *report.default_folders()]))
        report.write_docs(folders)
        report.write_readme(folders, Path("README.md"))
        print(f"{report.DOCS_PAGE} and README.md's results table rewritten from {', '.join(map(str, folders))}")
    print(f"done in {cfg['wall_s']:.0f} s; results in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
