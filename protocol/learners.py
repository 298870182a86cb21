"""The learners a worker can run, by name: a fact of the wire contract (a worker's hello names its learner, and the
chief admits only workers of the run's learner), so it lives here, torch-free. worker/learners.py maps each name to
its module.

Every learner has the same seams (worker/learners.py ``Learner``), so every federation strategy federates every
learner. Experience never leaves the device: a learner's trajectory memory or replay buffer stays on its worker.
"""

from __future__ import annotations

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


def names() -> list[str]:
    return list(LEARNERS)


def check(name: str) -> str:
    """``name`` when it is a learner, else a ValueError listing them."""
    if name not in LEARNERS:
        raise ValueError(f"unknown learner {name!r}; choose one of {', '.join(LEARNERS)}")
    return name
