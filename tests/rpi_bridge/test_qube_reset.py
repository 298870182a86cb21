"""The reset controller swings the simulated QUBE up and holds it inside the arm's travel: the controller's pieces
on given states, and 50 resets through the bridge's control core from varied starts (services/qube_sim/trials.py)
on nominal rigs, rigs spread +-15 %, 5x pendulum damping and Coulomb friction."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from protocol import qube
from rpi_bridge.control import ControlConfig
from rpi_bridge.frame import MAX_COMMAND, build_command, parse_reply
from rpi_bridge.reset import ResetConfig, ResetController
from rpi_bridge.velocity import VelocityFilter
from services.qube_sim.dynamics import QubeParams
from services.qube_sim.spi_peer import SimulatedQube
from services.qube_sim.trials import (
    CALM_ARM_DEG,
    CALM_ARM_SPEED,
    Condition,
    Start,
    run_condition,
    run_trial,
    summary,
    varied_start,
)

TICK = qube.PERIOD_S


def swing_up(
    sim: SimulatedQube, ctl: ResetController, seconds: float = 20.0, stop_at_ready: bool = True
) -> tuple[str, float, list[tuple[float, int, str, float]]]:
    """The bridge's loop without the core: one SPI transfer per tick, angles from the counts, both velocities
    from the 50 rad/s filter. The log has (time, command, phase, true arm angle)."""
    theta_filter, alpha_filter = VelocityFilter(TICK), VelocityFilter(TICK)
    command, phase, log = 0, "swing_up", []
    for k in range(round(seconds / TICK)):
        r = parse_reply(sim.transfer(build_command(command)))
        state = (r.theta, r.alpha, theta_filter.update(r.theta), alpha_filter.update(r.alpha))
        command, phase = ctl.step(state, TICK)
        log.append((k * TICK, command, phase, sim.state[0]))
        if phase == "failed" or (stop_at_ready and phase == "ready"):
            break
    return phase, log[-1][0], log


def test_reaches_ready_from_hanging_rest_within_the_voltage_cap() -> None:
    sim = SimulatedQube(period_s=TICK)
    phase, t, log = swing_up(sim, ResetController())
    assert phase == "ready", f"ended {phase} after {t:.2f} s"
    assert t < 6.0
    phases = [p for _, _, p, _ in log]
    assert phases[0] == "swing_up" and "holding" in phases
    assert max(abs(c) for _, c, _, _ in log) <= MAX_COMMAND  # +-10 V in every phase
    theta, alpha, _, _ = sim.state
    assert abs(alpha) < math.radians(5) and abs(theta) < math.radians(45)


def test_keeps_holding_after_ready() -> None:
    sim = SimulatedQube(period_s=TICK)
    _, _, log = swing_up(sim, ResetController(ResetConfig(hold_time_s=0.2)), seconds=9.0, stop_at_ready=False)
    ready_at = next(t for t, _, p, _ in log if p == "ready")
    after = [p for t, _, p, _ in log if t > ready_at + 0.5]
    assert after and set(after) == {"ready"}
    assert abs(sim.state[1]) < math.radians(3)


def test_fails_after_the_timeout_and_reset_clears_it() -> None:
    sim = SimulatedQube(period_s=TICK)
    ctl = ResetController(ResetConfig(timeout_s=1.0))
    alpha_filter = VelocityFilter(TICK)
    phase, ticks = "swing_up", 0
    while phase != "failed" and ticks < 1000:  # the amplifier stays off, so the swing-up cannot work
        r = parse_reply(sim.transfer(build_command(0, enable=False)))
        _, phase = ctl.step((r.theta, r.alpha, r.arm_velocity_rad_s, alpha_filter.update(r.alpha)), TICK)
        ticks += 1
    assert phase == "failed" and ticks * TICK == pytest.approx(1.0, abs=TICK)
    assert "within 1 s" in ctl.failure
    assert ctl.step((0.0, 0.0, 0.0, 0.0), TICK) == (0, "failed")  # latched, command 0
    ctl.reset()
    assert ctl.step((0.0, math.pi, 0.0, 0.0), TICK)[1] == "swing_up"


def test_phases_from_given_states() -> None:
    cfg = ResetConfig(hold_time_s=0.02, velocity_cutoff=None)  # use the alpha_dot given (0), no internal filter
    ctl = ResetController(cfg)
    assert ctl.step((0.0, math.pi, 0.0, 0.0), TICK)[1] == "swing_up"
    cmd, phase = ctl.step((0.0, math.radians(10), 0.0, 0.0), TICK)
    assert phase == "catch" and cmd > 0  # leaning to +alpha: positive command, the arm moves to -theta under it
    assert ctl.step((0.0, math.radians(1), 0.0, 0.0), TICK)[1] == "holding"
    assert ctl.step((0.0, math.radians(1), 0.0, 0.0), TICK)[1] == "holding"
    assert ctl.step((0.0, math.radians(1), 0.0, 0.0), TICK)[1] == "ready"
    assert ctl.step((0.0, math.radians(60), 0.0, 0.0), TICK)[1] == "swing_up"


def test_no_catch_with_the_arm_far_out_or_heading_for_the_soft_limit() -> None:
    ctl = ResetController(ResetConfig(velocity_cutoff=None))
    near_top = math.radians(10)
    assert ctl.step((math.radians(70), near_top, 0.0, 0.0), TICK)[1] == "swing_up"  # past catch_arm_limit
    assert ctl.step((math.radians(40), near_top, 10.0, 0.0), TICK)[1] == "swing_up"  # could not stop in time
    assert ctl.step((math.radians(40), near_top, -10.0, 0.0), TICK)[1] == "catch"  # heading back to the middle


def test_brakes_at_full_voltage_when_the_arm_could_not_stop_inside_the_soft_limit() -> None:
    ctl = ResetController(ResetConfig(velocity_cutoff=None))
    assert ctl.must_brake(math.radians(60), 8.0, TICK) == 1
    assert ctl.must_brake(math.radians(-60), -8.0, TICK) == -1
    assert ctl.must_brake(math.radians(60), -8.0, TICK) == 0
    assert ctl.must_brake(0.0, 3.0, TICK) == 0
    # +theta moving out: +command (drives theta negative) at the cap
    assert ctl.step((math.radians(60), math.pi / 2, 8.0, 0.0), TICK) == (MAX_COMMAND, "swing_up")
    assert ctl.step((math.radians(-60), math.pi / 2, -8.0, 0.0), TICK) == (-MAX_COMMAND, "swing_up")


def test_the_soft_limit_holds_from_a_fast_start_towards_the_stop() -> None:
    """The arm at 60 deg moving outwards at 6 rad/s, the pendulum swinging: it stops short of 110 deg (the soft
    limit is 80) and the swing-up never drives it out again."""
    for theta_dot in (6.0, -6.0):
        sim = SimulatedQube(period_s=TICK, arm_limit=math.radians(115))
        sim.reset_state(theta=math.copysign(math.radians(60), theta_dot), alpha=math.pi + 1.2, theta_dot=theta_dot,
                        alpha_dot=4.0)
        _, _, log = swing_up(sim, ResetController(), seconds=6.0)
        assert max(abs(th) for *_, th in log) < math.radians(95)


def test_swing_up_kicks_a_pendulum_at_rest_and_respects_the_cap() -> None:
    ctl = ResetController(ResetConfig(max_command=50))
    cmd, phase = ctl.step((0.0, math.pi, 0.0, 0.0), TICK)
    assert phase == "swing_up" and cmd != 0 and abs(cmd) <= 50


def test_bad_input() -> None:
    ctl = ResetController()
    with pytest.raises(ValueError):
        ctl.step((0.0, 0.0, 0.0, 0.0), 0.0)
    assert ctl.step((0.0, float("nan"), 0.0, 0.0), TICK) == (0, "failed")
    assert "non-finite" in ctl.failure
    with pytest.raises(ValueError, match=r"1\.\.416"):
        ResetConfig(max_command=500)  # 12 V: above the manual's 10 V
    with pytest.raises(ValueError, match="soft arm limit"):
        ControlConfig(reset=ResetConfig(arm_soft_limit=math.radians(120)))


# -- 50 resets from varied starts through the bridge's control core -------------------------------------------------

@pytest.mark.parametrize(("condition", "at_least"), [
    (Condition("nominal"), 49),
    (Condition("spread +-15 %", spread=0.15), 48),
    (Condition("5x pendulum damping", damping=5.0), 45),
])
def test_fifty_resets_succeed_inside_the_arm_travel(condition: Condition, at_least: int) -> None:
    results = run_condition(condition, trials=50)
    s = summary(results)
    assert s["ready"] >= at_least, (condition, s, [r.outcome for r in results if not r.ready])
    assert s["past_110_deg"] == 0 and s["end_stop_hits"] == 0 and s["faults"] == 0, (condition, s)


def test_resets_with_coulomb_friction() -> None:
    """Arm 1.5 mN m (about 0.3 V of motor voltage) and pendulum 0.1 mN m of Coulomb friction: the reset still
    works on most starts and never leaves the arm's travel."""
    s = summary(run_condition(Condition("coulomb", coulomb=(1.5e-3, 1e-4)), trials=20))
    assert s["ready"] >= 16 and s["past_110_deg"] == 0 and s["end_stop_hits"] == 0, s


