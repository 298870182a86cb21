"""``python -m bench.reset``: the bridge's self-test and swing-up reset on every rig family outside ``lab``.

For each family of services/qube_sim/families.py (each setting of the one-parameter sweep, the combined family,
Quanser's course-file damping) and each model given to the bridge (``nominal``: rpi_bridge.plant.PlantModel();
``true``: the family's own profile, RigProfile.plant_model(), standing in for an identified rig), ``--resets`` resets
(services/qube_sim/trials.py): rig ``i`` of the family (its parameters spread from rig seed ``--rig-seed`` + i)
starts up (calibration and self-test) and is reset from varied start ``--start`` + i (arm within +-60 deg, pendulum
up to 90 deg from hanging, both moving) as the worker resets it: up to 5 requests, 3 s of settling between them, the
bridge choosing a different strategy for each (rpi_bridge/reset.py STRATEGIES). The defaults (rig seeds 10000+,
starts 100+) were never used for tuning (that used rig seeds 0-7 and starts 0-7).

Reported per family and model: rigs whose self-test passed, resets that reached ready (and on the first request),
median and p90 seconds to ready (failed requests and settling included), the largest arm angle, trials past 110 deg,
end-stop hits. Writes ``bench/results/reset.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from bench.output import write_report
from rpi_bridge.control import ControlConfig, with_model
from rpi_bridge.reset import STRATEGIES, ResetConfig, strategy
from services.qube_sim import families
from services.qube_sim.profile import RigProfile
from services.qube_sim.trials import PERIOD_S, run_trial, summary, varied_start
from worker.qube_env import RESET_ATTEMPTS

RESULTS = Path("bench/results")
MODELS = ("nominal", "true")
#: How long one request is watched: the longest strategy's timeout, its winding down and a second (34 s).
WINDOW_S = max(strategy(ResetConfig(), n)[1].timeout_s for n in range(len(STRATEGIES))) + ResetConfig().wind_down_s + 1


def all_families() -> list[tuple[str, str, RigProfile]]:
    """(group, name, profile) of every family: the sweep's settings, combined, course."""
    rows = [("sweep", profile.name, profile) for _, _, profile in families.sweep()]
    return [*rows, ("combined", families.combined().name, families.combined()),
            ("course", families.course().name, families.course())]


def run_family(profile: RigProfile, model: str, resets: int, rig_seed: int, start: int) -> list:
    config = ControlConfig(period_s=PERIOD_S)
    if model == "true":
        config = with_model(config, profile.plant_model())
    return [run_trial(profile.rig_params(rig_seed + i), varied_start(start + i), config, max_seconds=WINDOW_S,
                      device_options=profile.device_options(), attempts=RESET_ATTEMPTS) for i in range(resets)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.reset", description=__doc__.splitlines()[0])
    parser.add_argument("--resets", type=int, default=50, help="resets per family and model (default 50)")
    parser.add_argument("--rig-seed", type=int, default=10_000, help="rig i's seed is this + i (default 10000)")
    parser.add_argument("--start", type=int, default=100, help="reset i starts from start this + i (default 100)")
    parser.add_argument("--models", nargs="+", choices=MODELS, default=list(MODELS))
    parser.add_argument("--only", nargs="+", default=None, help="family names to run (default all)")
    parser.add_argument("--out", type=Path, default=RESULTS / "reset.json")
    args = parser.parse_args(argv)
    if args.resets < 1:
        parser.error("--resets must be >= 1")
    rows = []
    for group, name, profile in all_families():
        if args.only and name not in args.only:
            continue
        for model in args.models:
            t0 = time.process_time()
            results = run_family(profile, model, args.resets, args.rig_seed, args.start)
            s = summary(results)
            row = {"group": group, "family": name, "model": model, **s,
                   "self_test_passed": sum(not r.outcome.startswith("start-up") for r in results),
                   "failures": [f"rig {args.rig_seed + i} start {args.start + i}: {r.outcome}"
                                for i, r in enumerate(results) if not r.ready],
                   "cpu_s": round(time.process_time() - t0, 1)}
            print(json.dumps({k: v for k, v in row.items() if k != "failures"}), flush=True)
            rows.append(row)
    totals = {}
    for group in ("sweep", "combined", "course"):
        for model in args.models:
            picked = [r for r in rows if r["group"] == group and r["model"] == model]
            if picked:
                trials = sum(r["trials"] for r in picked)
                totals[f"{group}/{model}"] = {
                    "trials": trials, "ready": sum(r["ready"] for r in picked),
                    "success": round(sum(r["ready"] for r in picked) / trials, 4),
                    "self_test_passed": sum(r["self_test_passed"] for r in picked)}
    print(json.dumps(totals), flush=True)
    write_report(args.out, "bench.reset", argv,
                 {"resets_per_family": args.resets, "rig_seeds_from": args.rig_seed, "starts_from": args.start,
                  "attempts": RESET_ATTEMPTS, "totals": totals, "results": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
