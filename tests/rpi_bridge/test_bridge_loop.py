"""The bridge's control loop on a simulated rig: deadline misses, late actions, the watchdog, faults and reset."""

from __future__ import annotations

import math
import threading

import pytest

from protocol import qube
from protocol.codec import decode
from protocol.messages import QubeAction, QubeState, QubeStatus, QubeTelemetry
from rpi_bridge.control import ControlConfig, ControlCore
from rpi_bridge.frame import RAD_PER_COUNT, build_reply
from rpi_bridge.reset import ResetConfig
from rpi_bridge.runner import BridgeRunner, InjectedTiming
from services.qube_sim.clock import VirtualClock
from tests.paths import ROOT
from tests.rpi_bridge.recording import RecordingQube

PERIOD = qube.PERIOD_S


class RecordingCore(ControlCore):
    """The real control core, keeping every action the runner hands it."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.acted: list[int | None] = []

    def act(self, command: int | None, deadline: float | None = None) -> int:
        self.acted.append(command)
        return super().act(command, deadline)


def lockstep_core(config: ControlConfig | None = None, **device_options: object,
                  ) -> tuple[ControlCore, RecordingQube, VirtualClock]:
    clock = VirtualClock()
    device = RecordingQube(seed=1, period_s=0, clock=clock, **device_options)
    return ControlCore(device, config or ControlConfig(), clock=clock), device, clock


def until_ready(core: ControlCore, clock: VirtualClock, request_id: int = 1, ticks: int = 5000):
    core.request_reset(request_id)
    for _ in range(ticks):
        s = core.sense()
        if s.awaits_action:
            return s
        core.act(None)
        clock.advance(PERIOD)
    raise AssertionError(f"no ready state; events {core.events}")


def hold_policy(s) -> int:
    """A crude bang-bang balance controller with the task's actions (LQR sign)."""
    u = -(12.7 * s.theta - 563.3 * s.alpha + 13.3 * s.theta_dot - 39.0 * s.alpha_dot)
    return 60 if u > 20 else (-60 if u < -20 else 0)


def test_reset_swings_up_and_hands_over_then_the_episode_runs() -> None:
    core, device, clock = lockstep_core()
    s = until_ready(core, clock, request_id=7)
    assert s.phase == "ready" and s.episode == 7 and abs(s.alpha) < math.radians(5)
    assert [e[0] for e in core.events] == ["calibrating", "self_test", "idle", "resetting", "ready"]
    for _ in range(500):
        core.act(hold_policy(s))
        clock.advance(PERIOD)
        s = core.sense()
        assert s.phase == "running" and s.awaits_action
    assert core.counters.applied == 500 and core.counters.misses == 0
    assert set(device.commands[-400:]) <= {-60, 0, 60}


def test_a_reset_that_fails_reports_so() -> None:
    core, _, clock = lockstep_core(ControlConfig(reset=ResetConfig(timeout_s=0.3)))
    core.request_reset(3)
    for _ in range(1000):  # start-up checks (about 1.2 s), 0.3 s of swing-up, up to 3 s holding the arm still
        core.sense()
        core.act(None)
        clock.advance(PERIOD)
        if any(e[0] == "reset_failed" for e in core.events):
            break
    assert any(e[:2] == ("reset_failed", 3) and "not held upright within 0 s (strategy 'standard'" in e[2]
               for e in core.events)
    assert core.phase == "idle"


def test_fall_ends_the_episode_without_counting_misses() -> None:
    core, _, clock = lockstep_core()
    s = until_ready(core, clock)
    for _ in range(2000):  # push one way until the pendulum falls out of the 7.5 deg band
        core.act(300)
        clock.advance(PERIOD)
        s = core.sense()
        if not s.awaits_action:
            break
    assert s.phase == "fallen" and abs(s.alpha) > math.radians(7.5)
    assert core.counters.misses == 0


