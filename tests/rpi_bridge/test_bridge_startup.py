"""Start-up checks of the bridge: calibration on purpose (a still window, kept across restarts, refused when it does
not match the rig) and the polarity and sensor self-test, on the simulated rig through the real control core."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from protocol import qube
from rpi_bridge.calibration import Calibration, CalibrationStore, decide, is_still
from rpi_bridge.control import LEDS, ControlConfig, ControlCore
from rpi_bridge.selftest import SelfTest, SelfTestConfig, judge
from services.qube_sim.clock import VirtualClock
from tests.rpi_bridge.recording import RecordingQube

PERIOD = qube.PERIOD_S


def make_core(store: CalibrationStore | None = None, recalibrate: bool = False, **device_options: object,
              ) -> tuple[ControlCore, RecordingQube, VirtualClock]:
    clock = VirtualClock()
    device = RecordingQube(seed=1, period_s=0, clock=clock, **device_options)
    return ControlCore(device, ControlConfig(), clock=clock, store=store, recalibrate=recalibrate), device, clock


def tick(core: ControlCore, clock: VirtualClock, n: int = 1) -> None:
    for _ in range(n):
        core.sense()
        core.act(None)
        clock.advance(PERIOD)


def until_started(core: ControlCore, clock: VirtualClock, seconds: float = 5.0) -> None:
    for _ in range(round(seconds / PERIOD)):
        tick(core, clock)
        if core.phase not in ("calibrating", "self_test"):
            return
    raise AssertionError(f"still {core.phase} after {seconds} s; events {core.events}")


# -- pure decisions -------------------------------------------------------------------------------------------------

def test_stillness_and_the_calibration_decision() -> None:
    assert is_still([(5, 100), (6, 101), (5, 100)], 2)
    assert not is_still([(5, 100), (5, 104)], 2) and not is_still([(0, 0), (9, 0)], 2) and not is_still([], 2)
    fresh = decide([(40, 7), (40, 7)], None)
    assert fresh.action == "calibrate" and (fresh.calibration.encoder0, fresh.calibration.encoder1) == (40, 7)
    stored = Calibration(12, 2048 * 3 + 5)  # counts wrap by whole turns of the pendulum
    kept = decide([(300, 5), (300, 5)], stored)
    assert kept.action == "keep" and kept.calibration == stored  # the arm's zero stays where it was
    refused = decide([(300, 5 + 200), (300, 5 + 200)], stored)
    assert refused.action == "refuse" and refused.calibration is None and "--recalibrate" in refused.reason
    assert "+35.2 deg" in refused.reason
    with pytest.raises(ValueError):
        decide([], None)


def test_calibration_angles() -> None:
    c = Calibration(100, 2000)
    theta, alpha = c.angles(100, 2000)
    assert theta == 0.0 and alpha == pytest.approx(-math.pi)
    theta, alpha = c.angles(100 - 512, 2000 + 1024)  # a quarter turn of the arm counter-clockwise, pendulum up
    assert theta == pytest.approx(math.pi / 2) and alpha == pytest.approx(0.0)


def test_store_round_trip_and_bad_files(tmp_path: Path) -> None:
    store = CalibrationStore.for_rig(tmp_path / "state", "rig7")
    assert store.load() is None
    store.save(Calibration(-3, 17, "2026-01-01T00:00:00"))
    assert store.path == tmp_path / "state" / "rig7-calibration.json"
    assert store.load() == Calibration(-3, 17, "2026-01-01T00:00:00")
    assert json.loads(store.path.read_text())["version"] == 1
    for bad in ("not json", '{"version": 2, "encoder0": 1, "encoder1": 2}', '{"version": 1, "encoder0": "x"}', "[]"):
        store.path.write_text(bad)
        assert store.load() is None  # logged and ignored: the bridge then calibrates only on a still rig
    store.clear()
    assert not store.path.exists()


def test_self_test_verdicts() -> None:
    up = [(0, 0), (3, 1), (9, 4), (15, 8)]
    assert judge(up).ok
    assert "encoder 0 (arm) counts backwards" in judge([(0, 0), (-3, 1), (-9, 4)]).detail
    assert "encoder 1 (pendulum) counts backwards" in judge([(0, 0), (3, -1), (9, -4)]).detail
    assert "motor leads are reversed" in judge([(0, 0), (-3, -1), (-9, -4)]).detail
    assert "did not move" in judge([(0, 0), (1, 0), (2, 3)]).detail
    assert "encoder 1 cable" in judge([(0, 0), (5, 0), (12, 1)]).detail
    # a loop that stalled while the negative half was held: the arm went far back, but the positive half decides
    stalled = [(0, 0), (1, 1), (3, 3), (7, 7), (12, 12), (10, 16), (-20, 19), (-55, 10)]
    assert judge(stalled).ok
    with pytest.raises(ValueError):
        judge([(0, 0)])
    with pytest.raises(ValueError):
        SelfTestConfig(pulse_counts=500)  # above 10 V


def test_self_test_sequence_is_a_small_doublet_and_stops_on_a_failure() -> None:
    cfg = SelfTestConfig()
    test = SelfTest(cfg)
    commands = []
    verdict = None
    counts = 0
    while verdict is None:
        command, verdict = test.step(counts, counts)
        commands.append(command)
        counts += 3
    assert verdict.ok
    assert max(abs(c) for c in commands) == cfg.pulse_counts == 83  # 2 V
    assert sum(commands) == 0  # out and back
    failing = SelfTest(cfg)
    verdict = None
    ticks = 0
    while verdict is None:
        _, verdict = failing.step(0, 0)  # nothing moves
        ticks += 1
    # every level tried (2, 3, 4, 5 V; each next one's baseline is the last reading of the one before), no return pulse
    levels = len(cfg.pulses())
    assert levels == 4 and not verdict.ok and ticks == levels * (2 * cfg.pulse_ticks + cfg.observe_ticks) + 1
    assert "did not move on a 208-count pulse (5.0 V after 2.0, 3.0, 4.0 V" in verdict.detail


# -- through the control core -----------------------------------------------------------------------------------

def test_start_up_calibrates_a_still_rig_then_self_tests_it(tmp_path: Path) -> None:
    store = CalibrationStore.for_rig(tmp_path, "rig0")
    core, device, clock = make_core(store)
    assert core.phase == "calibrating"
    until_started(core, clock)
    assert core.phase == "idle" and core.started
    assert [e[0] for e in core.events] == ["self_test", "idle"]
    assert "self-test passed" in core.events[-1][2]
    assert store.load() is not None
    assert max(abs(c) for c in device.commands) <= 83 and device.leds != LEDS["fault"]


def test_a_moving_pendulum_is_not_calibrated_and_resets_are_refused_until_it_hangs_still() -> None:
    core, device, clock = make_core()
    device.reset_state(alpha=math.pi - 0.6)  # swinging 34 deg
    core.request_reset(5)
    tick(core, clock, round(3.0 / PERIOD))
    assert core.phase == "calibrating" and core.calibration is None
    assert ("calibrating", 5, "reset 5 waits for the start-up checks") in core.events
    waiting = [e for e in core.events if e[0] == "calibrating" and e[1] == -1]
    assert waiting and "pendulum" in waiting[0][2] and "runs nothing until it hangs still" in waiting[0][2]
    assert not device.commands  # the amplifier stayed off
    device.reset_state()  # it has come to rest (hanging, at the calibration pose)
    for _ in range(round(4.0 / PERIOD)):
        tick(core, clock)
        if core.phase == "resetting":
            break
    assert core.phase == "resetting" and core.calibration is not None  # the pending reset is served


def test_calibration_is_kept_across_a_restart(tmp_path: Path) -> None:
    """A restart finds the arm where the last run left it (here 30 deg) and keeps its zero; calibrating again
    would have moved the zero to 30 deg."""
    store = CalibrationStore.for_rig(tmp_path, "rig0")
    core, _, clock = make_core(store)
    until_started(core, clock)
    arm = math.radians(30)
    restarted_device = RecordingQube(seed=1, period_s=0, clock=clock)
    restarted_device.reset_state(theta=arm)
    restarted = ControlCore(restarted_device, ControlConfig(), clock=clock, store=store)
    until_started(restarted, clock)
    assert restarted.phase == "idle" and "kept" in restarted.events[0][2]
    assert restarted.sense().theta == pytest.approx(arm, abs=0.1)  # (the self-test pulse moves it a little)
    again = ControlCore(restarted_device, ControlConfig(), clock=clock, store=store, recalibrate=True)
    until_started(again, clock)
    assert abs(again.sense().theta) < 0.1  # --recalibrate: the zero moves to where the arm is


def test_a_stored_calibration_that_does_not_match_is_refused(tmp_path: Path) -> None:
    store = CalibrationStore.for_rig(tmp_path, "rig0")
    store.save(Calibration(0, 300))  # the pendulum at rest would read 53 deg off hanging
    core, device, clock = make_core(store)
    core.request_reset(9)
    until_started(core, clock)
    assert core.phase == "fault" and core.refusal.startswith("calibration: the stored calibration does not match")
    assert any(e[0] == "reset_failed" and e[1] == 9 and "refuses to run" in e[2] for e in core.events)
    core.events.clear()
    core.request_reset(10)
    tick(core, clock, 3)
    assert core.phase == "fault" and core.events[0][:2] == ("reset_failed", 10)  # latched
    assert not device.commands and device.leds == LEDS["fault"]


@pytest.mark.parametrize(("fault", "message"), [
    ("reverse_motor", "motor leads are reversed"),
    ("reverse_encoder0", "encoder 0 (arm) counts backwards"),
    ("reverse_encoder1", "encoder 1 (pendulum) counts backwards"),
    ("dead_encoder1", "encoder 1 cable"),
])
def test_self_test_catches_wiring_faults_and_the_bridge_refuses_to_run(fault: str, message: str) -> None:
    core, device, clock = make_core(**{fault: True})
    core.request_reset(4)
    until_started(core, clock)
    assert core.phase == "fault" and core.refusal.startswith("self-test:") and message in core.refusal
    assert any(e[:2] == ("reset_failed", 4) for e in core.events)
    assert max(abs(c) for c in device.commands) <= 83 and len(device.commands) <= 20  # one small pulse only
    tick(core, clock, 100)
    assert core.phase == "fault" and not device.amplifier_active
    core.request_reset(5)
    tick(core, clock, 100)
    assert core.phase == "fault" and not device.amplifier_active  # no reset clears it: restart after fixing
