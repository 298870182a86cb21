"""The learners a worker can run, by name: a fact of the wire contract (a worker's hello names its learner, and the
chief admits only workers of the run's learner), so it lives here, torch-free. worker/learners.py maps each name to
its module.

Every learner has the same seams (worker/learners.py ``Learner``), so every federation strategy federates every
learner. Experience never leaves the device: a learner's trajectory memory or replay buffer stays on its worker.
"""

from __future__ import annotations

from protocol import qube
from protocol.tasks import TASKS

#: The paper's learner (Section III): every default names it.
DEFAULT = "ppo"

#: Name -> what it is, in one line.
LEARNERS: dict[str, str] = {
    "ppo": "Actor-Critic PPO, the paper's on-policy learner (worker/ppo.py): trajectory memory, K clipped steps per "
           "episode",
    "sac": "Soft Actor-Critic, off-policy (worker/sac.py): replay buffer, twin soft Q critics, entropy temperature; "
           "a categorical policy for discrete actions",
    "dqn": "Double DQN with n-step returns, off-policy (worker/dqn.py): replay buffer, target network, epsilon-greedy; "
           "discrete actions only",
}


#: The learners that act only in a discrete action space.
DISCRETE_ONLY = frozenset({"dqn"})

#: The learners whose policy a warm start can temper (--warm-temperature: worker/ppo.py ``temper``). SAC tunes its
#: entropy itself, and DQN's exploration is its epsilon schedule.
TEMPERED = ("ppo",)


def names() -> list[str]:
    return list(LEARNERS)


def check(name: str) -> str:
    """``name`` when it is a learner, else a ValueError listing them."""
    if name not in LEARNERS:
        raise ValueError(f"unknown learner {name!r}; choose one of {', '.join(LEARNERS)}")
    return name


def misfit(name: str, env_id: str, qube_actions: str | None = None) -> str | None:
    """Why learner ``name`` cannot learn task ``env_id`` (None: it can, or the task does not state its actions). On
    the QUBE tasks the action set ``qube_actions`` (protocol/qube.py) decides whether the actions are discrete."""
    spec = TASKS.get(env_id)
    discrete = spec.discrete if spec is not None else None
    if spec is not None and spec.qube and qube_actions is not None:
        discrete = qube.action_set(qube_actions).discrete
    if name in DISCRETE_ONLY and discrete is False:
        fits = ", ".join(n for n in LEARNERS if n not in DISCRETE_ONLY)
        which = f" with --qube-actions {qube_actions}" if spec is not None and spec.qube and qube_actions else ""
        return f"learner {name!r} needs discrete actions and {env_id}'s are continuous{which}; use {fits}"
    return None
