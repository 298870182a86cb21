"""``python -m bench.swingup``: can any swing-up within the bridge's limits bring a heavily damped pendulum to the top?

A feasibility study on services/qube_sim's own equations of motion (``derivatives_array`` and ``motor_torque_array``
of services/qube_sim/dynamics.py, the code the simulated rigs run, with the encoder cable's torque), for each
pendulum damping of a sweep from ``lab``'s Dp up to ``--dp-factors``' largest, and for Quanser's course-file damping
(``course``: Dr 1.5e-3, Dp 5e-4). Each rig is the family's nominal rig (services/qube_sim/families.py, no spread),
hanging at rest with the arm in the middle; the motor voltage is held for each 7 ms tick, at most the bridge's cap
(rpi_bridge.frame.MAX_COMMAND, 9.99 V), and the arm must stay within ``--arm-limits`` degrees (the bridge's reset
keeps to its soft limit, 80 deg; the bridge faults past 110 deg). Over ``--horizon`` seconds, two searches maximise
the height the pendulum reaches (min |alpha|, 0 is upright):

1. **a pump family** searched by ``scipy.optimize.differential_evolution``: bang-bang energy pumping (full voltage
   along alpha_dot*cos(alpha), Astrom & Furuta 2000), a linear pull towards the middle, and full-voltage braking
   whenever the arm could not stop inside a soft limit at a given deceleration; the three parameters (braking
   deceleration, centring weight, soft limit) are searched, all the states of a generation integrated at once;
2. **open-loop voltages** polished by ``scipy.optimize.minimize`` (L-BFGS-B, central-difference gradients in one
   batch): the best pump's tick voltages plus a piecewise-constant correction per ``--segment-ticks`` ticks (clipped
   to the cap), maximising a soft maximum of cos(alpha) with a penalty on arm travel past the limit.

Each best sequence is replayed tick by tick through ``QubeDynamics.step`` (the scalar simulator) to confirm it. The
JSON gives, per setting and arm limit: the pendulum's damping ratio (Jp about the pivot, mp Lp^2/3), the best height
reached (degrees from upright), the best pendulum energy reached as a fraction of the swing depth (-1 hanging at rest,
0 upright at rest: the energy needed), the arm's largest angle, and whether the top was reached (within 1 deg) and
reached inside the reset's catch region (|alpha| < 21 deg with |theta| < 57 deg).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import differential_evolution, minimize

from bench.output import write_report
from protocol.qube import PERIOD_S
from rpi_bridge.frame import MAX_COMMAND, VOLTS_PER_COUNT
from rpi_bridge.reset import ResetConfig
from services.qube_sim import families
from services.qube_sim.dynamics import QubeDynamics, QubeParams, derivatives_array, motor_torque_array

OUT = Path("bench/results/swingup.json")
#: The reset's measurements at heavy damping (``--reset-markdown``): bench.reset's and bench.sim2real ood's files.
RESET_HEAVY = Path("bench/results/reset-heavy.json")
OOD_SWINGUP = Path("bench/results/ood-swingup.json")
DP_FACTORS = (1.0, 2.5, 5.0, 7.5, 10.0, 15.0, 20.0, 30.0)
ARM_LIMITS_DEG = (80.0, 110.0)
VMAX = MAX_COMMAND * VOLTS_PER_COUNT
SUBSTEPS = 7  # 1 ms RK4 steps per 7 ms tick, as QubeDynamics.step
CATCH = ResetConfig()
TOP_DEG = 1.0


def settings(dp_factors: tuple[float, ...]) -> list[tuple[str, QubeParams]]:
    """(name, nominal plant) of ``course`` and of each Dp factor on ``lab``."""
    return [("course", families.course().params()),
            *[(f"Dp-x{k:g}", families.family("Dp", k).params()) for k in dp_factors]]


def damping_ratio(p: QubeParams) -> float:
    """Dp / (2 J w0) of the hanging pendulum, J = mp Lp^2/3 about its pivot, w0 = sqrt(mp g Lp/2 / J)."""
    j = p.mp * p.Lp**2 / 3.0
    return p.Dp / (2.0 * j * math.sqrt(p.mp * p.g * p.Lp / 2.0 / j))


def _rates(p: QubeParams, x: tuple[np.ndarray, ...], volts: np.ndarray) -> tuple[np.ndarray, ...]:
    theta, alpha, theta_dot, alpha_dot = x
    tau = motor_torque_array(p, volts, theta_dot) - p.cable_stiffness * (theta - p.cable_rest)
    theta_ddot, alpha_ddot = derivatives_array(p, theta_dot, alpha, alpha_dot, tau)
    return theta_dot, alpha_dot, theta_ddot, alpha_ddot


def tick(p: QubeParams, x: tuple[np.ndarray, ...], volts: np.ndarray) -> tuple[np.ndarray, ...]:
    """One 7 ms tick of many states at ``volts`` each: RK4 in 1 ms steps (QubeDynamics.step's integration)."""
    h = PERIOD_S / SUBSTEPS
    for _ in range(SUBSTEPS):
        k1 = _rates(p, x, volts)
        k2 = _rates(p, tuple(a + 0.5 * h * b for a, b in zip(x, k1, strict=True)), volts)
        k3 = _rates(p, tuple(a + 0.5 * h * b for a, b in zip(x, k2, strict=True)), volts)
        k4 = _rates(p, tuple(a + h * b for a, b in zip(x, k3, strict=True)), volts)
        x = tuple(a + h / 6.0 * (b + 2.0 * c + 2.0 * d + e) for a, b, c, d, e in zip(x, k1, k2, k3, k4, strict=True))
    return x


class Track:
    """What a batch of trajectories reached: best cos(alpha), its soft maximum, best energy, arm travel."""

    def __init__(self, p: QubeParams, n: int, beta: float = 30.0) -> None:
        self.p, self.beta = p, beta
        self.best_cos = np.full(n, -1.0)
        self.soft = np.zeros(n)
        self.best_energy = np.full(n, -1.0)
        self.max_arm = np.zeros(n)
        self.arm_at_best = np.zeros(n)
        self.catchable = np.zeros(n, dtype=bool)
        self.excess = np.zeros(n)

    def add(self, x: tuple[np.ndarray, ...], limit: float) -> None:
        p = self.p
        theta, alpha, _, alpha_dot = x
        c = np.cos(alpha)
        better = c > self.best_cos
        self.arm_at_best = np.where(better, np.abs(theta), self.arm_at_best)
        self.best_cos = np.maximum(self.best_cos, c)
        self.soft += np.exp(self.beta * (c - 1.0))
        j = p.mp * p.Lp**2 / 3.0
        energy = (0.5 * j * alpha_dot**2 + 0.5 * p.mp * p.g * p.Lp * (c - 1.0)) / (p.mp * p.g * p.Lp)
        self.best_energy = np.maximum(self.best_energy, energy)
        self.max_arm = np.maximum(self.max_arm, np.abs(theta))
        self.catchable |= (c > math.cos(CATCH.catch_angle)) & (np.abs(theta) < CATCH.catch_arm_limit)
        self.excess += np.maximum(0.0, np.abs(theta) - limit) ** 2

    def objective(self, ticks: int) -> np.ndarray:
        """Minimised: minus the soft maximum of cos(alpha) over the ticks, plus the arm-travel penalty."""
        return -(1.0 + np.log(self.soft / ticks) / self.beta) + 50.0 * self.excess / ticks


def hanging(n: int) -> tuple[np.ndarray, ...]:
    return np.zeros(n), np.full(n, math.pi), np.zeros(n), np.zeros(n)


def pump_volts(x: tuple[np.ndarray, ...], brake: np.ndarray, centre: np.ndarray, soft: np.ndarray) -> np.ndarray:
    """The pump family's voltage (+V drives theta negative): full voltage along alpha_dot*cos(alpha) (a kick at
    rest), a pull of ``centre`` per rad towards the middle, never outwards past ``soft``, and full braking when the
    arm could not stop inside ``soft`` at ``brake`` rad/s^2 after 1.3 ticks."""
    theta, alpha, theta_dot, alpha_dot = x
    s = alpha_dot * np.cos(alpha)
    direction = np.where(np.abs(s) < 1e-3, 1.0, np.sign(s))
    accel = np.clip(direction - centre * theta, -1.0, 1.0)
    accel = np.where((np.abs(theta) >= soft) & (accel * theta > 0), 0.0, accel)
    outward = np.sign(theta_dot)
    room = soft - outward * theta - np.abs(theta_dot) * 1.3 * PERIOD_S
    braking = (room <= 0) | (theta_dot**2 >= 2.0 * brake * np.maximum(room, 1e-9))
    return np.where(braking, VMAX * outward, -VMAX * accel)


def run_pumps(p: QubeParams, params: np.ndarray, ticks: int, limit: float) -> tuple[Track, np.ndarray]:
    """The pump family with each row of ``params`` (brake, centre, soft) from hanging rest: (track, volts per tick)."""
    n = params.shape[0]
    x, track = hanging(n), Track(p, n)
    volts = np.zeros((n, ticks))
    for k in range(ticks):
        volts[:, k] = pump_volts(x, params[:, 0], params[:, 1], params[:, 2])
        x = tick(p, x, volts[:, k])
        track.add(x, limit)
    return track, volts


def run_open_loop(p: QubeParams, volts: np.ndarray, limit: float) -> Track:
    """Each row of ``volts`` (V per tick, clipped to the cap) from hanging rest."""
    volts = np.clip(volts, -VMAX, VMAX)
    x, track = hanging(volts.shape[0]), Track(p, volts.shape[0])
    for k in range(volts.shape[1]):
        x = tick(p, x, volts[:, k])
        track.add(x, limit)
    return track


def search_pumps(p: QubeParams, ticks: int, limit: float, generations: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Stage 1: differential evolution over (brake, centre, soft); (best params, its volts per tick)."""
    bounds = [(60.0, 300.0), (0.0, 2.0), (0.5, limit)]

    def cost(population: np.ndarray) -> np.ndarray:
        return run_pumps(p, population.T, ticks, limit)[0].objective(ticks)

    result = differential_evolution(cost, bounds, vectorized=True, updating="deferred", popsize=8,
                                    maxiter=generations, seed=seed, polish=False, tol=1e-6)
    best = np.asarray(result.x)
    return best, run_pumps(p, best[None, :], ticks, limit)[1][0]


def polish(p: QubeParams, base: np.ndarray, limit: float, segment: int, iterations: int) -> np.ndarray:
    """Stage 2: L-BFGS-B over a piecewise-constant correction to ``base`` (volts per tick); the polished volts."""
    ticks = base.size
    segments = math.ceil(ticks / segment)
    expand = np.repeat(np.eye(segments), segment, axis=1)[:, :ticks]
    eps = 0.05

    def cost_and_grad(delta: np.ndarray) -> tuple[float, np.ndarray]:
        probes = np.vstack([delta, delta + eps * np.eye(segments), delta - eps * np.eye(segments)])
        cost = run_open_loop(p, base + probes @ expand, limit).objective(ticks)
        return float(cost[0]), (cost[1:segments + 1] - cost[segments + 1:]) / (2 * eps)

    result = minimize(cost_and_grad, np.zeros(segments), jac=True, method="L-BFGS-B",
                      bounds=[(-2 * VMAX, 2 * VMAX)] * segments, options={"maxiter": iterations})
    return np.clip(base + np.asarray(result.x) @ expand, -VMAX, VMAX)


def replay(p: QubeParams, volts: np.ndarray) -> dict[str, float]:
    """``volts`` tick by tick through the scalar simulator (QubeDynamics.step): height, energy and arm reached."""
    sim = QubeDynamics(p)
    best_cos, max_arm = -1.0, 0.0
    for v in volts:
        sim.step(float(v), PERIOD_S)
        best_cos, max_arm = max(best_cos, math.cos(sim.alpha)), max(max_arm, abs(sim.theta))
    return {"height_deg": round(math.degrees(math.acos(min(1.0, best_cos))), 2),
            "max_arm_deg": round(math.degrees(max_arm), 1)}


def describe(track: Track, i: int = 0) -> dict[str, Any]:
    height = math.degrees(math.acos(min(1.0, float(track.best_cos[i]))))
    return {"height_deg": round(height, 2), "energy": round(float(track.best_energy[i]), 3),
            "max_arm_deg": round(math.degrees(float(track.max_arm[i])), 1),
            "arm_at_highest_deg": round(math.degrees(float(track.arm_at_best[i])), 1),
            "reaches_top": height <= TOP_DEG, "reaches_catch": bool(track.catchable[i])}


def study(name: str, p: QubeParams, limit_deg: float, args: argparse.Namespace) -> dict[str, Any]:
    """Both searches on one setting and arm limit."""
    t0 = time.process_time()
    limit, ticks = math.radians(limit_deg), round(args.horizon / PERIOD_S)
    params, pump = search_pumps(p, ticks, limit, args.generations, args.seed)
    pump_track = run_open_loop(p, pump[None, :], limit)
    volts = polish(p, pump, limit, args.segment_ticks, args.iterations)
    track = run_open_loop(p, volts[None, :], limit)
    best = volts if track.objective(ticks)[0] <= pump_track.objective(ticks)[0] else pump
    best_track = run_open_loop(p, best[None, :], limit)
    within = best_track.max_arm[0] <= limit + 1e-6
    return {"setting": name, "Dp": p.Dp, "Dr": p.Dr, "damping_ratio": round(damping_ratio(p), 4),
            "arm_limit_deg": limit_deg, "pump": {"brake": round(float(params[0]), 1),
                                                 "centre": round(float(params[1]), 3),
                                                 "soft_limit_deg": round(math.degrees(float(params[2])), 1),
                                                 **describe(pump_track)},
            "best": {**describe(best_track), "within_arm_limit": bool(within)},
            "replayed": replay(p, best), "cpu_s": round(time.process_time() - t0, 1)}


def line(row: dict[str, Any]) -> str:
    """One unit's result as a line of text."""
    best = row["best"]
    return (f"{row['setting']:10s} zeta {row['damping_ratio']:.3f} arm {row['arm_limit_deg']:.0f}: pump "
            f"{row['pump']['height_deg']:6.1f} deg, best {best['height_deg']:6.1f} deg (energy {best['energy']:+.3f}, "
            f"arm {best['max_arm_deg']:.0f} deg), replayed {row['replayed']['height_deg']:.1f} deg")


def markdown(data: dict[str, Any]) -> str:
    """The study's table for the docs (``--markdown``), with the command that made it."""
    head = (f"Generated from `{OUT}`, made by `{data['command']}` (voltage cap {data['voltage_cap_v']} V, "
            f"{data['horizon_s']} s from hanging rest).\n\n")
    rows = ["| setting | Dp, Dr (N m s/rad) | damping ratio | arm limit | best pump: height reached | open-loop best: "
            "height reached | energy reached (needed: 0) | arm | top reached |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in data["results"]:
        best = r["best"]
        top = "yes" if best["reaches_top"] and best["within_arm_limit"] else "no"
        rows.append(f"| `{r['setting']}` | {r['Dp']:.2g}, {r['Dr']:.2g} | {r['damping_ratio']:.3f} | "
                    f"{r['arm_limit_deg']:.0f} deg | {r['pump']['height_deg']:.1f} deg | "
                    f"{best['height_deg']:.1f} deg | "
                    f"{best['energy']:+.2f} | {best['max_arm_deg']:.0f} deg | {top} |")
    return head + "\n".join(rows) + "\n"


def reset_markdown(heavy: dict[str, Any], ood: dict[str, Any]) -> str:
    """The reset's success at heavy damping for the docs (``--reset-markdown``): bench.reset's rows per family and
    bridge model, and bench.sim2real ood's per setting summed over its report seeds."""
    rows = ["| setting | measured by | bridge model | rigs' resets ready | on the first request |",
            "| --- | --- | --- | --- | --- |"]
    for r in heavy["results"]:
        name = r["family"].removeprefix("lab-")
        rows.append(f"| `{name}` | `bench.reset` | {r['model']} | {r['ready']} of {r['trials']} | "
                    f"{r['first_attempt']} |")
    sums: dict[tuple[str, str], list[int]] = {}
    for key, entry in ood["entries"].items():
        measure, setting, variant, _seed = key.split("/")
        if measure == "reset":
            total = sums.setdefault((setting, variant), [0, 0, 0])
            for i, field in enumerate(("ready", "resets", "first_attempt")):
                total[i] += entry[field]
    for (setting, variant), (ready, resets, first) in sorted(sums.items()):
        rows.append(f"| `{setting}` | `bench.sim2real ood` | {variant} | {ready} of {resets} | {first} |")
    head = (f"Generated from `{RESET_HEAVY}` (`{heavy['command']}`) and `{OOD_SWINGUP}` "
            f"(`{ood['config']['commands'][-1]}`, load average {ood['config']['load_at_start']} at its start).\n\n")
    return head + "\n".join(rows) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.swingup", description=__doc__.splitlines()[0])
    parser.add_argument("--dp-factors", type=float, nargs="+", default=list(DP_FACTORS))
    parser.add_argument("--arm-limits", type=float, nargs="+", default=list(ARM_LIMITS_DEG), help="degrees")
    parser.add_argument("--horizon", type=float, default=4.0, help="seconds from hanging rest (default 4)")
    parser.add_argument("--generations", type=int, default=25, help="differential evolution's (default 25)")
    parser.add_argument("--iterations", type=int, default=20, help="L-BFGS-B's (default 20)")
    parser.add_argument("--segment-ticks", type=int, default=10, help="ticks per open-loop segment (default 10)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--jobs", type=int, default=1, help="settings at a time (processes)")
    parser.add_argument("--markdown", action="store_true", help="only print --out's table for the docs")
    parser.add_argument("--reset-markdown", action="store_true",
                        help=f"only print the reset's table at heavy damping ({RESET_HEAVY}, {OOD_SWINGUP})")
    args = parser.parse_args(argv)
    if args.reset_markdown:
        print(reset_markdown(json.loads(RESET_HEAVY.read_text()), json.loads(OOD_SWINGUP.read_text())), end="")
        return 0
    if args.markdown:
        print(markdown(json.loads(args.out.read_text())), end="")
        return 0
    units = [(name, p, limit) for name, p in settings(tuple(args.dp_factors)) for limit in args.arm_limits]
    with ProcessPoolExecutor(max_workers=args.jobs, mp_context=get_context("spawn")) as pool:
        futures = [pool.submit(study, name, p, limit, args) for name, p, limit in units]
        rows = []
        for future in futures:
            row = future.result()
            print(line(row), flush=True)
            rows.append(row)
            write_report(args.out, "bench.swingup", argv,  # after every unit: an interrupted study keeps its rows
                         {"voltage_cap_v": round(VMAX, 3), "horizon_s": args.horizon, "tick_s": PERIOD_S,
                          "catch_deg": round(math.degrees(CATCH.catch_angle), 1),
                          "catch_arm_deg": round(math.degrees(CATCH.catch_arm_limit), 1), "results": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
