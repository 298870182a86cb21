"""``python -m services.dashboard``: a live web page of one run (workers' curves and states, rounds, transfers,
the rigs' phase and loop timing), served on 127.0.0.1 and updated by server-sent events."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from protocol.cli import add_common, broker_from, env, parse_checked, run_service, setup_logging
from services.dashboard.service import DashboardConfig, DashboardService

DEFAULT_PORT = 8050


def parse_port(text: str) -> int:
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"port must be a number 0-65535, got {text!r}") from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"port must be 0-65535, got {port}")
    return port


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m services.dashboard",
        description="Live dashboard of a federated run: subscribes to fedrl/<run>/# and the rigs' status and "
        "telemetry, serves a web page (no internet needed) and prints its URL.",
    )
    add_common(parser)
    parser.add_argument("--host", default=env("FEDRL_DASHBOARD_HOST", "127.0.0.1"),
                        help="interface to serve on (env FEDRL_DASHBOARD_HOST, default 127.0.0.1; 0.0.0.0 exposes "
                        "the page to the network, as inside a container)")
    parser.add_argument("--port", type=parse_port, default=env("FEDRL_DASHBOARD_PORT", str(DEFAULT_PORT)),
                        help=f"TCP port (env FEDRL_DASHBOARD_PORT, default {DEFAULT_PORT}; 0 = any free port)")
    parser.add_argument("--rigs", default=env("FEDRL_DASHBOARD_RIGS", ""),
                        help="comma-separated rig ids to show (env FEDRL_DASHBOARD_RIGS; default: every rig on the "
                        "broker)")
    parser.add_argument("--max-points", type=int, default=4000,
                        help="points per worker curve kept for a page that connects later (default 4000)")
    parser.add_argument("--url-file", type=Path, default=None,
                        help="write the page's URL into this file once it is served (for launchers)")
    args = parse_checked(parser, argv)
    if args.max_points < 2:
        parser.error("--max-points must be at least 2")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    setup_logging(args.log_level, "dashboard")
    rigs = [r.strip() for r in args.rigs.split(",") if r.strip()] or None

    def build() -> DashboardService:
        service = DashboardService(DashboardConfig(
            broker=broker_from(args), run_id=args.run_id, host=args.host, port=args.port, rigs=rigs,
            max_points=args.max_points, url_file=args.url_file))
        service.install_signal_handlers()
        return service

    return run_service("dashboard", build)


if __name__ == "__main__":
    sys.exit(main())
