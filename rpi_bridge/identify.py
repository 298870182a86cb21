"""The identification protocol: about 80 s of rig time that excite every parameter which decides control, as
pure code, and the :class:`Recording` it leaves for the host's fit (services/qube_sim/identify.py).

:class:`Identification` is a tick-by-tick state machine in the style of rpi_bridge/selftest.py: :meth:`step` takes
each tick's state (theta, alpha, theta_dot, alpha_dot), the time since the previous tick and the command written to
the motor at this tick's transfer, records (time, theta, alpha, written command) and returns the command for the next
write. The amplifier stays on throughout; commands in SPI counts (a positive one drives theta negative). Segments:

1. ``centre``: a PD on the arm brings it to the centre.
2. ``excite``: the hanging pendulum is pumped by pulses phase-locked to its own swing (+pulse while alpha_dot > 0:
   a positive command swings the hanging pendulum towards +alpha, rpi_bridge/selftest.py), so at its natural
   frequency whatever the rig (sqrt(3 g / (2 Lp)) / 2 pi = 1.70 Hz for the manual's Lp = 0.129 m, arm held; a
   free arm makes it a little faster), until it swings ``excite_amplitude``, with a weak arm PD.
3. ``decay``: the pendulum swings down freely for ``decay_s`` while a weak PD holds the arm (amplifier on, not
   off: its back-EMF would otherwise let the arm drift): long enough for viscous (exponential) and Coulomb (linear)
   decay to differ.
4. ``breakaway+`` / ``breakaway-``: from rest at the centre, the voltage rises by ``stair_volts`` every
   ``stair_s`` until the arm has moved ``breakaway_move`` (deadzone + static friction), then zero;
   ``breakaway_repeats`` times in each direction, each followed by a return to the centre (``return``).
5. ``step``: from ``step_start`` on one side, a short step of ``step_volts`` towards the other (inertia, motor
   gain, arm damping), cut short at ``step_travel`` past the centre, then a return to the centre.
6. ``prbs``: ``prbs_s`` of a seeded pseudo-random multi-level voltage (levels ``prbs_volts``, held 3-25 ticks)
   around a weak arm-centring PD, the level dropped while it pushes the arm outwards beyond ``prbs_travel``.

Safety, every tick: whenever the arm could not stop inside the reset's soft limit at the reset's braking rate
(rpi_bridge/reset.py's ``must_brake``), full ``max_command`` against its motion; an arm past the soft limit anyway,
a return to the centre that does not arrive, or a non-finite state aborts the protocol with a one-line reason
(command 0 from then on). No command ever exceeds ``max_command``.
"""

from __future__ import annotations

import gzip
import json
import math
import random
from collections.abc import Callable, Generator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from rpi_bridge.frame import MAX_COMMAND, clamp_command, volts_to_counts
from rpi_bridge.reset import ResetConfig, ResetController
from rpi_bridge.velocity import wrap_angle

if TYPE_CHECKING:
    from rpi_bridge.control import ControlCore

State = tuple[float, float, float, float]


#: Recordings a host makes of one rig before it gives up: a refused fit is recorded again once, with the next PRBS
#: sequence (services/qube_sim/identify.py). The rig time of every recording counts.
IDENTIFY_ATTEMPTS = 2


class RecordingError(ValueError):
    """A recording file that cannot be read or is not a valid recording (one line)."""