def test_watchdog_disables_the_amplifier_when_actions_stop() -> None:
    core, device, clock = lockstep_core(ControlConfig(action_timeout_s=0.1))
    s = until_ready(core, clock)
    core.act(hold_policy(s))
    for _ in range(30):  # 30 ticks x 7 ms > 0.1 s without any action
        clock.advance(PERIOD)
        s = core.sense()
        if s.phase == "fault":
            break
        core.act(None)
    assert s.phase == "fault" and "watchdog" in core.fault_reason
    assert core.counters.misses >= 10
    core.sense()
    assert not device.amplifier_active


@pytest.mark.parametrize(
    ("inject", "reason"),
    [
        (lambda d: setattr(d, "device_id", 0x0000), "wrong device id"),
        (lambda d: setattr(d, "forced_status", 0x01), "amplifier fault"),
        (lambda d: d.reset_state(alpha=0.0, theta=2.1), "past the 110 deg limit"),
    ],
)
def test_faults_disable_the_amplifier_and_a_reset_clears_them(inject, reason: str) -> None:
    core, device, clock = lockstep_core()
    s = until_ready(core, clock)
    core.act(hold_policy(s))
    inject(device)
    clock.advance(PERIOD)
    s = core.sense()
    assert s.phase == "fault" and reason in core.fault_reason, core.fault_reason
    assert not s.awaits_action and core.counters.faults == 1
    core.sense()
    assert not device.amplifier_active
    # Cause gone + reset request: the rig runs again.
    device.device_id, device.forced_status = 0x0309, 0
    device.reset_state()
    s = until_ready(core, clock, request_id=2)
    assert s.episode == 2 and device.amplifier_active


def test_real_time_loop_counts_misses_and_never_applies_a_late_action() -> None:
    """The real-time loop (not lockstep) on a stepped clock: the worker answers every state 0.5-4 ms after it is
    published, and every tenth one 8 ms late (past the 5 ms deadline) with a marker command. Each late answer is
    counted and dropped, its state gets the safe action, and the marker never reaches the motor. The clock moves
    only when the worker answers or the loop sleeps, so the outcome does not depend on the machine's speed (how
    fast real answers are is bench/latency.py's business)."""
    clock = SteppedClock()
    device = RecordingQube(seed=2, period_s=0, clock=clock)
    core = RecordingCore(device, ControlConfig(action_timeout_s=5.0), clock=clock)
    statuses: list[str] = []
    stop = threading.Event()
    answered = late = 0
    runner: BridgeRunner

    def sleep(seconds: float) -> None:
        clock.now += seconds

    def publish(topic: str, payload: bytes, qos: int) -> None:
        nonlocal answered, late
        msg = decode(payload, QubeState, QubeStatus, QubeTelemetry)
        if isinstance(msg, QubeStatus):
            statuses.append(msg.state)
        if not isinstance(msg, QubeState) or msg.phase not in ("ready", "running"):
            return
        if (answered + late) % 10 == 9:  # every tenth state: answer 8 ms late with a marker command
            clock.now += 0.008
            runner.on_action(QubeAction(rig_id="rig0", seq=msg.seq, command=77))
            late += 1
        else:
            clock.now += 0.0005 + 0.0035 * ((answered * 7) % 8) / 7
            u = -(12.7 * msg.theta - 563.3 * msg.alpha + 13.3 * msg.theta_dot - 39.0 * msg.alpha_dot)
            runner.on_action(QubeAction(rig_id="rig0", seq=msg.seq, command=max(-300, min(300, round(u)))))
            answered += 1
        if answered + late >= 300:
            stop.set()

    runner = BridgeRunner(core, "rig0", publish, deadline_s=0.005, clock=clock, sleep=sleep)
    runner.on_reset(1)
    runner.run(stop, max_ticks=5000)
    assert (answered, late) == (270, 30), core.events
    assert 77 not in core.acted, "a late action was applied"  # (the reset controller may send 77 itself)
    assert runner.slot.late == 30  # every late answer was counted and dropped
    assert core.counters.misses >= 30  # each of those states got the safe action instead
    assert core.counters.late_at_motor == 0  # every answer in time was written in time
    assert "ready" in statuses and statuses[-1] == "offline"
    assert runner.telemetry().latency_ms["n"] == 270
    assert runner.telemetry().latency_ms["max"] <= 4.0 + 1e-6


# -- the deadline held at the motor -------------------------------------------------------------------------------

