"""The bridge's control core as pure code: one tick = sense (read the rig, check safety, decide the phase) and act
(apply the worker's action or the safe one). No MQTT and no loop of its own: the runner (rpi_bridge/runner.py)
owns the loop and the transport, and the in-process simulated task drives the same core directly. The core reads
time only through the ``clock`` it is given (the runner's clock on a rig, a virtual clock in simulation).

Phases:

- ``calibrating``: amplifier off; waits until both encoders are still over a window, then calibrates, keeps the
  stored calibration or refuses (rpi_bridge/calibration.py);
- ``self_test``: a small pulse checks the motor's polarity and both encoders (rpi_bridge/selftest.py);
- ``idle``: amplifier off, waiting for a reset request;
- ``resetting``: the ResetController swings the pendulum up and holds it; on "ready" a new episode starts;
- ``ready``: the pendulum is held by the reset controller; states of the new episode are published, the first one
  already awaiting an action; the first action from the worker hands the rig over (if none comes, the hold
  continues);
- ``identifying``: the identification protocol (rpi_bridge/identify.py) drives the arm and records; on its end
  (complete or aborted) back to ``idle`` with :attr:`ControlCore.identification` holding the recording;
- ``running``: the worker's action for each state is applied if it is written to the motor within the deadline of
  that state's read, else the safe action (a miss);
- ``fallen``: the pendulum left the balance band; amplifier off until the next reset;
- ``fault``: amplifier disabled (watchdog: no action for too long, arm past its limit in any phase, a stall
  detected for too long, stall error or amplifier fault, wrong device id); a reset request clears it when the cause
  is gone. A failed start-up (calibration refused, self-test failed) is latched: the bridge refuses every reset
  until it is restarted.

Every state has its own LED colour (:data:`LEDS`, the table in deploy/rpi/README.md).
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace

from protocol import qube
from rpi_bridge.calibration import Calibration, CalibrationStore, decide, is_still
from rpi_bridge.device import QubeDevice
from rpi_bridge.frame import MAX_COMMAND, build_command, clamp_command, parse_reply
from rpi_bridge.identify import Identification, IdentifyConfig
from rpi_bridge.plant import PlantModel
from rpi_bridge.reset import STRATEGIES, ResetConfig, ResetController, strategy
from rpi_bridge.selftest import SelfTest, SelfTestConfig
from rpi_bridge.velocity import VelocityFilter

#: One colour per phase (red, green, blue; 0..999 each). "off" is the bridge stopped.
LEDS: dict[str, tuple[int, int, int]] = {
    "calibrating": (0, 999, 999),  # cyan
    "self_test": (999, 0, 999),  # magenta
    "idle": (0, 0, 999),  # blue
    "resetting": (999, 999, 0),  # yellow
    "identifying": (600, 0, 999),  # violet
    "ready": (999, 999, 999),  # white
    "running": (0, 999, 0),  # green
    "fallen": (999, 300, 0),  # orange
    "fault": (999, 0, 0),  # red
    "off": (0, 0, 0),
}

#: Phases in which the amplifier is enabled.
DRIVEN = ("self_test", "resetting", "identifying", "ready", "running")


def check_max_command(counts: int) -> int:
    """The clip of every action, in SPI counts: 1..MAX_COMMAND (the QUBE-Servo 2 manual's +-10 V)."""
    if not 0 < counts <= MAX_COMMAND:
        raise ValueError(f"max_command must be in 1..{MAX_COMMAND} (the QUBE-Servo 2 manual's +-10 V is {MAX_COMMAND} "
                         f"counts; 999 would be about 24 V), got {counts}")
    return counts


@dataclass(frozen=True)
class ControlConfig:
    """Safety and timing limits of one rig (angles in rad, times in s, commands in SPI counts)."""

    period_s: float = qube.PERIOD_S
    safe_command: int = 0
    max_command: int = 400  # actions are clipped to this (9.6 V); at most MAX_COMMAND (416 counts = 10 V)
    fall_limit: float = qube.BALANCE_BAND  # the paper's balance band: outside it the episode is over
    arm_limit: float = math.radians(110.0)  # |theta| beyond this in any phase disables the amplifier (stops ~115)
    action_timeout_s: float = 0.5  # running without any action this long disables the amplifier
    ready_timeout_s: float = 60.0  # ready without any action this long: back to idle
    stall_timeout_s: float = 0.1  # status "stall detected" this long with the amplifier on: fault
    calibration_window_s: float = 1.0  # both encoders still this long before calibrating
    still_counts: int = 2  # "still": each encoder within this many counts over the window
    hang_tolerance_counts: int = 6  # a stored calibration must read the resting pendulum within this of hanging
    self_test: SelfTestConfig = field(default_factory=SelfTestConfig)
    reset: ResetConfig = field(default_factory=ResetConfig)
    identify: IdentifyConfig | None = None  # None: the protocol's defaults at this period, max_command and soft limit

    def __post_init__(self) -> None:
        if not self.period_s > 0:
            raise ValueError(f"period_s must be positive, got {self.period_s}")
        check_max_command(self.max_command)
        if abs(self.safe_command) > self.max_command:
            raise ValueError(f"safe_command {self.safe_command} exceeds max_command {self.max_command}")
        if not 0 < self.arm_limit < math.pi:
            raise ValueError(f"arm_limit must be in (0, pi) rad, got {self.arm_limit}")
        if not 0 < self.fall_limit < math.pi:
            raise ValueError(f"fall_limit must be in (0, pi) rad, got {self.fall_limit}")
        soft = max(strategy(self.reset, n)[1].widest_soft_limit() for n in range(len(STRATEGIES)))
        if soft >= self.arm_limit:  # every retry strategy's, every pump variant's
            raise ValueError(f"the reset's soft arm limit ({math.degrees(soft):.0f} deg) must be inside the arm limit "
                             f"({math.degrees(self.arm_limit):.0f} deg)")
        for name in ("action_timeout_s", "ready_timeout_s", "stall_timeout_s", "calibration_window_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.still_counts < 0 or self.hang_tolerance_counts < 0:
            raise ValueError("still_counts and hang_tolerance_counts must be >= 0")


def identify_config(config: ControlConfig, attempt: int = 0) -> IdentifyConfig:
    """The identification protocol a bridge of ``config`` runs: its own, else the protocol's defaults at its period,
    command cap, soft limit and braking; ``attempt`` n > 0: with the n-th other PRBS sequence."""
    own = config.identify or IdentifyConfig(period_s=config.period_s, max_command=config.max_command,
                                            arm_soft_limit=config.reset.arm_soft_limit,
                                            brake_accel=config.reset.brake_accel)
    return replace(own, seed=own.seed + attempt) if attempt else own


def with_model(config: ControlConfig, model: PlantModel) -> ControlConfig:
    """``config`` for a rig of ``model`` (an identified one; rpi_bridge/plant.py): the reset's swing-up, hold gains
    and friction compensation and the self-test's first pulse come from it."""
    return replace(config, reset=replace(config.reset, model=model),
                   self_test=SelfTestConfig.for_model(model, config.self_test))


@dataclass(frozen=True)
class Sensed:
    """What one tick read: the state to publish and whether an action is expected for it."""

    seq: int
    episode: int
    phase: qube.Phase
    theta: float
    alpha: float
    theta_dot: float
    alpha_dot: float
    awaits_action: bool
    t: float = 0.0  # clock time of the read
    dt: float = 0.0  # measured time since the previous read


@dataclass
class Counters:
    ticks: int = 0
    misses: int = 0  # states of a running episode that got the safe action
    late_at_motor: int = 0  # actions that arrived but could not be written within the deadline (among the misses)
    faults: int = 0
    applied: int = 0


class ControlCore:
    """Phase machine and safety logic around one QUBE device."""

    def __init__(
        self,
        device: QubeDevice,
        config: ControlConfig | None = None,
        clock: Callable[[], float] = time.perf_counter,
        store: CalibrationStore | None = None,
        calibration: Calibration | None = None,
        recalibrate: bool = False,
    ) -> None:
        """``store`` keeps the calibration across restarts; ``calibration`` (instead of a store) is a stored one
        given directly; ``recalibrate`` ignores any stored calibration."""
        self.device = device
        self.cfg = config or ControlConfig()
        self.clock = clock
        self.store = store
        stored = calibration if calibration is not None else (store.load() if store is not None else None)
        self._stored = None if recalibrate else stored
        self.calibration: Calibration | None = None
        self.phase: qube.Phase = "calibrating"
        self.fault_reason = ""
        self.refusal = ""  # set when the start-up failed: every reset is refused until a restart
        self.episode = 0
        self.request_id = -1
        self.seq = 0
        self.counters = Counters()
        self.events: list[tuple[str, int, str]] = []  # (status, request id, detail) for the runner to publish
        self.write_latencies: deque[float] = deque(maxlen=20_000)  # read -> motor write of applied actions (s)
        self.periods: deque[float] = deque(maxlen=20_000)  # measured time between reads (s)
        self._reset_ctl = ResetController(self.cfg.reset)
        self._theta_filter = VelocityFilter(self.cfg.period_s)
        self._alpha_filter = VelocityFilter(self.cfg.period_s)
        self._window: deque[tuple[int, int]] = deque(maxlen=max(2, math.ceil(self.cfg.calibration_window_s /
                                                                              self.cfg.period_s)))
        self._windows_moving = 0
        self._self_test: SelfTest | None = None
        self._hold_command = 0
        self._since_action = 0.0
        self._stalled_for = 0.0
        self._pending_reset: int | None = None
        self._read_at: float | None = None
        self._filters_started = False
        self._provisional: Calibration | None = None  # angles before calibration: zero at the first reading
        self.started = False  # calibration and self-test passed
        self._theta = 0.0  # the last arm angle read, and its rate
        self._theta_dot = 0.0
        self._return_limit = 0.0  # a reset that starts past the arm limit may bring the arm back from there
        self._pending_identify: int | None = None
        self._identify_attempt = 0  # the pending identification's attempt (its PRBS sequence)
        self.identification: Identification | None = None  # the last identification run (its recording, failure)
        #: Answers to identification requests for the runner to send: (request id, the finished run or None, its
        #: outcome: "complete" or the one-line reason it has no recording).
        self.identify_answers: list[tuple[int, Identification | None, str]] = []
        self.reset_failures = 0  # resets in a row that did not reach ready: the next one's strategy (reset.py)
        self._reset_open = False  # a reset started and not ready yet

    # -- requests (the runner calls these between ticks) -------------------------------------------------------

    def request_reset(self, request_id: int) -> None:
        """Start a new episode. A repeat of the request last served is ignored, also once that reset has failed:
        a worker repeats its request until the rig acknowledges it, and a repeat that comes in late (a loaded
        broker) must not start a reset nobody asked for."""
        if request_id == self.request_id:
            return
        if self.phase in ("calibrating", "self_test") and self._pending_reset != request_id:
            self.events.append((self.phase, request_id, f"reset {request_id} waits for the start-up checks"))
        self._pending_reset = request_id

    def request_identify(self, request_id: int, attempt: int = 0) -> None:
        """Run the identification protocol once the start-up checks have passed (from idle, fallen or a cleared
        fault, as a reset); its recording is :attr:`identification` once the phase is back to idle. ``attempt``
        n > 0: with the n-th other PRBS sequence (:func:`identify_config`). A repeat of the request last served is
        ignored."""
        if request_id == self.request_id or request_id == self._pending_identify:
            return
        if self.phase in ("calibrating", "self_test"):
            self.events.append((self.phase, request_id, f"identification {request_id} waits for the start-up checks"))
        self._pending_identify = request_id
        self._identify_attempt = attempt

    def use_model(self, model: PlantModel) -> None:
        """Compute the resets (and a self-test still to come) from ``model`` from the next reset on: the rig's model
        changed (a simulated rig whose physics were drawn again). Not while a reset or an identification is under way
        (an episode may be: the reset that ends it takes the new model)."""
        if self.phase in ("resetting", "identifying"):
            raise RuntimeError(f"the bridge's model cannot change while {self.phase}")
        self.cfg = with_model(self.cfg, model)
        self._reset_ctl.base_config = self.cfg.reset

    @property
    def identify_pending(self) -> bool:
        """An identification request waits to be served at the next tick."""
        return self._pending_identify is not None

    @property
    def reset_pending(self) -> bool:
        """A reset request waits to be served at the next tick."""
        return self._pending_reset is not None

    # -- one tick -----------------------------------------------------------------------------------------------

    def sense(self) -> Sensed:
        """Apply the held command, read the rig, run the safety checks and the phase machine."""
        cfg = self.cfg
        self.counters.ticks += 1
        self.seq += 1
        self._serve_pending_reset()
        self._serve_pending_identify()
        enable = self.phase in DRIVEN
        written = clamp_command(self._hold_command, MAX_COMMAND) if enable else 0
        frame = build_command(written, enable=enable, leds=LEDS[self.phase])
        now = self.clock()
        reading = parse_reply(self.device.transfer(frame))
        dt = cfg.period_s if self._read_at is None or not now > self._read_at else now - self._read_at
        if self._read_at is not None:
            self.periods.append(dt)
        self._read_at = now
        counts = (reading.encoder0, reading.encoder1)
        if self._provisional is None:
            self._provisional = Calibration(*counts)
        calibration = self.calibration or self._stored or self._provisional
        theta, alpha = calibration.angles(*counts)
        if not self._filters_started:
            self._theta_filter.reset(theta)
            self._alpha_filter.reset(alpha)
            self._filters_started = True
        theta_dot = self._theta_filter.update(theta, dt)
        alpha_dot = self._alpha_filter.update(alpha, dt)

        self._stalled_for = self._stalled_for + dt if reading.stall_detected and enable else 0.0
        if not reading.device_ok:
            self._fault(f"wrong device id 0x{reading.device_id:04x} (expected 0x0309): SPI link fault")
        elif reading.stall_error or reading.amplifier_fault:
            self._fault("stall error" if reading.stall_error else "amplifier fault")
        elif self._stalled_for >= cfg.stall_timeout_s - 1e-9:
            self._fault(f"stall detected for {self._stalled_for:.2f} s: the arm is blocked (end stop, cable, hand?)")
        elif self.calibration is not None and abs(theta) > self._arm_limit_now(theta):
            self._fault(f"arm at {math.degrees(theta):.0f} deg, past the {math.degrees(cfg.arm_limit):.0f} deg limit")
        self._theta, self._theta_dot = theta, theta_dot

        awaits = False
        state = (theta, alpha, theta_dot, alpha_dot)
        if self.phase == "calibrating":
            self._calibrate(counts)
        elif self.phase == "self_test":
            self._run_self_test(counts)
        elif self.phase == "identifying":
            self._run_identification(state, dt, written)
        elif self.phase == "resetting":
            command, ctl_phase = self._reset_ctl.step(state, dt)
            self._hold_command = command
            if ctl_phase == "ready":
                self.phase = "ready"
                self.reset_failures, self._reset_open = 0, False
                self.episode = self.request_id
                self._since_action = 0.0
                self.events.append(("ready", self.request_id, ""))
                awaits = True  # the first state of the episode is actionable, as every later one
            elif ctl_phase == "failed":
                self._hold_command = 0
                self.phase = "idle"
                self.events.append(("reset_failed", self.request_id, self._reset_ctl.failure))
        elif self.phase == "ready":
            command, _ = self._reset_ctl.step(state, dt)
            self._hold_command = command  # keep holding until the worker takes over
            self._since_action += dt
            awaits = True
            if self._since_action > cfg.ready_timeout_s:
                self._to_idle("no action from the worker while ready")
                awaits = False
        elif self.phase == "running":
            self._since_action += dt
            if abs(alpha) > cfg.fall_limit:
                self.phase = "fallen"
                self._hold_command = 0
                self.events.append(("fallen", self.request_id, f"alpha {math.degrees(alpha):.1f} deg"))
            elif self._since_action > cfg.action_timeout_s:
                self._fault(f"watchdog: no action for {self._since_action:.2f} s")
            else:
                awaits = True
        return Sensed(self.seq, self.episode, self.phase, theta, alpha, theta_dot, alpha_dot, awaits, now, dt)

    def act(self, command: int | None, deadline: float | None = None) -> int:
        """Apply the action for the state just sensed (None: it did not come in time). With a ``deadline`` (clock
        time: the state's read + the deadline) the action is written only if the write starts by then; otherwise
        it counts as a miss. Returns what is held now."""
        if self.phase not in ("ready", "running"):
            return self._hold_command
        if command is None and self._pending_reset is not None:
            return self._hold_command  # the worker ended the episode with a reset, not a missed action
        if command is not None:
            command = clamp_command(command, self.cfg.max_command)
            if self._write(command, deadline):
                self.phase = "running"
                self._since_action = 0.0
                self._hold_command = command
                self.counters.applied += 1
                return command
            self.counters.late_at_motor += 1
        if self.phase == "running":
            self.counters.misses += 1
            self._hold_command = self.cfg.safe_command
            self._write(self._hold_command, None)
        return self._hold_command  # ready: the reset controller keeps holding

    def disable(self, reason: str = "bridge stopping") -> None:
        """Amplifier off, LEDs off (used on shutdown)."""
        self.device.transfer(build_command(0, enable=False, leds=LEDS["off"]))
        if not self.refusal:
            self.phase = "idle"
        self.fault_reason = reason

    # -- internals ----------------------------------------------------------------------------------------------

    def _write(self, command: int, deadline: float | None) -> bool:
        """One SPI transfer that sets the motor, unless the clock is already past ``deadline``."""
        now = self.clock()
        if deadline is not None and now > deadline:
            return False
        self.device.transfer(build_command(clamp_command(command, MAX_COMMAND), enable=True, leds=LEDS[self.phase]))
        if deadline is not None and self._read_at is not None:
            self.write_latencies.append(now - self._read_at)
        return True

    def _arm_limit_now(self, theta: float) -> float:
        """The arm limit, except while a reset that began past it (after a fault the arm coasts towards the stop)
        brings the arm back: then it may not move further out than where it began plus the distance it needs to
        stop at the reset's braking rate, plus 3 deg."""
        if self._return_limit and (self.phase != "resetting" or abs(theta) <= self.cfg.arm_limit):
            self._return_limit = 0.0
        return max(self.cfg.arm_limit, self._return_limit)

    def _serve_pending_reset(self) -> None:
        request = self._pending_reset
        if request is None or self.phase in ("calibrating", "self_test"):
            return
        self._pending_reset = None
        if self.refusal:
            self.events.append(("reset_failed", request, f"the bridge refuses to run: {self.refusal}"))
            return
        if not self.started:  # a fault (e.g. the SPI link) interrupted the start-up: start it again
            self._pending_reset = request
            self._restart_startup()
            return
        self._start_reset(request)

    def _restart_startup(self) -> None:
        self.phase = "calibrating"
        self.fault_reason = ""
        self.calibration = None
        self._window.clear()
        self._windows_moving = 0
        self._hold_command = 0
        self.events.append(("calibrating", self._pending_reset if self._pending_reset is not None else -1,
                            "start-up checks again after a fault"))

    def _calibrate(self, counts: tuple[int, int]) -> None:
        self._hold_command = 0
        self._window.append(counts)
        if len(self._window) < self._window.maxlen:  # type: ignore[operator]
            return
        samples = list(self._window)
        if not is_still(samples, self.cfg.still_counts):
            if self._windows_moving % 10 == 0:  # one status when it starts, then one every 10 windows
                spread = [max(s[i] for s in samples) - min(s[i] for s in samples) for i in (0, 1)]
                self.events.append(("calibrating", -1, f"waiting for the rig to be still before calibrating: over "
                                    f"the last {self.cfg.calibration_window_s:.1f} s the arm moved {spread[0]} and "
                                    f"the pendulum {spread[1]} counts; the bridge runs nothing until it hangs still"))
            self._windows_moving += 1
            self._window.clear()
            return
        decision = decide(samples, self._stored, self.cfg.hang_tolerance_counts)
        if decision.action == "refuse" or decision.calibration is None:
            self._refuse(f"calibration: {decision.reason}")
            return
        self.calibration = self._stored = decision.calibration
        if decision.action == "calibrate" and self.store is not None:
            self.store.save(decision.calibration)
        self._filters_started = False  # the angles jump to the calibrated frame
        self.phase = "self_test"
        self._self_test = SelfTest(self.cfg.self_test)
        self.events.append(("self_test", -1, decision.reason))

    def _run_self_test(self, counts: tuple[int, int]) -> None:
        assert self._self_test is not None
        command, verdict = self._self_test.step(*counts)
        self._hold_command = command
        if verdict is None:
            return
        if verdict.ok:
            self.phase = "idle"
            self.started = True
            self.events.append(("idle", -1, f"self-test passed: {verdict.detail}"))
        else:
            self._refuse(f"self-test: {verdict.detail}")

    def _refuse(self, reason: str) -> None:
        self.refusal = reason
        self._fault(reason)
        if self._pending_reset is not None:
            self._serve_pending_reset()

    def _serve_pending_identify(self) -> None:
        request = self._pending_identify
        if request is None or self.phase in ("calibrating", "self_test"):
            return
        if self._pending_reset is not None:  # a reset asked for since supersedes it
            self._pending_identify = None
            self._answer_identify(request, None, f"identification {request} superseded by a reset request")
            return
        self._pending_identify = None
        if self.refusal or not self.started:
            why = f"the bridge refuses to run: {self.refusal}" if self.refusal else "the start-up checks did not pass"
            self._answer_identify(request, None, f"identification {request} refused: {why}")
            return
        config = identify_config(self.cfg, self._identify_attempt)
        self.request_id = request
        self.fault_reason = ""
        self.phase = "identifying"
        self.identification = Identification(config)
        self._hold_command = 0
        self.events.append(("identifying", request, ""))

    def _run_identification(self, state: tuple[float, float, float, float], dt: float, written: int) -> None:
        ident = self.identification
        assert ident is not None
        self._hold_command = ident.step(state, dt, written)
        if ident.done:
            self._hold_command = 0
            self.phase = "idle"
            detail = (f"identification aborted: {ident.failure}" if ident.failure else
                      f"identification complete: {ident.t[-1]:.1f} s recorded")
            self.events.append(("idle", self.request_id, detail))
            self.identify_answers.append((self.request_id, ident, ident.failure or "complete"))

    def _answer_identify(self, request: int, ident: Identification | None, outcome: str) -> None:
        self.events.append(("idle", request, outcome))
        self.identify_answers.append((request, ident, outcome))

    def _start_reset(self, request_id: int) -> None:
        if self.phase == "identifying" and self.identification is not None:
            reason = f"a reset ({request_id}) was requested"
            self.identification.abort(reason)
            self.identify_answers.append((self.request_id, self.identification, reason))
        self.request_id = request_id
        if self._reset_open:  # the reset before did not reach ready (failed, faulted or given up)
            self.reset_failures += 1
        self._reset_open = True
        if abs(self._theta) > self.cfg.arm_limit:
            outward = max(0.0, math.copysign(1.0, self._theta) * self._theta_dot)
            stopping = outward * outward / (2.0 * self.cfg.reset.brake_accel)
            self._return_limit = abs(self._theta) + stopping + math.radians(3.0)
        self.fault_reason = ""
        self.phase = "resetting"
        self._reset_ctl.reset(self.reset_failures)
        self._hold_command = 0
        self.events.append(("resetting", request_id, f"strategy '{self._reset_ctl.strategy}'"))

    def _fault(self, reason: str) -> None:
        if self.phase == "identifying" and self.identification is not None:
            self.identification.abort(f"fault: {reason}")
            self.identify_answers.append((self.request_id, self.identification, f"fault: {reason}"))
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