@dataclass(frozen=True)
class IdentifyConfig:
    """Tunables of :class:`Identification` (angles in rad, times in s, voltages in V, commands in SPI counts)."""

    period_s: float = 0.007
    max_command: int = 400  # never exceeded (the bridge's clip; at most MAX_COMMAND = 10 V)
    arm_soft_limit: float = math.radians(80.0)  # the reset's: the protocol brakes to stay inside it
    brake_accel: float = 100.0  # braking assumed available at full voltage (the reset's)
    seed: int = 1  # the PRBS sequence
    # arm PD: volts = kp * (theta - target) + kd * theta_dot (a positive command drives theta negative)
    centre_kp: float = 8.0
    centre_kd: float = 0.5
    centre_ki: float = 20.0  # V per rad s, while the arm is stuck outside half the tolerance
    centre_ki_max: float = 3.0  # V: the integral's clamp
    hold_kp: float = 4.0  # the weak PD of excite, decay and prbs
    hold_kd: float = 0.2
    centre_tolerance: float = math.radians(5.0)
    centre_timeout_s: float = 4.0
    excite_volts: float = 2.5
    excite_amplitude: float = math.radians(30.0)
    excite_timeout_s: float = 10.0
    decay_s: float = 12.0
    stair_volts: float = 0.1
    stair_s: float = 0.1
    stair_max_volts: float = 4.0
    breakaway_move: float = math.radians(3.0)
    breakaway_repeats: int = 1  # per direction
    step_volts: tuple[float, ...] = (1.5, 3.0, 5.0)
    step_start: float = math.radians(30.0)
    step_s: float = 0.3
    step_travel: float = math.radians(30.0)  # past the centre
    prbs_s: float = 35.0  # (25 s of decay, two breakaways per direction and 60 s here fitted no better: docs)
    prbs_volts: tuple[float, ...] = (1.0, 2.0, 3.5)
    prbs_hold_ticks: tuple[int, int] = (3, 25)
    prbs_travel: float = math.radians(45.0)
    settle_s: float = 0.5  # at the centre before the next segment

    def __post_init__(self) -> None:
        if not 0 < self.max_command <= MAX_COMMAND:
            raise ValueError(f"max_command must be in 1..{MAX_COMMAND} (+-10 V), got {self.max_command}")
        if not self.period_s > 0:
            raise ValueError(f"period_s must be positive, got {self.period_s}")
        if not 0 < self.step_start < self.arm_soft_limit and self.step_travel < self.arm_soft_limit:
            raise ValueError("step_start and step_travel must be inside the soft limit")
        if not 0 < self.prbs_travel < self.arm_soft_limit:
            raise ValueError("prbs_travel must be inside the soft limit")
        top = max((self.excite_volts, self.stair_max_volts, *self.step_volts, *self.prbs_volts))
        if volts_to_counts(top) > self.max_command:
            raise ValueError(f"a protocol voltage ({top} V) exceeds max_command ({self.max_command} counts)")


class Recording(BaseModel):
    """What the protocol recorded, one entry per tick: ``t`` (s since the protocol began, at each read), the angles
    read (``alpha`` as the bridge reports it, wrapped to [-pi, pi): the fit unwraps it) and ``command``, the motor
    command written at that tick's transfer (it acts from that read until the next write, plus the loop's delay).
    ``segments``: (label, first tick, end tick). ``outcome``: "complete" or the reason it stopped."""

    model_config = ConfigDict(extra="forbid")

    format: int = 1
    period_s: float = Field(gt=0)
    t: list[float]
    theta: list[float]
    alpha: list[float]
    command: list[int]
    segments: list[tuple[str, int, int]]
    rig_seconds: float = Field(ge=0)
    outcome: str = "complete"
    config: dict[str, Any] = Field(default_factory=dict)
    rig: str = ""

    @model_validator(mode="after")
    def _consistent(self) -> Recording:
        n = len(self.t)
        if not len(self.theta) == len(self.alpha) == len(self.command) == n:
            raise ValueError(f"t, theta, alpha and command must have one entry per tick (lengths {n}, "
                             f"{len(self.theta)}, {len(self.alpha)}, {len(self.command)})")
        if not all(math.isfinite(v) for v in (*self.t, *self.theta, *self.alpha)):
            raise ValueError("t, theta and alpha must be finite")
        if any(b <= a for a, b in zip(self.t, self.t[1:], strict=False)):
            raise ValueError("t must increase")
        if any(abs(c) > MAX_COMMAND for c in self.command):
            raise ValueError(f"a command exceeds {MAX_COMMAND} counts")
        for label, a, b in self.segments:
            if not 0 <= a <= b <= n:
                raise ValueError(f"segment {label!r} [{a}, {b}) is outside the {n} ticks")
        return self

    @property
    def complete(self) -> bool:
        return self.outcome == "complete"

    def save(self, path: str | Path) -> None:
        """JSON, gzip-compressed when the name ends in .gz."""
        text = self.model_dump_json()
        p = Path(path)
        if p.suffix == ".gz":
            p.write_bytes(gzip.compress(text.encode()))
        else:
            p.write_text(text)

    @classmethod
    def load(cls, path: str | Path) -> Recording:
        """A recording file (JSON or gzip JSON); RecordingError with one line for anything else."""
        p = Path(path)
        try:
            raw = p.read_bytes()
            text = gzip.decompress(raw).decode() if raw[:2] == b"\x1f\x8b" else raw.decode()
            data = json.loads(text)
        except (OSError, EOFError, UnicodeDecodeError, json.JSONDecodeError, gzip.BadGzipFile) as exc:
            raise RecordingError(f"recording {p}: not readable JSON ({exc})") from None
        if not isinstance(data, dict):
            raise RecordingError(f"recording {p}: expected a JSON object, got {type(data).__name__}")
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            first = exc.errors()[0]
            where = ".".join(str(part) for part in first["loc"]) or "recording"
            more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
            raise RecordingError(f"recording {p}: {where}: {first['msg']}{more}") from None


