"""Command-line options shared by every process; each flag falls back to a FEDRL_* environment variable."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Callable
from typing import Any

from protocol.mqtt import DEFAULT_BROKER, BrokerAddress


def env(name: str, default: str) -> str:
    """The value of environment variable ``name``, or ``default`` when it is unset or empty."""
    return os.environ.get(name) or default


def add_common(parser: argparse.ArgumentParser, with_run: bool = True) -> None:
    """--broker, --run-id, --log-level (and the MQTT credentials through env vars)."""
    parser.add_argument("--broker", default=env("FEDRL_BROKER", DEFAULT_BROKER),
                        help="broker URL mqtt://[user:pass@]host:port or mqtts:// for TLS (env FEDRL_BROKER, "
                        f"default {DEFAULT_BROKER}); credentials and CA file also from FEDRL_MQTT_USERNAME, "
                        "FEDRL_MQTT_PASSWORD, FEDRL_MQTT_CA_FILE")
    if with_run:
        parser.add_argument("--run-id", default=env("FEDRL_RUN_ID", "default"),
                            help="run name, the topic prefix fedrl/<run>/ (env FEDRL_RUN_ID, default 'default')")
    parser.add_argument("--log-level", default=env("FEDRL_LOG_LEVEL", "INFO"),
                        help="DEBUG, INFO, WARNING or ERROR (env FEDRL_LOG_LEVEL, default INFO)")


def broker_from(args: argparse.Namespace) -> BrokerAddress:
    return BrokerAddress.from_env(args.broker)


def setup_logging(level: str, name: str) -> None:
    logging.basicConfig(level=level.upper(), format=f"%(asctime)s {name} %(levelname)s %(message)s")
    logging.getLogger("paho").setLevel(logging.WARNING)


def parse_checked(parser: argparse.ArgumentParser, argv: list[str] | None = None) -> argparse.Namespace:
    """``parse_args`` that also checks values taken from FEDRL_* variables against the options' choices
    (argparse checks only what is typed on the command line)."""
    args = parser.parse_args(argv)
    for action in parser._actions:
        value = getattr(args, action.dest, None)
        if action.choices is not None and value is not None and value not in action.choices:
            options = ", ".join(str(c) for c in action.choices)
            parser.error(f"argument {'/'.join(action.option_strings)}: invalid choice {value!r} "
                         f"(from the environment?); choose from {options}")
    return args


def run_service(name: str, build: Callable[[], Any]) -> int:
    """Build a service and run it, turning the expected failures into exit codes with one clear line:
    2 for a bad setting (ValueError while building), 1 for an unreachable broker, 130 for Ctrl-C."""
    try:
        service = build()
    except ValueError as err:
        print(f"{name}: {err}", file=sys.stderr)
        return 2
    try:
        code = service.run()
    except ConnectionError as err:
        print(f"{name}: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    return 0 if code is None else int(code)
