"""The model-based reset and self-test (rpi_bridge/plant.py, reset.py, selftest.py) on rigs outside ``lab``
(services/qube_sim/families.py): the LQR design, the hold against a sticky arm, a heavily damped swing-up, retries that
change strategy, and a self-test that passes sticky and heavy arms but still names every wiring fault."""

from __future__ import annotations

import math

import numpy as np
import pytest

from protocol import qube
from rpi_bridge.control import ControlConfig, ControlCore, with_model
from rpi_bridge.frame import build_command, parse_reply
from rpi_bridge.plant import FIRST_LQR_Q, LQR_Q, PlantModel, delayed, lqr_gains, zoh
from rpi_bridge.reset import LQR_GAINS, STRATEGIES, ResetConfig, ResetController, strategy
from rpi_bridge.velocity import VelocityFilter
from services.qube_sim import families
from services.qube_sim.clock import VirtualClock
from services.qube_sim.profile import RigProfile
from services.qube_sim.spi_peer import SimulatedQube

TICK = qube.PERIOD_S


def test_lqr_design_on_the_nominal_model_gives_the_gains_of_before() -> None:
    nominal = PlantModel()
    no_delay = lqr_gains(nominal, TICK, FIRST_LQR_Q, delay=False)
    assert no_delay[:4] == pytest.approx(LQR_GAINS, abs=0.05)  # LQR_GAINS has one decimal and no_delay[4] == 0.0
    k = lqr_gains(nominal, TICK, q_integral=1.0)  # what the hold uses: the delay and the integral in the state
    assert len(k) == 6 and k[5] > 0 and k[1] < 0
    # the closed loop of the delayed, integrating design is stable
    ad, bd = delayed(*zoh(*nominal.linearized(), TICK))
    az = np.zeros((6, 6))
    az[:5, :5], az[5, 0], az[5, 5] = ad, TICK, 1.0
    bz = np.vstack([bd, [[0.0]]])
    assert max(abs(np.linalg.eigvals(az - bz @ np.array([k])))) < 1.0


def test_model_from_a_profile() -> None:
    course = families.course()
    model = course.plant_model()
    assert model == PlantModel.from_profile(course.model_dump())
    assert (model.Dr, model.Dp, model.coulomb_arm, model.deadzone_v) == (1.5e-3, 5e-4, 0.0015, 0.05)
    assert PlantModel.from_profile({"name": "x", "km": 0.05}).kt == 0.05  # unknown keys ignored, kt follows km
    with pytest.raises(ValueError, match="mr must be positive"):
        PlantModel.from_profile({"mr": 0})
    with pytest.raises(ValueError, match="Dp must be a number"):
        PlantModel.from_profile({"Dp": "high"})


def hold_from(sim: SimulatedQube, ctl: ResetController, seconds: float) -> list[float]:
    """The reset controller on the rig for ``seconds``; the true arm angles."""
    tf, af = VelocityFilter(TICK), VelocityFilter(TICK)
    command, arm = 0, []
    for _ in range(round(seconds / TICK)):
        r = parse_reply(sim.transfer(build_command(command)))
        command, _ = ctl.step((r.theta, r.alpha, tf.update(r.theta), af.update(r.alpha)), TICK)
        arm.append(sim.state[0])
    return arm


def test_the_hold_brings_a_sticky_arm_back_inside_the_arm_band() -> None:
    """Arm friction 2.5x lab's, caught upright with the arm at 0.5 rad: friction compensation and the integral bring
    it back to the middle; without them it sticks on the way, where the LQR's arm feedback can no longer move it."""
    profile = families.family("arm_friction", 2.5)

    def run(**changes: float) -> list[float]:
        sim = SimulatedQube(profile.rig_params(0), period_s=TICK)
        sim.reset_state(theta=0.5, alpha=0.03)
        return hold_from(sim, ResetController(ResetConfig(model=profile.plant_model(), **changes)), 4.0)

    arm = run()
    assert max(abs(a) for a in arm) < math.radians(45) and abs(arm[-1]) < 0.05
    bare = run(friction_compensation=0.0, integral_weight=0.0)
    assert abs(bare[-1]) > 0.15


def swing_up_from_rest(profile: RigProfile, seed: int, seconds: float) -> tuple[str, float, ResetController]:
    """The reset controller (the profile's own model) on rig ``seed`` of ``profile``, hanging at rest: (last phase,
    seconds taken, controller)."""
    sim = SimulatedQube(profile.rig_params(seed), period_s=TICK, **profile.device_options())
    ctl = ResetController(ResetConfig(model=profile.plant_model()))
    tf, af = VelocityFilter(TICK), VelocityFilter(TICK)
    command, phase, ticks = 0, "swing_up", 0
    while ticks < round(seconds / TICK) and phase not in ("ready", "failed"):
        r = parse_reply(sim.transfer(build_command(command)))
        command, phase = ctl.step((r.theta, r.alpha, tf.update(r.theta), af.update(r.alpha)), TICK)
        ticks += 1
    return phase, ticks * TICK, ctl


