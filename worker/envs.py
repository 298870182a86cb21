"""The environments a worker learns, with per-device variation (paper Section V-B-1), and PPO presets.

Every supported task has an ``EnvSpec``: its ``protocol.tasks.TaskSpec`` (the termination condition TC on the
Performance Index, the mean return of the last 10 episodes; R_floor, the lowest return an episode can have, for the
chief's sign-safe Eq. 8-10; the episode length), read from the table the chief uses too, so both sides always agree;
the gymnasium id; and a tuned ``PPOConfig``.

Extension point: ``register_env(EnvSpec(TaskSpec(...), None, factory=...))`` adds a task whose environment is not a
plain gymnasium id (the QUBE-Servo 2 over MQTT); ``factory(spec, seed, device_noise)`` builds it.

MountainCarContinuous-v0: the paper's TC of 200 is above the largest return gym's reward allows (+100 once at
the goal minus 0.1 a^2 per step, so every return is < 100; the authors' code reshaped the reward to make 200
reachable). We keep gym's reward and use gym's own bar, 90. R_floor = -0.1 * 1^2 * 999 steps = -99.9.

Presets, measured with ``python -m worker.train_local --env ENV --seed S`` (one worker, no federation, the
paper's device noise on). "Episodes" counts env episodes up to and including the one whose return brings PI
to TC; the seeds past 3 ran during tuning with the same settings. Wall time: seeds 1-3, two runs at a time
under ``nice -n 10`` on the shared 2-core VM.

Deviations from the paper's configuration (details beside each ``register_env`` below):

- CartPole-v0: actor_lr 3e-4 (the paper's 1e-3 collapses on some seeds, see below).
- Acrobot-v1: reward_scale 0.1.
- Pendulum-v1: gamma 0.9, gae_lambda 0.95, reward_scale 0.1, max_grad_norm 0.5.
- MountainCarContinuous-v0: log_std_init 1.0, normalize_obs, reward_scale 0.1.

==============================  ============================================  ====================
env (TC)                        episodes to PI >= TC, per seed                wall s, seeds 1-3
==============================  ============================================  ====================
CartPole-v0 (195)               s1000-1003: 32 61 67 39; s2000-2003: 106 52   (12/12 seeds, 1.9-6.1)
                                88 24; s3000-3003: 61 34 45 41
Acrobot-v1 (-100)               s1-10: 18 41 69 24 39 23 29 21 22 28          2.4 4.7 6.7
Pendulum-v1 (-400)              s1-4: 179 270 235 151                         14.2 21.1 13.7
MountainCarContinuous-v0 (90)   s1-5: 28 38 40 24 23                          2.9 3.8 4.1
==============================  ============================================  ====================

Without its preset (the paper's configuration): CartPole-v0 collapses to always pushing one way (entropy 0,
PI about 9) on 4 of those 12 seeds (1000-1003, 2000-2003, 3000-3003 are the seeds of workers 0-3 in runs with
base seeds 1-3; seeds 1-10 happened to all solve, in 20-140 episodes); Acrobot-v1 seed 3 collapses to a
deterministic policy and stays at -500 (600 episodes; seeds 1-2 solve in 39 and 55); Pendulum-v1 seed 1 is at
PI -1559 after 600 episodes; MountainCarContinuous-v0 seed 1 is at PI -15 after 100 episodes (it learns to stand still).
For scale (Stable-Baselines3 2.9 PPO with the rl-baselines3-zoo hyperparameters, seeds 1-3, measured on the same VM
under the same stop rule; ``python -m bench.sb3_ref`` repeats it): CartPole 92-151, Acrobot 206-261, Pendulum
175-195, MountainCarContinuous 10-15 episodes.
"""

from __future__ import annotations

import random
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any, SupportsFloat

import gymnasium as gym
import numpy as np

from protocol.tasks import TASKS, TaskSpec
from worker import learners
from worker.dqn import DQNConfig
from worker.ppo import PPOConfig
from worker.qube_env import make_qube_env, make_qube_local_env
from worker.sac import SACConfig

# ----------------------------------------------------------------------------------------------------
# Per-device variation
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DeviceNoise:
    """The paper's per-device action noise: N(mean, std), times ``scale`` (0 turns it off).

    Section V-B-1: the same torque command moves each QUBE-Servo 2 by a slightly different amount
    (measured mean difference 0.002, standard deviation 0.0005), so the simulations add Gaussian noise with
    those moments to every action.
    """

    mean: float = 0.002
    std: float = 0.0005
    scale: float = 1.0

    def __post_init__(self) -> None:
        if not all(np.isfinite([self.mean, self.std, self.scale])) or self.std < 0 or self.scale < 0:
            raise ValueError(f"invalid DeviceNoise {self}: need finite values, std >= 0 and scale >= 0")


