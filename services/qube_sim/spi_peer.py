"""A simulated QUBE-Servo 2 behind the SPI frame: implements ``rpi_bridge.device.QubeDevice``.

Each :meth:`SimulatedQube.transfer` does what the real full-duplex exchange does, in order:

1. the physics runs for the time since the previous transfer with the command held (zero-order hold);
2. the sensors are sampled into the reply (encoders quantised to 2048 counts/rev, tachometer, status,
   current);
3. the command frame is applied: motor word and enable bit, LEDs and encoder sets, each only if its write-mask
   bit is set ([DS] Table 3).

So, as on the rig, a command computed from one reply acts from the next transfer on. Time advances by a fixed
``period_s`` per transfer (lockstep: deterministic), by a clock callable (real time), or only through explicit
:meth:`SimulatedQube.advance` calls (``period_s=0``).

Faults: the arm stops dead at +-``arm_limit`` (the physical end stops); a command of at least
``stall_voltage`` pushing the arm into a stop sets "stall detected", and after ``stall_error_after_s`` "stall
error", which disables the amplifier until a frame writes the enable bit off (Quanser's reset sequence).
``device_id`` and ``forced_status`` can be changed to inject communication faults or an amplifier fault; wiring
faults: ``reverse_motor`` (motor leads swapped: the arm turns the other way), ``reverse_encoder0`` /
``reverse_encoder1`` (an encoder counting backwards; the tachometer follows encoder 0) and ``dead_encoder1`` (the
pendulum encoder unplugged: its count never changes).

Non-ideal sensing and actuation (a rig profile's, services/qube_sim/profile.py; all off by default):
``sensing_latency_s`` (the reply reports the state of that long ago, interpolated between integration steps),
``encoder_noise_counts`` (Gaussian counts added to each encoder reading, rounded), ``action_delay_s`` (lo, hi: a motor
word reaches the motor a delay drawn uniformly from [lo, hi] after its frame) and ``missed_actions`` (the fraction of
motor words lost: the motor keeps the previous one). Each has its own random stream, seeded from ``seed``.
"""

from __future__ import annotations

import math
import random
from collections import deque
from collections.abc import Callable

from protocol import qube
from rpi_bridge.frame import (
    CURRENT_SCALE,
    CURRENT_ZERO,
    DEVICE_ID,
    FRAME_LEN,
    MASK_ENCODER0,
    MASK_ENCODER1,
    MASK_LED_BLUE,
    MASK_LED_GREEN,
    MASK_LED_RED,
    MASK_MOTOR,
    MASK_MOTOR_ENABLE,
    MODE_FULL,
    RAD_PER_COUNT,
    STATUS_STALL_DETECTED,
    STATUS_STALL_ERROR,
    QubeCommand,
    arm_rad_to_counts,
    build_reply,
    encode_tach,
    parse_command,
    pendulum_rad_to_counts,
)
from services.qube_sim.dynamics import QubeDynamics, QubeParams, command_to_voltage


