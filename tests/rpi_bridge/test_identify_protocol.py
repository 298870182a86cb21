"""The identification protocol (rpi_bridge/identify.py) and the core's ``identifying`` phase: it stays inside the arm's
travel on lab, the combined family and the 4x arm inertia family; it never writes more than max_command and records
exactly what was written; a fault aborts it with its reason; the recording round-trips through its file and a corrupt
file is refused with one line. Protocols shortened (decay, prbs) to keep the file fast; the steps are the full ones."""

from __future__ import annotations

import gzip
import json
import math
from pathlib import Path

import pytest

from rpi_bridge.control import ControlConfig, ControlCore
from rpi_bridge.frame import MAX_COMMAND, STATUS_AMPLIFIER_FAULT, parse_command
from rpi_bridge.identify import Identification, IdentifyConfig, IdentifyFailed, Recording, RecordingError, drive
from rpi_bridge.selftest import SelfTestConfig
from services.qube_sim import families
from services.qube_sim.clock import VirtualClock
from services.qube_sim.profile import LAB, RigProfile
from services.qube_sim.spi_peer import SimulatedQube

SHORT = IdentifyConfig(decay_s=4.0, prbs_s=15.0, breakaway_repeats=1)


class Spy:
    """A SimulatedQube that remembers every motor word written with the amplifier on."""

    def __init__(self, device: SimulatedQube) -> None:
        self.device = device
        self.written: list[int] = []

    def transfer(self, frame: bytes) -> bytes:
        cmd = parse_command(frame)
        self.written.append(cmd.motor if cmd.enabled else 0)
        return self.device.transfer(frame)

    def close(self) -> None:
        pass


def rig(profile: RigProfile, seed: int = 1, config: IdentifyConfig = SHORT) -> tuple[ControlCore, Spy, VirtualClock]:
    clock = VirtualClock()
    device = SimulatedQube(profile.rig_params(seed), seed=seed, period_s=0, clock=clock, **profile.device_options())
    spy = Spy(device)
    # a 4x heavier arm moves too little on the self-test's 4-tick pulse: give it 8 ticks (the self-test is not tested
    # here)
    core = ControlCore(spy, ControlConfig(identify=config, self_test=SelfTestConfig(pulse_ticks=8)), clock=clock)
    return core, spy, clock


@pytest.mark.parametrize("profile", [LAB, families.combined(), families.family("arm_inertia", 4.0)],
                         ids=["lab", "combined", "arm_inertia-x4"])
def test_the_protocol_stays_inside_the_arm_travel(profile: RigProfile) -> None:
    core, spy, clock = rig(profile)
    worst = [0.0]

    def tick() -> None:
        clock.advance(core.cfg.period_s)
        worst[0] = max(worst[0], abs(core.device.device.state[0]))  # type: ignore[attr-defined]

    rec = drive(core, tick)
    assert rec.complete and core.phase == "idle"
    assert worst[0] < SHORT.arm_soft_limit, f"arm reached {math.degrees(worst[0]):.0f} deg"
    labels = [label for label, _, _ in rec.segments]
    for wanted in ("excite", "decay", "breakaway+", "breakaway-", "step+5V", "step-5V", "prbs"):
        assert wanted in labels
    assert max(abs(c) for c in rec.command) <= SHORT.max_command
    # the recording holds exactly the words written at each of its ticks (its last tick is the last transfer)
    assert rec.command == spy.written[-len(rec.command):]
    assert 40 < rec.rig_seconds < 80


def test_a_fault_aborts_it_with_its_reason() -> None:
    core, _, clock = rig(LAB)
    ticks = [0]

    def tick() -> None:
        clock.advance(core.cfg.period_s)
        ticks[0] += 1
        if ticks[0] == 1500:  # in the middle of the protocol, the amplifier reports a fault
            core.device.device.forced_status = STATUS_AMPLIFIER_FAULT  # type: ignore[attr-defined]

    with pytest.raises(IdentifyFailed, match="fault: amplifier fault"):
        drive(core, tick)
    assert core.phase == "fault"
    assert core.identification is not None and core.identification.failure == "fault: amplifier fault"
    assert not core.identification.recording().complete


