"""Reset trials: the bridge's control core (calibration, self-test, safety checks, swing-up) driving a simulated
rig from varied starts, as the bridge would drive a real one. Used by tests/rpi_bridge/test_qube_reset.py and
``python -m bench.reset``.

A trial: a fresh core calibrates and self-tests the rig hanging at rest, then the rig is put into a start state
(the arm anywhere within +-60 deg, the pendulum up to 90 deg from hanging, both moving, like a rig after a fall or
a failed swing-up), a reset is requested, and the trial records whether and when the core reported ready, the
largest arm angle the (true) simulated arm reached, whether it touched an end stop and what the core reported.
At ready it also records the handover, the state an episode would start from (the arm's angle and speed), and how
far the arm swings while the hold goes on for ``WATCH_S`` more: a hold that hunts (friction against its arm loop)
hands over an arm still swinging, a harder start for the controller than a calm one.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, replace
from typing import Any

from protocol import qube
from rpi_bridge.control import ControlConfig, ControlCore, Sensed
from services.qube_sim.clock import VirtualClock
from services.qube_sim.dynamics import QubeParams
from services.qube_sim.spi_peer import SimulatedQube

PERIOD_S = qube.PERIOD_S
END_STOP = math.radians(115.0)  # the QUBE's arm stops, beyond rpi_bridge's 110 deg arm limit
#: How long the hold is watched after ready (s), and what counts as a calm handover: the arm this slow (rad/s) and
#: this near the middle (deg) at ready.
WATCH_S = 3.0
CALM_ARM_SPEED = 0.5
CALM_ARM_DEG = 20.0


@dataclass(frozen=True)
class Start:
    theta: float
    alpha: float
    theta_dot: float
    alpha_dot: float


def varied_start(index: int) -> Start:
    """Start ``index`` of a fixed, reproducible set: arm in +-60 deg at up to 2 rad/s, pendulum up to 90 deg from
    hanging at up to 3 rad/s."""
    rng = random.Random(1000 + index)
    return Start(theta=math.radians(rng.uniform(-60.0, 60.0)), alpha=math.pi + math.radians(rng.uniform(-90.0, 90.0)),
                 theta_dot=rng.uniform(-2.0, 2.0), alpha_dot=rng.uniform(-3.0, 3.0))


@dataclass(frozen=True)
class Condition:
    """A family of rigs: pendulum damping x ``damping``, parameters spread +-``spread`` (uniform, per rig),
    Coulomb friction torques ``coulomb`` = (arm, pendulum) in N m."""

    name: str
    damping: float = 1.0
    spread: float = 0.0
    coulomb: tuple[float, float] = (0.0, 0.0)

    def params(self, index: int) -> QubeParams:
        base = QubeParams()
        p = QubeParams.spread(index, self.spread, base) if self.spread > 0 else base
        return replace(p, Dp=p.Dp * self.damping, Cr=self.coulomb[0], Cp=self.coulomb[1])


@dataclass(frozen=True)
class TrialResult:
    ready: bool
    seconds: float  # from the reset request to ready (or to the end of the trial)
    max_arm_deg: float  # largest |theta| of the simulated arm during the reset
    hit_end_stop: bool
    outcome: str  # "ready", "reset_failed: <detail>", "fault: <reason>" or "timeout" (of the last attempt)
    attempts: int = 1  # reset requests made
    handover_arm_deg: float | None = None  # |theta| (deg) at ready, as the bridge read it
    handover_arm_speed: float | None = None  # |theta_dot| (rad/s) at ready
    hold_swing_deg: float | None = None  # largest |theta| (deg) over WATCH_S of holding after ready

    @property
    def calm(self) -> bool:
        """Ready with the arm slower than CALM_ARM_SPEED and nearer the middle than CALM_ARM_DEG."""
        return (self.ready and self.handover_arm_speed is not None and self.handover_arm_deg is not None
                and self.handover_arm_speed <= CALM_ARM_SPEED and self.handover_arm_deg <= CALM_ARM_DEG)


def start_up(params: QubeParams, config: ControlConfig | None = None, device_options: dict[str, Any] | None = None
             ) -> tuple[VirtualClock, SimulatedQube, ControlCore, str | None]:
    """A fresh core over a rig of ``params`` hanging at rest, through its start-up (calibration and self-test):
    (clock, device, core, None) when it ended idle, else the last item says how it ended ("start-up ended in ...")."""
    clock = VirtualClock()
    device = SimulatedQube(params, seed=0, period_s=0, clock=clock, arm_limit=END_STOP, **(device_options or {}))
    # the simulated rig is exactly at rest: a short stillness window is enough (the bridge uses 1 s)
    config = replace(config or ControlConfig(period_s=PERIOD_S), calibration_window_s=0.05)
    core = ControlCore(device, config, clock=clock)
    for _ in range(round(5.0 / PERIOD_S)):  # start-up: calibrate and self-test at rest
        core.sense()
        core.act(None)
        clock.advance(PERIOD_S)
        if core.phase != "calibrating" and core.phase != "self_test":
            break
    refused = None if core.phase == "idle" else f"start-up ended in {core.phase}: {core.fault_reason}"
    return clock, device, core, refused


def run_trial(params: QubeParams, start: Start, config: ControlConfig | None = None,
              max_seconds: float = 16.0, device_options: dict[str, Any] | None = None, attempts: int = 1,
              settle_s: float = 3.0) -> TrialResult:
    """One reset from ``start`` on a rig with ``params`` (see the module docstring); ``device_options``: a rig
    profile's sensing and actuation (RigProfile.device_options). With ``attempts`` > 1, as the worker does
    (worker/qube_env.py RESET_ATTEMPTS): a failed attempt is followed by ``settle_s`` idle and a new request (the
    core picks the next strategy), up to ``attempts`` requests; ``max_seconds`` is per attempt, ``seconds`` counts
    every attempt and settle."""
    clock, device, core, refused = start_up(params, config, device_options)
    if refused is not None:
        return TrialResult(False, 0.0, 0.0, False, refused)
    device.reset_state(theta=start.theta, alpha=start.alpha, theta_dot=start.theta_dot, alpha_dot=start.alpha_dot)
    for _ in range(10):  # idle while the velocity filters catch up with the new state
        core.sense()
        clock.advance(PERIOD_S)
    max_arm, hit, outcome, elapsed, attempt = 0.0, False, "timeout", 0.0, 0
    handover: Sensed | None = None
    while attempt < attempts:
        attempt += 1
        core.events.clear()
        core.request_reset(attempt)
        outcome = "timeout"
        for _ in range(round(max_seconds / PERIOD_S)):
            sensed = core.sense()
            theta = device.state[0]
            max_arm = max(max_arm, abs(theta))
            hit = hit or abs(theta) >= END_STOP - 1e-9
            if sensed.awaits_action:
                outcome, handover = "ready", sensed
                break
            failed = [e for e in core.events if e[0] == "reset_failed"]
            if failed:
                outcome = f"reset_failed: {failed[0][2]}"
                break
            if core.phase == "fault":
                outcome = f"fault: {core.fault_reason}"
                break
            core.act(None)
            clock.advance(PERIOD_S)
            elapsed += PERIOD_S
        if outcome == "ready" or attempt == attempts:
            break
        for _ in range(round(settle_s / PERIOD_S)):  # as the worker: the pendulum settles before the next request
            core.sense()
            core.act(None)
            clock.advance(PERIOD_S)
            elapsed += PERIOD_S
    if handover is None:
        return TrialResult(False, round(elapsed, 3), math.degrees(max_arm), hit, outcome, attempt)
    return TrialResult(True, round(elapsed, 3), math.degrees(max_arm), hit, outcome, attempt,
                       round(math.degrees(abs(handover.theta)), 2), round(abs(handover.theta_dot), 3),
                       round(math.degrees(watch_hold(core, clock)), 2))


def watch_hold(core: ControlCore, clock: VirtualClock) -> float:
    """The largest |theta| (rad) while the core holds on after ready for WATCH_S, no action coming (the bridge's
    ready phase: its reset controller keeps holding until the worker takes over)."""
    swing = 0.0
    for _ in range(round(WATCH_S / PERIOD_S)):
        core.act(None)
        clock.advance(PERIOD_S)
        sensed = core.sense()
        swing = max(swing, abs(sensed.theta))
    return swing


def run_condition(condition: Condition, trials: int = 50, config: ControlConfig | None = None) -> list[TrialResult]:
    """``trials`` resets, rig ``i`` (its parameters drawn from ``i``) from start ``i``."""
    return [run_trial(condition.params(i), varied_start(i), config) for i in range(trials)]


def _middle(values: list[float]) -> float | None:
    """The median of ``values`` as the reset tables take it (the upper one of an even count); None for none."""
    return sorted(values)[len(values) // 2] if values else None


def summary(results: list[TrialResult]) -> dict[str, float | int | None]:
    ready = [r for r in results if r.ready]
    times = sorted(r.seconds for r in ready)
    speed = _middle([r.handover_arm_speed for r in ready if r.handover_arm_speed is not None])
    swing = _middle([r.hold_swing_deg for r in ready if r.hold_swing_deg is not None])
    median_s = _middle(times)
    return {
        "trials": len(results),
        "ready": len(ready),
        "first_attempt": sum(r.ready and r.attempts == 1 for r in results),
        "median_s": round(median_s, 2) if median_s is not None else 0.0,
        "max_arm_deg": round(max((r.max_arm_deg for r in results), default=0.0), 1),
        "past_110_deg": sum(r.max_arm_deg > 110.0 for r in results),
        "end_stop_hits": sum(r.hit_end_stop for r in results),
        "faults": sum(r.outcome.startswith("fault") for r in results),
        "mean_s": round(sum(times) / len(times), 2) if times else 0.0,
        "p90_s": round(times[min(len(times) - 1, int(0.9 * len(times)))], 2) if times else 0.0,
        "calm_handovers": sum(r.calm for r in results),
        "handover_arm_speed_median": round(speed, 2) if speed is not None else None,
        "hold_swing_deg_median": round(swing, 1) if swing is not None else None,
    }