class SimulatedQube:
    """Physics behind the 17-byte SPI frame (see the module docstring)."""

    def __init__(
        self,
        params: QubeParams | None = None,
        seed: int | None = None,
        period_s: float | None = qube.PERIOD_S,
        clock: Callable[[], float] | None = None,
        arm_limit: float = 2.0,
        max_substep_s: float = 1e-3,
        stall_voltage: float = 5.0,
        stall_error_after_s: float = 5.0,
        max_elapsed_s: float = 1.0,
        initial_noise: float = 0.0,
        reverse_motor: bool = False,
        reverse_encoder0: bool = False,
        reverse_encoder1: bool = False,
        dead_encoder1: bool = False,
        sensing_latency_s: float = 0.0,
        encoder_noise_counts: float = 0.0,
        action_delay_s: tuple[float, float] = (0.0, 0.0),
        missed_actions: float = 0.0,
    ) -> None:
        if not 0 <= action_delay_s[0] <= action_delay_s[1] or sensing_latency_s < 0 or encoder_noise_counts < 0:
            raise ValueError("delays, latency and noise must be >= 0 (and the delay's lo <= hi)")
        if not 0 <= missed_actions < 1:
            raise ValueError(f"missed_actions must be in [0, 1), got {missed_actions}")
        self.params = params or QubeParams()
        self.dynamics = QubeDynamics(self.params, arm_limit=arm_limit)
        self.period_s = period_s or 0.0
        self.clock = clock
        self.max_substep_s = max_substep_s
        self.stall_voltage = stall_voltage
        self.stall_error_after_s = stall_error_after_s
        self.max_elapsed_s = max_elapsed_s
        self.device_id = DEVICE_ID
        self.forced_status = 0
        self.reverse_motor = reverse_motor
        self.reverse_encoder0 = reverse_encoder0
        self.reverse_encoder1 = reverse_encoder1
        self.dead_encoder1 = dead_encoder1
        self.command = 0
        self.enabled = False
        self.leds = (0, 0, 0)
        self.stall_time = 0.0
        self.stall_detected = False
        self.stall_error = False
        self.transfers = 0
        self._rng = random.Random(seed)
        self.sensing_latency_s = sensing_latency_s
        self.encoder_noise_counts = encoder_noise_counts
        self.action_delay_s = action_delay_s
        self.missed_actions = missed_actions
        self.lost_actions = 0
        self._noise_rng = random.Random(f"encoder-noise-{seed}")
        self._action_rng = random.Random(f"action-timing-{seed}")
        self._pending: list[tuple[float, int]] = []  # (dynamics time, motor word) not yet at the motor
        self._history: deque[tuple[float, float, float, float]] = deque()  # (time, theta, alpha, theta_dot)
        self._next_params: QubeParams | None = None
        self._offsets = [0, 0]
        self._last_clock = clock() if clock is not None else None
        self.reset_state(noise=initial_noise)

    # -- state -----------------------------------------------------------------------------------------
    def reset_state(
        self,
        alpha: float = math.pi,
        theta: float = 0.0,
        theta_dot: float = 0.0,
        alpha_dot: float = 0.0,
        noise: float = 0.0,
    ) -> None:
        """Put the rig in a state (default: hanging at rest), plus N(0, noise^2) on each component, and
        recalibrate the encoders as if zeroed with the arm at 0 and the pendulum hanging down."""

        def jitter() -> float:
            return self._rng.gauss(0.0, noise) if noise > 0 else 0.0

        self.dynamics.set_state(
            theta + jitter(), alpha + jitter(), theta_dot + jitter(), alpha_dot + jitter()
        )
        self._offsets = list(self._raw_counts(0.0, math.pi))
        self.stall_time, self.stall_detected, self.stall_error = 0.0, False, False
        self._history.clear()

    def set_params(self, params: QubeParams) -> None:
        """New physics from the next transfer on (domain randomisation: safe to call from another thread)."""
        self._next_params = params

    @property
    def state(self) -> tuple[float, float, float, float]:
        """True (theta, alpha wrapped, theta_dot, alpha_dot)."""
        return self.dynamics.state

    @property
    def time(self) -> float:
        return self.dynamics.time

    @property
    def amplifier_active(self) -> bool:
        return self.enabled and not self.stall_error

    @property
    def voltage(self) -> float:
        return command_to_voltage(self.command, self.params) if self.amplifier_active else 0.0

    def _raw_counts(self, theta: float | None = None, alpha: float | None = None) -> tuple[int, int]:
        """The counters before any set (zeroing), with the wiring faults applied (at the current state, or at
        ``theta``/``alpha``)."""
        raw0 = arm_rad_to_counts(self.dynamics.theta if theta is None else theta)
        raw1 = 0 if self.dead_encoder1 else pendulum_rad_to_counts(self.dynamics.alpha if alpha is None else alpha)
        return (-raw0 if self.reverse_encoder0 else raw0), (-raw1 if self.reverse_encoder1 else raw1)

    def encoder_counts(self) -> tuple[int, int]:
        """(encoder0, encoder1) as the rig would count them now."""
        raw0, raw1 = self._raw_counts()
        return raw0 - self._offsets[0], raw1 - self._offsets[1]

    # -- time ------------------------------------------------------------------------------------------
    def advance(self, dt: float) -> None:
        """Integrate ``dt`` seconds with the held command, in steps of at most ``max_substep_s``; a delayed motor
        word takes over at its time."""
        while self._pending and dt > 0:
            until = self._pending[0][0] - self.dynamics.time
            if until <= 1e-12:
                self.command = self._pending.pop(0)[1]
                continue
            chunk = min(dt, until)
            self._integrate(chunk)
            dt -= chunk
        while self._pending and self._pending[0][0] - self.dynamics.time <= 1e-12:
            self.command = self._pending.pop(0)[1]
        self._integrate(dt)

    def _integrate(self, dt: float) -> None:
        if dt <= 0:
            return
        n = max(1, math.ceil(dt / self.max_substep_s - 1e-9))
        h = dt / n
        for _ in range(n):
            voltage, active = self.voltage, self.amplifier_active
            if self.reverse_motor:
                voltage = -voltage
            self.dynamics.step(voltage, h, substeps=1, amplifier_on=active)
            self._update_stall(voltage if active else 0.0, h)
            if self.sensing_latency_s:
                self._remember()

    def _remember(self) -> None:
        d = self.dynamics
        self._history.append((d.time, d.theta, d.alpha, d.theta_dot))
        while len(self._history) > 2 and self._history[1][0] <= d.time - self.sensing_latency_s:
            self._history.popleft()

    def _sensed(self) -> tuple[float, float, float]:
        """(theta, alpha, theta_dot) as the sensors report them: ``sensing_latency_s`` old, linearly interpolated
        between integration steps (the oldest known state if the history is shorter)."""
        d = self.dynamics
        if not self.sensing_latency_s or not self._history:
            return d.theta, d.alpha, d.theta_dot
        at = d.time - self.sensing_latency_s
        older = None
        for entry in self._history:
            if entry[0] > at:
                if older is None:
                    return entry[1], entry[2], entry[3]
                w = (at - older[0]) / (entry[0] - older[0])
                return tuple(a + w * (b - a) for a, b in zip(older[1:], entry[1:], strict=True))  # type: ignore[return-value]
            older = entry
        return d.theta, d.alpha, d.theta_dot

    def _update_stall(self, voltage: float, h: float) -> None:
        if abs(voltage) >= self.stall_voltage and self.dynamics.pressing_limit(voltage):
            self.stall_detected = True
            self.stall_time += h
            if self.stall_time >= self.stall_error_after_s:
                self.stall_error = True
        else:
            self.stall_detected = False
            self.stall_time = 0.0

    # -- QubeDevice ------------------------------------------------------------------------------------
    def transfer(self, frame: bytes) -> bytes:
        if len(frame) != FRAME_LEN:
            raise ValueError(f"an SPI frame must be {FRAME_LEN} bytes, got {len(frame)}")
        if self._next_params is not None:
            self.params = self.dynamics.params = self._next_params
            self._next_params = None
        if self.clock is not None:
            now = self.clock()
            last = self._last_clock if self._last_clock is not None else now
            self._last_clock = now
            self.advance(min(max(0.0, now - last), self.max_elapsed_s))
        else:
            self.advance(self.period_s)
        self.transfers += 1
        if frame[0] != MODE_FULL:  # mode 0: the device id only, nothing changes ([DS] p.1)
            return self.device_id.to_bytes(2, "big") + bytes(FRAME_LEN - 2)
        reply = self._reply()
        self._apply(parse_command(frame))
        return reply

    def close(self) -> None:
        pass

    def _reply(self) -> bytes:
        d = self.dynamics
        theta, alpha, theta_dot = self._sensed()
        if self.sensing_latency_s:
            raw0, raw1 = self._raw_counts(theta, alpha)
            enc0, enc1 = raw0 - self._offsets[0], raw1 - self._offsets[1]
        else:
            enc0, enc1 = self.encoder_counts()
        if self.encoder_noise_counts:
            enc0 += round(self._noise_rng.gauss(0.0, self.encoder_noise_counts))
            if not self.dead_encoder1:
                enc1 += round(self._noise_rng.gauss(0.0, self.encoder_noise_counts))
        status = self.forced_status & 0xFF
        status |= STATUS_STALL_DETECTED if self.stall_detected else 0
        status |= STATUS_STALL_ERROR if self.stall_error else 0
        amps = (
            (self.voltage + self.params.km * d.theta_dot * (-1 if self.reverse_motor else 1)) / self.params.Rm
            if self.amplifier_active
            else 0.0
        )
        current = max(0, min(0xFFFF, CURRENT_ZERO + round(amps * CURRENT_SCALE)))
        return build_reply(
            device_id=self.device_id,
            encoder0=enc0,
            encoder1=enc1,
            # encoder0 counts/s (theta = -counts); the tachometer times encoder 0's edges, so it follows its wiring
            tach=encode_tach((1 if self.reverse_encoder0 else -1) * theta_dot / RAD_PER_COUNT),
            status=status,
            current=current,
        )

    def _write_motor(self, motor: int) -> None:
        """The motor word of a frame: lost (``missed_actions``), delayed (``action_delay_s``) or applied now."""
        if self.missed_actions and self._action_rng.random() < self.missed_actions:
            self.lost_actions += 1
            return
        lo, hi = self.action_delay_s
        if hi <= 0:
            self.command = motor
            return
        delay = lo + (hi - lo) * self._action_rng.random()
        self._pending.append((self.dynamics.time + delay, motor))
        self._pending.sort(key=lambda item: item[0])

    def _apply(self, cmd: QubeCommand) -> None:
        if cmd.writes(MASK_MOTOR):
            self._write_motor(cmd.motor)
        if cmd.writes(MASK_MOTOR_ENABLE):
            self.enabled = cmd.enabled
            if not cmd.enabled:  # disabling the amplifier clears a stall error ([QEX] resetQUBEServo)
                self.stall_error, self.stall_time, self.stall_detected = False, 0.0, False
        red, green, blue = self.leds
        self.leds = (
            cmd.leds[0] if cmd.writes(MASK_LED_RED) else red,
            cmd.leds[1] if cmd.writes(MASK_LED_GREEN) else green,
            cmd.leds[2] if cmd.writes(MASK_LED_BLUE) else blue,
        )
        enc0, enc1 = self.encoder_counts()
        if cmd.writes(MASK_ENCODER0):
            self._offsets[0] += enc0 - cmd.encoder0_set
        if cmd.writes(MASK_ENCODER1):
            self._offsets[1] += enc1 - cmd.encoder1_set