def test_a_reset_request_aborts_it_and_requests_wait_for_the_start_up() -> None:
    core, _, clock = rig(LAB)
    core.request_identify(7)
    assert core.identify_pending
    for _ in range(400):
        clock.advance(core.cfg.period_s)
        core.sense()
    assert core.phase == "identifying" and core.identification is not None
    core.request_reset(8)
    clock.advance(core.cfg.period_s)
    core.sense()
    assert core.phase == "resetting"
    assert core.identification.failure == "a reset (8) was requested"


def test_the_protocol_alone_brakes_a_fast_arm_and_aborts_past_the_soft_limit() -> None:
    ident = Identification(IdentifyConfig())
    assert ident.step((0.0, math.pi, 0.0, 0.0), 0.007) != ident.config.max_command
    # heading out at 20 rad/s from 30 deg: it cannot stop at 100 rad/s^2 inside 80 deg, so full command against it
    assert ident.step((math.radians(30), math.pi, 20.0, 0.0), 0.007) == ident.config.max_command
    assert ident.step((math.radians(85), math.pi, 1.0, 0.0), 0.007) == 0
    assert ident.done and "past the protocol's 80 deg soft limit" in ident.failure
    with pytest.raises(ValueError, match="max_command"):
        IdentifyConfig(max_command=MAX_COMMAND + 1)


def test_a_recording_round_trips_and_a_corrupt_file_is_refused_with_one_line(tmp_path: Path) -> None:
    ident = Identification(SHORT)
    for k in range(50):
        ident.step((0.01 * k, math.pi - 0.02 * k, 0.0, 0.0), 0.007)
    rec = ident.recording(rig="rig3")
    for name in ("r.json", "r.json.gz"):
        rec.save(tmp_path / name)
        assert Recording.load(tmp_path / name) == rec
    bad = json.loads((tmp_path / "r.json").read_text())
    bad["command"] = bad["command"][:-1]
    (tmp_path / "short.json").write_text(json.dumps(bad))
    (tmp_path / "trunc.json.gz").write_bytes(gzip.compress(b'{"period_s": 0.007')[:-5])
    (tmp_path / "list.json").write_text("[1, 2]")
    for name, expected in (("short.json", "one entry per tick"), ("trunc.json.gz", "not readable JSON"),
                           ("list.json", "expected a JSON object"), ("missing.json", "not readable JSON")):
        with pytest.raises(RecordingError, match=expected) as err:
            Recording.load(tmp_path / name)
        assert "\n" not in str(err.value)


def test_another_attempt_excites_with_the_next_prbs_sequence_also_when_asked_over_mqtt(amqtt_broker: str) -> None:
    """A host that refused a recording's fit asks again with ``attempt`` 1 (QubeIdentify): the bridge runs the
    protocol with the next PRBS sequence. In process, its PRBS commands differ from attempt 0's; over a real broker,
    the rig's recording says which sequence it ran."""
    import threading

    from protocol.mqtt import BrokerAddress, MqttConnection
    from protocol.transport import connector
    from rpi_bridge.service import BridgeService
    from worker.identify import request_recording

    def prbs(rec: Recording) -> list[int]:
        (a, b), = [(a, b) for label, a, b in rec.segments if label == "prbs"]
        return rec.command[a:b]

    recorded = []
    for attempt in (0, 1):
        core, _, clock = rig(LAB)
        recorded.append(drive(core, lambda core=core, clock=clock: clock.advance(core.cfg.period_s), attempt=attempt))
    assert [r.config["seed"] for r in recorded] == [1, 2] and prbs(recorded[0]) != prbs(recorded[1])

    clock = VirtualClock()
    device = SimulatedQube(LAB.rig_params(1), seed=1, period_s=0, clock=clock)
    service = BridgeService(device, "rigA", connector(BrokerAddress.parse(amqtt_broker)), ControlConfig(identify=SHORT),
                            lockstep=True, advance=clock.advance, clock=clock, client_prefix="identify-attempt")
    loop = threading.Thread(target=service.run, daemon=True)
    loop.start()
    conn = MqttConnection(BrokerAddress.parse(amqtt_broker), client_id="identify-attempt-host").start()
    try:
        rec = request_recording(conn, "rigA", 120.0, progress=lambda line: None, attempt=1)
    finally:
        conn.stop()
        service.stop_event.set()
        loop.join(10)
    assert rec.complete and rec.config["seed"] == 2 and 40 < rec.rig_seconds < 80
