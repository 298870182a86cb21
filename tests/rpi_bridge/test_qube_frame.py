"""QUBE-Servo 2 SPI frame codec, velocity filter and SPI device, against values worked out from the data
sheet."""

from __future__ import annotations

import math
import subprocess
import sys
import types

import pytest

from rpi_bridge import frame as qf
from rpi_bridge.device import QubeDevice, SpidevDevice
from rpi_bridge.frame import (
    build_command,
    build_reply,
    counts_to_arm_rad,
    counts_to_pendulum_rad,
    parse_command,
    parse_reply,
)
from rpi_bridge.velocity import VelocityFilter


def reply_bytes(
    dev: bytes = b"\x03\x09",
    enc0: bytes = b"\x00\x00\x00",
    enc1: bytes = b"\x00\x00\x00",
    tach: bytes = b"\x7f\xff\xff",
    status: int = 0,
    current: bytes = b"\x1f\xfe",
) -> bytes:
    """A MISO frame assembled by hand from [DS] Table 2 (independent of build_reply)."""
    raw = dev + enc0 + enc1 + tach + bytes([status]) + current + b"\x00\x00\x00"
    assert len(raw) == 17
    return raw


# --- command frame ([DS] Table 2, Table 3, p.2) -------------------------------------------------------------


def test_command_layout_and_enable_bit() -> None:
    raw = build_command(500)
    assert len(raw) == 17
    assert raw[0] == 0x01 and raw[1] == 0x00  # mode 1, padding
    assert raw[2] == 0x03  # write motor + motor enable
    assert raw[3:15] == bytes(12)  # LEDs and encoder sets untouched (mask bits clear)
    assert raw[15:17] == b"\x81\xf4"  # [DS] example: 0x81F4 = enabled, 500 (50 % duty)


@pytest.mark.parametrize(
    ("motor", "word"),
    [
        (0, b"\x80\x00"),
        (1, b"\x80\x01"),
        (999, b"\x83\xe7"),
        (-1, b"\xff\xff"),
        (-999, b"\xfc\x19"),
        (-500, b"\xfe\x0c"),
    ],
)
def test_motor_word_twos_complement_with_bit15(motor: int, word: bytes) -> None:
    raw = build_command(motor)
    assert raw[15:17] == word
    assert raw[15] & 0x80  # bit 15 set: amplifier enabled


def test_disabled_motor_word_is_zero() -> None:
    assert build_command(0, enable=False)[15:17] == b"\x00\x00"
    assert build_command(-700, enable=False)[15:17] == b"\x00\x00"
    assert build_command(300, enable=False)[2] == 0x03  # the enable bit is still written (as off)


@pytest.mark.parametrize("bad", [1000, -1000, 5000, 1.5, "1", None, True])
def test_motor_out_of_range_or_not_int(bad: object) -> None:
    with pytest.raises(ValueError, match="motor command"):
        build_command(bad)  # type: ignore[arg-type]


def test_clamp_command_helper() -> None:
    assert qf.clamp_command(1234.4) == 999
    assert qf.clamp_command(-1e9) == -999
    assert qf.clamp_command(12.6) == 13
    assert qf.clamp_command(500, limit=400) == 400
    assert qf.clamp_command(float("nan")) == 0
    assert qf.clamp_command(float("-inf")) == -999


def test_led_bytes_and_mask() -> None:
    raw = build_command(0, leds=(999, 0, 500))
    assert raw[2] == 0x1F  # 0b00011111: red, green, blue, enable, motor
    assert raw[3:5] == b"\x03\xe7"  # red 999
    assert raw[5:7] == b"\x00\x00"  # green 0
    assert raw[7:9] == b"\x01\xf4"  # blue 500
    with pytest.raises(ValueError, match="LED"):
        build_command(0, leds=(1000, 0, 0))
    with pytest.raises(ValueError, match="LED"):
        build_command(0, leds=(0, -1, 0))


