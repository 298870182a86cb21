"""bench.behaviour's whole grid (PPO's QUICK grid, make run's, and the off-policy runs) on the code of d3ad5ef, whose
own bench.behaviour has no off-policy runs and no final PI: the same runs, in today's format. Run from a worktree of
d3ad5ef: ``PYTHONPATH=<worktree> python bench/results/behaviour-d3ad5ef.make.py OUT.json``."""

import json
import sys
import tempfile
from pathlib import Path

from bench.paper import QUICK
from chief import strategies
from deploy.inprocess import run_federation

WORKERS = 4
runs = [("ppo", "CartPole-v0", "weighted", 1, 2000)]
runs += [("ppo", t, p, s, QUICK["max_episodes"]) for t in QUICK["tasks"] for p in strategies.names()
         for s in QUICK["seeds"]]
for algo, task, cap in (("sac", "Pendulum-v1", 6), ("sac", "MountainCarContinuous-v0", 2), ("dqn", "CartPole-v0", 12),
                        ("dqn", "Acrobot-v1", 3)):
    runs += [(algo, task, p, 101, cap) for p in ("sync", "independent")]
out = {}
with tempfile.TemporaryDirectory() as tmp:
    for algo, task, policy, seed, cap in runs:
        name = ("" if algo == "ppo" else f"{algo}-") + f"{task}-{policy}-s{seed}"
        summary = run_federation(task, policy, seed, WORKERS, cap, Path(tmp) / name, plot=False,
                                 tensorboard_files=False, models=False, algo=algo)
        out[name] = [[w["id"], w["episodes"], w["steps"], w.get("final_pi")] for w in summary["workers"]]
        print(name, out[name], flush=True)
Path(sys.argv[1]).write_text(json.dumps(out, indent=1) + "\n")
print(len(out), "runs")
