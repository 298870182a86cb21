"""The QUBE-Servo 2 SPI frame (QFLEX 2 Embedded data sheet, "[DS]"), as pure code.

One transfer exchanges 17 bytes full duplex, big-endian fields ([DS] Table 2):

    byte   MOSI (host -> QUBE)              MISO (QUBE -> host)
    0      mode (0x01 = full packet)        device id MSB
    1      padding 0x00                     device id LSB      (0x0309 when healthy)
    2      write mask ([DS] Table 3)        encoder0 23-16
    3-4    red LED MSB, LSB (0..999)        encoder0 15-8, 7-0
    5-6    green LED MSB, LSB               encoder1 23-16, 15-8
    7-8    blue LED MSB, LSB                encoder1 7-0, tachometer 23-16
    9-11   set encoder0 (24 bit)            tachometer 15-8, 7-0, status
    12-14  set encoder1 (24 bit)            current sense MSB, LSB, null
    15-16  motor word                       null, null

Motor word: bit 15 enables the PWM amplifier, bits 14-0 hold -999..999 in two's complement
(10 x duty %, 999 is about 24 V); enabled word = ``(cmd & 0x7FFF) | 0x8000``, 0x0000 disables.

Sign conventions (Quanser's QUBE-Servo 2 Arduino example ``QuanserQUBEServo2_Pendulum.ino``; gym_brt's hardware
interface uses the same):

- arm: ``theta = -counts0 * 2*pi/2048`` (counter-clockwise positive);
- pendulum: ``alpha = (counts1 mod 2048) * 2*pi/2048 - pi``, so alpha = 0 upright and +-pi hanging when
  encoder1 was zeroed with the pendulum hanging at rest; wrapped to [-pi, pi);
- a positive motor command turns the arm in the direction of increasing encoder0 counts, so theta decreases.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

FRAME_LEN = 17
MODE_ID_ONLY = 0x00  # [DS] p.1: reads the device id only, changes nothing
MODE_FULL = 0x01  # [DS] p.1: full 17-byte command packet
DEVICE_ID = 0x0309  # [DS]: "any other value indicates a fault in communication"

# Write mask bits ([DS] Table 3); bit 7 is unused.
MASK_MOTOR = 0x01
MASK_MOTOR_ENABLE = 0x02
MASK_LED_RED = 0x04
MASK_LED_GREEN = 0x08
MASK_LED_BLUE = 0x10
MASK_ENCODER0 = 0x20
MASK_ENCODER1 = 0x40
MASK_LEDS = MASK_LED_RED | MASK_LED_GREEN | MASK_LED_BLUE
MASK_ENCODERS = MASK_ENCODER0 | MASK_ENCODER1
MASK_ALL = 0x7F

# Status byte bits ([DS] Table 4).
STATUS_AMPLIFIER_FAULT = 0x01
STATUS_STALL_DETECTED = 0x02
STATUS_STALL_ERROR = 0x04

MOTOR_MAX = 999  # [DS] p.2: -999..999 = 10 x PWM duty %
MOTOR_ENABLE_BIT = 0x8000
VOLTS_PER_COUNT = 24.0 / MOTOR_MAX  # [DS] p.2: 500 counts (50 % duty) is "approximately 12 VDC"
MAX_NORMAL_VOLTS = 10.0  # [UM] Table 2.2 and its caution: recommended (and "max motor input") +-10 V
MAX_COMMAND = math.floor(MAX_NORMAL_VOLTS / VOLTS_PER_COUNT)  # 416 counts = 9.99 V: the cap of every command sent
LED_MAX = 999  # [DS]: 0x0000..0x03E7 per colour

TACH_IDLE = 0x7FFFFF  # [DS] p.3: value at zero speed (about 20 counts/s)
TACH_DIRECTION_BIT = 0x800000  # [DS] p.3: MSB is the direction, 0 = counter-clockwise
TACH_CLOCK_S = 25e-9  # [DS] p.3: the tachometer counts 40 MHz cycles between encoder0 A rising edges

CURRENT_ZERO = 8190  # [DS] eq. (2)
CURRENT_SCALE = 9828

COUNTS_PER_REV = 2048  # 512-line encoders in quadrature ([UM] Table 2.2)
RAD_PER_COUNT = 2.0 * math.pi / COUNTS_PER_REV

_U24 = 0x1000000


def _check_int(name: str, value: object, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{name} must be an int in [{lo}, {hi}], got {type(value).__name__} {value!r}")
    if not lo <= value <= hi:
        raise ValueError(f"{name} must be in [{lo}, {hi}], got {value}")
    return value


def _check_len(raw: bytes, what: str) -> None:
    if len(raw) != FRAME_LEN:
        raise ValueError(f"{what} must be {FRAME_LEN} bytes, got {len(raw)}")


def _s24(value: int) -> int:
    """24-bit two's complement to a signed int (subtract 0x1000000, not 0xFFFFFF: that is off by one)."""
    return value - _U24 if value & 0x800000 else value


