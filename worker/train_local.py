"""One worker, no federation: Algorithm 2 without the chief, episode by episode. For experiments and tuning.

    python -m worker.train_local --env CartPole-v0 --seed 1
    python -m worker.train_local --env Pendulum-v1 --seed 1 --set gamma=0.9 --set actor_lr=3e-4
    python -m worker.train_local --env Pendulum-v1 --algo sac --seed 1

Each episode: run it to the end storing every transition in the FIFO memory; PI = mean of the last 10
returns; stop once PI >= TC (with at least 10 episodes); otherwise the learner's ``update()`` (worker/learners.py).
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from typing import Any

import torch

from protocol import learners as names
from protocol.tasks import performance_index, solved
from runtime.settings import returns_code
from worker import learners
from worker.envs import DeviceNoise, env_spec, make_env
from worker.episode import run_episode
from worker.settings import TrainLocalSettings


def train(
    env_id: str,
    seed: int,
    max_episodes: int,
    config: Any = None,
    device_noise: DeviceNoise | None = None,
    on_episode: Callable[[int, float, float, int, Any], None] | None = None,
    algo: str = names.DEFAULT,
) -> list[float]:
    """Learn ``env_id`` alone with learner ``algo`` until PI >= TC or ``max_episodes``; returns the episode returns.

    ``config`` defaults to the env's preset for the learner, ``device_noise`` to the paper's. ``on_episode(episode,
    return, PI, steps, stats)`` is called after every episode (stats is None for the final, solving episode).
    """
    spec = env_spec(env_id)
    env = make_env(env_id, seed, device_noise)
    learner = learners.get(algo).learner_class(env.observation_space, env.action_space,
                                               config or spec.learner_config(algo), seed=seed)
    returns: list[float] = []
    try:
        for episode in range(1, max_episodes + 1):
            ret, steps = run_episode(env, learner, seed=seed if episode == 1 else None)
            returns.append(ret)
            pi = performance_index(returns)
            if solved(returns, spec.tc):
                if on_episode is not None:
                    on_episode(episode, ret, pi, steps, None)
                break
            stats = learner.update()
            if on_episode is not None:
                on_episode(episode, ret, pi, steps, stats)
    finally:
        env.close()
    return returns


@returns_code
def main(argv: list[str] | None = None) -> int:
    s = TrainLocalSettings.load(argv, prog="python -m worker.train_local", description=__doc__.split("\n")[0])
    torch.set_num_threads(1)

    spec = env_spec(s.env)
    config = spec.learner_config(s.algo, **s.learner_overrides())
    print(f"{s.env} seed {s.seed}, {s.algo}: TC {spec.tc}, {config}", flush=True)
    start, total_steps = time.monotonic(), 0

    def report(episode: int, ret: float, pi: float, steps: int, stats: Any) -> None:
        nonlocal total_steps
        total_steps += steps
        if stats is None or episode % s.print_every == 0:
            extra = "" if stats is None else (
                f" | actor {stats.actor_loss:+.3f} critic {stats.critic_loss:.3f} entropy {stats.entropy:.3f}"
                + (f" kl {stats.approx_kl:.4f}" if math.isfinite(getattr(stats, "approx_kl", math.nan)) else ""))
            print(f"ep {episode:5d} steps {total_steps:8d} return {ret:9.2f} PI {pi:9.2f}"
                  f" t {time.monotonic() - start:6.1f}s{extra}", flush=True)

    returns = train(s.env, s.seed, s.max_episodes, config, DeviceNoise(scale=s.device_noise), report, s.algo)
    ok = solved(returns, spec.tc)
    print(f"RESULT env={s.env} algo={s.algo} seed={s.seed} solved={ok} episodes={len(returns)} steps={total_steps} "
          f"PI={performance_index(returns):.2f} wall={time.monotonic() - start:.1f}s", flush=True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
