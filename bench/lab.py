"""``python -m bench.lab``: the lab pipeline (``python -m deploy.lab``) on simulated rigs outside ``lab``, seed by
seed, and what a lab pays for it.

Each seed is one lab: its rigs' true physics is a family of services/qube_sim/families.py (default the combined
family) spread per rig by the rig's seed, given to the simulators only (``FEDRL_RIG_PROFILE``); the pipeline identifies
the rigs, pretrains around them and fine-tunes them. Per seed it reports the last rig (the one that needed the most
rig time, identification included): its fine-tune episodes and balance steps, and its rig minutes (identification +
balance + swing-up resets); zero-shot, how many rigs balanced their first fine-tune episode to the end (2450) with
the pretrained controller before any update; and whether any worker stopped on its rig. Medians with quartiles over
the seeds, unfinished runs counted as worse than any finished one. Targets (the issue "Know each rig"): at most 15
episodes and 6 rig minutes per rig, identification included, no worker stopped on its rig, zero-shot on 9 of 10 rigs.
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

from bench.output import write_report
from bench.runs import read_records
from bench.stats import spread_censored
from protocol.qube import MAX_RETURN

OUT = Path("bench/results/lab.json")
TARGETS = {"episodes": 15, "rig_min": 6.0, "zero_shot_share": 0.9}


def seeds_of(text: str) -> list[int]:
    lo, _, hi = text.partition("-")
    return list(range(int(lo), int(hi or lo) + 1))


def truth_file(family: str, folder: Path) -> Path:
    """The family's profile as a file for the simulators (FEDRL_RIG_PROFILE)."""
    from services.qube_sim import families

    if family == "combined":
        profile = families.combined()
    elif family == "course":
        profile = families.course()
    elif family in ("lab", "ideal"):
        from services.qube_sim.profile import load_profile

        profile = load_profile(family)
    else:
        name, _, factor = family.rpartition("-x")
        profile = families.family(name, float(factor))
    path = folder / f"truth-{family}.json"
    folder.mkdir(parents=True, exist_ok=True)
    path.write_text(profile.to_json())
    return path


def run_seed(seed: int, family: str, args: argparse.Namespace, runs: Path) -> dict[str, Any]:
    """One lab: deploy.lab to its end (or as far as it gets), then what its records say."""
    folder = runs / f"{family}-{args.qube_actions}-s{seed}"
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("FEDRL_")},
           "FEDRL_RIG_PROFILE": str(truth_file(family, runs)), "PYTHONUNBUFFERED": "1"}
    command = [sys.executable, "-m", "deploy.lab", "--env", args.env, "--workers", str(args.workers), "--seed",
               str(seed), "--run-dir", str(folder), "--max-episodes", str(args.max_episodes), "--pretrain-episodes",
               str(args.pretrain_episodes), "--qube-actions", args.qube_actions]
    began = time.monotonic()
    with (runs / f"{folder.name}.log").open("w") as log:
        code = subprocess.run(command, env=env, stdout=log, stderr=subprocess.STDOUT, check=False).returncode
    wall = time.monotonic() - began
    print(f"seed {seed}: exit code {code}, {wall / 60:.1f} wall minutes ({folder})", flush=True)
    return {"seed": seed, "exit_code": code, "wall_s": round(wall, 1), **measure(folder)}