def test_encoder_reset_mask_and_fields() -> None:
    raw = build_command(0, reset_encoders=True)
    assert raw[2] == 0x63  # 0b01100011: set encoder1, set encoder0, enable, motor
    assert raw[9:15] == bytes(6)
    raw = build_command(0, reset_encoders=True, encoder_values=(-1, 0x123456))
    assert raw[9:12] == b"\xff\xff\xff" and raw[12:15] == b"\x12\x34\x56"


def test_quanser_reset_frame_with_explicit_mask() -> None:
    # [QEX] resetQUBEServo(): mask 0b01111111, encoders 0, amplifier disabled (clears a stall error)
    raw = build_command(0, enable=False, leds=(0, 0, 0), reset_encoders=True, write_mask=0x7F)
    assert raw[:3] == b"\x01\x00\x7f" and raw[3:] == bytes(14)
    assert build_command(0, write_mask=0x00)[2] == 0x00
    with pytest.raises(ValueError, match="write mask"):
        build_command(0, write_mask=0x80)


def test_command_round_trip() -> None:
    for kwargs in (
        dict(motor=-999),
        dict(motor=999, leds=(1, 2, 3)),
        dict(motor=-1, enable=False, reset_encoders=True),
        dict(motor=123, reset_encoders=True, encoder_values=(-8388608, 8388607), write_mask=0x41),
    ):
        cmd = parse_command(build_command(**kwargs))  # type: ignore[arg-type]
        enable = kwargs.get("enable", True)
        assert cmd.mode == 0x01
        assert cmd.enabled is enable
        assert cmd.motor == (kwargs["motor"] if enable else 0)
        assert cmd.leds == kwargs.get("leds", (0, 0, 0))
        assert (cmd.encoder0_set, cmd.encoder1_set) == kwargs.get("encoder_values", (0, 0))
    cmd = parse_command(build_command(-999))
    assert cmd.write_mask == 0x03 and cmd.writes(qf.MASK_MOTOR) and not cmd.writes(qf.MASK_ENCODER0)


# --- reply frame ([DS] Table 2, Table 4, eq. 2, p.3) --------------------------------------------------------


@pytest.mark.parametrize(
    ("field", "value"),
    [(b"\xff\xff\xff", -1), (b"\x80\x00\x00", -8388608), (b"\x7f\xff\xff", 8388607), (b"\x00\x08\x00", 2048)],
)
def test_encoder_sign_extension(field: bytes, value: int) -> None:
    reading = parse_reply(reply_bytes(enc0=field, enc1=field))
    assert reading.encoder0 == value and reading.encoder1 == value


def test_device_id_check() -> None:
    assert parse_reply(reply_bytes()).device_ok
    assert parse_reply(reply_bytes()).device_id == 777
    bad = parse_reply(reply_bytes(dev=b"\x00\x00"))
    assert bad.device_id == 0 and not bad.device_ok
    assert not parse_reply(reply_bytes(dev=b"\xff\xff")).device_ok


@pytest.mark.parametrize(
    ("status", "error", "detected", "fault"),
    [
        (0x00, False, False, False),
        (0x01, False, False, True),
        (0x02, False, True, False),
        (0x04, True, False, False),
        (0x07, True, True, True),
    ],
)
def test_status_bits(status: int, error: bool, detected: bool, fault: bool) -> None:
    r = parse_reply(reply_bytes(status=status))
    assert (r.stall_error, r.stall_detected, r.amplifier_fault) == (error, detected, fault)


def test_current_sense_in_amps() -> None:
    assert parse_reply(reply_bytes(current=(8190).to_bytes(2, "big"))).current_a == 0.0
    assert parse_reply(reply_bytes(current=(8190 + 9828).to_bytes(2, "big"))).current_a == pytest.approx(1.0)
    assert parse_reply(reply_bytes(current=(8190 - 4914).to_bytes(2, "big"))).current_a == pytest.approx(-0.5)