@dataclass
class _Tick:
    theta: float
    alpha: float
    theta_dot: float
    alpha_dot: float
    dt: float


class Abort(Exception):
    """The protocol cannot go on safely (its message is the one-line reason)."""


@dataclass
class Identification:
    """The protocol tick by tick (see the module docstring): :meth:`step` until :attr:`done`; then
    :meth:`recording`. :attr:`failure` is the one-line reason when it stopped early."""

    config: IdentifyConfig = field(default_factory=IdentifyConfig)

    def __post_init__(self) -> None:
        cfg = self.config
        self._guard = ResetController(ResetConfig(arm_soft_limit=cfg.arm_soft_limit, brake_accel=cfg.brake_accel,
                                                  max_command=cfg.max_command))
        self._script = self._run()
        self._started = False
        self._last = 0
        self._now = 0.0
        self.t: list[float] = []
        self.theta: list[float] = []
        self.alpha: list[float] = []
        self.command: list[int] = []
        self.segments: list[tuple[str, int, int]] = []
        self.segment = ""
        self.done = False
        self.failure = ""
        self._tick = _Tick(0.0, math.pi, 0.0, 0.0, cfg.period_s)

    # -- the tick ---------------------------------------------------------------------------------------------

    def step(self, state: State, dt: float, written: int | None = None) -> int:
        """Record this tick (``written``: the command written at its transfer; None: the one this returned last
        time) and return the command for the next write (0 once done)."""
        written = self._last if written is None else written
        if self.done:
            return 0
        if self._started:
            self._now += dt
        self.t.append(self._now)
        self.theta.append(state[0])
        self.alpha.append(state[1])
        self.command.append(int(written))
        if not all(math.isfinite(v) for v in state):
            return self.abort("a non-finite state reached the identification protocol")
        self._tick = _Tick(*state, dt if dt > 0 else self.config.period_s)
        try:
            command = next(self._script) if not self._started else self._script.send(self._tick)
            self._started = True
            command = self._guarded(command)
        except StopIteration:
            self._close_segment()
            self.done = True
            self._last = 0
            return 0
        except Abort as reason:
            return self.abort(str(reason))
        self._last = command
        return command

    def abort(self, reason: str) -> int:
        """Stop here with ``reason`` (a fault outside the protocol, or its own); the command is 0 from now on."""
        if not self.done:
            self._close_segment()
            self.done = True
            self.failure = reason
            self._last = 0
        return 0

    def recording(self, rig: str = "") -> Recording:
        return Recording(period_s=self.config.period_s, t=list(self.t), theta=list(self.theta),
                         alpha=list(self.alpha), command=list(self.command), segments=list(self.segments),
                         rig_seconds=self.t[-1] if self.t else 0.0, outcome=self.failure or "complete",
                         config=json.loads(json.dumps(asdict(self.config))), rig=rig)

    def _guarded(self, command: float) -> int:
        cfg, s = self.config, self._tick
        if abs(s.theta) > cfg.arm_soft_limit:
            raise Abort(f"arm at {math.degrees(s.theta):.0f} deg, past the protocol's "
                        f"{math.degrees(cfg.arm_soft_limit):.0f} deg soft limit in segment {self.segment!r} despite "
                        "braking: the rig is faster or weaker than the protocol assumes")
        brake = self._guard.must_brake(s.theta, s.theta_dot, s.dt)
        if brake:
            return brake * cfg.max_command
        return clamp_command(command, cfg.max_command)

    # -- segments ---------------------------------------------------------------------------------------------

    def _begin(self, label: str) -> None:
        self._close_segment()
        self.segment = label
        self.segments.append((label, len(self.t) - 1, len(self.t) - 1))

    def _close_segment(self) -> None:
        if self.segments:
            label, start, _ = self.segments[-1]
            self.segments[-1] = (label, start, max(start, len(self.t) - 1))

    def _ticks(self, seconds: float) -> int:
        return max(1, round(seconds / self.config.period_s))

    def _pd(self, kp: float, kd: float, target: float = 0.0) -> float:
        s = self._tick
        return volts_to_counts(kp * (s.theta - target) + kd * s.theta_dot)

    def _run(self) -> Generator[float, _Tick, None]:
        cfg = self.config
        yield from self._centre("centre")
        yield from self._excite()
        self._begin("decay")
        for _ in range(self._ticks(cfg.decay_s)):
            yield self._pd(cfg.hold_kp, cfg.hold_kd)
        yield from self._centre("return")
        for _ in range(cfg.breakaway_repeats):
            for direction in (1, -1):
                yield from self._breakaway(direction)
                yield from self._centre("return")
        for volts in cfg.step_volts:
            for direction in (1, -1):
                yield from self._step(direction, volts)
                yield from self._centre("return")
        yield from self._prbs()
        yield from self._centre("return")

    def _centre(self, label: str, target: float = 0.0) -> Generator[float, _Tick, None]:
        """PD to ``target``, plus an integral while the arm is stuck outside half the tolerance (dry friction would
        otherwise hold it short: arm friction 3x lab's stops a PD 9 deg out), until the arm has been within the
        tolerance and slow for ``settle_s``. An arm within the tolerance but never slow by the timeout (a lightly
        damped pendulum still swinging shakes a low-friction arm) is centred enough: the segments record what moves
        the arm, and only an arm that never reached the tolerance ends the identification."""
        cfg = self.config
        self._begin(label)
        still = 0
        integral = 0.0  # volts
        for _ in range(self._ticks(cfg.centre_timeout_s)):
            s = self._tick
            error = s.theta - target
            near = abs(error) < cfg.centre_tolerance and abs(s.theta_dot) < 0.3
            still = still + 1 if near else 0
            if still >= self._ticks(cfg.settle_s):
                return
            if abs(error) > cfg.centre_tolerance / 2 and abs(s.theta_dot) < 0.3:  # held short by friction
                integral = max(-cfg.centre_ki_max, min(cfg.centre_ki_max, integral + cfg.centre_ki * error * s.dt))
            yield self._pd(cfg.centre_kp, cfg.centre_kd, target) + volts_to_counts(integral)
        if abs(self._tick.theta - target) < cfg.centre_tolerance:
            return
        raise Abort(f"the arm did not settle within {math.degrees(cfg.centre_tolerance):.0f} deg of "
                    f"{math.degrees(target):.0f} deg in {cfg.centre_timeout_s:.0f} s (at "
                    f"{math.degrees(self._tick.theta):.0f} deg): blocked arm or a rig much weaker than assumed?")

    def _excite(self) -> Generator[float, _Tick, None]:
        cfg = self.config
        self._begin("excite")
        pulse = volts_to_counts(cfg.excite_volts)
        for _ in range(self._ticks(cfg.excite_timeout_s)):
            s = self._tick
            if abs(wrap_angle(s.alpha - math.pi)) >= cfg.excite_amplitude:
                return
            direction = 1.0 if s.alpha_dot >= 0 else -1.0
            yield direction * pulse + self._pd(cfg.hold_kp, cfg.hold_kd)
        # a pendulum that would not swing this far still decays from where it got: carry on

    def _breakaway(self, direction: int) -> Generator[float, _Tick, None]:
        cfg = self.config
        self._begin("breakaway+" if direction > 0 else "breakaway-")
        start = self._tick.theta
        volts = 0.0
        per_stair = self._ticks(cfg.stair_s)
        while volts < cfg.stair_max_volts:
            volts += cfg.stair_volts
            for _ in range(per_stair):
                if abs(self._tick.theta - start) >= cfg.breakaway_move:
                    for _ in range(self._ticks(0.2)):  # let it slide to a stop on friction alone
                        yield 0
                    return
                yield direction * volts_to_counts(volts)

    def _step(self, direction: int, volts: float) -> Generator[float, _Tick, None]:
        """A positive command drives theta negative: start on the +theta side for a positive step."""
        cfg = self.config
        yield from self._centre("return", direction * cfg.step_start)
        self._begin(f"step{'+' if direction > 0 else '-'}{volts:g}V")
        for _ in range(self._ticks(cfg.step_s)):
            if -direction * self._tick.theta >= cfg.step_travel:
                break
            yield direction * volts_to_counts(volts)
        for _ in range(self._ticks(0.15)):  # coast: back-EMF and friction alone
            yield 0

    def _prbs(self) -> Generator[float, _Tick, None]:
        cfg = self.config
        self._begin("prbs")
        rng = random.Random(f"identify-prbs-{cfg.seed}")
        lo, hi = cfg.prbs_hold_ticks
        left = self._ticks(cfg.prbs_s)
        while left > 0:
            level = volts_to_counts(rng.choice(cfg.prbs_volts)) * rng.choice((-1, 1))
            for _ in range(min(left, rng.randint(lo, hi))):
                left -= 1
                s = self._tick
                outward = level * s.theta < 0  # a positive command drives theta negative
                push = 0.0 if outward and abs(s.theta) > cfg.prbs_travel else level
                yield push + self._pd(cfg.hold_kp, cfg.hold_kd)


