"""The polarity and sensor self-test at bridge start, as pure code.

With the pendulum hanging still and the arm calibrated, a small doublet (+2 V for 4 ticks, then -2 V for 4 ticks, so
the arm stops again) must move the arm the expected way and both encoders as expected:

- encoder 0 counts up: a positive command turns the arm towards increasing encoder-0 counts (theta decreasing,
  Quanser's convention, rpi_bridge/frame.py);
- encoder 1 first moves up: the hanging pendulum lags the arm, so its first swing under a positive command is
  towards increasing encoder-1 counts (alpha_ddot > 0; services/qube_sim/dynamics.py gives the same sign).

A sticky or heavy arm may not move on 2 V (arm dry friction 1.7x ``lab``'s moved it 4 counts, 4x its inertia about
as little): while the arm moves less than ``arm_min_counts``, the doublet is repeated at the next level of
``levels_v`` (2, 3, 4, 5 V), and the verdict is the judgement of the first doublet that moved it (or of the last).
With a plant model (rpi_bridge/plant.py) the first level is the lowest at least ``breakaway_margin`` times the model's
breakaway voltage (static arm friction and deadzone). :func:`judge` turns what the encoders did into a verdict that
names the likely wiring fault; :class:`SelfTest` produces the command of each tick and, when the pulse was fine, a
mirrored doublet that brings the arm back. A few degrees of arm and pendulum motion (about 21 counts of arm on the
nominal simulated rig); 5 V for 28 ms cannot hurt a reversed rig.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from rpi_bridge.frame import MAX_COMMAND, VOLTS_PER_COUNT, volts_to_counts
from rpi_bridge.plant import PlantModel


@dataclass(frozen=True)
class SelfTestConfig:
    pulse_counts: int = round(volts_to_counts(2.0))  # 83 counts = 2 V: the first doublet
    levels_v: tuple[float, ...] = (2.0, 3.0, 4.0, 5.0)  # V: the doublets tried while the arm does not move
    pulse_ticks: int = 4
    observe_ticks: int = 10  # after the doublet: the pendulum's first swing is complete by then
    arm_min_counts: int = 5  # the arm must move at least this much (0.9 deg)
    pendulum_min_counts: int = 3  # the pendulum's first excursion must reach this (0.5 deg)

    def __post_init__(self) -> None:
        if not 0 < self.pulse_counts <= MAX_COMMAND:
            raise ValueError(f"pulse_counts must be in 1..{MAX_COMMAND}, got {self.pulse_counts}")
        if self.pulse_ticks < 1 or self.observe_ticks < 0:
            raise ValueError("pulse_ticks must be >= 1 and observe_ticks >= 0")
        if self.arm_min_counts < 1 or self.pendulum_min_counts < 1:
            raise ValueError("arm_min_counts and pendulum_min_counts must be >= 1")
        if any(not 0 < round(volts_to_counts(v)) <= MAX_COMMAND for v in self.levels_v):
            raise ValueError(f"levels_v must each be in (0, {MAX_COMMAND * VOLTS_PER_COUNT:.2f}] V")

    @classmethod
    def for_model(cls, model: PlantModel, base: SelfTestConfig | None = None,
                  breakaway_margin: float = 1.5) -> SelfTestConfig:
        """``base`` (default the defaults) for a rig of ``model``: the first doublet at the lowest level that is at
        least ``breakaway_margin`` times the model's breakaway voltage (static arm friction * Rm/kt + deadzone)."""
        base = base or cls()
        breakaway = max(model.static_arm, model.coulomb_arm) * model.volts_per_newton_metre + model.deadzone_v
        levels = [v for v in base.levels_v if v >= breakaway_margin * breakaway] or [max(base.levels_v)]
        first = round(volts_to_counts(levels[0]))
        return replace(base, pulse_counts=first, levels_v=tuple(levels))

    def pulses(self) -> list[int]:
        """The doublets' amplitudes in counts: ``pulse_counts``, then each level above it."""
        higher = sorted({round(volts_to_counts(v)) for v in self.levels_v} - {self.pulse_counts})
        return [self.pulse_counts, *(c for c in higher if c > self.pulse_counts)]


@dataclass(frozen=True)
class Verdict:
    ok: bool
    detail: str