def test_tachometer_decoding() -> None:
    assert parse_reply(reply_bytes(tach=b"\x7f\xff\xff")).tach_counts_per_s == 0.0  # stopped
    assert parse_reply(reply_bytes(tach=b"\xff\xff\xff")).tach_counts_per_s == 0.0
    period = (40_000).to_bytes(3, "big")  # 40000 cycles of 25 ns = 1 ms per 4 counts -> 4000 counts/s
    cw = parse_reply(reply_bytes(tach=bytes([period[0] | 0x80]) + period[1:]))
    ccw = parse_reply(reply_bytes(tach=period))  # direction bit 0 = counter-clockwise
    assert cw.tach_counts_per_s == pytest.approx(4000.0)
    assert ccw.tach_counts_per_s == pytest.approx(-4000.0)
    # counter-clockwise = theta increasing (theta = -counts * 2 pi / 2048)
    assert ccw.arm_velocity_rad_s == pytest.approx(4000.0 * 2 * math.pi / 2048)
    for speed in (-30000.0, -250.0, 25.0, 1000.0, 99999.0):
        assert qf.decode_tach(qf.encode_tach(speed)) == pytest.approx(speed, rel=2e-3)
    assert qf.encode_tach(0.0) == qf.TACH_IDLE


def test_reply_round_trip() -> None:
    raw = build_reply(
        device_id=0x0309, encoder0=-5, encoder1=123456, tach=qf.encode_tach(-812.0), status=0x06, current=9000
    )
    r = parse_reply(raw)
    assert (r.device_id, r.encoder0, r.encoder1, r.status, r.current_raw) == (0x0309, -5, 123456, 0x06, 9000)
    assert r.tach_counts_per_s == pytest.approx(-812.0, rel=1e-3)
    assert raw[14:] == bytes(3)
    # the hardware counters wrap modulo 2**24
    assert parse_reply(build_reply(encoder0=(1 << 23))).encoder0 == -(1 << 23)
    assert parse_reply(build_reply(encoder1=-1)).encoder1 == -1
    assert parse_reply(build_reply()) == parse_reply(reply_bytes())


@pytest.mark.parametrize("n", [0, 1, 16, 18, 34])
def test_bad_lengths(n: int) -> None:
    with pytest.raises(ValueError, match="17 bytes"):
        parse_reply(bytes(n))
    with pytest.raises(ValueError, match="17 bytes"):
        parse_command(bytes(n))


# --- angles -------------------------------------------------------------------------------------------------


def test_arm_angle_convention() -> None:
    assert counts_to_arm_rad(0) == 0.0
    assert counts_to_arm_rad(512) == pytest.approx(
        -math.pi / 2
    )  # +counts (positive command) = theta decreasing
    assert counts_to_arm_rad(-2048) == pytest.approx(2 * math.pi)
    for theta in (-1.7, -0.01, 0.0, 0.5, 2.0):
        assert counts_to_arm_rad(qf.arm_rad_to_counts(theta)) == pytest.approx(
            theta, abs=qf.RAD_PER_COUNT / 2
        )


def test_pendulum_angle_convention() -> None:
    assert counts_to_pendulum_rad(0) == pytest.approx(-math.pi)  # zeroed hanging down
    assert counts_to_pendulum_rad(1024) == pytest.approx(0.0)  # upright
    assert counts_to_pendulum_rad(-1024) == pytest.approx(0.0)
    assert counts_to_pendulum_rad(2048) == pytest.approx(-math.pi)
    assert counts_to_pendulum_rad(512) == pytest.approx(-math.pi / 2)
    for c in range(-5000, 5000, 37):
        assert -math.pi <= counts_to_pendulum_rad(c) < math.pi
    for alpha in (-3.0, -0.2, 0.0, 0.3, 3.1, 7.0, -9.0):
        got = counts_to_pendulum_rad(qf.pendulum_rad_to_counts(alpha))
        wrapped = (alpha + math.pi) % (2 * math.pi) - math.pi
        assert abs((got - wrapped + math.pi) % (2 * math.pi) - math.pi) <= qf.RAD_PER_COUNT / 2 + 1e-12


