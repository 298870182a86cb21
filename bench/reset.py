"""``python -m bench.reset``: success of the bridge's swing-up reset over pendulum damping x rig spread x friction.

Each condition runs 50 resets (services/qube_sim/trials.py): the bridge's control core (start-up checks, safety
checks, swing-up and hold) drives a simulated rig from 50 varied starts (arm within +-60 deg, pendulum up to 90 deg
from hanging, both moving); rig ``i`` of a spread condition has its parameters drawn uniformly within the spread.
Reported per condition: resets that reached ready, the largest arm angle any trial reached, trials past 110 deg,
end-stop hits, faults, mean and p90 time to ready. Writes ``bench/results/reset.json``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

from bench.output import write_report
from services.qube_sim.trials import Condition, run_condition, summary

RESULTS = Path("bench/results")
COULOMB = (1.5e-3, 1e-4)  # N m: arm (about 0.3 V of motor voltage), pendulum


def conditions(dampings: list[float], spreads: list[float], friction: bool) -> list[Condition]:
    frictions = [(0.0, 0.0), COULOMB] if friction else [(0.0, 0.0)]
    return [Condition(f"damping x{d:g}, spread +-{s:.0%}, " + ("Coulomb" if c != (0.0, 0.0) else "no Coulomb"),
                      damping=d, spread=s, coulomb=c)
            for c, s, d in itertools.product(frictions, spreads, dampings)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.reset", description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=50, help="resets per condition (default 50)")
    parser.add_argument("--damping", type=float, nargs="+", default=[1.0, 2.0, 5.0, 10.0],
                        help="pendulum damping factors (default 1 2 5 10)")
    parser.add_argument("--spread", type=float, nargs="+", default=[0.0, 0.15],
                        help="rig spreads, fractions (default 0 0.15)")
    parser.add_argument("--no-friction", action="store_true", help="skip the Coulomb friction conditions")
    parser.add_argument("--out", type=Path, default=RESULTS / "reset.json")
    args = parser.parse_args(argv)
    if args.trials < 1 or any(d <= 0 for d in args.damping) or any(not 0 <= s < 1 for s in args.spread):
        parser.error("--trials must be >= 1, damping factors > 0 and spreads in [0, 1)")
    rows = []
    for condition in conditions(args.damping, args.spread, not args.no_friction):
        t0 = time.monotonic()
        results = run_condition(condition, args.trials)
        row = {"condition": condition.name, "damping": condition.damping, "spread": condition.spread,
               "coulomb_nm": list(condition.coulomb), **summary(results),
               "failures": [f"start {i}: {r.outcome}" for i, r in enumerate(results) if not r.ready],
               "cpu_s": round(time.monotonic() - t0, 1)}
        print(json.dumps(row), flush=True)
        rows.append(row)
    write_report(args.out, "bench.reset", argv,
                 {"trials_per_condition": args.trials, "coulomb_nm": list(COULOMB), "results": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
