"""``python -m chief``: the federation's chief (paper Algorithm 1)."""

from __future__ import annotations

import sys

from chief.service import ChiefService
from chief.settings import ChiefSettings
from runtime.cli import run_service, setup_logging, stop_on_signals
from runtime.settings import returns_code

DESCRIPTION = (
    "Chief of a federated RL run: waits for the workers, runs the rounds of Algorithm 1 (PI-weighted gradient "
    "sharing and soft transfer), writing metrics.jsonl and TensorBoard event files (tensorboard/, with the tb extra) "
    "as it goes, then summary.json and learning_curve.png into the run folder. "
    "Started again with the same --run-id and --run-dir, it resumes the run from its saved state "
    "(chief-state.msgpack). Exit code 0 when the run ended normally (all solved or the episode limit), 2 on a bad "
    "setting or an unusable run folder, 3 when no worker came, 4 when the run was aborted (every unfinished worker "
    "offline for --idle-timeout s), 130 when it was interrupted (Ctrl-C or SIGTERM: the summary says "
    "'interrupted', and the same command resumes the run), 6 when another chief holds the run (its claim on "
    "fedrl/<run>/claim). With --role edge --edge-id <edge> it is an edge chief of a tiered run instead "
    "(docs/explanation/tiered.md): it closes its workers' part of each round into one partial for the root chief "
    "(--edges N) and passes the root's answers on to them."
)


@returns_code
def main(argv: list[str] | None = None) -> int:
    s = ChiefSettings.load(argv, prog="python -m chief", description=DESCRIPTION)
    setup_logging(s.log_level, "chief")

    if s.role == "edge":
        from chief.edge import EdgeService

        def edge() -> EdgeService:
            service = EdgeService(s)
            stop_on_signals(service.interrupt)  # SIGTERM, SIGINT or SIGHUP: a clean stop, exit 130
            return service

        return run_service(f"edge {s.edge_id}", edge)

    def build() -> ChiefService:
        service = ChiefService(s)
        stop_on_signals(service.interrupt)  # Ctrl-C ends the run resumably, with its summary and curve
        return service

    return run_service("chief", build)


if __name__ == "__main__":
    sys.exit(main())
