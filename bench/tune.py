"""``python -m bench.tune TASK STRATEGY --algo sac --seeds 1 2 --set KEY=VALUE ...``: tuning runs of a learner's preset.

Each run is an in-process federation (deploy.inprocess, as bench.paper runs them) whose workers take the task's preset
for the learner with the ``--set`` overrides (KEY one of the learner's configuration fields, as ``python -m
worker.train_local --set``). Only tuning seeds are allowed (bench.paper.TUNING_SEEDS): the report seeds stay unseen.
Each run appends one line to ``--out`` (default bench/results/tuning.jsonl): the task, strategy, learner, overrides,
seed, the last worker's episodes and env steps (null when unfinished within ``--max-episodes``), every worker's
episodes and whether it solved, and the wall seconds with the machine's load average when the run ended.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from bench import output
from bench.paper import TUNING_SEEDS
from chief import strategies
from protocol import learners, qube


def tuned(task: str, algo: str, overrides: dict[str, Any]) -> Any:
    """Replace the task's preset for ``algo`` by itself with ``overrides`` (in this process: the in-process workers
    read it); returns the configuration."""
    from worker import envs

    spec = envs.env_spec(task)
    config = spec.learner_config(algo, **overrides)
    if algo == learners.DEFAULT:
        envs.ENVS[task] = replace(spec, config=config)
    else:
        envs.ENVS[task] = replace(spec, presets={**spec.presets, algo: config})
    return config


def run(task: str, strategy: str, algo: str, seed: int, workers: int, max_episodes: int,
        overrides: dict[str, Any], qube_actions: str = qube.DEFAULT_ACTIONS) -> dict[str, Any]:
    """One tuning federation; its line of the log (``qube_actions``: the QUBE tasks' action set, named in the line
    when it is not the paper's)."""
    from deploy.inprocess import run_federation
    from deploy.settings import InprocessSettings

    if seed not in TUNING_SEEDS:
        raise ValueError(f"seed {seed} is not a tuning seed ({TUNING_SEEDS[0]}-{TUNING_SEEDS[-1]})")
    tuned(task, algo, overrides)
    run_dir = Path(tempfile.mkdtemp(prefix="tune-"))
    t0 = time.monotonic()
    try:
        summary = run_federation(InprocessSettings.given(env=task, policy=strategy, seed=seed, workers=workers,
                                 max_episodes=max_episodes, run_dir=run_dir / "run", algo=algo,
                                 qube_actions=qube_actions), plot=False,
                                 tensorboard_files=False, models=False)
    finally:
        shutil.rmtree(run_dir, ignore_errors=True)
    actions = {} if qube_actions == qube.DEFAULT_ACTIONS else {"qube_actions": qube_actions}
    return {"task": task, "strategy": strategy, "algo": algo, **actions, "set": overrides, "seed": seed,
            "workers": workers, "max_episodes": max_episodes, "last_worker_episodes": summary.episodes_to_all_solved,
            "last_worker_steps": summary.steps_of_last_worker,
            "per_worker": [[w.id, w.episodes, w.solved] for w in summary.workers],
            "wall_s": round(time.monotonic() - t0, 1), "load_average": [round(x, 2) for x in os.getloadavg()]}


def main(argv: list[str] | None = None) -> int:
    from worker.settings import parse_overrides

    parser = argparse.ArgumentParser(prog="python -m bench.tune", description=__doc__.splitlines()[0])
    parser.add_argument("task")
    parser.add_argument("strategy", choices=strategies.names())
    parser.add_argument("--algo", choices=learners.names(), default=learners.DEFAULT)
    parser.add_argument("--seeds", nargs="+", type=int, default=[1], help="tuning seeds only (1-12)")
    parser.add_argument("--workers", type=int, default=4)
    parser.add_argument("--max-episodes", type=int, default=60)
    parser.add_argument("--qube-actions", choices=list(qube.ACTION_SETS), default=qube.DEFAULT_ACTIONS,
                        help="the QUBE tasks' action set (docs/explanation/qube-actions.md)")
    parser.add_argument("--set", dest="overrides", nargs="*", default=[], metavar="KEY=VALUE")
    parser.add_argument("--out", type=Path, default=Path("bench/results/tuning.jsonl"))
    args = parser.parse_args(argv)
    overrides = parse_overrides(args.overrides, args.algo)
    if bad := [s for s in args.seeds if s not in TUNING_SEEDS]:
        parser.error(f"not tuning seeds: {bad} (the report seeds stay unseen)")
    for seed in args.seeds:
        line = run(args.task, args.strategy, args.algo, seed, args.workers, args.max_episodes, overrides,
                   args.qube_actions)
        output.append_line(args.out, line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