class IdentifyFailed(RuntimeError):
    """The protocol did not finish (its message is the one-line reason)."""


def drive(core: ControlCore, wait: Callable[[], None], request_id: int = 1,
          progress: Callable[[str], None] | None = None, startup_s: float = 60.0, attempt: int = 0) -> Recording:
    """Run the start-up checks and the protocol on ``core``, one tick per ``wait()`` (real time: sleep to the next
    period; a simulated rig: advance its clock), and return the complete recording; IdentifyFailed with the reason
    otherwise. ``progress`` gets each segment's label as it begins; ``attempt``: ControlCore.request_identify's."""
    core.request_identify(request_id, attempt)
    period = core.cfg.period_s
    limit = round(startup_s / period)
    ticks, segment = 0, ""
    while True:
        wait()
        core.sense()
        ticks += 1
        ident = core.identification
        if ident is None or core.identify_pending:
            if core.refusal:
                raise IdentifyFailed(f"the bridge refuses to run: {core.refusal}")
            if core.phase == "fault" and core.started:
                raise IdentifyFailed(f"fault before the protocol: {core.fault_reason}")
            if ticks > limit:
                raise IdentifyFailed(f"the start-up checks did not pass within {startup_s:.0f} s (phase {core.phase})")
            if not core.identify_pending and core.started:  # refused (see the core's events)
                detail = next((e[2] for e in reversed(core.events) if e[1] == request_id), "")
                raise IdentifyFailed(detail or "identification refused")
            continue
        if progress is not None and ident.segment != segment:
            segment = ident.segment
            progress(segment)
        if ident.done:
            if ident.failure:
                raise IdentifyFailed(ident.failure)
            return ident.recording()
