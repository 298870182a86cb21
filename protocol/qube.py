"""The QUBE-Servo 2 balance task's facts, shared by the rig (rpi_bridge, services.qube_sim), the worker and bench.

Paper Section V-B-2: the agent acts every 7 ms and earns +1 per step while the pendulum stays within 7.5 degrees
of upright; the episode ends when it leaves that band and is cut off at a return of 2450 (about 17 s of balance),
which is also the task's termination condition TC (protocol.tasks, "qube" and "qube-local").
"""

from __future__ import annotations

import math
from typing import Literal

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