class DeviceNoiseWrapper(gym.Wrapper):
    """One device's actuation error: a fixed per-device offset plus per-step jitter.

    At construction the device draws its offset once, ``offset ~ N(mean, std)``, from its own seed, so every
    worker is a slightly different device and the same seed is the same device. Each step then perturbs the
    action's physical effect by ``noise = scale * (offset + N(0, std))``:

    - ``"action"`` (Box actions, e.g. Pendulum torque, MountainCar force): the action, first clipped to the
      action space, gets ``+ noise`` (the env clips again at its own limits, as a saturating motor would);
    - ``"force"`` (CartPole): the push force magnitude is ``force_mag * (1 + noise)``, a relative error;
    - ``"torque"`` (Acrobot): the applied torque of every discrete choice is ``torque + noise``
      (torques are -1, 0, +1, the same scale as the continuous tasks' actions).

    With ``scale == 0`` the environment is untouched (Box actions are still clipped to the space).
    ``last_noise`` holds the noise of the latest step.
    """

    TARGETS = ("action", "force", "torque")

    def __init__(self, env: gym.Env, noise: DeviceNoise, seed: int, target: str) -> None:
        super().__init__(env)
        if target not in self.TARGETS:
            raise ValueError(f"noise target must be one of {self.TARGETS}, not {target!r}")
        if target == "action" and not isinstance(env.action_space, gym.spaces.Box):
            raise ValueError("the 'action' noise target needs a Box action space")
        self.noise, self.target = noise, target
        self.rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xDE7]))  # device stream
        self.offset = float(self.rng.normal(noise.mean, noise.std))
        self.last_noise = 0.0
        base: Any = env.unwrapped  # CartPoleEnv or AcrobotEnv for the force and torque targets
        self._base_force = float(base.force_mag) if target == "force" else 0.0
        self._base_torques = list(base.AVAIL_TORQUE) if target == "torque" else []

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        if isinstance(self.action_space, gym.spaces.Box):
            space = self.action_space
            action = np.clip(np.asarray(action, dtype=space.dtype), space.low, space.high)
        if self.noise.scale == 0.0:
            return self.env.step(action)
        base: Any = self.env.unwrapped
        self.last_noise = self.noise.scale * (self.offset + float(self.rng.normal(0.0, self.noise.std)))
        if self.target == "action":
            action = (action + self.last_noise).astype(self.action_space.dtype)
        elif self.target == "force":
            base.force_mag = self._base_force * (1.0 + self.last_noise)
        else:  # an instance attribute shadows AcrobotEnv.AVAIL_TORQUE for this device only
            base.AVAIL_TORQUE = [t + self.last_noise for t in self._base_torques]
        return self.env.step(action)


def rng_states(env: gym.Env) -> list[dict[str, Any]]:
    """The state of every RNG that decides what ``env`` does next (for a worker's resumable state, worker/resume.py):
    per layer of its wrapper chain, outermost first, each numpy Generator or ``random.Random`` it holds (the device
    noise's stream, the task's ``np_random``). Other state of an env (a rig's physics) is not in it."""
    return [{name: value.bit_generator.state if isinstance(value, np.random.Generator) else value.getstate()
             for name, value in vars(layer).items() if isinstance(value, (np.random.Generator, random.Random))}
            for layer in _layers(env)]


def set_rng_states(env: gym.Env, states: list[dict[str, Any]]) -> None:
    """Restore ``rng_states`` output into an env built like the one it was taken from (a ValueError if it is not)."""
    layers = _layers(env)
    if len(states) != len(layers):
        raise ValueError(f"RNG states of {len(states)} env layers for an env of {len(layers)}")
    for layer, state in zip(layers, states, strict=True):
        for name, value in state.items():
            if isinstance(value, dict):  # a numpy Generator's bit generator state (made if the env had none yet)
                rng = np.random.Generator(getattr(np.random, value["bit_generator"])())
                rng.bit_generator.state = value
                setattr(layer, name, rng)
            else:
                rng_py = random.Random()
                rng_py.setstate(value)
                setattr(layer, name, rng_py)


def _layers(env: gym.Env) -> list[Any]:
    """``env`` and every env it wraps, outermost first."""
    layers: list[Any] = [env]
    while isinstance(layers[-1], gym.Wrapper):
        layers.append(layers[-1].env)
    return layers


