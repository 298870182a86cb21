"""The bridge's control core as pure code: one tick = sense (read the rig, check safety, decide the phase) and act
(apply the worker's action or the safe one). No MQTT and no clock of its own: the runner (rpi_bridge/runner.py)
owns time and transport, and the in-process simulated task drives the same core directly.

Phases:

- ``idle``: amplifier off, waiting for a reset request;
- ``resetting``: the ResetController swings the pendulum up and holds it; on "ready" a new episode starts;
- ``ready``: the pendulum is held by the reset controller; states of the new episode are published; the first
  action from the worker hands the rig over (if none comes, the hold continues);
- ``running``: the worker's action for each state is applied if it comes in time, else the safe action (a miss);
- ``fallen``: the pendulum left the balance band; motor at 0 until the next reset;
- ``fault``: amplifier disabled (watchdog: no action for too long, arm past its limit, stall or amplifier fault,
  wrong device id); a reset request clears it when the cause is gone.

LEDs show the phase: yellow resetting, green ready/running, blue idle/fallen, red fault.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from rpi_bridge.device import QubeDevice
from rpi_bridge.frame import build_command, clamp_command, parse_reply
from rpi_bridge.reset import ResetConfig, ResetController
from rpi_bridge.velocity import VelocityFilter

Phase = Literal["idle", "resetting", "ready", "running", "fallen", "fault"]

LEDS: dict[str, tuple[int, int, int]] = {
    "idle": (0, 0, 999),
    "resetting": (999, 999, 0),
    "ready": (0, 999, 0),
    "running": (0, 999, 0),
    "fallen": (0, 0, 999),
    "fault": (999, 0, 0),
}


@dataclass(frozen=True)
class ControlConfig:
    """Safety and timing limits of one rig (angles in rad, times in s, commands in SPI counts)."""

    period_s: float = 0.007
    safe_command: int = 0
    max_command: int = 400  # actions are clipped to this (about 9.6 V)
    fall_limit: float = math.radians(7.5)  # the paper's balance band: outside it the episode is over
    arm_limit: float = math.radians(110.0)  # |theta| beyond this disables the amplifier (end stops ~115 deg)
    action_timeout_s: float = 0.5  # running without any action this long disables the amplifier
    ready_timeout_s: float = 60.0  # ready without any action this long: back to idle
    reset: ResetConfig = field(default_factory=ResetConfig)


@dataclass(frozen=True)
class Sensed:
    """What one tick read: the state to publish and whether an action is expected for it."""

    seq: int
    episode: int
    phase: Phase
    theta: float
    alpha: float
    theta_dot: float
    alpha_dot: float
    awaits_action: bool


@dataclass
class Counters:
    ticks: int = 0
    misses: int = 0
    late_actions: int = 0
    faults: int = 0
    applied: int = 0


class ControlCore:
    """Phase machine and safety logic around one QUBE device."""

    def __init__(self, device: QubeDevice, config: ControlConfig | None = None) -> None:
        self.device = device
        self.cfg = config or ControlConfig()
        self.phase: Phase = "idle"
        self.fault_reason = ""
        self.episode = 0
        self.request_id = -1
        self.seq = 0
        self.counters = Counters()
        self.events: list[tuple[str, int, str]] = []  # (status, request id, detail) for the runner to publish
        self._reset_ctl = ResetController(self.cfg.reset)
        self._theta_filter = VelocityFilter(self.cfg.period_s)
        self._alpha_filter = VelocityFilter(self.cfg.period_s)
        self._hold_command = 0
        self._since_action = 0.0
        self._pending_reset: int | None = None
        self._zeroed = False

    # -- requests (the runner calls these between ticks) -------------------------------------------------------

    def request_reset(self, request_id: int) -> None:
        """Start a new episode; a repeat of the request already being served is ignored."""
        if request_id == self.request_id and self.phase in ("resetting", "ready", "running"):
            return
        self._pending_reset = request_id

    # -- one tick -----------------------------------------------------------------------------------------------

    def sense(self) -> Sensed:
        """Apply the held command, read the rig, run the safety checks and the phase machine."""
        cfg = self.cfg
        self.counters.ticks += 1
        self.seq += 1
        if self._pending_reset is not None:
            self._start_reset(self._pending_reset)
            self._pending_reset = None
        enable = self.phase in ("resetting", "ready", "running")
        frame = build_command(self._hold_command if enable else 0, enable=enable, leds=LEDS[self.phase],
                              reset_encoders=not self._zeroed)
        self._zeroed = True
        reading = parse_reply(self.device.transfer(frame))
        theta, alpha = reading.theta, reading.alpha
        if self.counters.ticks == 1:
            self._theta_filter.reset(theta)
            self._alpha_filter.reset(alpha)
        theta_dot = self._theta_filter.update(theta)
        alpha_dot = self._alpha_filter.update(alpha)

        if not reading.device_ok:
            self._fault(f"wrong device id 0x{reading.device_id:04x} (expected 0x0309): SPI link fault")
        elif reading.stall_error or reading.amplifier_fault:
            self._fault("stall error" if reading.stall_error else "amplifier fault")
        elif abs(theta) > cfg.arm_limit and self.phase in ("ready", "running"):
            # (during a reset the ResetController keeps the arm away from the stops itself, with a timeout)
            self._fault(f"arm at {math.degrees(theta):.0f} deg, past the {math.degrees(cfg.arm_limit):.0f} deg limit")

        awaits = False
        if self.phase == "resetting":
            command, ctl_phase = self._reset_ctl.step((theta, alpha, theta_dot, alpha_dot), cfg.period_s)
            self._hold_command = command
            if ctl_phase == "ready":
                self.phase = "ready"
                self.episode = self.request_id
                self._since_action = 0.0
                self.events.append(("ready", self.request_id, ""))
            elif ctl_phase == "failed":
                self._hold_command = 0
                self.phase = "idle"
                self.events.append(("reset_failed", self.request_id,
                                    f"the pendulum was not held upright within {cfg.reset.timeout_s:.0f} s"))
        elif self.phase == "ready":
            command, _ = self._reset_ctl.step((theta, alpha, theta_dot, alpha_dot), cfg.period_s)
            self._hold_command = command  # keep holding until the worker takes over
            self._since_action += cfg.period_s
            awaits = True
            if self._since_action > cfg.ready_timeout_s:
                self._to_idle("no action from the worker while ready")
                awaits = False
        elif self.phase == "running":
            self._since_action += cfg.period_s
            if abs(alpha) > cfg.fall_limit:
                self.phase = "fallen"
                self._hold_command = 0
                self.events.append(("fallen", self.request_id, f"alpha {math.degrees(alpha):.1f} deg"))
            elif self._since_action > cfg.action_timeout_s:
                self._fault(f"watchdog: no action for {self._since_action:.2f} s")
            else:
                awaits = True
        return Sensed(self.seq, self.episode, self.phase, theta, alpha, theta_dot, alpha_dot, awaits)

    def act(self, command: int | None) -> int:
        """Apply the action for the state just sensed (None: it did not come in time). Returns what was applied."""
        if self.phase not in ("ready", "running"):
            return self._hold_command
        if command is None and self._pending_reset is not None:
            return self._hold_command  # the worker ended the episode with a reset, not a missed action
        if command is None:
            if self.phase == "running":
                self.counters.misses += 1
                self._hold_command = self.cfg.safe_command
                self._send(self._hold_command)
            return self._hold_command  # ready: the reset controller keeps holding
        command = clamp_command(command, self.cfg.max_command)
        self.phase = "running"
        self._since_action = 0.0
        self._hold_command = command
        self.counters.applied += 1
        self._send(command)
        return command

    def disable(self, reason: str = "bridge stopping") -> None:
        """Amplifier off (used on shutdown)."""
        self.device.transfer(build_command(0, enable=False, leds=LEDS["idle"]))
        self.phase = "idle"
        self.fault_reason = reason

    # -- internals ----------------------------------------------------------------------------------------------

    def _send(self, command: int) -> None:
        self.device.transfer(build_command(command, enable=True, leds=LEDS[self.phase]))

    def _start_reset(self, request_id: int) -> None:
        self.request_id = request_id
        self.fault_reason = ""
        self.phase = "resetting"
        self._reset_ctl.reset()
        self._hold_command = 0
        self.events.append(("resetting", request_id, ""))

    def _fault(self, reason: str) -> None:
        if self.phase != "fault":
            self.counters.faults += 1
            self.events.append(("fault", self.request_id, reason))
        self.phase = "fault"
        self.fault_reason = reason
        self._hold_command = 0

    def _to_idle(self, reason: str) -> None:
        self.phase = "idle"
        self._hold_command = 0
        self.events.append(("idle", self.request_id, reason))
