"""``python -m worker``: one federated PPO worker (paper Algorithm 2)."""

from __future__ import annotations

import sys

from runtime.cli import run_service, setup_logging, stop_on_signals
from runtime.settings import returns_code
from worker.settings import WorkerSettings

DESCRIPTION = (
    "A federated RL worker: Actor-Critic PPO on its own environment, sharing its actor gradient and Performance "
    "Index with the chief after every episode and applying what the chief sends back. Exits when it has solved the "
    "task (after the chief acknowledged its mature actor) or when the run ends: exit code 0 then, 1 on an error, 2 "
    "on a bad setting, 3 when no run started, 4 when the run was aborted before this worker solved, 7 when its "
    "saved state does not fit the resumed run, 130 when it was stopped before it solved by Ctrl-C, SIGTERM or the "
    "chief's interrupted run (then its resumable state is saved, --state-dir)."
)


@returns_code
def main(argv: list[str] | None = None) -> int:
    s = WorkerSettings.load(argv, prog="python -m worker", description=DESCRIPTION)
    from worker.service import WorkerService, auto_worker_id  # torch: after --help and the settings' checks

    if s.worker_id == "auto":
        s = s.model_copy(update={"worker_id": auto_worker_id()})
    setup_logging(s.log_level, f"worker[{s.worker_id}]")

    def build() -> WorkerService:
        service = WorkerService(s)
        stop_on_signals(service.interrupt)  # SIGTERM: say "stopped" and disconnect, no last will
        return service

    return run_service("worker", build)


if __name__ == "__main__":
    sys.exit(main())
