"""``python -m bench.unidentified``: which of a simulated rig's values, as its identified profile has them wrong, make a
lab's warm start fall on it.

For each rig of a lab that ``python -m bench.lab`` ran (its folder under ``--runs-dir``), the controller the lab
started its fine-tune from plays greedy episodes on the rig's identified profile, then on that profile with one group
of values (:data:`GROUPS`) set to the rig's truth (``truth-<family>.json``'s ``rig_params`` of the rig's seed), then
with all of them. A controller that holds the identified rig and falls once one group is the truth's falls for what
the pipeline does not know well enough about the rig: the identification's next target, or the pretrain's next range
to widen. Simulated rigs only: it needs their truth.

``python -m bench.unidentified --runs-dir runs/bench-lab --seed 532 --rigs 1,2 --episodes 10 --out FILE``
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

from bench.lab import family_profile, lab_name
from bench.output import write_report
from protocol.qube import MAX_RETURN
from protocol.tasks import worker_seed
from services.qube_sim.dynamics import QubeParams
from services.qube_sim.profile import NONIDEAL, PLANT, RigProfile

#: Group -> the profile fields it sets to the truth's (km and kt together as ``km``; the delays from the truth's
#: profile, which does not spread them per rig).
GROUPS: dict[str, tuple[str, ...]] = {
    "plant": ("mr", "Lr", "mp", "Lp", "Dr", "Dp", "km"),
    "arm friction": ("coulomb_arm", "static_arm", "deadzone_v"),
    "pendulum friction": ("coulomb_pendulum", "static_pendulum"),
    "cable": ("cable_stiffness", "cable_rest_rad"),
    "voltage offset": ("voltage_offset_v",),
    "delays": ("sensing_latency_ms", "action_delay_ms", "action_jitter_ms"),
}

def variant(identified: dict[str, Any], truth: QubeParams, truth_profile: RigProfile,
            fields: tuple[str, ...]) -> dict[str, Any]:
    """The identified profile ``identified`` (a profile's JSON) with ``fields`` set to the rig's truth ``truth`` (its
    plant; the delays from ``truth_profile``), as a plain profile (no identification record: it is not one)."""
    out = {k: v for k, v in identified.items() if k != "identified"}
    for name in fields:
        if name == "km":
            out["km"], out["kt"] = truth.km, truth.kt
        elif name in PLANT or name in NONIDEAL:
            out[name] = getattr(truth, {**PLANT, **NONIDEAL}[name])
        else:
            out[name] = getattr(truth_profile, name)
    return out


def returns_on(model: Path, profile: dict[str, Any], rig_model: Path, rig_seed: int, episodes: int) -> list[float]:
    """``model``'s greedy returns on the rig ``profile`` describes (its resets from ``rig_model``, as in the lab):
    worker.evaluate's episodes, the rig simulated with the rig's own seed."""
    import torch

    from worker.evaluate import evaluate

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "rig.json"
        path.write_text(json.dumps(profile))
        return evaluate(model, "qube-local", episodes=episodes, seed=rig_seed, rig_profile=str(path),
                        rig_model=str(rig_model)).returns


def start_model(folder: Path) -> Path:
    """The controller a lab's fine-tune started from (deploy.lab's choice, else its pretrain's first solver)."""
    from bench.lab import first_model
    from deploy.lab import chosen

    model = chosen(folder) or first_model(folder)
    if model is None:
        raise ValueError(f"{folder}: no pretrained controller (the lab did not get past its pretrain)")
    return model


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.unidentified", description=__doc__.split("\n\n")[0])
    p.add_argument("--runs-dir", type=Path, required=True, help="a bench.lab --runs-dir")
    p.add_argument("--seed", type=int, required=True, help="the lab's seed")
    p.add_argument("--family", default="combined")
    p.add_argument("--qube-actions", default="paper")
    p.add_argument("--rigs", default=None, help="comma-separated rig indices (default: every identified rig)")
    p.add_argument("--episodes", type=int, default=10)
    p.add_argument("--out", type=Path, default=None, help="results JSON (default: printed only)")
    args = p.parse_args(argv)
    folder = args.runs_dir / lab_name(args.family, args.qube_actions, args.seed)
    try:
        model = start_model(folder)
        truth_profile = family_profile(args.family)  # what bench.lab gave the simulators (truth-<family>.json)
    except ValueError as err:
        print(f"bench.unidentified: {err}", file=sys.stderr)
        return 1
    identified = sorted((folder / "identified").glob("rig*.json"))
    rigs = [int(r) for r in args.rigs.split(",")] if args.rigs else list(range(len(identified)))
    results: dict[str, dict[str, list[float]]] = {}
    for i in rigs:
        path = folder / "identified" / f"rig{i}.json"
        rig_seed = worker_seed(args.seed, i)
        truth = truth_profile.rig_params(rig_seed)
        data = json.loads(path.read_text())
        groups = {"identified": (), **GROUPS, "all": tuple(f for g in GROUPS.values() for f in g)}
        results[f"rig{i}"] = {}
        for name, fields in groups.items():
            returns = returns_on(model, variant(data, truth, truth_profile, fields), path, rig_seed, args.episodes)
            results[f"rig{i}"][name] = returns
            falls = sum(r < MAX_RETURN for r in returns)
            print(f"rig{i} {name:18s} fell {falls} of {len(returns)}", flush=True)
    if args.out is not None:
        write_report(args.out, "bench.unidentified", argv, {
            "lab": str(folder), "model": str(model), "episodes": args.episodes, "groups": GROUPS,
            "falls": {rig: {g: sum(r < MAX_RETURN for r in rs) for g, rs in by.items()} for rig, by in results.items()},
            "returns": results})
    return 0


if __name__ == "__main__":
    sys.exit(main())
