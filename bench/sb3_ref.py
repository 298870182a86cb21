"""References: Stable-Baselines3 with its rl-baselines3-zoo hyperparameters, under our stop rule, one per learner of
ours: SB3's PPO beside our PPO, and beside our SAC SB3's SAC on the continuous tasks and its DQN on the discrete ones
(SB3's SAC has no discrete variant; the zoo has SAC entries for Pendulum-v1 and MountainCarContinuous-v0 and DQN
entries for CartPole-v1 and Acrobot-v1).

Hyperparameters: rl-baselines3-zoo (DLR-RM/rl-baselines3-zoo), ``hyperparams/ppo.yml`` at commit 22e3ff2,
``hyperparams/sac.yml`` at c94924e and ``hyperparams/dqn.yml`` at ce95481; the values are copied into ``ZOOS`` below
(keys an entry leaves out take SB3's defaults, as in the zoo). The zoo has no CartPole-v0 entry: its CartPole-v1 entry
is used (the tasks differ only in the episode limit, 200 against 500 steps). ``normalize: true`` is the zoo's
VecNormalize of observations and rewards (with the entry's gamma). The QUBE balance task has no zoo entry and no SB3
reference.

Stop rule, the same as our workers' (protocol.tasks.solved): training stops the first time the mean return of the
last 10 completed training episodes (all vector envs pooled, in the order they completed) reaches TC. Each env
is our own task env (worker.envs.make_env: the same episode limit and the paper's device noise, of device
``worker_seed(seed, 0)``), wrapped in SB3's Monitor to see the raw returns. Episodes and env steps count every
vector env. The budget is the zoo's n_timesteps (learning-rate and exploration schedules run over it as in the zoo);
a run that does not meet TC within it is reported as unfinished.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from typing import Any

from protocol.tasks import PI_WINDOW, performance_index, solved, task, worker_seed


def linear(start: float) -> Any:
    """The zoo's ``lin_<x>``: x times the remaining share of training (1 at the start, 0 at the end)."""
    def schedule(progress_remaining: float) -> float:
        return progress_remaining * start
    return schedule


@dataclass(frozen=True)
class ZooEntry:
    """One entry of an rl-baselines3-zoo hyperparams/<algo>.yml."""

    zoo_key: str  # the entry's name in the zoo's file
    n_envs: int
    n_timesteps: int
    normalize: bool
    kwargs: dict[str, Any] = field(default_factory=dict)  # the SB3 algorithm's keyword arguments
    policy_kwargs: dict[str, Any] = field(default_factory=dict)


#: rl-baselines3-zoo hyperparams, per SB3 algorithm, per task of ours.
ZOOS: dict[str, dict[str, ZooEntry]] = {
    "ppo": {  # hyperparams/ppo.yml, commit 22e3ff2
        "CartPole-v0": ZooEntry("CartPole-v1", n_envs=8, n_timesteps=100_000, normalize=False, kwargs={
            "n_steps": 32, "batch_size": 256, "gae_lambda": 0.8, "gamma": 0.98, "n_epochs": 20, "ent_coef": 0.0,
            "learning_rate": ("lin", 1e-3), "clip_range": ("lin", 0.2)}),
        "Acrobot-v1": ZooEntry("Acrobot-v1", n_envs=16, n_timesteps=1_000_000, normalize=True, kwargs={
            "n_steps": 256, "gae_lambda": 0.94, "gamma": 0.99, "n_epochs": 4, "ent_coef": 0.0}),
        "Pendulum-v1": ZooEntry("Pendulum-v1", n_envs=4, n_timesteps=100_000, normalize=False, kwargs={
            "n_steps": 1024, "gae_lambda": 0.95, "gamma": 0.9, "n_epochs": 10, "ent_coef": 0.0,
            "learning_rate": 1e-3, "clip_range": 0.2, "use_sde": True, "sde_sample_freq": 4}),
        "MountainCarContinuous-v0": ZooEntry(
            "MountainCarContinuous-v0", n_envs=1, n_timesteps=20_000, normalize=True,
            kwargs={"batch_size": 256, "n_steps": 8, "gamma": 0.9999, "learning_rate": 7.77e-05, "ent_coef": 0.00429,
                    "clip_range": 0.1, "n_epochs": 10, "gae_lambda": 0.9, "max_grad_norm": 5, "vf_coef": 0.19,
                    "use_sde": True},
            policy_kwargs={"log_std_init": -3.29, "ortho_init": False}),
    },
    "sac": {  # hyperparams/sac.yml, commit c94924e
        "Pendulum-v1": ZooEntry("Pendulum-v1", n_envs=1, n_timesteps=20_000, normalize=False,
                                kwargs={"learning_rate": 1e-3}),
        "MountainCarContinuous-v0": ZooEntry(
            "MountainCarContinuous-v0", n_envs=1, n_timesteps=50_000, normalize=False,
            kwargs={"learning_rate": 3e-4, "buffer_size": 50_000, "batch_size": 512, "ent_coef": 0.1,
                    "train_freq": 32, "gradient_steps": 32, "gamma": 0.9999, "tau": 0.01, "learning_starts": 0,
                    "use_sde": True},
            policy_kwargs={"log_std_init": -3.67, "net_arch": [64, 64]}),
    },
    "dqn": {  # hyperparams/dqn.yml, commit ce95481
        "CartPole-v0": ZooEntry("CartPole-v1", n_envs=1, n_timesteps=50_000, normalize=False, kwargs={
            "learning_rate": 2.3e-3, "batch_size": 64, "buffer_size": 100_000, "learning_starts": 1000,
            "gamma": 0.99, "target_update_interval": 10, "train_freq": 256, "gradient_steps": 128,
            "exploration_fraction": 0.16, "exploration_final_eps": 0.04}, policy_kwargs={"net_arch": [256, 256]}),
        "Acrobot-v1": ZooEntry("Acrobot-v1", n_envs=1, n_timesteps=100_000, normalize=False, kwargs={
            "learning_rate": 6.3e-4, "batch_size": 128, "buffer_size": 50_000, "learning_starts": 0, "gamma": 0.99,
            "target_update_interval": 250, "train_freq": 4, "gradient_steps": -1, "exploration_fraction": 0.12,
            "exploration_final_eps": 0.1}, policy_kwargs={"net_arch": [256, 256]}),
    },
}
#: PPO's entries (the reference of our PPO).
ZOO = ZOOS["ppo"]