class SteppedClock:
    """A clock the test moves by hand (seconds)."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def running_core(clock: SteppedClock) -> tuple[RecordingCore, RecordingQube]:
    """A core in the running phase on a rig whose physics follows ``clock``."""
    device = RecordingQube(seed=1, period_s=0, clock=clock)
    core = RecordingCore(device, ControlConfig(), clock=clock)
    core.request_reset(1)
    for _ in range(5000):
        s = core.sense()
        if s.awaits_action:
            break
        core.act(None)
        clock.now += PERIOD
    core.act(hold_policy(s))
    return core, device


def test_an_action_is_written_only_within_the_deadline_of_its_states_read() -> None:
    clock = SteppedClock()
    core, device = running_core(clock)
    clock.now += PERIOD
    s = core.sense()
    deadline = s.t + 0.007
    clock.now = deadline - 1e-4  # in time, just: written
    written = len(device.commands)
    assert core.act(55, deadline) == 55 and device.commands[-1] == 55 and len(device.commands) == written + 1
    assert core.write_latencies[-1] == pytest.approx(0.007 - 1e-4)
    clock.now += PERIOD
    s = core.sense()
    clock.now = s.t + 0.007 + 1e-4  # arrived in time (the runner's slot accepted it), but the write would be late
    misses, written = core.counters.misses, len(device.commands)
    assert core.act(77, s.t + 0.007) == 0  # the safe action instead
    assert 77 not in device.commands[written:] and device.commands[-1] == 0  # (the reset's hold may have sent 77)
    assert core.counters.late_at_motor == 1 and core.counters.misses == misses + 1


def test_the_runner_passes_the_deadline_of_the_read_to_the_motor() -> None:
    """A loop thread that wakes up late (here: the worker's answer makes publishing take 9 ms) writes nothing
    late, although the action arrived within 7 ms."""
    clock = SteppedClock()
    core, device = running_core(clock)
    runner: BridgeRunner

    def slow_publish(topic: str, payload: bytes, qos: int) -> None:
        msg = decode(payload, QubeState, QubeStatus, QubeTelemetry)
        if isinstance(msg, QubeState) and msg.phase == "running":
            clock.now += 0.003
            runner.on_action(QubeAction(rig_id="rig0", seq=msg.seq, command=77))  # arrives at +3 ms: accepted
            clock.now += 0.006  # the loop gets the CPU back at +9 ms

    runner = BridgeRunner(core, "rig0", slow_publish, deadline_s=0.007, clock=clock)
    clock.now += PERIOD
    written = len(device.commands)  # (the reset's hold may have sent 77 itself)
    runner.tick(clock.now)
    assert runner.slot.late == 0 and 77 not in device.commands[written:]
    assert core.counters.late_at_motor == 1 and core.counters.misses == 1
    assert runner.telemetry().late_at_motor == 1


class TurningArm:
    """A QUBE device whose arm turns at a constant ``speed`` (rad/s) in the time of ``clock``."""

    def __init__(self, clock: SteppedClock, speed: float) -> None:
        self.clock, self.speed, self.t0 = clock, speed, clock()

    def transfer(self, frame: bytes) -> bytes:
        return build_reply(encoder0=round(-self.speed * (self.clock() - self.t0) / RAD_PER_COUNT))

    def close(self) -> None:
        pass


def test_the_measured_period_feeds_the_velocity_filters() -> None:
    """Ticks alternating 2 and 12 ms: fed the measured period, the 50 rad/s filter is exact for a steady turn (to
    the encoder's quantisation); fed the nominal 7 ms it would swing by about +-12 %."""
    clock = SteppedClock()
    core = ControlCore(TurningArm(clock, 5.0), ControlConfig(), clock=clock)
    estimates = []
    for k in range(200):
        clock.now += 0.002 if k % 2 else 0.012
        estimates.append(core.sense().theta_dot)
    settled = estimates[100:]
    assert max(abs(v - 5.0) for v in settled) < 0.1, (min(settled), max(settled))
    assert sorted(core.periods)[0] == pytest.approx(0.002) and sorted(core.periods)[-1] == pytest.approx(0.012)


# -- the first state of an episode is actionable ---------------------------------------------------------------

def test_the_first_ready_state_awaits_an_action_in_process_and_through_the_runner() -> None:
    core, _, clock = lockstep_core()
    states: list[QubeState] = []
    runner: BridgeRunner

    def answer(topic: str, payload: bytes, qos: int) -> None:
        msg = decode(payload, QubeState, QubeStatus, QubeTelemetry)
        if isinstance(msg, QubeState) and msg.phase in ("ready", "running"):
            states.append(msg)
            runner.on_action(QubeAction(rig_id="rig0", seq=msg.seq, command=hold_policy(msg)))

    runner = BridgeRunner(core, "rig0", answer, lockstep=True, advance=clock.advance)
    runner.on_reset(1)
    stop = threading.Event()
    runner.run(stop, max_ticks=700)
    first = states[0]
    assert first.phase == "ready" and first.seq == min(s.seq for s in states)
    assert runner.slot.late == 0 and core.counters.applied == len(states)  # every state's action applied
    assert len(states) > 100 and core.counters.misses == 0


# -- safety: stall detection, the arm limit in every phase, voltage caps, LEDs -------------------------------------

def test_a_stall_detected_during_the_reset_disables_the_amplifier() -> None:
    """An obstacle (end stops at +-20 deg, e.g. a cable) blocks the swing-up: the QUBE flags "stall detected" and
    the bridge disables the amplifier after 0.1 s, long before the QUBE's own stall error (5 s)."""
    core, device, clock = lockstep_core(arm_limit=math.radians(20))
    core.request_reset(1)
    first_stall = None
    for k in range(3000):
        clock.advance(PERIOD)
        core.sense()
        if first_stall is None and device.stall_detected:
            first_stall = k
        if core.phase == "fault":
            break
        core.act(None)
    assert core.phase == "fault" and "stall detected" in core.fault_reason, core.fault_reason
    assert first_stall is not None and (k - first_stall) * PERIOD < 0.2
    clock.advance(PERIOD)
    core.sense()
    assert not device.amplifier_active


def test_the_arm_limit_faults_during_a_reset_too() -> None:
    core, device, clock = lockstep_core()
    core.request_reset(1)
    while core.phase != "resetting":
        core.sense()
        core.act(None)
        clock.advance(PERIOD)
    device.reset_state(theta=math.radians(112), alpha=math.pi)
    clock.advance(PERIOD)
    s = core.sense()
    assert s.phase == "fault" and "past the 110 deg limit" in core.fault_reason
    clock.advance(PERIOD)
    core.sense()
    assert not device.amplifier_active


def test_voltage_caps_follow_the_manual() -> None:
    from rpi_bridge.__main__ import main as bridge_main

    with pytest.raises(ValueError, match=r"1\.\.416"):
        ControlConfig(max_command=500)
    assert bridge_main(["--max-command", "999"]) == 2
    core, device, clock = lockstep_core(ControlConfig(max_command=416))
    s = until_ready(core, clock)
    for _ in range(300):
        core.act(999 if s.alpha > 0 else -999)  # a worker asking for full scale
        clock.advance(PERIOD)
        s = core.sense()
        if not s.awaits_action:
            break
    assert device.commands and max(abs(c) for c in device.commands) <= 416  # swing-up, hold and actions


def test_each_phase_has_its_own_led_colour_documented_in_the_rpi_readme() -> None:

    from rpi_bridge.control import LEDS

    colours = list(LEDS.values())
    assert len(set(colours)) == len(colours)
    assert set(LEDS) == {"calibrating", "self_test", "idle", "resetting", "identifying", "ready", "running", "fallen",
                         "fault", "off"}
    readme = (ROOT / "deploy" / "rpi" / "README.md").read_text()
    for phase, (r, g, b) in LEDS.items():
        assert f"| `{phase}` | {r}, {g}, {b} |" in readme, phase
    core, device, clock = lockstep_core()
    seen = {}
    core.request_reset(1)
    for _ in range(800):
        s = core.sense()
        seen[s.phase] = device.leds  # the LEDs written by the previous frame of that phase
        core.act(hold_policy(s) if s.awaits_action else None)
        clock.advance(PERIOD)
    core.sense()
    assert seen["running"] == LEDS["running"] and device.leds == LEDS[core.phase]


# -- the simulated rig under the real loop's timing ----------------------------------------------------------------

def test_injected_timing_draws_delays_and_misses() -> None:
    t = InjectedTiming((0.001, 0.007), miss_rate=0.1, seed=3)
    draws = [t.draw() for _ in range(2000)]
    delays = [d for d in draws if d is not None]
    assert 150 < draws.count(None) < 250 and t.injected_misses == draws.count(None)
    assert 0.001 <= min(delays) and max(delays) <= 0.007 and 0.0035 < sum(delays) / len(delays) < 0.0045
    assert InjectedTiming.parse("0:7", 0.003).delay_s == (0.0, 0.007)
    for bad in ("7:0", "a:b", "1:2:3"):
        with pytest.raises(ValueError):
            InjectedTiming.parse(bad, 0.0)
    with pytest.raises(ValueError):
        InjectedTiming((0.0, 0.001), miss_rate=1.5)


def test_a_lockstep_rig_with_injected_timing_writes_each_action_after_its_delay() -> None:
    core, _, clock = lockstep_core()
    timing = InjectedTiming((0.002, 0.006), miss_rate=0.05, seed=1)
    runner: BridgeRunner

    def answer(topic: str, payload: bytes, qos: int) -> None:
        msg = decode(payload, QubeState, QubeStatus, QubeTelemetry)
        if isinstance(msg, QubeState) and msg.phase in ("ready", "running"):
            runner.on_action(QubeAction(rig_id="rig0", seq=msg.seq, command=hold_policy(msg)))

    runner = BridgeRunner(core, "rig0", answer, lockstep=True, advance=clock.advance, timing=timing)
    runner.on_reset(1)
    runner.run(threading.Event(), max_ticks=900)
    latencies = list(core.write_latencies)
    assert len(latencies) > 100 and min(latencies) >= 0.002 - 1e-9 and max(latencies) <= 0.006 + 1e-9
    assert core.counters.misses >= timing.injected_misses > 0  # each lost action got the safe one
    assert core.periods[-1] == pytest.approx(PERIOD)  # the read-to-read period stays 7 ms
    with pytest.raises(ValueError):
        BridgeRunner(core, "rig0", answer, lockstep=False, timing=timing)


def test_a_reset_brings_back_an_arm_that_came_to_rest_past_the_limit() -> None:
    """After an arm-limit fault the amplifier is off and the arm coasts to rest near the stop: the next reset
    brings it back and swings up (a reset that let it go further out would still fault)."""
    core, device, clock = lockstep_core()
    s = until_ready(core, clock)
    device.reset_state(theta=math.radians(113), alpha=math.pi)  # at rest past the limit, as after a fault
    clock.advance(PERIOD)
    assert core.sense().phase == "fault"
    s = until_ready(core, clock, request_id=2)
    assert s.phase == "ready" and s.episode == 2 and abs(s.theta) < math.radians(45)
    assert max(abs(c) for c in device.commands) <= 416


def test_a_reset_requested_while_the_arm_still_coasts_out_after_a_fault_brakes_it_and_brings_it_back() -> None:
    """The pendulum falls with the arm swinging out at 6 rad/s: the amplifier goes off (fallen), the arm coasts past
    110 deg (fault), and the reset requested at once brakes it and brings it back, although it first moves some
    degrees further out."""
    core, device, clock = lockstep_core()
    s = until_ready(core, clock)
    core.act(0)  # running
    device.reset_state(theta=math.radians(70), alpha=math.pi, theta_dot=6.0)
    phases = []
    while s.phase != "fault" and len(phases) < 100:
        clock.advance(PERIOD)
        s = core.sense()
        phases.append(s.phase)
        core.act(None)
    assert phases[0] == "fallen" and s.phase == "fault" and device.state[2] > 2.0
    clock.advance(PERIOD)  # the worker's reset request comes a tick later
    s = until_ready(core, clock, request_id=2)
    assert s.phase == "ready" and abs(s.theta) < math.radians(45)
