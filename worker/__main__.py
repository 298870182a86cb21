"""``python -m worker``: one federated PPO worker (paper Algorithm 2)."""

from __future__ import annotations

import sys

from protocol.cli import run_service, setup_logging
from protocol.settings import returns_code
from worker.service import WorkerConfig, WorkerService, auto_worker_id
from worker.settings import WorkerSettings

DESCRIPTION = (
    "A federated RL worker: Actor-Critic PPO on its own environment, sharing its actor gradient and Performance "
    "Index with the chief after every episode and applying what the chief sends back. Exits when it has solved the "
    "task (after the chief acknowledged its mature actor) or when the run ends: exit code 0 then, 1 on an error, 2 "
    "on a bad setting, 3 when no run started, 4 when the run was aborted before this worker solved."
)


@returns_code
def main(argv: list[str] | None = None) -> int:
    s = WorkerSettings.load(argv, prog="python -m worker", description=DESCRIPTION)
    worker_id = auto_worker_id() if s.worker_id == "auto" else s.worker_id
    setup_logging(s.log_level, f"worker[{worker_id}]")

    def build() -> WorkerService:
        return WorkerService(WorkerConfig(
            broker=s.address(), run_id=s.run_id, worker_id=worker_id, env_id=s.env, device_noise=s.device_noise,
            reply_timeout=s.reply_timeout, start_timeout=s.start_timeout, ack_timeout=s.ack_timeout,
            resend_interval=s.resend_interval, max_payload=s.max_payload, model_dir=s.model_dir, rig_id=s.rig_id,
            env_options=s.env_options()))

    return run_service("worker", build)


if __name__ == "__main__":
    sys.exit(main())
