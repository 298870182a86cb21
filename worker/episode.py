"""Building a worker's environment and learner, and running one episode (the inner loop of Algorithm 2).

No training happens inside an episode: between a state and its action there is only the actor's forward pass,
which is what keeps a real rig's 7 ms deadline.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym

from protocol import learners as names
from worker import learners
from worker.envs import DeviceNoise, env_spec, make_env
from worker.learners import Learner


def build_learner_and_env(
    env_id: str,
    seed: int,
    device_noise: float,
    init_seed: int | None = None,
    rig_id: str | None = None,
    conn: Any = None,
    spec_only: bool = False,
    env_options: dict[str, Any] | None = None,
    algo: str = names.DEFAULT,
    overrides: dict[str, Any] | None = None,
) -> tuple[gym.Env, Learner]:
    """The env of this device and a learner ``algo`` (worker/learners.py) with the env's preset for it (and
    ``overrides`` of its fields), both seeded by ``seed`` (``init_seed``: the networks' initial weights, shared by the
    workers of a run).

    ``rig_id`` and ``conn`` (an open MqttConnection) are for envs that drive a rig over MQTT; ``spec_only`` builds
    a throwaway pair just to learn the actor's shape; ``env_options`` go to the factory of such envs too (e.g. the
    ``rig_profile`` and ``randomize`` of qube-local).
    """
    spec = env_spec(env_id)
    noise = DeviceNoise(scale=device_noise)
    extra = {"rig_id": rig_id, "conn": conn, "probe": spec_only, **(env_options or {})} if spec.factory else {}
    env = make_env(env_id, seed, noise, **extra)
    config = spec.learner_config(algo, **(overrides or {}))
    learner = learners.get(algo).learner_class(env.observation_space, env.action_space, config, seed=seed,
                                               init_seed=init_seed)
    return env, learner


def run_episode(env: gym.Env, learner: Learner, seed: int | None = None) -> tuple[float, int]:
    """Act until the episode ends, storing every transition in the learner's trajectory memory.

    Returns the episode's return and its number of steps.
    """
    obs, _ = env.reset(seed=seed)
    ret, steps = 0.0, 0
    while True:
        action = learner.act(obs)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        learner.remember(obs, action, float(reward), next_obs, bool(terminated), bool(truncated))
        ret += float(reward)
        steps += 1
        obs = next_obs
        if terminated or truncated:
            return ret, steps
