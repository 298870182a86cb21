"""Rig time: what a lab pays for a controller, in seconds of a rig's life (QUBE-Servo 2 tasks only).

Per episode a rig spends ``balance_s`` under the policy (``balance_steps`` control periods) and ``reset_s`` swinging
the pendulum up again; its **rig time** is their sum. Between episodes it may also stand **idle**, waiting for the
federation's answer to its submission: a round closes only when its slowest contributor has submitted (under a
bounded staleness S a worker waits only for the answer to its round S rounds back).

How the seconds are obtained depends on the rig's clock (docs/explanation/qube.md):

- ``realtime`` and ``delayed``: measured by the worker (wall time of each reset and episode; idle = the wall time it
  waits for the chief's answer), sent with each submission;
- ``lockstep`` and ``qube-local``: from the simulated clock: balance seconds = balance steps x the period (PERIOD_S),
  reset seconds = the ticks the swing-up took x the period, and idle seconds modelled from the records by
  :func:`model_idle`, since a lockstep rig's simulated time stands still while it waits.

Pure: no clocks are read here.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Literal

from protocol.qube import PERIOD_S

#: The largest number of seconds a field of rig time may carry on the wire (about 116 days).
SECONDS_LIMIT = 1e7
#: A rig's clock: ``realtime`` (a real rig, or services.qube_sim ticking in real time), ``lockstep`` (simulated time,
#: one period per answered state) or ``delayed`` (lockstep with the real loop's delays and misses).
Clock = Literal["lockstep", "delayed", "realtime"]
#: The clocks under which a worker measures its rig time in wall seconds (the others: from the simulated clock).
MEASURED_CLOCKS: frozenset[str] = frozenset({"realtime", "delayed"})
#: The rig-time fields of a WorkerUpdate/MatureParams and of its episode's record in metrics.jsonl.
RIG_FIELDS = ("balance_steps", "balance_s", "reset_s", "idle_s")


def ticks_to_s(ticks: int) -> float:
    """Seconds of ``ticks`` control periods of the simulated clock."""
    return ticks * PERIOD_S


@dataclass(frozen=True)
class EpisodeTime:
    """One episode's rig time: ``balance_steps`` control periods under the policy (``balance_s`` seconds) after a
    swing-up of ``reset_s`` seconds; ``idle_s`` the measured wait for the federation since the last submission
    (None when not measured: modelled later by :func:`model_idle`)."""

    balance_steps: int
    balance_s: float
    reset_s: float
    idle_s: float | None = None

    @property
    def rig_s(self) -> float:
        """Rig time of the episode: balance plus reset."""
        return self.balance_s + self.reset_s


@dataclass
class RigTotals:
    """A rig's sums over its episodes (summary.json ``workers[]``, the console summary, the dashboard)."""

    balance_steps: int = 0
    balance_s: float = 0.0
    reset_s: float = 0.0
    idle_s: float = 0.0

    @property
    def rig_s(self) -> float:
        return self.balance_s + self.reset_s

    def add(self, episode: EpisodeTime) -> None:
        self.balance_steps += episode.balance_steps
        self.balance_s += episode.balance_s
        self.reset_s += episode.reset_s
        self.idle_s += episode.idle_s or 0.0

    def fields(self, digits: int = 3) -> dict[str, float | int]:
        """The totals as summary.json keys them (seconds rounded to ``digits``)."""
        balance, reset = round(self.balance_s, digits), round(self.reset_s, digits)
        return {"balance_steps": self.balance_steps, "balance_s": balance, "reset_s": reset,
                "idle_s": round(self.idle_s, digits), "rig_s": round(balance + reset, digits)}


@dataclass
class IdleModel:
    """Idle seconds of rigs whose clock stands still while they wait (lockstep), modelled round by round.

    Each rig has its own clock, ``free``: when it may play its next episode. In a round, a contributor plays
    (resets and balances) for its episode's rig time, so it is ready at ``free + rig_s``; the round closes when its
    slowest contributor is ready, ``close = max(ready)``. With ``staleness`` S = 0 each contributor waits for that
    close (``close - ready``) and is free again at ``close``. Under a bounded staleness S it waits only for the
    answer to its own round S contributions back (``gate``: that round's close, 0 when it has none yet): it is free
    at ``max(ready, gate)`` and waits the difference. A rig that sits a round out (finished, timed out) neither
    waits nor moves.
    """

    free: dict[str, float] = field(default_factory=dict)
    idle: dict[str, float] = field(default_factory=dict)
    staleness: int = 0
    closes: dict[str, list[float]] = field(default_factory=dict)  # each rig's last S + 1 rounds' close times

    def close(self, contributions: Mapping[str, float]) -> float:
        """Close one round whose contributors spent ``contributions`` (worker -> rig seconds, 0 for a later step of
        a per-step strategy's episode); returns its close time on the simulated clock."""
        if not contributions:
            return max(self.free.values(), default=0.0)
        ready = {w: self.free.get(w, 0.0) + s for w, s in contributions.items()}
        close = max(ready.values())
        for w, at in ready.items():
            closes = self.closes.setdefault(w, [])
            closes.append(close)
            gate = closes[-1 - self.staleness] if len(closes) > self.staleness else 0.0
            del closes[:-1 - self.staleness]
            self.idle[w] = self.idle.get(w, 0.0) + max(0.0, gate - at)
            self.free[w] = max(at, gate)
        return close


def model_idle(rounds: Iterable[Mapping[str, float]], staleness: int = 0) -> dict[str, float]:
    """Each worker's idle seconds over ``rounds`` (in order; each: contributor -> that round's rig seconds), whose
    workers may leave ``staleness`` of their rounds unanswered."""
    model = IdleModel(staleness=staleness)
    for contributions in rounds:
        model.close(contributions)
    return model.idle
