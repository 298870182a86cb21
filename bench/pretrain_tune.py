"""``python -m bench.pretrain_tune SEED --attempt N --set KEY=VALUE ...``: one tuning run of ``deploy.lab``'s
pretrain (stage 2) on a lab of tuning seed SEED, and its learning curve.

The lab's three rigs are of the combined family (services/qube_sim/families.py), identified as ``deploy.lab``'s
stage 1 does (``python -m services.qube_sim --identify``, kept in ``--runs-dir``/s<SEED>/identified); the pretrain is
the in-process federation of stage 2 (3 workers, ``plain``, randomised around the identified rigs), its learners with
deploy.lab's pretrain overrides (``PRETRAIN_SET``) and then the ``--set`` ones (as ``deploy.lab --pretrain-set``,
which replaces them: here ``--set entropy_coef=0.01`` restores the preset's value); ``--attempt N`` runs
the pretrain of the lab's attempt N (its seed as ``deploy.lab`` gives it). Only tuning seeds are allowed: this tool's
701-709 and the labs bench.lab was tuned on (521-540); bench.lab's report seeds (501-510) and bench.ood's (601-610) stay
unseen.

Each run appends one line to ``--out``: the seed, action set, overrides, every worker's episodes and whether it met TC,
and its learning curve (PI, the first episode of a full return, and the policy's entropy at fixed episodes), which
says how far a run got when it was stopped before the end. ``--summarise RUN_DIR`` writes the line of a run folder
made before (an interrupted run included) without running anything.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from bench import output
from protocol.qube import DEFAULT_ACTIONS, MAX_RETURN
from protocol.tasks import worker_seed
from runtime.records import METRICS, SUMMARY, RunSummary
from services.qube_sim.pretrain import EASE_IN

#: The seeds this tool may tune on (never a report seed): its own, and bench.lab's tuning labs.
TUNING_SEEDS = (*range(701, 710), *range(521, 541))
#: Episodes at which the learning curve is read.
CHECKPOINTS = (25, 50, 100, 150, 200, 300, 400, 500, 600)
OUT = Path("bench/results/pretrain-tuning.jsonl")
RIGS = 3


def identified(seed: int, runs: Path) -> Path:
    """The folder of the lab's identified rigs, identifying those not there yet (deploy.lab's stage 1)."""
    from bench.lab import truth_file

    folder = runs / f"s{seed}" / "identified"
    folder.mkdir(parents=True, exist_ok=True)
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("FEDRL_")},
           "FEDRL_RIG_PROFILE": str(truth_file("combined", runs))}
    for i in range(RIGS):
        path = folder / f"rig{i}.json"
        if not path.exists():
            subprocess.run([sys.executable, "-m", "services.qube_sim", "--rig-id", f"rig{i}", "--seed",
                            str(worker_seed(seed, i)), "--identify", str(path)], env=env, check=True,
                           stdout=subprocess.DEVNULL)
    return folder


def curve(run_dir: Path) -> dict[str, Any]:
    """Per worker: episodes played, the last PI, the first episode of a full return, PI and entropy at CHECKPOINTS.
    Read as JSON lines, not typed records: a tuning run stopped at any moment may leave records of any shape."""
    episodes: dict[str, list[dict[str, Any]]] = {}
    for line in (run_dir / METRICS).read_text().splitlines():
        record = json.loads(line)
        if record.get("type") == "episode":
            episodes.setdefault(record["worker"], []).append(record)
    out = {}
    for worker, rows in sorted(episodes.items()):
        out[worker] = {
            "episodes": len(rows), "last_pi": round(rows[-1]["pi"], 1),
            "first_full_return": next((r["episode"] for r in rows if r["return"] >= MAX_RETURN), None),
            "pi": {k: round(rows[k - 1]["pi"], 1) for k in CHECKPOINTS if k <= len(rows)},
            "entropy": {k: round(rows[k - 1]["stats"]["entropy"], 3) for k in CHECKPOINTS
                        if k <= len(rows) and rows[k - 1].get("stats")}}
    return out


def run(seed: int, actions: str, overrides: dict[str, Any], max_episodes: int, runs: Path, attempt: int = 1,
        ease_in: int = EASE_IN) -> Path:
    """The pretrain (attempt ``attempt``) of ``deploy.lab`` on the lab of ``seed``, with the PPO preset's
    ``overrides``; its run folder."""
    from deploy.inprocess import run_federation
    from deploy.lab import attempt_seed
    from deploy.settings import InprocessSettings
    from services.qube_sim.pretrain import for_lab
    from services.qube_sim.profile import DRAWN_MODEL, load_profile

    folder = identified(seed, runs)
    profile = folder.parent / f"pretrain-profile-ease{ease_in}.json"
    profile.write_text(for_lab([load_profile(folder / f"rig{i}.json") for i in range(RIGS)], actions,
                               name=f"around-{RIGS}-identified", ease_in=ease_in).to_json())
    run_dir = runs / (f"s{seed}-{actions}" + f"-attempt{attempt}" * (attempt > 1)
                      + f"-ease{ease_in}" * (ease_in != EASE_IN) + "".join(f"-{k}={v}" for k, v in overrides.items()))
    run_federation(InprocessSettings.given(env="qube-local", policy="plain", workers=RIGS,
                                           seed=attempt_seed(seed, attempt), max_episodes=max_episodes,
                                           run_dir=run_dir, rig_profile=str(profile), rig_model=DRAWN_MODEL,
                                           qube_actions=actions,
                                           learner_set=[f"{k}={v!r}" for k, v in overrides.items()]),
                   plot=False, tensorboard_files=False, models=False, tolerate_failures=True)
    return run_dir


def line_of(run_dir: Path, seed: int, actions: str, overrides: dict[str, Any], wall_s: float | None,
            attempt: int = 1, ease_in: int = EASE_IN) -> dict[str, Any]:
    summary = RunSummary.read(run_dir) if (run_dir / SUMMARY).exists() else None
    return {"seed": seed, "attempt": attempt, "ease_in": ease_in, "qube_actions": actions, "set": overrides,
            "finished": summary is not None,
            "end_reason": summary.end_reason if summary else "stopped before its end",
            "last_worker_episodes": summary.episodes_to_all_solved if summary else None,
            "solved": [w.id for w in summary.workers if w.solved] if summary else None,
            "curve": curve(run_dir), "wall_s": wall_s, "load_average": [round(x, 2) for x in os.getloadavg()]}


def main(argv: list[str] | None = None) -> int:
    from deploy.lab import PRETRAIN_SET
    from worker.settings import parse_overrides

    p = argparse.ArgumentParser(prog="python -m bench.pretrain_tune", description=__doc__.splitlines()[0])
    p.add_argument("seed", type=int, help="a tuning seed: 701-709, or a tuning lab of bench.lab, 521-540")
    p.add_argument("--attempt", type=int, default=1, help="the lab's pretrain attempt N (deploy.lab's seed of it)")
    p.add_argument("--qube-actions", default=DEFAULT_ACTIONS)
    p.add_argument("--ease-in", type=int, default=EASE_IN, metavar="N",
                   help=f"ease the arm's dry friction in over each worker's first N episodes (default {EASE_IN}, "
                   "deploy.lab's; 0: the whole range from the first)")
    p.add_argument("--set", dest="overrides", nargs="*", default=[], metavar="KEY=VALUE")
    p.add_argument("--max-episodes", type=int, default=600)
    p.add_argument("--runs-dir", type=Path, default=Path("runs/pretrain-tune"))
    p.add_argument("--out", type=Path, default=OUT)
    p.add_argument("--summarise", type=Path, metavar="RUN_DIR", help="run nothing: the line of this run folder")
    args = p.parse_args(argv)
    if args.seed not in TUNING_SEEDS:
        p.error(f"{args.seed} is not a tuning seed (701-709, 521-540): report seeds stay unseen")
    if args.attempt < 1:
        p.error("--attempt counts from 1")
    overrides = parse_overrides((*PRETRAIN_SET, *args.overrides))
    began = time.monotonic()
    run_dir = args.summarise or run(args.seed, args.qube_actions, overrides, args.max_episodes, args.runs_dir,
                                    args.attempt, args.ease_in)
    wall = None if args.summarise else round(time.monotonic() - began, 1)
    line = line_of(run_dir, args.seed, args.qube_actions, overrides, wall, args.attempt, args.ease_in)
    output.append_line(args.out, line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
