"""``python -m bench.behaviour``: the per-worker episodes and env steps of a fixed grid of federations, to show that
a refactor changed no behaviour (the same seeds give the same result before and after).

The grid is every task and strategy of ``make bench-quick`` (bench.paper.QUICK: CartPole-v0 and Acrobot-v1, its
seeds, its episode cap, 4 workers) plus ``make run``'s federation (CartPole-v0, weighted, seed 1), each in process
(deploy/inprocess.py). ``--out FILE`` writes ``{run: [[worker, episodes, steps], ...]}``; ``--compare A B`` says
which runs of two such files differ (exit 1 if any). Run it at two commits (``git worktree add``) and compare.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from bench.paper import QUICK
from chief import strategies

WORKERS = 4
MAKE_RUN = ("CartPole-v0", "weighted", 1, 2000)  # deploy.run_local's defaults


def grid() -> list[tuple[str, str, int, int]]:
    """(task, strategy, seed, episode cap) of every run."""
    return [MAKE_RUN] + [(task, policy, seed, QUICK["max_episodes"]) for task in QUICK["tasks"]
                         for policy in strategies.names() for seed in QUICK["seeds"]]


def per_worker(task: str, policy: str, seed: int, cap: int, runs_dir: Path) -> list[list[object]]:
    from deploy.inprocess import run_federation

    summary = run_federation(task, policy, seed, WORKERS, cap, runs_dir / f"{task}-{policy}-s{seed}", plot=False,
                             tensorboard_files=False, models=False)
    return [[w["id"], w["episodes"], w["steps"]] for w in summary["workers"]]


def compare(a: dict[str, list], b: dict[str, list]) -> list[str]:
    """The runs whose per-worker results differ, or that only one file has."""
    return sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.behaviour", description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, help="write the grid's per-worker results here (JSON)")
    parser.add_argument("--compare", nargs=2, type=Path, metavar=("A", "B"), help="compare two such files")
    args = parser.parse_args(argv)
    if args.compare:
        a, b = (json.loads(p.read_text()) for p in args.compare)
        differ = compare(a, b)
        print(f"{len(set(a) | set(b)) - len(differ)} runs identical per worker (episodes, env steps), "
              f"{len(differ)} differ" + (f": {', '.join(differ)}" if differ else ""))
        return 1 if differ else 0
    if args.out is None:
        parser.error("give --out FILE or --compare A B")
    results: dict[str, list] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for task, policy, seed, cap in grid():
            key = f"{task}-{policy}-s{seed}"
            results[key] = per_worker(task, policy, seed, cap, Path(tmp))
            print(f"{key}: " + ", ".join(f"{w} {e} ep / {s} steps" for w, e, s in results[key]), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1) + "\n")
    print(f"{len(results)} runs in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