def measure(folder: Path) -> dict[str, Any]:
    """The last rig's numbers and the zero-shot count from a pipeline's folder."""
    progress = json.loads((folder / "lab.json").read_text()) if (folder / "lab.json").exists() else {}
    rows = progress.get("rigs", [])
    finetune = folder / "finetune"
    summary = json.loads((finetune / "summary.json").read_text()) if (finetune / "summary.json").exists() else None
    pretrain = folder / "pretrain" / "summary.json"
    pre = json.loads(pretrain.read_text()) if pretrain.exists() else None
    out: dict[str, Any] = {"stages_done": progress.get("done", []),
                           "pretrain_episodes": pre.get("episodes_to_all_solved") if pre else None}
    if summary is None or not rows:
        return {**out, "finished": False}
    first: dict[str, float] = {}
    for e in read_records(finetune)[1]:
        if e.worker not in first:
            first[e.worker] = e.return_
    workers = {w["id"]: w for w in summary["workers"]}
    per_rig = []
    for row in rows:
        w = workers.get(row["worker"], {})
        rig = w.get("rig") or {}
        minutes = (rig.get("rig_s", 0.0) + row["identify_s"]) / 60
        per_rig.append({"rig": row["rig"], "solved": bool(w.get("solved")), "episodes": w.get("episodes"),
                        "balance_steps": rig.get("balance_steps"), "identify_s": row["identify_s"],
                        "rig_min": round(minutes, 3), "stopped": w.get("state") in ("failed", "stopped"),
                        "zero_shot": first.get(row["worker"]) == MAX_RETURN})
    last = max(per_rig, key=lambda r: r["rig_min"])
    finished = all(r["solved"] for r in per_rig)
    return {**out, "finished": finished, "end_reason": summary.get("end_reason"), "rigs": per_rig,
            "last": {k: last[k] for k in ("rig", "episodes", "balance_steps", "rig_min")},
            "zero_shot": sum(r["zero_shot"] for r in per_rig), "stopped": sum(r["stopped"] for r in per_rig)}


def aggregate(results: list[dict[str, Any]]) -> dict[str, Any]:
    done = [r for r in results if r.get("finished")]

    def of(key: str) -> list[float | None]:
        return [r["last"][key] if r.get("finished") else None for r in results]

    rigs = [rig for r in results for rig in r.get("rigs", [])]
    zero = sum(rig["zero_shot"] for rig in rigs)
    table = {"seeds": len(results), "finished": len(done), "episodes": spread_censored(of("episodes")),
             "balance_steps": spread_censored(of("balance_steps")), "rig_min": spread_censored(of("rig_min")),
             "zero_shot": f"{zero} of {len(rigs)} rigs", "stopped_workers": sum(r.get("stopped", 0) for r in results)}
    median = table["episodes"]["median"]
    table["targets"] = {
        "episodes": median is not None and median <= TARGETS["episodes"],
        "rig_min": table["rig_min"]["median"] is not None and table["rig_min"]["median"] <= TARGETS["rig_min"],
        "zero_shot": bool(rigs) and zero / len(rigs) >= TARGETS["zero_shot_share"],
        "no_worker_stopped": table["stopped_workers"] == 0}
    return table


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.lab", description=__doc__.splitlines()[0])
    p.add_argument("--family", default="combined", help="the rigs' true family (services/qube_sim/families.py): "
                   "combined, course, lab, or <parameter>-x<factor> (default combined)")
    p.add_argument("--seeds", default="501-510", help="report seeds LO-HI (never used for tuning; default 501-510)")
    p.add_argument("--env", default="qube-local", choices=("qube-local", "qube"))
    p.add_argument("--workers", type=int, default=3)
    p.add_argument("--max-episodes", type=int, default=150)
    p.add_argument("--pretrain-episodes", type=int, default=600)
    p.add_argument("--qube-actions", default="paper")
    p.add_argument("--runs-dir", type=Path, default=Path("runs/bench-lab"))
    p.add_argument("--out", type=Path, default=OUT)
    args = p.parse_args(argv)
    runs = args.runs_dir
    runs.mkdir(parents=True, exist_ok=True)
    began = time.monotonic()
    load = os.getloadavg()[0]
    results = [run_seed(seed, args.family, args, runs) for seed in seeds_of(args.seeds)]
    table = aggregate(results)
    write_report(args.out, "bench.lab", argv, {
        "family": args.family, "env": args.env, "workers": args.workers, "qube_actions": args.qube_actions,
        "seeds": args.seeds, "load_at_start": round(load, 2), "wall_s": round(time.monotonic() - began, 1),
        "targets": TARGETS, "table": table, "results": results})
    print(json.dumps(table, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