def test_trial_start_is_applied() -> None:
    """The trials really start where they say (a guard on the harness)."""
    r = run_trial(QubeParams(), Start(theta=math.radians(70), alpha=math.pi, theta_dot=0.0, alpha_dot=0.0))
    assert r.ready and r.max_arm_deg >= 69.0


def test_reset_config_validation_keeps_catch_inside_boost() -> None:
    with pytest.raises(ValueError):
        ResetConfig(catch_angle=math.radians(30), boost_min_angle=math.radians(20))
    assert replace(ResetConfig(), swing_accel=50.0).swing_accel == 50.0


def test_a_trial_records_the_handover_and_the_hold_after_it() -> None:
    """At ready a trial records the arm as the episode would start from it (inside the reset's arm band) and how far
    it swings while the hold goes on; a calm handover is one both slow and near the middle; a failed trial has no
    handover. The summary counts the calm ones."""
    r = run_trial(QubeParams(), varied_start(3))
    assert r.ready and r.handover_arm_deg is not None and r.handover_arm_speed is not None
    assert r.handover_arm_deg <= math.degrees(ResetConfig().arm_band) + 1e-6
    assert r.hold_swing_deg is not None and r.hold_swing_deg >= r.handover_arm_deg - 1.0  # it starts from there
    calm = replace(r, handover_arm_deg=CALM_ARM_DEG / 2, handover_arm_speed=CALM_ARM_SPEED / 2)
    assert calm.calm and not replace(calm, handover_arm_speed=CALM_ARM_SPEED * 2).calm
    assert not replace(calm, handover_arm_deg=CALM_ARM_DEG * 2).calm and not replace(calm, ready=False).calm
    failed = run_trial(QubeParams(), varied_start(3), max_seconds=0.5)
    assert not failed.ready and failed.handover_arm_speed is None and not failed.calm
    s = summary([calm, r, failed])
    assert s["calm_handovers"] == 1 + r.calm and s["handover_arm_speed_median"] is not None


def test_the_reset_hands_over_a_calm_arm_on_lab_rigs() -> None:
    """The hold after a swing-up settles the arm before it hands over: a hold whose arm mode is slow and lightly
    damped (the first design's weights, rpi_bridge/plant.py FIRST_LQR_Q) handed over none of 16 such resets calm
    (bench/results/reset-tuning-hold-1-10-0-0.json), and a warm start fell on such handovers. Tuning rig seeds and
    starts."""
    from services.qube_sim.profile import load_profile

    lab = load_profile("lab")
    results = [run_trial(lab.rig_params(i), varied_start(i), max_seconds=40.0, device_options=lab.device_options())
               for i in range(8)]
    s = summary(results)
    assert s["ready"] == 8 and s["calm_handovers"] >= 5, s
    assert s["hold_swing_deg_median"] is not None and s["hold_swing_deg_median"] < 15.0, s