def _u24(value: int) -> bytes:
    return (value % _U24).to_bytes(3, "big")


def clamp_command(value: float, limit: int = MOTOR_MAX) -> int:
    """Round any number to a valid motor command, saturated at +-``limit`` (<= 999); NaN gives 0."""
    limit = min(abs(int(limit)), MOTOR_MAX)
    if value != value:  # NaN
        return 0
    return round(max(-limit, min(limit, value)))


def volts_to_counts(volts: float) -> float:
    """Amplifier volts to SPI motor counts (not rounded, not clamped)."""
    return volts / VOLTS_PER_COUNT


def _motor_word(motor: int, enable: bool) -> int:
    _check_int("motor command", motor, -MOTOR_MAX, MOTOR_MAX)
    return ((motor & 0x7FFF) | MOTOR_ENABLE_BIT) if enable else 0x0000


def build_command(
    motor: int,
    enable: bool = True,
    leds: tuple[int, int, int] | None = None,
    reset_encoders: bool = False,
    write_mask: int | None = None,
    encoder_values: tuple[int, int] = (0, 0),
) -> bytes:
    """The 17-byte MOSI frame (mode 0x01).

    ``motor`` is an int in -999..999 (ValueError otherwise; see :func:`clamp_command`); ``enable=False`` sends
    the word 0x0000, which disables the amplifier. The default write mask writes the motor and its enable bit,
    plus the LEDs when ``leds`` (r, g, b, each 0..999) is given and both encoders when ``reset_encoders`` (set
    to ``encoder_values``, normally 0). An explicit ``write_mask`` (0x00..0x7F) replaces the default.
    """
    word = _motor_word(motor, enable)
    mask = MASK_MOTOR | MASK_MOTOR_ENABLE
    if leds is not None:
        if len(leds) != 3:
            raise ValueError(f"leds must be (red, green, blue), got {leds!r}")
        for name, v in zip(("red", "green", "blue"), leds, strict=True):
            _check_int(f"{name} LED", v, 0, LED_MAX)
        mask |= MASK_LEDS
    if reset_encoders:
        mask |= MASK_ENCODERS
    if write_mask is not None:
        mask = _check_int("write mask", write_mask, 0, MASK_ALL)
    red, green, blue = leds if leds is not None else (0, 0, 0)
    enc0, enc1 = encoder_values
    _check_int("encoder0 value", enc0, -(_U24 // 2), _U24 // 2 - 1)
    _check_int("encoder1 value", enc1, -(_U24 // 2), _U24 // 2 - 1)
    return (
        bytes((MODE_FULL, 0x00, mask))
        + red.to_bytes(2, "big")
        + green.to_bytes(2, "big")
        + blue.to_bytes(2, "big")
        + _u24(enc0)
        + _u24(enc1)
        + word.to_bytes(2, "big")
    )


@dataclass(frozen=True)
class QubeCommand:
    """A decoded MOSI frame (what the QUBE is asked to do)."""

    mode: int
    write_mask: int
    leds: tuple[int, int, int]
    encoder0_set: int
    encoder1_set: int
    motor: int  # -999..999 from bits 14-0 (sign-extended 15-bit two's complement)
    enabled: bool  # bit 15 of the motor word

    def writes(self, bit: int) -> bool:
        return bool(self.write_mask & bit)


def parse_command(raw: bytes) -> QubeCommand:
    """Decode a 17-byte MOSI frame (the simulated peer's side). ValueError on a wrong length."""
    _check_len(raw, "command frame")
    word = int.from_bytes(raw[15:17], "big")
    motor = word & 0x7FFF
    if motor & 0x4000:
        motor -= 0x8000
    return QubeCommand(
        mode=raw[0],
        write_mask=raw[2],
        leds=(
            int.from_bytes(raw[3:5], "big"),
            int.from_bytes(raw[5:7], "big"),
            int.from_bytes(raw[7:9], "big"),
        ),
        encoder0_set=_s24(int.from_bytes(raw[9:12], "big")),
        encoder1_set=_s24(int.from_bytes(raw[12:15], "big")),
        motor=motor,
        enabled=bool(word & MOTOR_ENABLE_BIT),
    )


def decode_tach(raw: int) -> float:
    """Tachometer field to signed encoder0 counts/s ([DS] p.3: counts/s = 4 / (tach * 25 ns)).

    Bits 22-0 are 40 MHz cycles between encoder0 A edges; 0x7FFFFF (and 0) mean stopped and give 0.
    Bit 23 is the direction, 0 = counter-clockwise. Counter-clockwise is taken as decreasing encoder0 counts
    (inference: Quanser's theta = -counts is counter-clockwise positive), so the result has the sign of
    d(encoder0)/dt.
    """
    period = raw & 0x7FFFFF
    if period in (0, TACH_IDLE):
        return 0.0
    speed = 4.0 / (period * TACH_CLOCK_S)
    return speed if raw & TACH_DIRECTION_BIT else -speed


def encode_tach(counts_per_s: float) -> int:
    """Inverse of :func:`decode_tach` for the simulator: signed counts/s to the 24-bit field."""
    speed = abs(counts_per_s)
    if speed <= 4.0 / (TACH_IDLE * TACH_CLOCK_S):
        return TACH_IDLE
    period = max(1, min(TACH_IDLE - 1, round(4.0 / (speed * TACH_CLOCK_S))))
    return period | (TACH_DIRECTION_BIT if counts_per_s > 0 else 0)


@dataclass(frozen=True)
class QubeReading:
    """A decoded MISO frame: raw fields plus decoded properties."""

    device_id: int
    encoder0: int  # signed counts (arm)
    encoder1: int  # signed counts (pendulum)
    tach_raw: int  # 24-bit field
    status: int
    current_raw: int

    @property
    def device_ok(self) -> bool:
        return self.device_id == DEVICE_ID

    @property
    def tach_counts_per_s(self) -> float:
        return decode_tach(self.tach_raw)

    @property
    def arm_velocity_rad_s(self) -> float:
        """theta_dot from the tachometer (theta = -counts * 2*pi/2048)."""
        return -self.tach_counts_per_s * RAD_PER_COUNT

    @property
    def stall_error(self) -> bool:
        return bool(self.status & STATUS_STALL_ERROR)

    @property
    def stall_detected(self) -> bool:
        return bool(self.status & STATUS_STALL_DETECTED)

    @property
    def amplifier_fault(self) -> bool:
        return bool(self.status & STATUS_AMPLIFIER_FAULT)

    @property
    def current_a(self) -> float:
        """Motor current, ``(Isense - 8190) / 9828`` ([DS] eq. 2). The data sheet labels it mA, but the
        formula gives amps: Quanser's own display code (``QUBEServo2.cpp``, I = 3.3/(4*4095) * (Isense/2 - 4095),
        about (Isense - 8190)/9927) agrees within 1 %."""
        return (self.current_raw - CURRENT_ZERO) / CURRENT_SCALE

    @property
    def theta(self) -> float:
        return counts_to_arm_rad(self.encoder0)

    @property
    def alpha(self) -> float:
        return counts_to_pendulum_rad(self.encoder1)


def parse_reply(raw: bytes) -> QubeReading:
    """Decode a 17-byte MISO frame ([DS] Table 2). ValueError on a wrong length."""
    _check_len(raw, "reply frame")
    return QubeReading(
        device_id=int.from_bytes(raw[0:2], "big"),
        encoder0=_s24(int.from_bytes(raw[2:5], "big")),
        encoder1=_s24(int.from_bytes(raw[5:8], "big")),
        tach_raw=int.from_bytes(raw[8:11], "big"),
        status=raw[11],
        current_raw=int.from_bytes(raw[12:14], "big"),
    )


def build_reply(
    device_id: int = DEVICE_ID,
    encoder0: int = 0,
    encoder1: int = 0,
    tach: int = TACH_IDLE,
    status: int = 0,
    current: int = CURRENT_ZERO,
) -> bytes:
    """The 17-byte MISO frame (for the simulated peer and tests). Encoder counts wrap modulo 2**24 like the
    hardware counters; ``tach`` is the raw 24-bit field (see :func:`encode_tach`), ``current`` the raw
    Isense."""
    _check_int("device id", device_id, 0, 0xFFFF)
    _check_int("encoder0", encoder0, -(1 << 62), 1 << 62)
    _check_int("encoder1", encoder1, -(1 << 62), 1 << 62)
    _check_int("tach", tach, 0, 0xFFFFFF)
    _check_int("status", status, 0, 0xFF)
    _check_int("current", current, 0, 0xFFFF)
    return (
        device_id.to_bytes(2, "big")
        + _u24(encoder0)
        + _u24(encoder1)
        + tach.to_bytes(3, "big")
        + bytes((status,))
        + current.to_bytes(2, "big")
        + bytes(3)
    )


def counts_to_arm_rad(counts: int) -> float:
    """Arm angle theta = -counts * 2*pi/2048 (Quanser convention: counter-clockwise positive)."""
    return -counts * RAD_PER_COUNT


def counts_to_pendulum_rad(counts: int) -> float:
    """Pendulum angle alpha = (counts mod 2048) * 2*pi/2048 - pi, in [-pi, pi): 0 upright when encoder1 was
    zeroed with the pendulum hanging down at rest."""
    return (counts % COUNTS_PER_REV) * RAD_PER_COUNT - math.pi


def arm_rad_to_counts(theta: float) -> int:
    """Inverse of :func:`counts_to_arm_rad`, to the nearest count (for the simulator)."""
    return math.floor(-theta / RAD_PER_COUNT + 0.5)


def pendulum_rad_to_counts(alpha: float) -> int:
    """Encoder1 counts for a continuous (unwrapped) pendulum angle, zero hanging at alpha = -pi; round-trips
    with :func:`counts_to_pendulum_rad` up to the wrap of alpha into [-pi, pi)."""
    return math.floor((alpha + math.pi) / RAD_PER_COUNT + 0.5)