def reference(learner: str, env_id: str) -> str | None:
    """The SB3 algorithm beside our ``learner`` on ``env_id``: PPO beside PPO, DQN beside DQN; beside SAC, SAC where
    the zoo has a SAC entry (continuous actions) and else DQN where it has a DQN entry (discrete actions); None without
    an entry."""
    for algo in {"ppo": ("ppo",), "sac": ("sac", "dqn"), "dqn": ("dqn",)}.get(learner, ()):
        if env_id in ZOOS[algo]:
            return algo
    return None


def label(algo: str) -> str:
    """The strategy name of an SB3 reference run (``sb3-zoo-ppo``...)."""
    return f"sb3-zoo-{algo}"


class StopRule:
    """Our stop rule over a stream of completed episodes: solved the first time the mean of the last PI_WINDOW
    returns is >= TC. Remembers the episode count and env steps at that moment."""

    def __init__(self, tc: float) -> None:
        self.tc = tc
        self.returns: list[float] = []
        self.solved_episode: int | None = None
        self.solved_steps: int | None = None

    def episode_done(self, episode_return: float, steps_so_far: int) -> bool:
        """Record a completed episode; True once the rule is met (and stays met)."""
        if self.solved_episode is not None:
            return True
        self.returns.append(float(episode_return))
        if solved(self.returns, self.tc):
            self.solved_episode, self.solved_steps = len(self.returns), int(steps_so_far)
            return True
        return False

    @property
    def pi(self) -> float | None:
        return performance_index(self.returns) if self.returns else None


def _make_callback(rule: StopRule) -> Any:
    from stable_baselines3.common.callbacks import BaseCallback

    class StopAtTC(BaseCallback):
        """Stops training the first time the stop rule is met (episodes from the Monitor's ``info['episode']``)."""

        def _on_step(self) -> bool:
            for info in self.locals.get("infos", []):
                episode = info.get("episode")
                if episode is not None and rule.episode_done(float(episode["r"]), self.num_timesteps):
                    return False
            return True

    return StopAtTC()


def build(env_id: str, seed: int, algo: str = "ppo") -> tuple[Any, ZooEntry]:
    """The zoo's SB3 ``algo`` (ppo, sac or dqn) on ``n_envs`` copies of our env of device ``worker_seed(seed, 0)``."""
    import torch
    from stable_baselines3 import DQN, PPO, SAC
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecNormalize

    from worker.envs import DeviceNoise, make_env

    zoo = ZOOS[algo]
    if env_id not in zoo:
        raise ValueError(f"no rl-baselines3-zoo {algo} entry for {env_id}; have {', '.join(zoo)}")
    torch.set_num_threads(1)
    entry = zoo[env_id]
    device = worker_seed(seed, 0)
    vec: VecEnv = DummyVecEnv([lambda: Monitor(make_env(env_id, device, DeviceNoise())) for _ in range(entry.n_envs)])
    vec.seed(device)
    if entry.normalize:
        vec = VecNormalize(vec, gamma=entry.kwargs.get("gamma", 0.99))
    kwargs = {k: linear(v[1]) if isinstance(v, tuple) and v[0] == "lin" else v for k, v in entry.kwargs.items()}
    cls: Any = {"ppo": PPO, "sac": SAC, "dqn": DQN}[algo]
    with warnings.catch_warnings():  # the zoo's MountainCarContinuous batch (256) exceeds its rollout (8): as intended
        warnings.filterwarnings("ignore", message=".*mini-batch size.*")
        model = cls("MlpPolicy", vec, seed=seed, device="cpu", verbose=0,
                    policy_kwargs=entry.policy_kwargs or None, **kwargs)
    return model, entry


def run(env_id: str, seed: int, max_steps: int | None = None, algo: str = "ppo") -> dict[str, Any]:
    """Train SB3's ``algo`` until the stop rule is met or the zoo's budget (or ``max_steps``) is spent; the result as
    a dict."""
    t0 = time.monotonic()
    model, entry = build(env_id, seed, algo)
    rule = StopRule(task(env_id).tc)
    budget = entry.n_timesteps if max_steps is None else min(max_steps, entry.n_timesteps)
    model.learn(total_timesteps=budget, callback=_make_callback(rule))
    finished = rule.solved_episode is not None
    return {"kind": "sb3", "task": env_id, "strategy": label(algo), "seed": seed, "workers": 1,
            "zoo_entry": entry.zoo_key, "n_envs": entry.n_envs, "budget_steps": budget, "finished": finished,
            "episodes": rule.solved_episode if finished else len(rule.returns),
            "steps": rule.solved_steps if finished else int(model.num_timesteps),
            "final_pi": rule.pi, "pi_window": PI_WINDOW, "wall_s": round(time.monotonic() - t0, 2)}
