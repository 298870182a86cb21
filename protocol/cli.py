"""Command-line options shared by every process; each flag falls back to a FEDRL_* environment variable."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Callable, Sequence
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


def add_run_options(parser: argparse.ArgumentParser, policies: Sequence[str]) -> None:
    """--env, --policy, --seed, --max-episodes, --round-timeout: what a run is, for the chief and the launchers.

    ``policies`` are the federation strategies' names (``chief.strategies.names()``: the chief's registry, which
    this package may not import).
    """
    from protocol.tasks import TASKS

    parser.add_argument("--env", default=env("FEDRL_ENV", "CartPole-v0"), choices=sorted(TASKS),
                        help="task every worker learns (env FEDRL_ENV, default CartPole-v0)")
    parser.add_argument("--policy", default=env("FEDRL_POLICY", "weighted"), choices=list(policies),
                        help=f"federation policy: {', '.join(policies)} (env FEDRL_POLICY, default weighted; "
                        "python -m chief.strategies describes them)")
    parser.add_argument("--seed", type=int, default=int(env("FEDRL_SEED", "1")),
                        help="base seed; worker i uses seed*1000 + i (env FEDRL_SEED, default 1)")
    parser.add_argument("--max-episodes", type=int, default=int(env("FEDRL_MAX_EPISODES", "2000")),
                        help="M, the most rounds a run may take (env FEDRL_MAX_EPISODES, default 2000)")
    parser.add_argument("--round-timeout", type=float, default=float(env("FEDRL_ROUND_TIMEOUT", "30")),
                        help="seconds a round waits for a silent worker after the first submission "
                        "(env FEDRL_ROUND_TIMEOUT, default 30)")


def add_device_noise(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device-noise", type=float, default=float(env("FEDRL_DEVICE_NOISE", "1.0")),
                        help="scale of the per-device action noise N(0.002, 0.0005) of the paper; 0 turns it off "
                        "(env FEDRL_DEVICE_NOISE, default 1.0)")
