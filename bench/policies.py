"""``python -m bench.policies``: episodes and env steps until the last worker solves, per federation policy and seed.

Runs one federation per policy and seed, ``--jobs`` at a time, either as ``make run`` does (``--mode mqtt``:
``deploy.run_local``, embedded broker, chief and N workers as separate processes) or in one process
(``--mode inprocess``: ``deploy.inprocess``, the same chief and worker logic without MQTT, which gives the same
per-worker result). It audits each run folder (``python -m chief.audit``), collects its summary.json, and writes
``bench/results/policies-<env>-n<N>.json`` (with the mode) plus a PNG comparing the policies (the paper's Figure 7
in spirit). Runs that did not finish within M are reported as unfinished, never dropped.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from chief import strategies
from chief.audit import AuditFailure, audit
from chief.records import SUMMARY, RunSummary
from protocol.tasks import TASKS

RESULTS = Path("bench/results")


def run_once(env_id: str, policy: str, seed: int, workers: int, max_episodes: int, out: Path,
             mode: str = "mqtt") -> dict:
    run_dir = out / f"{env_id}-{policy}-s{seed}-n{workers}-{mode}"
    shutil.rmtree(run_dir, ignore_errors=True)
    t0 = time.monotonic()
    launcher = "deploy.run_local" if mode == "mqtt" else "deploy.inprocess"
    extra = ["--run-id", f"bench-{policy}-s{seed}"] if mode == "mqtt" else []
    proc = subprocess.run(
        [sys.executable, "-m", launcher, "--env", env_id, "--policy", policy, "--seed", str(seed),
         "--workers", str(workers), "--max-episodes", str(max_episodes), "--run-dir", str(run_dir), *extra],
        capture_output=True, text=True)
    wall = time.monotonic() - t0
    if not (run_dir / SUMMARY).exists():
        return {"policy": policy, "seed": seed, "error": proc.stdout[-2000:] + proc.stderr[-2000:], "wall_s": wall}
    s = RunSummary.read(run_dir)
    try:
        report = audit(run_dir)
        audited = f"passed: {report}"
    except AuditFailure as failure:
        audited = f"FAILED: {failure}"
    return {"policy": policy, "seed": seed, "mode": mode, "episodes_to_all_solved": s.episodes_to_all_solved,
            "steps_of_last_worker": s.steps_of_last_worker, "end_reason": s.end_reason,
            "first_solved": min((w.episodes for w in s.workers if w.solved), default=None),
            "per_worker": {w.id: {"episodes": w.episodes, "steps": w.steps, "solved": w.solved} for w in s.workers},
            "audit": audited, "wall_s": round(wall, 1), "run_dir": str(run_dir)}


def spread(values: list[float]) -> dict[str, float | None]:
    """Median and interquartile range (None when empty)."""
    if not values:
        return {"median": None, "q1": None, "q3": None, "min": None, "max": None}
    q = statistics.quantiles(values, n=4, method="inclusive") if len(values) > 1 else [values[0]] * 3
    return {"median": statistics.median(values), "q1": q[0], "q3": q[2], "min": min(values), "max": max(values)}


def aggregate(runs: list[dict]) -> dict[str, dict]:
    table: dict[str, dict] = {}
    for policy in sorted({r["policy"] for r in runs}):
        mine = [r for r in runs if r["policy"] == policy]
        done = [r for r in mine if r.get("episodes_to_all_solved") is not None]
        table[policy] = {"runs": len(mine), "all_solved_runs": len(done),
                         "unfinished_seeds": [r["seed"] for r in mine if r.get("episodes_to_all_solved") is None],
                         "audits_passed": sum(1 for r in mine if str(r.get("audit", "")).startswith("passed")),
                         "last_worker_episodes": spread([r["episodes_to_all_solved"] for r in done]),
                         "last_worker_steps": spread([r["steps_of_last_worker"] for r in done]),
                         "episodes": [r.get("episodes_to_all_solved") for r in mine]}
    return table


def markdown(report: dict) -> str:
    """The README table: median [IQR] of the last worker's episodes and env steps, per policy."""
    rows = ["| policy | last worker's episodes, median [IQR] | env steps, median [IQR] | per seed | all solved | "
            "audit |", "| --- | --- | --- | --- | --- | --- |"]
    for policy, t in report["summary"].items():
        e, s = t["last_worker_episodes"], t["last_worker_steps"]
        eps = " ".join("-" if x is None else str(x) for x in t["episodes"])
        cell_e = "-" if e["median"] is None else f"{e['median']:g} [{e['q1']:g}-{e['q3']:g}]"
        cell_s = "-" if s["median"] is None else f"{s['median']:,.0f} [{s['q1']:,.0f}-{s['q3']:,.0f}]"
        rows.append(f"| {policy} | {cell_e} | {cell_s} | {eps} | {t['all_solved_runs']}/{t['runs']} | "
                    f"{t['audits_passed']}/{t['runs']} passed |")
    return "\n".join(rows)


def plot(runs: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    policies = sorted({r["policy"] for r in runs})
    fig, ax = plt.subplots(figsize=(6, 4), dpi=110)
    for x, policy in enumerate(policies):
        ys = [r["episodes_to_all_solved"] for r in runs if r["policy"] == policy and r.get("episodes_to_all_solved")]
        missed = sum(1 for r in runs if r["policy"] == policy and r.get("episodes_to_all_solved") is None)
        if missed:
            ax.annotate(f"{missed} unfinished", (x, 0), ha="center", fontsize=8)
        ax.scatter([x] * len(ys), ys, alpha=0.7)
        if ys:
            ax.hlines(statistics.median(ys), x - 0.25, x + 0.25, color="black")
    ax.set_xticks(range(len(policies)), policies)
    ax.set_ylabel("episodes until the last worker solved")
    ax.set_title(title)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.policies", description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="CartPole-v0", choices=sorted(TASKS))
    parser.add_argument("--policies", nargs="+", default=strategies.names(), choices=strategies.names())
    parser.add_argument("--seeds", nargs="+", type=int, default=list(range(101, 111)),
                        help="base seeds (default 101-110: never used for tuning; the presets were tuned on 1-12)")
    parser.add_argument("--workers", type=int, default=4)
    parser.add_argument("--max-episodes", type=int, default=2000)
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--mode", choices=["mqtt", "inprocess"], default="mqtt",
                        help="mqtt: as make run (separate processes, embedded broker); inprocess: the same logic in "
                        "one process per run (default mqtt)")
    parser.add_argument("--jobs", type=int, default=1,
                        help="runs at a time (default 1; an MQTT run already uses N+2 processes)")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    plan = [(policy, seed) for seed in args.seeds for policy in args.policies]
    runs = []
    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        futures = [pool.submit(run_once, args.env, policy, seed, args.workers, args.max_episodes, args.out / "runs",
                               args.mode) for policy, seed in plan]
        for future in futures:
            result = future.result()
            runs.append(result)
            print(json.dumps(result), flush=True)
    stem = f"policies-{args.env}-n{args.workers}"
    report = {"env": args.env, "workers": args.workers, "seeds": args.seeds, "max_episodes": args.max_episodes,
              "mode": args.mode, "summary": aggregate(runs), "runs": runs}
    (args.out / f"{stem}.json").write_text(json.dumps(report, indent=2) + "\n")
    plot(runs, args.out / f"{stem}.png", f"{args.env}, {args.workers} workers")
    print(markdown(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
