"""``python -m services.dashboard``: a live web page of one run (workers' curves and states, rounds, transfers,
the rigs' phase and loop timing), served on 127.0.0.1 and updated by server-sent events."""

from __future__ import annotations

import sys

from runtime.cli import run_service, setup_logging
from runtime.settings import returns_code
from services.dashboard.service import DashboardConfig, DashboardService
from services.dashboard.settings import DashboardSettings

DESCRIPTION = (
    "Live dashboard of a federated run: subscribes to fedrl/<run>/# and the rigs' status and telemetry, serves a web "
    "page (no internet needed) and prints its URL."
)


@returns_code
def main(argv: list[str] | None = None) -> int:
    s = DashboardSettings.load(argv, prog="python -m services.dashboard", description=DESCRIPTION)
    setup_logging(s.log_level, "dashboard")

    def build() -> DashboardService:
        service = DashboardService(DashboardConfig(
            broker=s.address(), run_id=s.run_id, host=s.dashboard_host, port=s.dashboard_port,
            rigs=s.dashboard_rigs or None, max_points=s.dashboard_max_points, url_file=s.dashboard_url_file,
            key=s.key()), connect=s.connector())
        service.install_signal_handlers()
        return service

    return run_service("dashboard", build)


if __name__ == "__main__":
    sys.exit(main())
