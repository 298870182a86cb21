"""What every process's ``main`` shares besides its settings (runtime/settings.py): logging and exit codes."""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from typing import Any


def setup_logging(level: str, name: str) -> None:
    logging.basicConfig(level=level.upper(), format=f"%(asctime)s {name} %(levelname)s %(message)s")
    logging.getLogger("paho").setLevel(logging.WARNING)


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
