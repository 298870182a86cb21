"""The bridge's control loop on a simulated rig: deadline misses, late actions, the watchdog, faults and reset."""

from __future__ import annotations

import math
import queue
import threading
import time

import pytest

from protocol.codec import decode
from protocol.messages import QubeAction, QubeState, QubeStatus, QubeTelemetry
from rpi_bridge.control import ControlConfig, ControlCore
from rpi_bridge.frame import parse_command
from rpi_bridge.reset import ResetConfig
from rpi_bridge.runner import BridgeRunner
from services.qube_sim.clock import VirtualClock
from services.qube_sim.spi_peer import SimulatedQube

PERIOD = 0.007


class RecordingQube(SimulatedQube):
    """A simulated rig that also keeps every motor command it was sent (the real peer, plus a log)."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.commands: list[int] = []

    def transfer(self, frame: bytes) -> bytes:
        cmd = parse_command(frame)
        if cmd.enabled:
            self.commands.append(cmd.motor)
        return super().transfer(frame)


class RecordingCore(ControlCore):
    """The real control core, keeping every action the runner hands it."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.acted: list[int | None] = []

    def act(self, command: int | None) -> int:
        self.acted.append(command)
        return super().act(command)


def lockstep_core(config: ControlConfig | None = None) -> tuple[ControlCore, RecordingQube, VirtualClock]:
    clock = VirtualClock()
    device = RecordingQube(seed=1, period_s=0, clock=clock)
    return ControlCore(device, config or ControlConfig()), device, clock


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
    assert [e[0] for e in core.events] == ["resetting", "ready"]
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
    for _ in range(200):
        core.sense()
        core.act(None)
        clock.advance(PERIOD)
    assert ("reset_failed", 3) in [(e[0], e[1]) for e in core.events]
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
    device = RecordingQube(seed=2, period_s=0, clock=time.perf_counter)
    core = RecordingCore(device, ControlConfig(action_timeout_s=5.0))
    states: queue.Queue[QubeState] = queue.Queue()
    statuses: list[str] = []

    def publish(topic: str, payload: bytes, qos: int) -> None:
        msg = decode(payload, QubeState, QubeStatus, QubeTelemetry)
        if isinstance(msg, QubeState):
            states.put(msg)
        elif isinstance(msg, QubeStatus):
            statuses.append(msg.state)

    runner = BridgeRunner(core, "rig0", publish, deadline_s=0.005)
    stop = threading.Event()
    loop = threading.Thread(target=runner.run, args=(stop,), daemon=True)
    loop.start()
    runner.on_reset(1)
    answered = late = 0
    try:
        deadline = time.monotonic() + 30
        while answered + late < 300 and time.monotonic() < deadline:
            s = states.get(timeout=10)
            if s.phase not in ("ready", "running"):
                continue
            if (answered + late) % 10 == 9:  # every tenth state: answer 8 ms late with a marker command
                time.sleep(0.008)
                runner.on_action(QubeAction(rig_id="rig0", seq=s.seq, command=77))
                late += 1
            else:
                u = -(12.7 * s.theta - 563.3 * s.alpha + 13.3 * s.theta_dot - 39.0 * s.alpha_dot)
                runner.on_action(QubeAction(rig_id="rig0", seq=s.seq, command=max(-300, min(300, round(u)))))
                answered += 1
    finally:
        stop.set()
        loop.join(timeout=5)
    assert late == 30
    assert 77 not in core.acted, "a late action was applied"  # (the reset controller may send 77 itself)
    assert runner.slot.late >= 30  # every late answer was counted and dropped
    assert core.counters.misses >= 30  # each of those states got the safe action instead
    assert "ready" in statuses and statuses[-1] == "offline"
    telemetry = runner.telemetry()
    assert telemetry.latency_ms["n"] >= 200 and telemetry.latency_ms["p50"] < 5.0