def judge(samples: list[tuple[int, int]], config: SelfTestConfig | None = None, pulse: int | None = None,
          tried: str = "") -> Verdict:
    """Verdict from the raw (encoder0, encoder1) counts read during one doublet of ``pulse`` counts (default the
    config's first), the first sample being the baseline before it; ``tried`` names the doublets before it."""
    cfg = config or SelfTestConfig()
    pulse = cfg.pulse_counts if pulse is None else pulse
    if len(samples) < 2:
        raise ValueError("judge needs the baseline and at least one sample after it")
    base0, base1 = samples[0]
    # the arm during the positive pulse only (the readings that the negative one cannot have reached yet): a loop
    # that stalls while the negative pulse is held must not turn a good rig into a reversed one
    arm = [s[0] - base0 for s in samples[1 : cfg.pulse_ticks + 2]]
    arm_move = max(arm, key=abs)
    pendulum_first = next((s[1] - base1 for s in samples[1:] if abs(s[1] - base1) >= cfg.pendulum_min_counts), 0)
    seen = f"encoder 0 moved {arm_move:+d} counts, encoder 1 first moved {pendulum_first:+d} counts"
    if abs(arm_move) < cfg.arm_min_counts:
        return Verdict(False, f"the arm did not move on a {pulse}-count pulse ({pulse * VOLTS_PER_COUNT:.1f} V{tried}; "
                       f"{seen}): amplifier, motor cable or encoder 0 cable?")
    if pendulum_first == 0:
        return Verdict(False, f"the pendulum encoder did not change while the arm moved ({seen}): encoder 1 cable "
                       "unplugged, or the pendulum is missing?")
    if arm_move > 0 and pendulum_first > 0:
        return Verdict(True, f"polarity and encoders as expected on a {pulse * VOLTS_PER_COUNT:.1f} V doublet ({seen})")
    if arm_move < 0 and pendulum_first > 0:
        return Verdict(False, f"encoder 0 (arm) counts backwards ({seen}): its wiring is reversed")
    if arm_move > 0:
        return Verdict(False, f"encoder 1 (pendulum) counts backwards ({seen}): its wiring is reversed")
    return Verdict(False, f"the arm turned the wrong way ({seen}): the motor leads are reversed (or both encoders "
                   "count backwards)")


class SelfTest:
    """The test tick by tick: :meth:`step` takes the raw counts just read and returns (command, verdict); the
    verdict is None until the test is over."""

    def __init__(self, config: SelfTestConfig | None = None) -> None:
        self.config = config or SelfTestConfig()
        self._pulses = self.config.pulses()
        self._level = 0
        self._start_level()
        self._back: list[int] = []
        self._passed: Verdict | None = None
        self.verdict: Verdict | None = None

    def _start_level(self) -> None:
        c, p = self.config, self._pulses[self._level]
        self._push = [p] * c.pulse_ticks + [-p] * c.pulse_ticks
        self._measure = [0, *self._push, *([0] * c.observe_ticks)]  # the first tick reads the baseline
        self._samples: list[tuple[int, int]] = []
        self._tick = 0

    def step(self, encoder0: int, encoder1: int) -> tuple[int, Verdict | None]:
        """Command for the next tick, and the verdict once the test is over (a failed test stops at once)."""
        k = self._tick
        self._tick += 1
        if k < len(self._measure):
            self._samples.append((encoder0, encoder1))
            if k + 1 < len(self._measure):
                return self._measure[k + 1], None
            pulse = self._pulses[self._level]
            tried = ""
            if self._level:
                tried = f" after {', '.join(f'{q * VOLTS_PER_COUNT:.1f}' for q in self._pulses[:self._level])} V"
            verdict = judge(self._samples, self.config, pulse, tried)
            base0 = self._samples[0][0]
            moved = max(abs(s[0] - base0) for s in self._samples[1:self.config.pulse_ticks + 2])
            if moved < self.config.arm_min_counts and self._level + 1 < len(self._pulses):
                self._level += 1  # the arm did not move: the next level
                self._start_level()
                return self.step(encoder0, encoder1)
            if not verdict.ok:
                self.verdict = verdict
                return 0, verdict
            self._passed = verdict
            self._back = [-u for u in self._push] + [0]
            return self._back[0], None
        back = k - len(self._measure) + 1
        if back < len(self._back):
            return self._back[back], None
        self.verdict = self._passed
        return 0, self.verdict
