"""``python -m bench.behaviour``: the per-worker episodes, env steps and final performance index of a fixed grid of
federations, to show that a refactor changed no behaviour (the same seeds give the same result before and after).

The grid is every task and strategy of ``make bench-quick`` (bench.paper.QUICK: PPO on CartPole-v0 and Acrobot-v1,
its seeds, its episode cap, 4 workers), ``make run``'s federation (CartPole-v0, weighted, seed 1), and the off-policy
learners, short (OFF_POLICY: SAC on Pendulum-v1 and MountainCarContinuous-v0, DQN on CartPole-v0 and Acrobot-v1, under
``sync`` and ``independent``, one seed, a few episodes: the final PI is what shows that their learning is the same),
each in process (deploy/inprocess.py). ``--out FILE`` writes ``{run: [[worker, episodes, steps, final PI], ...]}``
(``--only PATTERN ...``: the runs whose name matches one of the shell patterns); ``--compare A B`` says which runs of
two such files differ (exit 1 if any). Run it at two commits (``git worktree add``) and compare.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import sys
import tempfile
from pathlib import Path
from typing import NamedTuple

from bench.paper import QUICK
from chief import strategies

WORKERS = 4


class Run(NamedTuple):
    task: str
    strategy: str
    seed: int
    cap: int  # the episode cap M
    algo: str = "ppo"

    @property
    def name(self) -> str:
        return ("" if self.algo == "ppo" else f"{self.algo}-") + f"{self.task}-{self.strategy}-s{self.seed}"


MAKE_RUN = Run("CartPole-v0", "weighted", 1, 2000)  # deploy.run_local's defaults
#: (learner, task, episode cap) of the off-policy runs, each under OFF_POLICY_STRATEGIES with seed 101.
OFF_POLICY = (("sac", "Pendulum-v1", 6), ("sac", "MountainCarContinuous-v0", 2), ("dqn", "CartPole-v0", 12),
              ("dqn", "Acrobot-v1", 3))
OFF_POLICY_STRATEGIES = ("sync", "independent")


def grid() -> list[Run]:
    """Every run: make run's, make bench-quick's, then the off-policy learners'."""
    return ([MAKE_RUN] + [Run(task, policy, seed, QUICK["max_episodes"]) for task in QUICK["tasks"]
                          for policy in strategies.names() for seed in QUICK["seeds"]]
            + [Run(task, policy, 101, cap, algo) for algo, task, cap in OFF_POLICY for policy in OFF_POLICY_STRATEGIES])


def per_worker(run: Run, runs_dir: Path) -> list[list[object]]:
    from deploy.inprocess import run_federation
    from deploy.settings import InprocessSettings

    summary = run_federation(InprocessSettings.given(env=run.task, policy=run.strategy, seed=run.seed, workers=WORKERS,
                             max_episodes=run.cap, run_dir=runs_dir / run.name, algo=run.algo), plot=False,
                             tensorboard_files=False, models=False)
    return [[w.id, w.episodes, w.steps, w.final_pi] for w in summary.workers]


def compare(a: dict[str, list], b: dict[str, list]) -> list[str]:
    """The runs whose per-worker results differ, or that only one file has."""
    return sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.behaviour", description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, help="write the grid's per-worker results here (JSON)")
    parser.add_argument("--only", nargs="+", metavar="PATTERN", help="only the runs whose name matches one of these")
    parser.add_argument("--compare", nargs=2, type=Path, metavar=("A", "B"), help="compare two such files")
    args = parser.parse_args(argv)
    if args.compare:
        a, b = (json.loads(p.read_text()) for p in args.compare)
        differ = compare(a, b)
        print(f"{len(set(a) | set(b)) - len(differ)} runs identical per worker (episodes, env steps, final PI), "
              f"{len(differ)} differ" + (f": {', '.join(differ)}" if differ else ""))
        return 1 if differ else 0
    if args.out is None:
        parser.error("give --out FILE or --compare A B")
    runs = [r for r in grid() if not args.only or any(fnmatch.fnmatchcase(r.name, p) for p in args.only)]
    results: dict[str, list] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for run in runs:
            results[run.name] = per_worker(run, Path(tmp))
            print(f"{run.name}: " + ", ".join(f"{w} {e} ep / {s} steps / PI {pi}" for w, e, s, pi in results[run.name]),
                  flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1) + "\n")
    print(f"{len(results)} runs in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
