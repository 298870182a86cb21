"""``python -m chief``: the federation's chief (paper Algorithm 1)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from chief import strategies
from chief.service import ChiefConfig, ChiefService
from protocol.cli import add_common, add_run_options, broker_from, env, parse_checked, run_service, setup_logging
from protocol.mqtt import max_payload_from_env


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m chief",
        description="Chief of a federated RL run: waits for the workers, runs the rounds of Algorithm 1 (PI-weighted "
        "gradient sharing and soft transfer), writing metrics.jsonl and TensorBoard event files (tensorboard/, with "
        "the tb extra) as it goes, then summary.json and learning_curve.png into the run folder. Started again with "
        "the same --run-id and --run-dir, it resumes the run from its saved state (chief-state.msgpack). Exit code 0 "
        "when the run ended normally (all solved or the episode limit), 2 on a bad option or an unusable run folder, "
        "3 when no worker came, 4 when the run was aborted (every unfinished worker offline for --idle-timeout s). "
        "FEDRL_MAX_PAYLOAD (bytes) splits larger messages into chunks.",
    )
    add_common(parser)
    parser.add_argument("--workers", type=int, default=int(env("FEDRL_WORKERS", "4")),
                        help="number of workers to wait for (env FEDRL_WORKERS, default 4)")
    add_run_options(parser, strategies.names())
    parser.add_argument("--start-timeout", type=float, default=float(env("FEDRL_START_TIMEOUT", "300")),
                        help="seconds to wait for all workers before starting with those present "
                        "(env FEDRL_START_TIMEOUT, default 300)")
    parser.add_argument("--idle-timeout", type=float, default=float(env("FEDRL_IDLE_TIMEOUT", "120")),
                        help="end the run when every unfinished worker is offline this long "
                        "(env FEDRL_IDLE_TIMEOUT, default 120)")
    parser.add_argument("--run-dir", type=Path, default=Path(env("FEDRL_RUN_DIR", "runs/latest")),
                        help="folder for summary.json, metrics.jsonl, learning_curve.png "
                        "(env FEDRL_RUN_DIR, default runs/latest)")
    args = parse_checked(parser, argv)
    if args.workers < 1:
        parser.error("--workers must be at least 1")
    if args.max_episodes < 1:
        parser.error("--max-episodes must be at least 1")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    setup_logging(args.log_level, "chief")

    def build() -> ChiefService:
        return ChiefService(ChiefConfig(
            broker=broker_from(args), run_id=args.run_id, workers=args.workers, env_id=args.env,
            policy=args.policy, seed=args.seed, max_episodes=args.max_episodes, round_timeout=args.round_timeout,
            start_timeout=args.start_timeout, idle_timeout=args.idle_timeout, run_dir=args.run_dir,
            max_payload=max_payload_from_env()))

    return run_service("chief", build)


if __name__ == "__main__":
    sys.exit(main())
