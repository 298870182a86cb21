"""Robustness of a balance controller on simulated QUBE-Servo 2 rigs, in the way RealAIGym tests controllers
(dfki-ric-underactuated-lab/double_pendulum, docs "Controller Robustness": model inaccuracies, measurement noise,
torque noise, delays): rigs drawn from a profile, torque pulses on the arm at random times, extra encoder noise.

Pulse sizes are fractions of the motor's stall torque at the bridge's voltage limit, kt * V / Rm with V = 400 SPI
counts (9.6 V): 0.042 * 9.6 / 8.4 = 48 mN m (QUBE-Servo 2 User Manual Table 2.2). The balance task's own actions are
+-60 counts (1.44 V): the controller's authority is 7.2 mN m, 15 % of stall (AUTHORITY). A pulse lasts ``pulse_ms``
(default 50 ms, about 7 control periods: a tap on the arm, short against the pendulum's natural period of about
0.6 s).

Each rig plays two disturbed episodes, pulses of growing size (random sign) at random times (the first after
``first_s``, then gaps drawn uniformly from [gap_s / 2, 3 gap_s / 2]), until the pendulum falls or the episode reaches
the task's cut-off:

- **the trial**: the ladder 2, 4, 6, 8, 10, 12, 15 % of stall, every pulse within the controller's authority, so a
  controller can cancel each one while it acts. Passed when the pendulum balances to the end;
- **the sweep** (``sweep``): the ladder on to 20, 25, 30 % of stall, twice the authority: what no action can cancel
  while it acts, to find where the controller gives out. It gives the largest pulse survived.

A pulse counts as survived when the pendulum is still balanced ``settle_s`` after it ended (or at the end of the
episode).
"""

from __future__ import annotations

import random
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from protocol.qube import MAX_RETURN
from rpi_bridge.control import ControlConfig
from rpi_bridge.frame import VOLTS_PER_COUNT
from services.qube_sim.dynamics import QubeParams
from services.qube_sim.profile import RigProfile
from worker.qube_env import ACTIONS, PERIOD_S, QubeLocalEnv

STALL_VOLTAGE = ControlConfig().max_command * VOLTS_PER_COUNT  # 9.6 V: the bridge's command limit
#: The controller's authority as a fraction of the stall torque: its largest action over the bridge's limit.
AUTHORITY = max(abs(a) for a in ACTIONS) / ControlConfig().max_command
LADDER = (0.02, 0.04, 0.06, 0.08, 0.10, 0.12, 0.15, 0.20, 0.25, 0.30)  # fractions of the stall torque: the sweep
TRIAL_LADDER = tuple(f for f in LADDER if f <= AUTHORITY + 1e-12)  # the trial: pulses within the authority


def stall_torque(params: QubeParams | None = None) -> float:
    """kt * V / Rm at the bridge's voltage limit (N m)."""
    p = params or QubeParams()
    return p.kt * STALL_VOLTAGE / p.Rm


@dataclass(frozen=True)
class Disturbances:
    """What hits each rig (see the module docstring)."""

    pulse_ms: float = 50.0  # 0: no pulses
    first_s: float = 1.0
    gap_s: float = 1.5
    settle_s: float = 0.5
    sensor_noise_counts: float = 1.0  # extra encoder noise (standard deviation, counts)
    ladder: tuple[float, ...] = TRIAL_LADDER  # the trial's pulses
    sweep: tuple[float, ...] = LADDER  # the sweep's pulses (empty: no sweep; the trial gives the largest survived)


@dataclass
class RigResult:
    """One rig's trial."""

    rig: int
    seed: int
    balanced_to_end: bool  # the trial
    balance_s: float  # ... its seconds balanced
    largest_pulse_nm: float  # the largest pulse survived in the sweep (in the trial without one; 0: none)
    largest_pulse_of_stall: float  # ... as a fraction of the stall torque
    pulses: list[dict[str, float]] = field(default_factory=list)  # the trial's: start_s, torque_nm, survived
    sweep_pulses: list[dict[str, float]] = field(default_factory=list)  # the sweep's


