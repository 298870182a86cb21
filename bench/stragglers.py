"""``python -m bench.stragglers``: what one straggler costs a federation with k-of-n rounds (``--quorum``).

Three in-process federations (deploy/inprocess.py) of the same task, seed and episode cap: ``baseline``, N - 1
workers at their own pace, every round waiting for all of them; ``quorum``, the same N - 1 plus one worker
``--slowdown`` times slower, rounds closing with a quorum of N - 1 (its late submissions dropped); and, unless
``--no-unbounded``, ``unbounded``, the same N with every round waiting for the straggler. Each run's time per round
is the median gap between two rounds' close times in its records (metrics.jsonl ``t``, the chief's clock); the
slowdown is the quorum run's against the baseline's (``--repeat R``: R pairs, interleaved in ABBA order so that a
load that drifts weighs on both alike, and the median of the pairs' slowdowns). Every run is audited. Writes
bench/results/stragglers.json.

With ``--edges E`` every run is tiered (E edge chiefs, worker i behind edge e<i mod E>, k counted across the edges:
docs/explanation/tiered.md), the baseline's N - 1 workers too; it writes bench/results/stragglers-edges.json.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.output import command
from chief.audit import audit
from deploy.inprocess import run_federation
from deploy.settings import InprocessSettings
from runtime.records import RoundRecord, read_metrics

OUT = Path("bench/results/stragglers.json")
OUT_EDGES = Path("bench/results/stragglers-edges.json")


def rounds_of(run_dir: Path) -> list[RoundRecord]:
    """A run's round records, in order (metrics.jsonl)."""
    return [r for r in read_metrics(run_dir) if isinstance(r, RoundRecord)]


def seconds_per_round(run_dir: Path) -> float:
    """The median gap between two consecutive rounds' close times (s)."""
    times = [r.t for r in rounds_of(run_dir)]
    return statistics.median(b - a for a, b in itertools.pairwise(times))


def measure(name: str, workers: int, episodes: int, seed: int, env: str, folder: Path, quorum: int = 0,
            pace: dict[str, float] | None = None, edges: int = 0, pair: int = 0) -> dict[str, Any]:
    """One federation, audited: its median seconds per round and what it did."""
    run_dir = folder / f"{name}-{pair}"
    began = time.monotonic()
    summary = run_federation(InprocessSettings.given(env=env, policy="weighted", seed=seed, workers=workers,
                             max_episodes=episodes, run_dir=run_dir, quorum=quorum, edges=edges), plot=False,
                             tensorboard_files=False, models=False, pace=pace)
    report = audit(run_dir)
    rounds = rounds_of(run_dir)
    return {"name": name, "pair": pair, "workers": workers, "quorum": quorum or None, "pace": pace or {},
            "edges": edges, "rounds": summary.rounds, "s_per_round": round(seconds_per_round(run_dir), 4),
            "wall_s": round(time.monotonic() - began, 1),
            "rounds_without": sum(1 for r in rounds if r.late),
            "late_refused": (summary.rejected_messages or {}).get("late", 0), "audit": str(report)}


def pair_slowdowns(runs: list[dict[str, Any]]) -> list[float]:
    """Each pair's quorum run against its own baseline (%), in pair order."""
    per = {(r["name"], r["pair"]): r["s_per_round"] for r in runs}
    pairs = sorted({p for name, p in per if name == "quorum"})
    return [round(100 * (per[("quorum", p)] / per[("baseline", p)] - 1), 1) for p in pairs]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.stragglers", description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, default=16, help="N, the straggler included (default 16)")
    parser.add_argument("--slowdown", type=float, default=10.0, help="how many times slower the straggler plays")
    parser.add_argument("--episodes", type=int, default=12, help="episode cap of every run (default 12)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--env", default="CartPole-v0")
    parser.add_argument("--no-unbounded", action="store_true", help="leave out the run that waits for the straggler")
    parser.add_argument("--edges", type=int, default=0, help="E edge chiefs in every run (default 0: flat)")
    parser.add_argument("--repeat", type=int, default=1, help="baseline and quorum runs R times each, interleaved "
                        "in ABBA order; the slowdown is the median of the R pairs' (default 1)")
    parser.add_argument("--out", type=Path, default=None, help=f"default {OUT}, with --edges {OUT_EDGES}")
    args = parser.parse_args(argv)
    args.out = args.out or (OUT_EDGES if args.edges else OUT)
    e = args.edges
    n, slow = args.workers, f"w{args.workers - 1}"
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        kinds: dict[str, dict[str, Any]] = {"baseline": {"workers": n - 1},
                                            "quorum": {"workers": n, "quorum": n - 1, "pace": {slow: args.slowdown}}}
        runs: list[dict[str, Any]] = []
        for i in range(args.repeat):  # pairs in ABBA order: a load that drifts weighs on both sides alike
            for name in ("baseline", "quorum") if i % 2 == 0 else ("quorum", "baseline"):
                runs.append(measure(name, episodes=args.episodes, seed=args.seed, env=args.env, folder=folder,
                                    edges=e, pair=i, **kinds[name]))
        if not args.no_unbounded:
            runs.append(measure("unbounded", n, args.episodes, args.seed, args.env, folder,
                                pace={slow: args.slowdown}, edges=e))
    per_pair = pair_slowdowns(runs)
    base = statistics.median(r["s_per_round"] for r in runs if r["name"] == "baseline")
    result = {"env": args.env, "seed": args.seed, "episodes": args.episodes, "slowdown": args.slowdown, "edges": e,
              "straggler": slow, "load_average_at_start": load, "load_average_at_end": os.getloadavg()[0],
              "cores": os.cpu_count(), "repeat": args.repeat, "pair_slowdowns_pct": per_pair,
              "runs": runs, "quorum_slowdown_pct": round(statistics.median(per_pair), 1),
              **({"unbounded_slowdown_pct": round(100 * (runs[-1]["s_per_round"] / base - 1), 1)}
                 if not args.no_unbounded else {}),
              "command": command("bench.stragglers", argv)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    for r in runs:
        print(f"{r['name']:>10}: {r['workers']} workers, {r['s_per_round']:.3f} s per round (median), "
              f"{r['rounds_without']} rounds closed without the straggler; audit: {r['audit']}")
    print(f"k-of-n: {result['quorum_slowdown_pct']:+.1f} % per round against {n - 1} workers without the straggler"
          + (f" (median of {args.repeat} pairs: {', '.join(f'{p:+.1f}' for p in per_pair)})" if args.repeat > 1 else "")
          + (f"; waiting for it: {result['unbounded_slowdown_pct']:+.1f} %" if not args.no_unbounded else "")
          + f"; {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
