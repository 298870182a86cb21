"""``python -m bench.staleness``: idle seconds per rig when one rig resets slower, without and with bounded staleness.

Three simulated QUBE-Servo 2 rigs (``qube-local``) learn under one strategy (default ``plain``) in process
(deploy/inprocess.py), once per staleness S (default 0 and 1: ChiefSettings.max_staleness). One rig (default the
last, ``w2``) has a swing-up reset ``--slow-factor`` times (default 3) as long as its simulated swing-up took: the
rig's reported reset seconds are scaled (its physics are the others'), which is what a slower reset costs the
federation's rounds. On the simulated clock a rig's idle seconds are modelled from the records
(protocol.rigtime.IdleModel, with the run's S): under S = 0 every rig waits for each round's slowest rig, under S it
waits only for the answer to its round S back. Every run is audited. Writes ``bench/results/staleness.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from chief.audit import audit
from deploy.inprocess import run_federation
from deploy.settings import InprocessSettings
from protocol.tasks import worker_seed
from worker.envs import ENVS, register_env
from worker.qube_env import QubeLocalEnv

RESULTS = Path("bench/results")
ENV = "qube-local"


class SlowResetQube(QubeLocalEnv):
    """A simulated rig whose every reset is reported ``factor`` times as long as its swing-up took."""

    factor = 3.0

    def _started(self, reset_s: float) -> None:
        super()._started(reset_s * self.factor)


@contextmanager
def slow_rig(seed: int, index: int, factor: float) -> Iterator[None]:
    """While inside: worker ``index`` of a run of base seed ``seed`` drives a SlowResetQube (through the env
    registry's factory for qube-local, put back afterwards)."""
    spec = ENVS[ENV]
    assert spec.factory is not None
    base = spec.factory
    slow_seed = worker_seed(seed, index)

    def factory(spec_: Any, seed_: int, noise: Any, **extra: Any) -> Any:
        env = base(spec_, seed_, noise, **extra)
        if seed_ == slow_seed and isinstance(env, QubeLocalEnv):
            env.__class__ = SlowResetQube
            env.factor = factor  # type: ignore[attr-defined]
        return env

    register_env(dataclasses.replace(spec, factory=factory), overwrite=True)
    try:
        yield
    finally:
        register_env(spec, overwrite=True)


def run_one(staleness: int, args: argparse.Namespace, runs: Path) -> dict[str, Any]:
    """One federation with staleness S; its rigs' times and the audit's verdict."""
    run_dir = runs / f"s{staleness}"
    began = time.monotonic()
    with slow_rig(args.seed, args.slow_rig, args.slow_factor):
        summary = run_federation(InprocessSettings.given(env=ENV, policy=args.policy, seed=args.seed, workers=3,
                                 max_episodes=args.episodes, run_dir=run_dir, max_staleness=staleness), plot=False,
                                 tensorboard_files=False, models=False)
    report = audit(run_dir)
    rigs = {w.id: {k: getattr(w.rig, k) for k in ("idle_s", "reset_s", "balance_s", "rig_s")} | {
        "episodes": w.episodes, "solved": w.solved} for w in summary.workers}
    return {"max_staleness": staleness, "rigs": rigs, "idle_s_total": round(sum(r["idle_s"] for r in rigs.values()), 3),
            "rounds": summary.rounds, "end_reason": summary.end_reason, "audit": str(report),
            "wall_s": round(time.monotonic() - began, 1), "run_dir": str(run_dir)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.staleness", description=__doc__.splitlines()[0])
    parser.add_argument("--staleness", type=int, nargs="+", default=[0, 1], help="values of S (default 0 1)")
    parser.add_argument("--episodes", type=int, default=30, help="M, the episode cap of each run (default 30)")
    parser.add_argument("--policy", default="plain")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--slow-rig", type=int, default=2, help="index of the slow rig (default 2: w2)")
    parser.add_argument("--slow-factor", type=float, default=3.0, help="its resets take this many times as long")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    runs = args.out / "runs" / "staleness"
    result = {"bench": "staleness", "env": ENV, "policy": args.policy, "seed": args.seed, "episodes": args.episodes,
              "slow_rig": f"w{args.slow_rig}", "slow_factor": args.slow_factor, "machine": platform.machine(),
              "runs": [run_one(s, args, runs) for s in args.staleness]}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "staleness.json").write_text(json.dumps(result, indent=1) + "\n")
    for run in result["runs"]:
        idle = ", ".join(f"{w} {r['idle_s']:.1f} s" for w, r in run["rigs"].items())
        print(f"S={run['max_staleness']}: idle {idle} (total {run['idle_s_total']:.1f} s); {run['rounds']} rounds; "
              f"{run['audit']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
