"""``python -m bench.policies``: episodes until all workers solve, per federation policy and seed.

Runs ``deploy.run_local`` (embedded broker, chief and N workers as separate processes) once per policy and seed,
collects each run's summary.json, and writes ``bench/results/policies-<env>-n<N>.json`` plus a PNG comparing the
policies (the paper's Figure 7 in spirit).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

from chief.federation import POLICIES
from protocol.tasks import TASKS

RESULTS = Path("bench/results")


def run_once(env_id: str, policy: str, seed: int, workers: int, max_episodes: int, out: Path) -> dict:
    run_dir = out / f"{env_id}-{policy}-s{seed}-n{workers}"
    t0 = time.monotonic()
    proc = subprocess.run(
        [sys.executable, "-m", "deploy.run_local", "--env", env_id, "--policy", policy, "--seed", str(seed),
         "--workers", str(workers), "--max-episodes", str(max_episodes), "--run-dir", str(run_dir),
         "--run-id", f"bench-{policy}-s{seed}"],
        capture_output=True, text=True)
    wall = time.monotonic() - t0
    summary_path = run_dir / "summary.json"
    if not summary_path.exists():
        return {"policy": policy, "seed": seed, "error": proc.stdout[-2000:] + proc.stderr[-2000:], "wall_s": wall}
    s = json.loads(summary_path.read_text())
    return {"policy": policy, "seed": seed, "episodes_to_all_solved": s["episodes_to_all_solved"],
            "first_solved": min((w["episodes"] for w in s["workers"] if w["solved"]), default=None),
            "per_worker": {w["id"]: w["episodes"] for w in s["workers"]}, "wall_s": round(wall, 1),
            "run_dir": str(run_dir)}


def aggregate(runs: list[dict]) -> dict[str, dict]:
    table: dict[str, dict] = {}
    for policy in sorted({r["policy"] for r in runs}):
        eps = [r["episodes_to_all_solved"] for r in runs if r["policy"] == policy]
        solved = [e for e in eps if e is not None]
        table[policy] = {"runs": len(eps), "all_solved_runs": len(solved),
                         "median_episodes_to_all_solved": statistics.median(solved) if solved else None,
                         "mean_episodes_to_all_solved": round(statistics.mean(solved), 1) if solved else None,
                         "episodes": eps}
    return table


def plot(runs: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    policies = sorted({r["policy"] for r in runs})
    fig, ax = plt.subplots(figsize=(6, 4), dpi=110)
    for x, policy in enumerate(policies):
        ys = [r["episodes_to_all_solved"] for r in runs if r["policy"] == policy and r.get("episodes_to_all_solved")]
        ax.scatter([x] * len(ys), ys, alpha=0.7)
        if ys:
            ax.hlines(statistics.median(ys), x - 0.25, x + 0.25, color="black")
    ax.set_xticks(range(len(policies)), policies)
    ax.set_ylabel("episodes until all workers solved")
    ax.set_title(title)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.policies", description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="CartPole-v0", choices=sorted(TASKS))
    parser.add_argument("--policies", nargs="+", default=list(POLICIES), choices=POLICIES)
    parser.add_argument("--seeds", nargs="+", type=int, default=[1, 2, 3])
    parser.add_argument("--workers", type=int, default=4)
    parser.add_argument("--max-episodes", type=int, default=2000)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    runs = []
    for seed in args.seeds:
        for policy in args.policies:
            result = run_once(args.env, policy, seed, args.workers, args.max_episodes, args.out / "runs")
            runs.append(result)
            print(json.dumps(result), flush=True)
    stem = f"policies-{args.env}-n{args.workers}"
    report = {"env": args.env, "workers": args.workers, "seeds": args.seeds, "max_episodes": args.max_episodes,
              "summary": aggregate(runs), "runs": runs}
    (args.out / f"{stem}.json").write_text(json.dumps(report, indent=2) + "\n")
    plot(runs, args.out / f"{stem}.png", f"{args.env}, {args.workers} workers")
    print(json.dumps(report["summary"], indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