def test_a_heavily_damped_pendulum_swings_up() -> None:
    """Pendulum damping 5x lab's: the energy target rises on turnarounds below horizontal too."""
    phase, _, ctl = swing_up_from_rest(families.family("Dp", 5.0), 0, 15.0)
    assert phase == "ready", ctl.failure


def test_a_pendulum_damped_10x_is_pumped_at_full_voltage_to_the_top() -> None:
    """Pendulum damping 10x lab's (Dp 5e-4, damping ratio 0.18): a model that damped pumps at full voltage from the
    start, pulled to the middle, and reaches the top (the pump of before turned back about 80 deg short). Not on
    every rig: this one does (docs/how-to/ood.md gives how often)."""
    profile = families.family("Dp", 10.0)
    assert profile.plant_model().damping_ratio == pytest.approx(0.176, abs=0.002)
    phase, seconds, ctl = swing_up_from_rest(profile, 0, 8.0)
    assert ctl.hard and phase == "ready", ctl.failure
    assert seconds < 8.0


def test_the_hard_pump_switches_on_its_own_prediction_horizon() -> None:
    """Pumping hard, the bang-bang direction follows alpha_dot*cos(alpha) at the state ``hard_prediction_ticks``
    ahead, not ``prediction_ticks`` (the gentle pump's): just past horizontal and rising, a pendulum predicted back
    below horizontal flips the full-voltage push."""
    model = PlantModel(Dp=5e-4)  # damped enough to pump hard from the start
    state = (0.0, 1.59, 0.0, -3.0)  # arm at rest in the middle, pendulum 1.59 rad from upright, rising

    def command(**changes: float) -> int:
        ctl = ResetController(ResetConfig(model=model, velocity_cutoff=None, **changes))
        assert ctl.hard
        return ctl.step(state, TICK)[0]

    now, ahead = command(hard_prediction_ticks=0.0), command(hard_prediction_ticks=2.0)
    assert abs(now) == abs(ahead) == ResetConfig().max_command and now == -ahead
    assert command(hard_prediction_ticks=0.0, prediction_ticks=2.0) == now
    for ticks in (-0.5, 6.0):
        with pytest.raises(ValueError, match="prediction_ticks"):
            ResetConfig(hard_prediction_ticks=ticks)


def test_each_retry_pumps_hard_in_its_own_way_inside_the_arm_limit() -> None:
    """The cycle a heavily damped pendulum settles into short of the top depends on the hard pump, so each retry
    pumps differently: no two strategies share prediction, pull, soft limit and braking, and a retry acting on the
    state now flips the standard pump's push where the pendulum's 1-tick prediction crosses horizontal. Every
    strategy's soft limit lies inside the bridge's arm limit, which ControlConfig checks for each."""
    pumps = {(c.hard_prediction_ticks, c.hard_centre, c.hard_soft_limit, c.hard_brake_accel)
             for c in (strategy(ResetConfig(), n)[1] for n in range(len(STRATEGIES)))}
    assert len(pumps) == len(STRATEGIES)
    assert all(limit < ControlConfig().arm_limit - math.radians(30) for _, _, limit, _ in pumps)
    ctl = ResetController(ResetConfig(model=PlantModel(Dp=5e-4), velocity_cutoff=None, settle_max_s=0.0))
    state = (0.0, 1.575, 0.0, -3.0)  # arm at rest in the middle, pendulum just past horizontal, rising
    commands = {}
    for failures in range(len(STRATEGIES)):
        ctl.reset(failures)  # pumping hard from the start (the model's damping); a retry's settling ends at once
        commands[ctl.strategy] = ctl.step(state, TICK)[0]
        assert ctl.hard and ctl.phase == "swing_up"
    assert commands["standard"] == -commands["wide"] and abs(commands["wide"]) == ResetConfig().max_command
    narrow = ResetConfig(arm_soft_limit=math.radians(60), hard_soft_limit=math.radians(60))
    with pytest.raises(ValueError, match=r"soft arm limit \(76 deg\)"):  # "patient" pumps inside 76 deg
        ControlConfig(arm_limit=math.radians(75), reset=narrow)


