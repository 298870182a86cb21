"""One worker, no federation: Algorithm 2 without the chief, episode by episode. For experiments and tuning.

    python -m worker.train_local --env CartPole-v0 --seed 1
    python -m worker.train_local --env Pendulum-v1 --seed 1 --set gamma=0.9 --set actor_lr=3e-4

Each episode: run it to the end storing every transition in the FIFO memory; PI = mean of the last 10
returns; stop once PI >= TC (with at least 10 episodes); otherwise ``update()`` (K critic + actor steps).
"""

from __future__ import annotations

import argparse
import ast
import sys
import time
from collections.abc import Callable
from dataclasses import fields
from typing import Any

import torch

from protocol.tasks import performance_index, solved
from worker.envs import DeviceNoise, env_spec, make_env
from worker.episode import run_episode
from worker.ppo import PPOConfig, PPOLearner, UpdateStats


def train(
    env_id: str,
    seed: int,
    max_episodes: int,
    config: PPOConfig | None = None,
    device_noise: DeviceNoise | None = None,
    on_episode: Callable[[int, float, float, int, UpdateStats | None], None] | None = None,
) -> list[float]:
    """Learn ``env_id`` alone until PI >= TC or ``max_episodes``; returns the episode returns.

    ``config`` defaults to the env's preset, ``device_noise`` to the paper's. ``on_episode(episode, return,
    PI, steps, stats)`` is called after every episode (stats is None for the final, solving episode).
    """
    spec = env_spec(env_id)
    env = make_env(env_id, seed, device_noise)
    learner = PPOLearner(env.observation_space, env.action_space, config or spec.ppo_config(), seed=seed)
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


def _parse_override(text: str) -> tuple[str, Any]:
    key, sep, raw = text.partition("=")
    names = {f.name for f in fields(PPOConfig)}
    if not sep or key not in names:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE with KEY one of {sorted(names)}, got {text!r}")
    lowered = raw.strip().lower()
    if lowered in ("true", "false", "none"):
        return key, {"true": True, "false": False, "none": None}[lowered]
    try:
        return key, ast.literal_eval(raw)
    except (ValueError, SyntaxError):
        return key, raw


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m worker.train_local", description=__doc__.split("\n")[0])
    parser.add_argument("--env", default="CartPole-v0")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--episodes", type=int, default=2000, help="maximum episodes (the paper's M)")
    parser.add_argument("--device-noise", type=float, default=1.0, help="DeviceNoise scale; 0 turns it off")
    parser.add_argument("--set", dest="overrides", action="append", type=_parse_override, default=[],
                        metavar="KEY=VALUE", help="override a PPOConfig field of the preset (repeatable)")
    parser.add_argument("--every", type=int, default=10, help="print every N episodes")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    spec = env_spec(args.env)
    config = spec.ppo_config(**dict(args.overrides))
    print(f"{args.env} seed {args.seed}: TC {spec.tc}, {config}", flush=True)
    start, total_steps = time.monotonic(), 0

    def report(episode: int, ret: float, pi: float, steps: int, stats: UpdateStats | None) -> None:
        nonlocal total_steps
        total_steps += steps
        if stats is None or episode % args.every == 0:
            extra = "" if stats is None else (
                f" | actor {stats.actor_loss:+.3f} critic {stats.critic_loss:.3f} entropy {stats.entropy:.3f}"
                f" kl {stats.approx_kl:.4f}")
            print(f"ep {episode:5d} steps {total_steps:8d} return {ret:9.2f} PI {pi:9.2f}"
                  f" t {time.monotonic() - start:6.1f}s{extra}", flush=True)

    returns = train(args.env, args.seed, args.episodes, config, DeviceNoise(scale=args.device_noise), report)
    ok = solved(returns, spec.tc)
    print(f"RESULT env={args.env} seed={args.seed} solved={ok} episodes={len(returns)} steps={total_steps} "
          f"PI={performance_index(returns):.2f} wall={time.monotonic() - start:.1f}s", flush=True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
