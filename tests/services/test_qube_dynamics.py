"""QUBE-Servo 2 physics (gym_brt equations with a braking back-EMF) and the simulated SPI peer."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from rpi_bridge.device import QubeDevice
from rpi_bridge.frame import (
    DEVICE_ID,
    RAD_PER_COUNT,
    build_command,
    counts_to_arm_rad,
    counts_to_pendulum_rad,
    parse_reply,
)
from services.qube_sim.dynamics import QubeDynamics, QubeParams, command_to_voltage, linearize, wrap_angle
from services.qube_sim.spi_peer import SimulatedQube


def run(
    d: QubeDynamics, seconds: float, voltage: float = 0.0, dt: float = 0.007, **kw: object
) -> list[tuple]:
    out = []
    for _ in range(round(seconds / dt)):
        d.step(voltage, dt, **kw)  # type: ignore[arg-type]
        out.append(d.state)
    return out


def test_parameters_from_the_user_manual() -> None:
    p = QubeParams()
    assert (p.Rm, p.km, p.kt, p.mr, p.Lr, p.mp, p.Lp) == (8.4, 0.042, 0.042, 0.095, 0.085, 0.024, 0.129)
    assert p.Jr == pytest.approx(5.72e-5, rel=1e-3) and p.Jp == pytest.approx(3.33e-5, rel=1e-3)


def test_command_to_voltage() -> None:
    assert command_to_voltage(500) == pytest.approx(500 / 999 * 24)  # about 12 V ([DS] example)
    assert command_to_voltage(999) == 15.0 and command_to_voltage(-999) == -15.0  # amplifier max +-15 V
    assert command_to_voltage(0) == 0.0


def test_upright_is_unstable() -> None:
    d = QubeDynamics()
    d.set_state(0.0, 0.01)
    states = run(d, 1.0)
    assert abs(states[-1][1]) > 0.5
    a, b = linearize()
    assert a[3][1] > 0  # alpha_ddot grows with alpha upright
    assert b[2] < 0  # +V drives theta negative


def test_hanging_is_stable_and_decays() -> None:
    d = QubeDynamics()
    d.set_state(0.0, math.pi + 0.2)
    states = run(d, 6.0)
    dev = [abs(wrap_angle(s[1] - math.pi)) for s in states]
    assert max(dev) <= 0.2 + 1e-3  # bounded by the initial disturbance
    assert max(dev[-140:]) < 0.15  # the last second swings less: damping
    assert abs(states[-1][0]) < 0.1


def test_energy_conserved_without_damping_or_motor() -> None:
    d = QubeDynamics(replace(QubeParams(), Dr=0.0, Dp=0.0))
    d.set_state(0.3, 2.0, 3.0, -4.0)  # a lively swing
    e0 = d.energy()
    energies = []
    for _ in range(round(4.0 / 0.007)):
        d.step(0.0, 0.007, amplifier_on=False)  # open circuit: no torque, no back-EMF
        energies.append(d.energy())
    drift = max(abs(e - e0) for e in energies) / e0
    assert drift < 0.01
    assert drift < 1e-6  # RK4 at 1 ms sub-steps is far better than the 1 % budget


def test_damping_and_back_emf_only_remove_energy() -> None:
    d = QubeDynamics()
    d.set_state(0.0, 2.0, 5.0, 0.0)
    last = d.energy()
    for _ in range(300):
        d.step(0.0, 0.007)  # amplifier on at 0 V: the back-EMF brakes the arm
        e = d.energy()
        assert e <= last + 1e-12
        last = e
    # dE/dt = tau*theta_dot - Dr*theta_dot^2 - Dp*alpha_dot^2 with tau = -km^2*theta_dot/Rm at 0 V
    p = d.params
    _, _, td, ad = d.state
    e0 = d.energy()
    d.step(0.0, 1e-4, substeps=1)
    expected = -(p.km * p.kt / p.Rm + p.Dr) * td * td - p.Dp * ad * ad
    assert (d.energy() - e0) / 1e-4 == pytest.approx(expected, rel=0.02, abs=1e-7)


def test_positive_command_moves_theta_negative() -> None:
    d = QubeDynamics()
    d.set_state(0.0, math.pi)
    run(d, 0.1, voltage=command_to_voltage(200))
    assert d.theta < -0.05
    sim = SimulatedQube(period_s=0.007)
    sim.transfer(build_command(200))
    for _ in range(15):
        r = parse_reply(sim.transfer(build_command(200)))
    assert r.encoder0 > 0 and counts_to_arm_rad(r.encoder0) < 0  # +command: encoder0 counts up, theta down
    assert r.arm_velocity_rad_s < 0


def test_varied_params_are_deterministic_and_bounded() -> None:
    base = QubeParams()
    a, b, c = QubeParams.varied(1), QubeParams.varied(1), QubeParams.varied(2)
    assert a == b and a != c
    for seed in range(20):
        p = QubeParams.varied(seed, scale=0.05)
        for name in ("mr", "Lr", "mp", "Lp", "Dr", "Dp", "km"):
            assert 0.85 - 1e-12 <= getattr(p, name) / getattr(base, name) <= 1.15 + 1e-12
        assert p.km / base.km == pytest.approx(p.kt / base.kt)
        assert (p.Rm, p.g) == (base.Rm, base.g)


def test_arm_hard_stop() -> None:
    d = QubeDynamics(arm_limit=1.0)
    d.set_state(0.0, math.pi)
    run(d, 1.0, voltage=-6.0)  # drives theta positive into the stop
    assert d.theta == pytest.approx(1.0) and d.at_limit == 1 and d.pressing_limit(-6.0)
    run(d, 0.2, voltage=+6.0)
    assert d.theta < 1.0 and d.at_limit == 0


# --- simulated SPI peer -------------------------------------------------------------------------------------


def test_sim_is_a_qube_device_with_the_right_id() -> None:
    sim = SimulatedQube()
    assert isinstance(sim, QubeDevice)
    r = parse_reply(sim.transfer(build_command(0)))
    assert r.device_id == DEVICE_ID and r.device_ok and r.status == 0
    assert counts_to_pendulum_rad(r.encoder1) == pytest.approx(-math.pi)  # hanging, encoder1 zeroed down
    sim.device_id = 0
    assert not parse_reply(sim.transfer(build_command(0))).device_ok
    mode0 = sim.transfer(b"\x00" + bytes(16))
    assert mode0[:2] == b"\x00\x00" and len(mode0) == 17
    with pytest.raises(ValueError):
        sim.transfer(bytes(5))


def test_sim_counts_match_the_true_state() -> None:
    sim = SimulatedQube(period_s=0.007)
    sim.reset_state(alpha=0.4, theta=-0.3, theta_dot=2.0, alpha_dot=-1.0)
    for _ in range(20):
        r = parse_reply(sim.transfer(build_command(0, enable=False)))
        theta, alpha, theta_dot, _ = sim.state
        assert counts_to_arm_rad(r.encoder0) == pytest.approx(theta, abs=RAD_PER_COUNT)
        assert abs(wrap_angle(counts_to_pendulum_rad(r.encoder1) - alpha)) <= RAD_PER_COUNT
        assert r.arm_velocity_rad_s == pytest.approx(theta_dot, rel=0.01, abs=0.06)


def test_sim_lockstep_is_deterministic_and_clock_mode_follows_the_clock() -> None:
    def trace(sim: SimulatedQube) -> list[bytes]:
        return [sim.transfer(build_command((k * 37) % 400 - 200)) for k in range(100)]

    a = SimulatedQube(QubeParams.varied(3), seed=5, period_s=0.007, initial_noise=0.05)
    b = SimulatedQube(QubeParams.varied(3), seed=5, period_s=0.007, initial_noise=0.05)
    assert trace(a) == trace(b)
    assert a.time == pytest.approx(0.7)

    now = [10.0]
    c = SimulatedQube(clock=lambda: now[0])
    c.transfer(build_command(0))
    assert c.time == 0.0
    now[0] += 0.25
    c.transfer(build_command(0))
    assert c.time == pytest.approx(0.25)
    manual = SimulatedQube(period_s=0)
    manual.transfer(build_command(0))
    manual.advance(0.1)
    assert manual.time == pytest.approx(0.1)


def test_sim_command_acts_from_the_next_transfer_and_only_when_enabled() -> None:
    sim = SimulatedQube(period_s=0.007)
    sim.transfer(build_command(400, enable=False))
    for _ in range(20):
        sim.transfer(build_command(400, enable=False))
    assert sim.voltage == 0.0 and abs(sim.state[0]) < 1e-9  # disabled amplifier: no motion
    sim.transfer(build_command(400))
    assert sim.voltage == pytest.approx(command_to_voltage(400)) and abs(sim.state[0]) < 1e-9
    sim.transfer(build_command(400))
    assert sim.state[0] < 0.0
    sim.transfer(build_command(0, write_mask=0x00))  # mask 0: nothing changes
    assert sim.command == 400 and sim.enabled


def test_sim_encoder_reset_and_leds() -> None:
    sim = SimulatedQube(period_s=0.007)
    for _ in range(30):
        sim.transfer(build_command(300))
    r = parse_reply(sim.transfer(build_command(0, reset_encoders=True, leds=(999, 0, 0))))
    assert r.encoder0 > 0  # the reply of the resetting transfer still has the old counts
    assert sim.leds == (999, 0, 0)
    sim.advance(0.0)
    enc0, _ = sim.encoder_counts()
    assert enc0 == 0
    r = parse_reply(
        sim.transfer(build_command(0, reset_encoders=True, encoder_values=(100, -7), write_mask=0x60))
    )
    assert sim.encoder_counts() == (100, -7)


def test_sim_stall_at_the_end_stop() -> None:
    sim = SimulatedQube(period_s=0.01, arm_limit=1.0, stall_error_after_s=1.0)
    r = None
    for _ in range(60):  # -220 counts (-5.3 V) pushes theta positive into the stop
        r = parse_reply(sim.transfer(build_command(-220)))
    assert r is not None and r.stall_detected and not r.stall_error
    assert sim.state[0] == pytest.approx(1.0) and sim.state[2] == 0.0
    assert r.current_a == pytest.approx(-220 / 999 * 24 / 8.4, rel=0.01)  # stalled: I = V / Rm
    for _ in range(60):
        r = parse_reply(sim.transfer(build_command(-220)))
    assert r.stall_error and not sim.amplifier_active and sim.voltage == 0.0
    sim.transfer(build_command(0, enable=False))  # disabling the amplifier clears the stall error ([QEX])
    r = parse_reply(sim.transfer(build_command(0)))
    assert not r.stall_error and not r.stall_detected
    sim.forced_status = 0x01
    assert parse_reply(sim.transfer(build_command(0))).amplifier_fault


# --- options for realism: Coulomb friction, rig spread, wiring faults ---------------------------------------


def test_coulomb_friction_only_removes_energy_and_stops_a_swing() -> None:
    frictionless = replace(QubeParams(), Dr=0.0, Dp=0.0)
    d = QubeDynamics(replace(frictionless, Cr=1.5e-3, Cp=1e-4))
    d.set_state(0.3, math.pi - 0.5, 2.0, 0.0)
    last = d.energy()
    for _ in range(round(8.0 / 0.007)):
        d.step(0.0, 0.007, amplifier_on=False)
        assert d.energy() <= last + 1e-12
        last = d.energy()
    assert abs(d.state[3]) < 0.05 and abs(d.state[2]) < 0.05  # at rest after 8 s
    free = QubeDynamics(frictionless)
    free.set_state(0.3, math.pi - 0.5, 2.0, 0.0)
    run(free, 8.0, amplifier_on=False)
    assert abs(wrap_angle(free.state[1] - math.pi)) + abs(free.state[3]) > 0.3  # without friction: still swinging


def test_coulomb_friction_holds_the_arm_against_a_small_voltage() -> None:
    stiff = QubeDynamics(replace(QubeParams(), Cr=1.5e-3))  # 1.5 mN m is 0.3 V at stall (kt/Rm = 5 mN m/V)
    loose = QubeDynamics()
    for d in (stiff, loose):
        d.set_state(0.0, math.pi)
        run(d, 1.0, voltage=0.2)
    assert abs(stiff.theta) < 0.5 * abs(loose.theta)


def test_spread_params_are_deterministic_and_bounded() -> None:
    base = QubeParams()
    assert QubeParams.spread(4, 0.15) == QubeParams.spread(4, 0.15) != QubeParams.spread(5, 0.15)
    ratios = [getattr(QubeParams.spread(i, 0.15), n) / getattr(base, n) for i in range(50)
              for n in ("mr", "Lr", "mp", "Lp", "Dr", "Dp", "km")]
    assert min(ratios) >= 0.85 and max(ratios) <= 1.15 and max(ratios) - min(ratios) > 0.25
    with pytest.raises(ValueError):
        QubeParams.spread(1, 1.5)


@pytest.mark.parametrize(("fault", "arm_sign", "pendulum_sign"), [
    ({}, 1, 1),
    ({"reverse_motor": True}, -1, -1),
    ({"reverse_encoder0": True}, -1, 1),
    ({"reverse_encoder1": True}, 1, -1),
    ({"dead_encoder1": True}, 1, 0),
])
def test_wiring_faults(fault: dict, arm_sign: int, pendulum_sign: int) -> None:
    """A positive command counts encoder 0 up and first swings the pendulum's count up; each fault flips what it
    should (the tachometer follows encoder 0)."""
    sim = SimulatedQube(period_s=0.007, **fault)
    r0 = parse_reply(sim.transfer(build_command(0)))
    assert (r0.encoder0, r0.encoder1) == (0, 0)
    first_pendulum = 0
    for _ in range(6):
        r = parse_reply(sim.transfer(build_command(100)))
        if not first_pendulum and abs(r.encoder1) >= 2:
            first_pendulum = r.encoder1
    assert math.copysign(1, r.encoder0) == arm_sign and abs(r.encoder0) > 5
    assert (first_pendulum > 0) - (first_pendulum < 0) == pendulum_sign
    assert math.copysign(1, r.tach_counts_per_s) == arm_sign