def test_course_damping_fails_early_with_one_line_naming_the_cause() -> None:
    """Quanser's course-file damping (Dp 5e-4 and Dr 1.5e-3): no pump within 10 V reaches the top
    (bench/results/swingup.json), so the attempt ends within seconds with the cause, not after its 15 s timeout."""
    phase, seconds, ctl = swing_up_from_rest(families.course(), 0, 15.0)
    assert phase == "failed" and seconds < 8.0
    assert "the swing-up cannot pump this pendulum to the top within 10 V" in ctl.failure
    assert "Dp 5.0e-04" in ctl.failure
    assert "\n" not in ctl.failure and "docs/how-to/ood.md" in ctl.failure


def test_retries_change_strategy_and_a_success_clears_the_count() -> None:
    clock = VirtualClock()
    device = SimulatedQube(period_s=0, clock=clock)
    reset = ResetConfig(timeout_s=0.05, settle_max_s=0.02)  # no swing-up can succeed this fast
    core = ControlCore(device, ControlConfig(calibration_window_s=0.05, reset=reset), clock=clock)
    while core.phase in ("calibrating", "self_test"):
        core.sense()
        clock.advance(TICK)
    used, failures = [], []
    for request in range(1, 7):
        core.events.clear()
        core.request_reset(request)
        while not any(e[0] == "reset_failed" for e in core.events):
            core.sense()
            clock.advance(TICK)
        used += [e[2] for e in core.events if e[0] == "resetting"]
        failures += [e[2] for e in core.events if e[0] == "reset_failed"]
    names = [name for name, _ in STRATEGIES]
    assert used == [f"strategy '{n}'" for n in [*names, names[-1]]]
    assert all(f"strategy '{n}'" in f for n, f in zip([*names, names[-1]], failures, strict=True))
    assert core.reset_failures == 5
    core.cfg = ControlConfig()  # a reset that can succeed: the count starts again
    core._reset_ctl = ResetController(ResetConfig())
    core.request_reset(7)
    for _ in range(round(20 / TICK)):
        if core.sense().awaits_action:
            break
        clock.advance(TICK)
    assert core.phase == "ready" and core.reset_failures == 0


def start_up(params: object, model: PlantModel | None = None, **wiring: bool) -> tuple[str, str]:
    """(phase after the start-up checks, the last event's detail) of a core on a rig with ``params``."""
    clock = VirtualClock()
    device = SimulatedQube(params, seed=0, period_s=0, clock=clock, **wiring)  # type: ignore[arg-type]
    config = ControlConfig(calibration_window_s=0.05)
    core = ControlCore(device, with_model(config, model) if model else config, clock=clock)
    for _ in range(round(5.0 / TICK)):
        core.sense()
        core.act(None)
        clock.advance(TICK)
        if core.phase not in ("calibrating", "self_test"):
            break
    return core.phase, core.events[-1][2]


@pytest.mark.parametrize(("parameter", "factor"), [("arm_friction", 3.0), ("arm_inertia", 4.0)])
def test_the_self_test_passes_sticky_and_heavy_arms_and_still_names_each_wiring_fault(parameter: str,
                                                                                         factor: float) -> None:
    profile = families.family(parameter, factor)
    params = profile.rig_params(0)
    for model in (None, profile.plant_model()):
        phase, detail = start_up(params, model)
        assert phase == "idle" and "self-test passed" in detail, detail
    for wiring, message in (("reverse_motor", "motor leads are reversed"),
                            ("reverse_encoder0", "encoder 0 (arm) counts backwards"),
                            ("reverse_encoder1", "encoder 1 (pendulum) counts backwards"),
                            ("dead_encoder1", "encoder 1 cable")):
        phase, detail = start_up(params, None, **{wiring: True})
        assert phase == "fault" and message in detail, (wiring, detail)


def test_the_hold_weights_are_a_setting_of_the_reset() -> None:
    """``ResetConfig.hold_weights`` (default rpi_bridge/plant.py LQR_Q) designs the hold's gains; four weights >= 0,
    not all zero, else a ValueError naming them."""
    model = PlantModel()
    assert ResetConfig(model=model).hold_gains() == lqr_gains(model, TICK, LQR_Q, q_integral=1.0)
    first = ResetConfig(model=model, hold_weights=FIRST_LQR_Q).hold_gains()
    assert first == lqr_gains(model, TICK, FIRST_LQR_Q, q_integral=1.0) and abs(first[0]) < abs(
        ResetConfig(model=model).hold_gains()[0])  # the first design's arm gain was the weaker
    for bad in ((1.0, 10.0, 0.0), (1.0, -1.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0)):
        with pytest.raises(ValueError, match="hold_weights must be four weights"):
            ResetConfig(hold_weights=bad)  # type: ignore[arg-type]
