"""The polarity and sensor self-test at bridge start, as pure code.

With the pendulum hanging still and the arm calibrated, a small doublet (+2 V for 4 ticks, then -2 V for 4 ticks, so
the arm stops again) must move the arm the expected way and both encoders as expected:

- encoder 0 counts up: a positive command turns the arm towards increasing encoder-0 counts (theta decreasing,
  Quanser's convention, rpi_bridge/frame.py);
- encoder 1 first moves up: the hanging pendulum lags the arm, so its first swing under a positive command is
  towards increasing encoder-1 counts (alpha_ddot > 0; services/qube_sim/dynamics.py gives the same sign).

:func:`judge` turns what the encoders did into a verdict that names the likely wiring fault; :class:`SelfTest`
produces the command of each tick and, when the pulse was fine, a mirrored doublet that brings the arm back.
A few degrees of arm and pendulum motion (about 21 counts of arm on the nominal simulated rig); 2 V for 28 ms cannot
hurt a reversed rig.
"""

from __future__ import annotations

from dataclasses import dataclass

from rpi_bridge.frame import MAX_COMMAND, volts_to_counts


@dataclass(frozen=True)
class SelfTestConfig:
    pulse_counts: int = round(volts_to_counts(2.0))  # 83 counts = 2 V
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


@dataclass(frozen=True)
class Verdict:
    ok: bool
    detail: str


def judge(samples: list[tuple[int, int]], config: SelfTestConfig | None = None) -> Verdict:
    """Verdict from the raw (encoder0, encoder1) counts read during the test, the first sample being the
    baseline before the pulse."""
    cfg = config or SelfTestConfig()
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
        return Verdict(False, f"the arm did not move on a {cfg.pulse_counts}-count pulse ({seen}): amplifier, motor "
                       "cable or encoder 0 cable?")
    if pendulum_first == 0:
        return Verdict(False, f"the pendulum encoder did not change while the arm moved ({seen}): encoder 1 cable "
                       "unplugged, or the pendulum is missing?")
    if arm_move > 0 and pendulum_first > 0:
        return Verdict(True, f"polarity and encoders as expected ({seen})")
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
        c = self.config
        push = [c.pulse_counts] * c.pulse_ticks + [-c.pulse_counts] * c.pulse_ticks
        self._measure = [0, *push, *([0] * c.observe_ticks)]  # the first tick reads the baseline
        self._back = [-u for u in push] + [0]
        self._samples: list[tuple[int, int]] = []
        self._tick = 0
        self._passed: Verdict | None = None
        self.verdict: Verdict | None = None

    def step(self, encoder0: int, encoder1: int) -> tuple[int, Verdict | None]:
        """Command for the next tick, and the verdict once the test is over (a failed test stops at once)."""
        k = self._tick
        self._tick += 1
        if k < len(self._measure):
            self._samples.append((encoder0, encoder1))
            if k + 1 < len(self._measure):
                return self._measure[k + 1], None
            verdict = judge(self._samples, self.config)
            if not verdict.ok:
                self.verdict = verdict
                return 0, verdict
            self._passed = verdict
            return self._back[0], None
        back = k - len(self._measure) + 1
        if back < len(self._back):
            return self._back[back], None
        self.verdict = self._passed
        return 0, self.verdict
