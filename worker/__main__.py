"""``python -m worker``: one federated PPO worker (paper Algorithm 2)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from protocol.cli import add_common, add_device_noise, broker_from, env, parse_checked, run_service, setup_logging
from protocol.mqtt import max_payload_from_env
from protocol.tasks import TASKS
from worker.service import WorkerConfig, WorkerService, auto_worker_id


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m worker",
        description="A federated RL worker: Actor-Critic PPO on its own environment, sharing its actor gradient "
        "and Performance Index with the chief after every episode and applying what the chief sends back. "
        "Exits when it has solved the task (after the chief acknowledged its mature actor) or when the run ends: "
        "exit code 0 then, 1 on an error, 2 on a bad option, 3 when no run started, 4 when the run was aborted "
        "before this worker solved.",
    )
    add_common(parser)
    parser.add_argument("--id", default=env("FEDRL_WORKER_ID", "auto"),
                        help="worker id, unique in the run (env FEDRL_WORKER_ID; default 'auto' = hostname plus a "
                        "random suffix)")
    parser.add_argument("--env", default=env("FEDRL_ENV", "CartPole-v0"), choices=sorted(TASKS),
                        help="task to learn; must match the chief's (env FEDRL_ENV, default CartPole-v0)")
    add_device_noise(parser)
    parser.add_argument("--rig-id", default=env("FEDRL_RIG_ID", "") or None,
                        help="QUBE-Servo 2 rig to drive when --env qube (env FEDRL_RIG_ID)")
    parser.add_argument("--reply-timeout", type=float, default=float(env("FEDRL_REPLY_TIMEOUT", "120")),
                        help="seconds to wait for the chief's answer to an episode before going on alone "
                        "(env FEDRL_REPLY_TIMEOUT, default 120)")
    parser.add_argument("--ack-timeout", type=float, default=float(env("FEDRL_ACK_TIMEOUT", "600")),
                        help="after solving, seconds to keep sending the mature actor until the chief acknowledges it "
                        "(env FEDRL_ACK_TIMEOUT, default 600)")
    parser.add_argument("--resend-interval", type=float, default=float(env("FEDRL_RESEND_INTERVAL", "30")),
                        help="send an unanswered submission again after this many seconds (also at once after a "
                        "reconnect or a chief restart; env FEDRL_RESEND_INTERVAL, default 30)")
    parser.add_argument("--start-timeout", type=float, default=float(env("FEDRL_START_TIMEOUT", "600")),
                        help="seconds to wait for the chief to start the run (env FEDRL_START_TIMEOUT, default 600)")
    parser.add_argument("--model-dir", type=Path, default=Path(p) if (p := env("FEDRL_MODEL_DIR", "")) else None,
                        help="save the mature model here as <id>.pt (env FEDRL_MODEL_DIR; default: not saved)")
    args = parse_checked(parser, argv)
    if args.device_noise < 0:
        parser.error("--device-noise must be >= 0")
    if args.id == "auto":
        args.id = auto_worker_id()
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    setup_logging(args.log_level, f"worker[{args.id}]")

    def build() -> WorkerService:
        return WorkerService(WorkerConfig(
            broker=broker_from(args), run_id=args.run_id, worker_id=args.id, env_id=args.env,
            device_noise=args.device_noise, reply_timeout=args.reply_timeout, start_timeout=args.start_timeout,
            ack_timeout=args.ack_timeout, resend_interval=args.resend_interval, max_payload=max_payload_from_env(),
            model_dir=args.model_dir, rig_id=args.rig_id))

    return run_service("worker", build)


if __name__ == "__main__":
    sys.exit(main())