# --- velocity filter ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("method", ["exact", "bilinear"])
@pytest.mark.parametrize("dt", [0.001, 0.007])
def test_velocity_filter_tracks_a_ramp(method: str, dt: float) -> None:
    f = VelocityFilter(dt, 50.0, method=method)
    speed, angle = 3.0, -1.0
    for _ in range(int(0.3 / dt)):
        angle += speed * dt
        v = f.update((angle + math.pi) % (2 * math.pi) - math.pi)
    assert v == pytest.approx(speed, rel=1e-6)


def test_velocity_filter_unwraps_across_pi() -> None:
    dt, speed = 0.007, 8.0
    f = VelocityFilter(dt)
    angle = 2.0
    f.reset(angle, speed)
    seen = []
    for _ in range(200):  # crosses +pi -> -pi several times
        angle += speed * dt
        seen.append(f.update((angle + math.pi) % (2 * math.pi) - math.pi))
    assert max(abs(v - speed) for v in seen) < 1e-9


def test_velocity_filter_first_sample_and_variable_dt() -> None:
    f = VelocityFilter(0.01)
    assert f.update(1.0) == 0.0
    angle = 1.0
    for k in range(400):
        dt = 0.005 if k % 2 else 0.009
        angle -= 2.0 * dt
        v = f.update(angle, dt)
    assert v == pytest.approx(-2.0, rel=1e-6)
    with pytest.raises(ValueError):
        VelocityFilter(0.0)
    with pytest.raises(ValueError):
        VelocityFilter(0.01, method="euler")


# --- SPI device ---------------------------------------------------------------------------------------------


class FakeSpiDev:
    def __init__(self) -> None:
        self.calls: list[list[int]] = []
        self.opened: tuple[int, int] | None = None
        self.closed = False

    def open(self, bus: int, device: int) -> None:
        self.opened = (bus, device)

    def xfer2(self, data: list[int]) -> list[int]:
        self.calls.append(list(data))
        return list(reply_bytes())

    def close(self) -> None:
        self.closed = True


def test_spidev_device_with_a_fake_module(monkeypatch: pytest.MonkeyPatch) -> None:
    fake = FakeSpiDev()
    monkeypatch.setitem(sys.modules, "spidev", types.SimpleNamespace(SpiDev=lambda: fake))
    dev = SpidevDevice(bus=0, device=1)
    assert isinstance(dev, QubeDevice)
    assert fake.opened == (0, 1)
    assert fake.mode == 2 and fake.max_speed_hz == 1_000_000  # type: ignore[attr-defined]
    reply = dev.transfer(build_command(-999))
    assert parse_reply(reply).device_ok
    assert fake.calls == [list(build_command(-999))]  # exactly one 17-byte xfer2
    with pytest.raises(ValueError):
        dev.transfer(b"\x01")
    dev.close()
    assert fake.closed


def test_spidev_missing_gives_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "spidev", None)  # makes `import spidev` raise ImportError
    with pytest.raises(RuntimeError, match=r"pip install \.\[bridge\]"):
        SpidevDevice()


def test_bridge_imports_stay_light() -> None:
    code = (
        "import sys, rpi_bridge, rpi_bridge.frame, rpi_bridge.velocity, rpi_bridge.device, rpi_bridge.reset, "
        "rpi_bridge.control, rpi_bridge.runner, rpi_bridge.service, rpi_bridge.settings, rpi_bridge.__main__; "
        "assert 'torch' not in sys.modules and 'gymnasium' not in sys.modules, 'heavy import'; "
        "assert 'spidev' not in sys.modules; "
        "upper = sorted(m for m in sys.modules if m.split('.')[0] in ('chief', 'worker', 'services', 'deploy', "
        "'bench')); assert not upper, f'the bridge needs only protocol, runtime and rpi_bridge: {upper}'"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
