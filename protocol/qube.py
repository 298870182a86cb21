"""The QUBE-Servo 2 balance task's facts, shared by the rig (rpi_bridge, services.qube_sim), the worker and bench.

Paper Section V-B-2: the agent acts every 7 ms and earns +1 per step while the pendulum stays within 7.5 degrees
of upright; the episode ends when it leaves that band and is cut off at a return of 2450 (about 17 s of balance),
which is also the task's termination condition TC (protocol.tasks, "qube" and "qube-local").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

#: The control period: one state read, one action, one env step (s).
PERIOD_S = 0.007
#: The balance band: +1 per step while |alpha| <= this (rad); outside it the episode is over.
BALANCE_BAND = math.radians(7.5)
#: An episode is cut off at this return (steps in the band); TC of the QUBE tasks.
MAX_RETURN = 2450

#: A bridge's phases (rpi_bridge/control.py): a worker answers states in ``ready``/``running``; ``fallen`` and
#: ``fault`` end an episode.
Phase = Literal["calibrating", "self_test", "idle", "resetting", "identifying", "ready", "running", "fallen", "fault"]
#: What a rig's status reports: its phase, or a failed reset, or (its MQTT last will) offline.
RigState = Literal[Phase, "reset_failed", "offline"]


@dataclass(frozen=True)
class ActionSet:
    """What the balance task's actions are: discrete SPI motor counts, or a continuous command in [-1, 1] scaled to
    +-``limit`` counts (1 count = 24/999 V; a positive command drives the arm's angle negative)."""

    name: str
    levels: tuple[int, ...] | None  # the discrete actions' counts; None: continuous
    limit: int  # the largest |command| of the set, counts
    note: str

    @property
    def discrete(self) -> bool:
        return self.levels is not None

    def command(self, action: Any) -> int:
        """The motor counts of one action: a level's index, or a number in [-1, 1] (clipped)."""
        if self.levels is not None:
            return self.levels[int(action)]
        value = float(action[0] if hasattr(action, "__len__") else action)
        value = max(-1.0, min(1.0, value)) if math.isfinite(value) else 0.0
        return round(value * self.limit)


#: The task's action sets (docs/explanation/qube-actions.md justifies their limits). ``paper``, the default, is the
#: paper's three actions of +-60 counts (1.44 V, 7.2 mN m: 15 % of the motor's stall torque at 10 V), weak against a
#: sticky arm's 2-6 mN m of dry friction; ``levels`` and ``voltage`` reach +-150 counts (3.6 V, 18 mN m at stall:
#: three times the highest arm breakaway torque of the rig families we test), with fine steps near zero.
ACTION_SETS: dict[str, ActionSet] = {a.name: a for a in (
    ActionSet("paper", (-60, 0, 60), 60, "the paper's three actions (Section V-B-2): +-60 counts, 1.44 V"),
    ActionSet("levels", (-150, -100, -60, -30, 0, 30, 60, 100, 150), 150,
              "nine levels up to +-150 counts (3.6 V), for PPO and DQN"),
    ActionSet("voltage", None, 150, "a continuous command up to +-150 counts (3.6 V), for SAC (and PPO)"),
)}
DEFAULT_ACTIONS = "paper"


def action_set(name: str | None) -> ActionSet:
    """The action set ``name`` (None: the paper's), or a ValueError listing them."""
    try:
        return ACTION_SETS[name or DEFAULT_ACTIONS]
    except KeyError:
        raise ValueError(f"unknown QUBE action set {name!r}; choose one of {', '.join(ACTION_SETS)}") from None