# ----------------------------------------------------------------------------------------------------
# Specs and registry
# ----------------------------------------------------------------------------------------------------

#: ``factory(spec, seed, device_noise, **extra)``: builds a device's env; ``extra`` are the keyword arguments
#: given to ``make_env`` (e.g. the MQTT connection and rig id of a QUBE-Servo 2).
EnvFactory = Callable[..., gym.Env]


@dataclass(frozen=True)
class EnvSpec:
    """A task: how to build its environment and how to learn it. When learning is finished (TC), the lowest return
    (R_floor) and the episode length are the task's facts in ``protocol.tasks``, which the chief reads too."""

    task: TaskSpec  # the task's facts (protocol.tasks.TASKS)
    gym_id: str | None  # gymnasium id, or None when ``factory`` builds the env
    config: PPOConfig = field(default_factory=PPOConfig)  # PPO preset; use ``ppo_config()`` for a copy
    #: Presets of the other learners (worker/learners.py), by learner name; a learner without one takes its defaults.
    presets: Mapping[str, Any] = field(default_factory=dict)
    noise_target: str = "action"  # how DeviceNoise acts, see DeviceNoiseWrapper
    factory: EnvFactory | None = None  # custom builder ``factory(spec, seed, device_noise, **extra)``

    @property
    def env_id(self) -> str:
        """The name used across the system (protocol.tasks, CLI, messages)."""
        return self.task.env_id

    @property
    def tc(self) -> float:
        """Termination condition: learning ends when PI (mean of the last 10 returns) >= tc."""
        return self.task.tc

    @property
    def r_floor(self) -> float:
        """Lowest possible episode return."""
        return self.task.r_floor

    @property
    def max_steps(self) -> int:
        """Episode length limit."""
        return self.task.max_steps

    def ppo_config(self, **overrides: Any) -> PPOConfig:
        """A fresh copy of the preset, with ``overrides`` applied."""
        return replace(self.config, **overrides)

    def learner_config(self, algo: str, **overrides: Any) -> Any:
        """A fresh copy of learner ``algo``'s preset for this task (its defaults when the task has none), with
        ``overrides`` applied."""
        if algo == "ppo":
            return self.ppo_config(**overrides)
        preset = self.presets.get(algo)
        return replace(preset, **overrides) if preset is not None else learners.get(algo).config_class(**overrides)


def _task(env_id: str, **kwargs: Any) -> EnvSpec:
    """A gymnasium task of protocol.tasks (its env id is its gymnasium id)."""
    return EnvSpec(task=TASKS[env_id], gym_id=env_id, **kwargs)


ENVS: dict[str, EnvSpec] = {}


def register_env(spec: EnvSpec, overwrite: bool = False) -> EnvSpec:
    """Add a task to the registry (the extension point for the QUBE-Servo 2 and other devices)."""
    if spec.env_id in ENVS and not overwrite:
        raise ValueError(f"env {spec.env_id!r} is already registered")
    if spec.gym_id is None and spec.factory is None:
        raise ValueError(f"env {spec.env_id!r} needs a gym_id or a factory")
    ENVS[spec.env_id] = spec
    return spec


def env_spec(env_id: str) -> EnvSpec:
    """The spec of a registered env id; ValueError listing the supported ones otherwise."""
    try:
        return ENVS[env_id]
    except KeyError:
        raise ValueError(f"unsupported env {env_id!r}; supported: {', '.join(sorted(ENVS))}") from None


def make_env(env_id: str, seed: int, device_noise: DeviceNoise | None = None, render_mode: str | None = None,
             **extra: Any) -> gym.Env:
    """Build the environment of one device (worker).

    ``seed`` selects the device (its noise offset and jitter stream); seed the dynamics as usual with
    ``env.reset(seed=seed)`` on the first reset. ``device_noise`` defaults to the paper's DeviceNoise().
    Raw (unclipped) Box actions may be passed to ``step``: the wrapper clips them to the action space.
    ``render_mode`` (gymnasium tasks only, e.g. "rgb_array" for a video) is passed to ``gym.make``.
    ``extra`` keyword arguments go to the spec's factory (gymnasium tasks take none).
    """
    spec = env_spec(env_id)
    noise = DeviceNoise() if device_noise is None else device_noise
    if spec.factory is not None:
        if render_mode is not None:
            raise ValueError(f"{env_id} cannot be rendered (render_mode is for the gymnasium tasks)")
        return spec.factory(spec, seed, noise, **extra)
    if extra:
        raise ValueError(f"{env_id} is a gymnasium task and takes no extra arguments, got {sorted(extra)}")
    assert spec.gym_id is not None  # register_env: a spec without a factory has a gymnasium id
    with warnings.catch_warnings():  # CartPole-v0 is deliberate (the paper's task): no deprecation notice
        warnings.filterwarnings("ignore", message=".*is out of date.*")
        env = gym.make(spec.gym_id, max_episode_steps=spec.max_steps, disable_env_checker=True,
                       render_mode=render_mode)
    return DeviceNoiseWrapper(env, noise, seed, spec.noise_target)


