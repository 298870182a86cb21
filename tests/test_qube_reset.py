"""The reset controller swings the simulated QUBE up and holds it, through SPI frames at the bridge's 7 ms
tick."""

from __future__ import annotations

import math

import pytest

from rpi_bridge.frame import build_command, parse_reply
from rpi_bridge.reset import ResetConfig, ResetController
from rpi_bridge.velocity import VelocityFilter
from services.qube_sim.dynamics import QubeParams
from services.qube_sim.spi_peer import SimulatedQube

TICK = 0.007


def swing_up(
    sim: SimulatedQube, ctl: ResetController, seconds: float = 20.0, stop_at_ready: bool = True
) -> tuple[str, float, list[tuple[float, int, str]]]:
    """The bridge's loop: one SPI transfer per tick (the physics runs 7 ms in 1 ms RK4 steps in between),
    angles from the counts, theta_dot from the tachometer, alpha_dot from the 50 rad/s filter."""
    alpha_filter = VelocityFilter(TICK)
    command, phase, log = 0, "swing_up", []
    for k in range(round(seconds / TICK)):
        r = parse_reply(sim.transfer(build_command(command)))
        state = (r.theta, r.alpha, r.arm_velocity_rad_s, alpha_filter.update(r.alpha))
        command, phase = ctl.step(state, TICK)
        log.append((k * TICK, command, phase))
        if phase == "failed" or (stop_at_ready and phase == "ready"):
            break
    return phase, log[-1][0], log


def test_reaches_ready_from_hanging_rest() -> None:
    sim = SimulatedQube(period_s=TICK)
    ctl = ResetController()
    phase, t, log = swing_up(sim, ctl)
    assert phase == "ready", f"ended {phase} after {t:.2f} s"
    assert t < ResetConfig().timeout_s
    assert t < 6.0  # measured 3.1 s (nominal rig, hanging at rest)
    phases = [p for _, _, p in log]
    assert phases[0] == "swing_up" and "holding" in phases
    assert all(abs(c) <= 400 for _, c, p in log if p == "swing_up")  # swing-up cap
    assert all(abs(c) <= 500 for _, c, _ in log)
    theta, alpha, _, _ = sim.state
    assert abs(alpha) < math.radians(5) and abs(theta) < math.radians(45)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_reaches_ready_on_varied_rigs(seed: int) -> None:
    sim = SimulatedQube(QubeParams.varied(seed, scale=0.05), seed=seed, period_s=TICK, initial_noise=0.02)
    phase, t, _ = swing_up(sim, ResetController())
    assert phase == "ready", f"seed {seed}: ended {phase} after {t:.2f} s"


def test_keeps_holding_after_ready() -> None:
    sim = SimulatedQube(period_s=TICK)
    ctl = ResetController(ResetConfig(hold_time_s=0.2))
    _, _, log = swing_up(sim, ctl, seconds=9.0, stop_at_ready=False)
    ready_at = next(t for t, _, p in log if p == "ready")
    after = [p for t, _, p in log if t > ready_at + 0.5]
    assert after and set(after) == {"ready"}
    assert abs(sim.state[1]) < math.radians(3)


def test_fails_after_the_timeout_and_reset_clears_it() -> None:
    sim = SimulatedQube(period_s=TICK)
    ctl = ResetController(ResetConfig(timeout_s=1.0))
    alpha_filter = VelocityFilter(TICK)
    phase = "swing_up"
    ticks = 0
    while phase != "failed" and ticks < 1000:
        # the amplifier stays off, so the swing-up cannot work
        r = parse_reply(sim.transfer(build_command(0, enable=False)))
        _, phase = ctl.step((r.theta, r.alpha, r.arm_velocity_rad_s, alpha_filter.update(r.alpha)), TICK)
        ticks += 1
    assert phase == "failed" and ticks * TICK == pytest.approx(1.0, abs=TICK)
    assert ctl.step((0.0, 0.0, 0.0, 0.0), TICK) == (0, "failed")  # latched, command 0
    ctl.reset()
    assert ctl.step((0.0, math.pi, 0.0, 0.0), TICK)[1] == "swing_up"


def test_phases_from_given_states() -> None:
    cfg = ResetConfig(
        hold_time_s=0.02, balance_band=math.radians(5), catch_angle=math.radians(20), velocity_cutoff=None
    )  # use the alpha_dot given (0), no internal filter
    ctl = ResetController(cfg)
    assert ctl.step((0.0, math.pi, 0.0, 0.0), TICK)[1] == "swing_up"
    cmd, phase = ctl.step((0.0, math.radians(10), 0.0, 0.0), TICK)
    assert (
        phase == "catch" and cmd > 0
    )  # leaning to +alpha: positive command, the arm moves to -theta under it
    assert ctl.step((0.0, math.radians(1), 0.0, 0.0), TICK)[1] == "holding"
    assert ctl.step((0.0, math.radians(1), 0.0, 0.0), TICK)[1] == "holding"
    assert ctl.step((0.0, math.radians(1), 0.0, 0.0), TICK)[1] == "ready"
    assert ctl.step((0.0, math.radians(60), 0.0, 0.0), TICK)[1] == "swing_up"


def test_swing_up_kicks_a_pendulum_at_rest_and_respects_the_cap() -> None:
    ctl = ResetController(ResetConfig(max_command_swing=50))
    cmd, phase = ctl.step((0.0, math.pi, 0.0, 0.0), TICK)
    assert phase == "swing_up" and cmd != 0 and abs(cmd) <= 50


def test_bad_input() -> None:
    ctl = ResetController()
    with pytest.raises(ValueError):
        ctl.step((0.0, 0.0, 0.0, 0.0), 0.0)
    assert ctl.step((0.0, float("nan"), 0.0, 0.0), TICK) == (0, "failed")