def pulse_schedule(seed: int, d: Disturbances, ladder: tuple[float, ...],
                   horizon_s: float) -> list[tuple[float, float]]:
    """(start s, fraction of stall with sign) for each pulse of ``ladder`` that starts before ``horizon_s``."""
    rng = random.Random(f"pulses-{seed}")
    schedule, t = [], d.first_s
    for fraction in ladder:
        if d.pulse_ms <= 0 or t >= horizon_s:
            break
        schedule.append((t, fraction * rng.choice((-1.0, 1.0))))
        t += d.pulse_ms / 1e3 + rng.uniform(0.5 * d.gap_s, 1.5 * d.gap_s)
    return schedule


def run_rig(act: Callable[[np.ndarray], int], profile: RigProfile, rig: int, seed: int, d: Disturbances,
            max_steps: int = MAX_RETURN) -> RigResult:
    """Rig ``seed`` of ``profile`` under the controller ``act(obs) -> action index``: the trial, then the sweep."""
    env = QubeLocalEnv(seed=seed, profile=profile)
    torque = stall_torque(env.device.params)
    balance_s, fell, pulses = _episode(env, act, torque, pulse_schedule(seed, d, d.ladder, max_steps * PERIOD_S), d,
                                       seed, max_steps)
    sweep: list[dict[str, float]] = []
    if d.sweep and d.pulse_ms > 0:
        _, _, sweep = _episode(env, act, torque, pulse_schedule(seed, d, d.sweep, max_steps * PERIOD_S), d, None,
                               max_steps)
    survived_nm = [abs(float(p["torque_nm"])) for p in (sweep or pulses) if p["survived"]]
    largest = max(survived_nm, default=0.0)
    return RigResult(rig=rig, seed=seed, balanced_to_end=not fell, balance_s=round(balance_s, 3),
                     largest_pulse_nm=largest, largest_pulse_of_stall=round(largest / torque, 4), pulses=pulses,
                     sweep_pulses=sweep)


def _episode(env: QubeLocalEnv, act: Callable[[np.ndarray], int], torque: float,
             schedule: list[tuple[float, float]], d: Disturbances, seed: int | None,
             max_steps: int) -> tuple[float, bool, list[dict[str, float]]]:
    """One disturbed episode: (seconds balanced, fell, each pulse with whether it was survived)."""
    obs, _ = env.reset(seed=seed)
    noise = env.device.encoder_noise_counts
    env.device.encoder_noise_counts = noise + d.sensor_noise_counts  # from the episode's start (not the reset)
    steps, fell, ended = 0, False, False
    while not ended:
        t = steps * PERIOD_S
        active = [s for start, s in schedule if start <= t < start + d.pulse_ms / 1e3]
        env.device.dynamics.external_torque = active[0] * torque if active else 0.0
        obs, _, terminated, truncated, _ = env.step(act(obs))
        steps += 1
        fell, ended = terminated, terminated or truncated or steps >= max_steps
    env.device.dynamics.external_torque = 0.0
    env.device.encoder_noise_counts = noise
    balance_s = steps * PERIOD_S
    pulses = []
    for start, signed in schedule:
        if start >= balance_s:
            break
        survived = not fell or balance_s >= start + d.pulse_ms / 1e3 + d.settle_s
        pulses.append({"start_s": round(start, 3), "torque_nm": round(signed * torque, 6), "survived": survived})
    return balance_s, fell, pulses


def run_rigs(act: Callable[[np.ndarray], int], profile: RigProfile, rigs: int, seed: int,
             d: Disturbances | None = None) -> list[RigResult]:
    """``rigs`` rigs of ``profile`` (rig i has seed ``seed + i``), each one disturbed episode."""
    d = d or Disturbances()
    return [run_rig(act, profile, i, seed + i, d) for i in range(rigs)]


def summary(results: list[RigResult]) -> dict[str, Any]:
    return {"rigs": len(results), "balanced_to_end": sum(r.balanced_to_end for r in results),
            "median_balance_s": float(np.median([r.balance_s for r in results])) if results else 0.0,
            "smallest_largest_pulse_nm": min((r.largest_pulse_nm for r in results), default=0.0),
            "median_largest_pulse_of_stall": float(np.median([r.largest_pulse_of_stall for r in results]))
            if results else 0.0}