# ----------------------------------------------------------------------------------------------------
# The supported tasks and their presets (see the module docstring for the measured results)
# ----------------------------------------------------------------------------------------------------

# The paper's configuration with a lower actor learning rate: at 1e-3 the actor collapses to a deterministic
# policy (entropy 0, it never recovers) on 4 of 12 seeds; at 3e-4 all 12 solved (table above).
# DQN, tuned for 4 workers under ``sync`` on tuning seeds 1-3 only (python -m bench.tune CartPole-v0 sync
# --algo dqn --max-episodes 60; bench/results/tuning.jsonl lines 7-9, line 6 is K = 50): learning from 64 transitions
# on (the default 500 is about 25 early episodes of one worker), epsilon down to 0.02 within the first 500 env steps,
# K = 200 gradient steps per episode (K = 50: stuck near return 100, unsolved at 60 episodes), the target network
# copied every 200 steps, batches of 128 (64 left seed 2 unsolved at 50 episodes in a quick replica of sync outside
# the federation, not logged). Last worker's episodes, seeds 1-3: 19, 56, 38. utd_ratio (per-episode strategies and
# independent workers) keeps its default 1.0, untuned.
CARTPOLE_DQN = DQNConfig(learning_starts=64, eps_decay_steps=500, eps_end=0.02, update_epochs=200,
                         target_update_interval=200, batch_size=128)
register_env(_task("CartPole-v0", config=PPOConfig(actor_lr=3e-4), noise_target="force",
                   presets={"dqn": CARTPOLE_DQN}))

# Returns of -1 per step (down to -500) are far from the critic's initial 0: with the L1 loss of Eq. 3 the
# critic needs many episodes to catch up, the advantages are noise meanwhile, and some seeds collapse to a
# deterministic policy that never reaches the goal. Scaling rewards by 0.1 fixes that.
# DQN on Acrobot-v1: CartPole-v0's DQN values with epsilon falling over 1,000 env steps (an early
# Acrobot episode is 500), tried on tuning seed 1 only (python -m bench.tune Acrobot-v1 sync --algo dqn --seeds 1
# --max-episodes 60 --set ...; bench/results/tuning.jsonl): every worker solved, the last at episode 38 (6,834 steps).
# Report seeds 101-110 (docs/results.md): sync 48 episodes, independent 47.5; no gain from sync.
ACROBOT_DQN = replace(CARTPOLE_DQN, eps_decay_steps=1000)
register_env(_task("Acrobot-v1", config=PPOConfig(reward_scale=0.1), noise_target="torque",
                   presets={"dqn": ACROBOT_DQN}))

# As in the SB3 zoo: a short horizon (gamma 0.9, lambda 0.95); plus reward scale 0.1 (costs up to -16.3 per
# step) and gradient-norm clipping 0.5 (rare large steps from Gaussian tails otherwise undo progress).
# SAC, tuned for 4 workers under ``sync`` on tuning seeds 1-2 only (python -m deploy.inprocess-style runs,
# docs/explanation/learners.md): the zoo's Pendulum learning rate (1e-3 for every network), learning from 200
# transitions on, and two gradient steps per env step (K = 400 per 200-step episode under sync, utd_ratio 2 for the
# per-episode strategies). Smaller networks and batches than SAC's defaults, for the 2-core machine (tuning runs, last
# worker's episodes: 128x128, batch 256, K 600, seed 1: 13 under sync, 17 independent; this preset, seed 2: 16 under
# sync, in 214 s against about 350 s).
PENDULUM_SAC = SACConfig(hidden_sizes=(64, 64), actor_lr=1e-3, critic_lr=1e-3, batch_size=128, learning_starts=200,
                         update_epochs=400, utd_ratio=2.0)
register_env(_task("Pendulum-v1", config=PPOConfig(
    gamma=0.9, gae_lambda=0.95, reward_scale=0.1, max_grad_norm=0.5), presets={"sac": PENDULUM_SAC}))

