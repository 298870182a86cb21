"""The tasks a federation can learn and their termination conditions, shared by the chief and the workers.

TC is the termination condition on the Performance Index (mean return of the last 10 episodes); R_floor is the
lowest return an episode can have, which the chief's sign-safe Eq. 8-10 need (chief/federation.py); R_ceiling the
highest, above which a reported return is a lie the chief refuses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from protocol import qube

#: PI is the mean return of this many most recent episodes (paper Section IV).
PI_WINDOW = 10


@dataclass(frozen=True)
class TaskSpec:
    env_id: str
    tc: float
    r_floor: float
    r_ceiling: float
    max_steps: int
    note: str = ""
    #: The action space: True discrete, False continuous, None not stated (a registered extension task); the
    #: launchers refuse a learner that cannot act in it (protocol/learners.py misfit) before any process starts.
    discrete: bool | None = None
    #: A QUBE-Servo 2 task: its actions are those of the run's action set (protocol/qube.py ACTION_SETS; ``discrete``
    #: is the default set's).
    qube: bool = False


TASKS: dict[str, TaskSpec] = {
    t.env_id: t
    for t in (
        TaskSpec("CartPole-v0", tc=195.0, r_floor=0.0, r_ceiling=200.0, max_steps=200, discrete=True),
        TaskSpec(
            "MountainCarContinuous-v0",
            tc=90.0,
            r_floor=-99.9,
            r_ceiling=100.0,
            max_steps=999,
            discrete=False,
            note="gym's own reward (+100 at the goal minus 0.1*a^2 per step) never exceeds 100, so the paper's "
            "TC of 200 is unreachable; 90 is gym's reward_threshold. Floor: -0.1 * 1^2 * 999 steps.",
        ),
        TaskSpec("Acrobot-v1", tc=-100.0, r_floor=-500.0, r_ceiling=0.0, max_steps=500, discrete=True),
        TaskSpec("Pendulum-v1", tc=-400.0, r_floor=-200 * 16.2736044, r_ceiling=0.0, max_steps=200, discrete=False,
                 note="floor: 200 steps at the largest cost pi^2 + 0.1*8^2 + 0.001*2^2 (paper Eq. 12)"),
        TaskSpec("qube", tc=float(qube.MAX_RETURN), r_floor=0.0, r_ceiling=float(qube.MAX_RETURN),
                 max_steps=qube.MAX_RETURN, discrete=True, qube=True,
                 note=f"QUBE-Servo 2 balance: +1 per {qube.PERIOD_S * 1e3:g} ms step while |alpha| <= "
                 f"{math.degrees(qube.BALANCE_BAND):g} deg (paper Section V-B-2), on a rig reached over MQTT (a real "
                 "one behind rpi_bridge, or services.qube_sim)"),
        TaskSpec("qube-local", tc=float(qube.MAX_RETURN), r_floor=0.0, r_ceiling=float(qube.MAX_RETURN),
                 max_steps=qube.MAX_RETURN, discrete=True, qube=True,
                 note="the same balance task on the simulated rig in the worker's own process (no MQTT)"),
    )
}


def task(env_id: str) -> TaskSpec:
    """The spec of a supported env id, or a ValueError listing the supported ones."""
    try:
        return TASKS[env_id]
    except KeyError:
        raise ValueError(f"unsupported env {env_id!r}; supported: {', '.join(TASKS)}") from None


def solved(returns: list[float], tc: float) -> bool:
    """Learning is complete when the mean of the last PI_WINDOW returns reaches TC."""
    return len(returns) >= PI_WINDOW and performance_index(returns) >= tc


def performance_index(returns: list[float]) -> float:
    """PI: mean return of the last PI_WINDOW episodes (of all episodes while there are fewer)."""
    if not returns:
        return float("nan")
    window = returns[-PI_WINDOW:]
    return float(sum(window) / len(window))


def worker_seed(base_seed: int, index: int) -> int:
    """Seed of worker ``index`` (its network, sampling, env and device noise; also its simulated rig's physics).

    Spaced by 1000 so that runs with base seeds 1, 2, 3 ... share no worker seed (up to 1000 workers).
    """
    return base_seed * 1000 + index


def worker_index(seed: int) -> int:
    """The index of the worker (and of its rig) whose seed is ``seed``: the inverse of :func:`worker_seed`."""
    return seed % 1000
