"""worker.envs: the task registry and the per-device action noise (paper Section V-B-1)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from protocol.tasks import TASKS, TaskSpec
from worker.envs import ENVS, DeviceNoise, EnvSpec, env_spec, make_env, register_env

torch.set_num_threads(1)

SUPPORTED = ("CartPole-v0", "MountainCarContinuous-v0", "Acrobot-v1", "Pendulum-v1")


def rollout(env: gym.Env, actions: list, seed: int) -> np.ndarray:
    """Observations of a fixed action sequence (stops at the end of the episode)."""
    obs, _ = env.reset(seed=seed)
    seen = [obs]
    for action in actions:
        obs, _, terminated, truncated, _ = env.step(action)
        seen.append(obs)
        if terminated or truncated:
            break
    return np.array(seen)


def actions_for(env_id: str, n: int = 60) -> list:
    rng = np.random.default_rng(0)
    space = gym.make(env_id).action_space
    if isinstance(space, gym.spaces.Discrete):
        return [int(a) for a in rng.integers(0, space.n, n)]
    return [rng.uniform(-1, 1, space.shape).astype(np.float32) * space.high for _ in range(n)]


def test_registry_matches_protocol_tasks() -> None:
    assert set(SUPPORTED) <= set(ENVS)
    for env_id in SUPPORTED:
        spec, task = env_spec(env_id), TASKS[env_id]
        assert (spec.tc, spec.r_floor, spec.max_steps) == (task.tc, task.r_floor, task.max_steps)
    assert env_spec("MountainCarContinuous-v0").tc == 90.0 and env_spec("Pendulum-v1").r_floor < -3000
    assert env_spec("CartPole-v0").ppo_config() == env_spec("CartPole-v0").config  # a copy of the preset


def test_unknown_env_id_lists_the_supported_ones() -> None:
    with pytest.raises(ValueError, match=r"supported: .*CartPole-v0.*Pendulum-v1"):
        make_env("LunarLander-v3", seed=0)
    with pytest.raises(ValueError, match="already registered"):
        register_env(env_spec("CartPole-v0"))


def test_register_env_extension_point() -> None:
    built = []

    def factory(spec: EnvSpec, seed: int, noise: DeviceNoise, rig: str = "") -> gym.Env:
        built.append((spec.env_id, seed, noise.scale, rig))
        return gym.make("CartPole-v1")

    spec = register_env(EnvSpec(TaskSpec("test-device", tc=1.0, r_floor=0.0, r_ceiling=1.0, max_steps=10), None,
                                 factory=factory))
    try:
        env = make_env("test-device", seed=5, device_noise=DeviceNoise(scale=0.5), rig="r1")
        assert isinstance(env.action_space, gym.spaces.Discrete) and built == [("test-device", 5, 0.5, "r1")]
        with pytest.raises(ValueError, match="no extra arguments"):
            make_env("CartPole-v0", seed=0, rig="r1")
        with pytest.raises(ValueError, match="gym_id or a factory"):
            register_env(EnvSpec(TaskSpec("nothing", tc=1.0, r_floor=0.0, r_ceiling=1.0, max_steps=1), gym_id=None))
    finally:
        ENVS.pop(spec.env_id)


def test_device_offsets_differ_by_worker_seed_and_are_reproducible() -> None:
    offsets = [make_env("Pendulum-v1", seed=s).offset for s in range(200)]
    assert len(set(offsets)) == 200
    assert make_env("Pendulum-v1", seed=3).offset == offsets[3]
    # a draw per worker from N(0.002, 0.0005): the sample mean is within 4 standard errors
    assert abs(np.mean(offsets) - 0.002) < 4 * 0.0005 / np.sqrt(200)
    assert 0.0003 < np.std(offsets) < 0.0007


def test_step_noise_is_offset_plus_jitter_and_reproducible() -> None:
    def noises(seed: int) -> list[float]:
        env = make_env("CartPole-v0", seed=seed)
        env.reset(seed=0)
        out = []
        for i in range(20):
            env.step(i % 2)
            out.append(env.last_noise)
            # the push force of this device: force_mag * (1 + noise)
            assert env.unwrapped.force_mag == pytest.approx(10.0 * (1.0 + env.last_noise))
        return out

    first = noises(1)
    assert first == noises(1) and first != noises(2)
    assert len(set(first)) == 20 and all(0.0 < n < 0.005 for n in first)
    scaled = make_env("CartPole-v0", seed=1, device_noise=DeviceNoise(scale=2.0))
    scaled.reset(seed=0)
    scaled.step(0)
    assert scaled.last_noise == pytest.approx(2.0 * first[0])


def test_acrobot_noise_shifts_the_applied_torque() -> None:
    env = make_env("Acrobot-v1", seed=4)
    env.reset(seed=0)
    env.step(2)
    noise = env.last_noise
    assert env.unwrapped.AVAIL_TORQUE == pytest.approx([-1 + noise, noise, 1 + noise])
    assert gym.make("Acrobot-v1").unwrapped.AVAIL_TORQUE == [-1.0, 0.0, 1]  # other devices are untouched


@pytest.mark.filterwarnings("ignore:.*is out of date")
@pytest.mark.parametrize("env_id", SUPPORTED)
def test_scale_zero_leaves_the_env_unchanged(env_id: str) -> None:
    actions = actions_for(env_id)
    plain = rollout(gym.make(env_id), actions, seed=11)
    quiet = rollout(make_env(env_id, seed=3, device_noise=DeviceNoise(scale=0.0)), actions, seed=11)
    np.testing.assert_array_equal(plain, quiet)
    noisy = rollout(make_env(env_id, seed=3), actions, seed=11)
    assert noisy.shape != plain.shape or not np.array_equal(noisy, plain)


def test_box_actions_are_clipped_then_noised() -> None:
    quiet = make_env("Pendulum-v1", seed=0, device_noise=DeviceNoise(scale=0.0))
    plain = gym.make("Pendulum-v1")
    a = rollout(quiet, [np.array([5.0], np.float32)] * 5, seed=2)  # a raw policy sample beyond the limit
    b = rollout(plain, [np.array([2.0], np.float32)] * 5, seed=2)
    np.testing.assert_array_equal(a, b)
    mcc = make_env("MountainCarContinuous-v0", seed=0)
    mcc.reset(seed=0)
    mcc.step(np.array([0.5], np.float32))
    assert 0.0 < mcc.last_noise < 0.005


def test_episode_limits() -> None:
    env = make_env("CartPole-v0", seed=0)
    assert env.spec.max_episode_steps == 200
    assert make_env("MountainCarContinuous-v0", seed=0).spec.max_episode_steps == 999


def test_device_noise_validation() -> None:
    with pytest.raises(ValueError):
        DeviceNoise(scale=-1.0)
    with pytest.raises(ValueError):
        DeviceNoise(std=float("nan"))