# Exploration help: the paper's settings learn to stand still (the -0.1 a^2 cost, the goal never seen).
# A wide initial Gaussian (std e^1 = 2.7, clipped to [-1, 1] by the env: near bang-bang random pushes) reaches
# the goal by chance in the first episodes; observation normalisation (the velocity is O(0.01)) is essential
# to learn from it; reward scale 0.1 helps a little.
# SAC: its untrained policy with white noise pushes back and forth and almost never reaches the goal, so
# nothing but the cost of moving enters the replay; pink acting noise (noise_beta 1, Eberhard et al. 2023) swings the
# car up (python -m bench.exploration, bench/results/exploration.json). Tuned for 4 workers under sync on tuning
# seeds 1-3 only (python -m bench.tune MountainCarContinuous-v0 sync --algo sac --seeds ... --max-episodes 40 --set
# ...; bench/results/tuning.jsonl): gamma 0.999 (the goal pays once, hundreds of steps after the pushes that earn
# it), a low starting temperature (0.1) and entropy target (-3: a calm policy, since TC 90 leaves little room for the
# cost of random pushes), lr 3e-4 and batch 256 (lr 1e-3 collapsed to pushing short of the goal on seed 2), a fixed
# input scale (the velocity is O(0.01)), K = 200 per episode under sync, utd_ratio 1 elsewhere. Last worker's
# episodes under sync, seeds 1-3: 19, 32, 28 (report seeds: docs/results.md).
MCC_SAC = SACConfig(hidden_sizes=(64, 64), batch_size=256, learning_starts=0, update_epochs=200, utd_ratio=1.0,
                    obs_scale=(1.0, 15.0), noise_beta=1.0, init_alpha=0.1, target_entropy=-3.0, gamma=0.999)
register_env(_task("MountainCarContinuous-v0", config=PPOConfig(
    log_std_init=1.0, normalize_obs=True, reward_scale=0.1), presets={"sac": MCC_SAC}))

# QUBE-Servo 2 balance (paper Section V-B-2), over MQTT ("qube") or in process ("qube-local"). With the paper's
# defaults the actor collapses to a policy that falls at once (one worker, seed 1: PI 8.9 at episode 800). The
# observation needs scaling (angles O(0.1) rad, velocities O(1-10) rad/s). Running statistics (normalize_obs)
# learned fastest alone (solved at 138, 136, 111 episodes for seeds 1-3), but they differ between workers, so a
# transferred actor is fed differently scaled inputs on its recipient: in a 3-rig federation one worker stayed
# below PI 100 for 250 episodes after two transfers. A fixed scale, the same everywhere, keeps Eq. 11 meaningful;
# with it, actor lr 1e-3 collapsed on seed 1001 and 3e-4 solved alone at episodes 109 (seed 1000, lr 1e-3),
# 755 (1001) and 294 (1002).
QUBE_OBS_SCALE = (8.0, 0.3, 1.0, 0.1)
QUBE_CONFIG = PPOConfig(obs_scale=QUBE_OBS_SCALE, actor_lr=3e-4)
# SAC on the QUBE: the same fixed input scale (for the same reason); its other values are SAC's defaults, untuned.
# DQN on the QUBE (its three actions): the same scale and CartPole-v0's DQN values, with epsilon falling over 2,000
# env steps (a falling pendulum's episodes are short). One tuning run, 3 rigs under sync, seed 1: every rig solved at
# episode 62, the last after 51,737 steps (about 6 minutes of rig time); PPO's report median under plain is 50,040.
# Report seeds 101-105 under sync: 45 episodes, 26,162 balance steps (4 of 5 solved; docs/results.md).
# A SAC try with Pendulum-v1's smaller networks (64x64, lr 1e-3, batch 128, K = 200) was still at PI 50 after 89
# episodes and was stopped.
QUBE_PRESETS = {"sac": SACConfig(obs_scale=QUBE_OBS_SCALE),
                "dqn": replace(CARTPOLE_DQN, obs_scale=QUBE_OBS_SCALE, eps_decay_steps=2000)}
register_env(EnvSpec(task=TASKS["qube"], gym_id=None, config=QUBE_CONFIG, presets=QUBE_PRESETS,
                     factory=make_qube_env))
register_env(EnvSpec(task=TASKS["qube-local"], gym_id=None, config=QUBE_CONFIG, presets=QUBE_PRESETS,
                     factory=make_qube_local_env))
