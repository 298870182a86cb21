"""What every process's ``main`` shares besides its settings (runtime/settings.py): logging and exit codes."""

from __future__ import annotations

import functools
import logging
import signal
import sys
from collections.abc import Callable
from typing import Any

from runtime.storage import EXIT_STORAGE, StorageError, is_storage_fault


def setup_logging(level: str, name: str) -> None:
    logging.basicConfig(level=level.upper(), format=f"%(asctime)s {name} %(levelname)s %(message)s")
    logging.getLogger("paho").setLevel(logging.WARNING)


def run_service(name: str, build: Callable[[], Any]) -> int:
    """Build a service and run it, turning the expected failures into exit codes with one clear line:
    2 for a bad setting (ValueError while building), 1 for an unreachable broker, 5 (EXIT_STORAGE) for a full,
    read-only or forbidden disk (the path and the errno), 130 for Ctrl-C."""
    try:
        service = build()
    except ValueError as err:
        print(f"{name}: {err}", file=sys.stderr)
        return 2
    except OSError as err:
        if not is_storage_fault(err):
            raise
        print(f"{name}: {StorageError(err.errno, err.strerror, err.filename)}", file=sys.stderr)
        return EXIT_STORAGE
    try:
        code = service.run()
    except StorageError as err:
        print(f"{name}: {err}", file=sys.stderr)
        return EXIT_STORAGE
    except ConnectionError as err:
        print(f"{name}: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    return 0 if code is None else int(code)


#: The signals that stop a process cleanly: Ctrl-C, ``kill``/``timeout``/compose/systemd, a closed terminal or ssh.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def stop_on_signals(stop: Callable[[], None]) -> None:
    """Make the first SIGINT (Ctrl-C), SIGTERM or SIGHUP call ``stop``, so that a service ends its work cleanly; a
    second one acts as usual (KeyboardInterrupt, or the end of the process). Call it from the main thread."""

    def first(signum: int, frame: Any) -> None:
        for sig in STOP_SIGNALS:
            signal.signal(sig, signal.default_int_handler if sig == signal.SIGINT else signal.SIG_DFL)
        logging.getLogger(__name__).warning("%s: stopping cleanly (again to stop at once)",
                                            signal.Signals(signum).name)
        stop()

    for sig in STOP_SIGNALS:
        signal.signal(sig, first)


def exits_on_storage_faults(name: str) -> Callable[[Callable[..., int]], Callable[..., int]]:
    """Wrap an entry point so that a full, read-only or forbidden disk is one line naming the path and the errno,
    and exit code 5 (EXIT_STORAGE), instead of a traceback (the launcher, whose writes are not inside a service)."""

    def wrap(main: Callable[..., int]) -> Callable[..., int]:
        @functools.wraps(main)
        def wrapper(*args: Any, **kwargs: Any) -> int:
            try:
                return main(*args, **kwargs)
            except OSError as err:
                if not is_storage_fault(err):
                    raise
                shown = err if isinstance(err, StorageError) else StorageError(err.errno, err.strerror, err.filename)
                print(f"{name}: {shown}", file=sys.stderr)
                return EXIT_STORAGE

        return wrapper

    return wrap
