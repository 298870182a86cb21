"""``python -m bench.exploration``: how often SAC's untrained policy reaches a task's goal, per colour of its noise.

SAC explores by sampling its own policy. On MountainCarContinuous-v0 the goal pays +100 once and every push costs
0.1 a^2, so until a worker has reached the goal its replay holds nothing to learn from but the cost of moving. The
untrained policy is a tanh-squashed Gaussian around zero; with white noise (a fresh draw each step) its pushes
cancel out, and with coloured noise (``SACConfig.noise_beta``, worker/sac.py ``colored_noise``) the same marginal
distribution keeps its sign for a while and swings the car up.

For each beta, ``--episodes`` episodes of one untrained SACLearner (the task's SAC preset with that ``noise_beta``,
learner seed 0, env seeds 0, 1, ...): the share that reached the goal (terminated before the time limit) and their
mean length. Writes ``bench/results/exploration.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from bench.output import write_report

RESULTS = Path("bench/results")


def goal_rate(task: str, beta: float, episodes: int) -> dict[str, Any]:
    """Episodes of an untrained SAC learner with acting noise of colour ``beta``: how many reached the goal."""
    from worker import envs
    from worker.sac import SACConfig, SACLearner

    config = envs.env_spec(task).learner_config("sac", noise_beta=beta)
    assert isinstance(config, SACConfig)
    env = envs.make_env(task, seed=0)
    learner = SACLearner(env.observation_space, env.action_space, config, seed=0)
    reached, lengths = 0, []
    for episode in range(episodes):
        obs, _ = env.reset(seed=episode)
        terminated = truncated = False
        steps = 0
        while not (terminated or truncated):  # as a worker plays: the episode's end also ends its noise sequence
            action = learner.act(obs)
            next_obs, reward, terminated, truncated, _ = env.step(action)
            learner.remember(obs, action, float(reward), next_obs, terminated, truncated)
            obs, steps = next_obs, steps + 1
        reached += bool(terminated)
        lengths.append(steps)
    env.close()
    return {"beta": beta, "episodes": episodes, "reached_goal": reached, "share": reached / episodes,
            "mean_length": sum(lengths) / len(lengths)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.exploration", description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="MountainCarContinuous-v0")
    parser.add_argument("--betas", type=float, nargs="+", default=[0.0, 0.5, 1.0, 2.0])
    parser.add_argument("--episodes", type=int, default=40)
    parser.add_argument("--out", type=Path, default=RESULTS / "exploration.json")
    args = parser.parse_args(argv)
    if args.episodes < 1 or any(not 0 <= b <= 4 for b in args.betas):
        parser.error("--episodes must be >= 1 and each beta in [0, 4]")
    rows = []
    for beta in args.betas:
        row = goal_rate(args.task, beta, args.episodes)
        print(json.dumps(row), flush=True)
        rows.append(row)
    write_report(args.out, "bench.exploration", argv, {"task": args.task, "results": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
