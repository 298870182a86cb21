"""Worker processes forked from one that has imported torch once (``python -m deploy.run_local --fork-workers``).

Each ``python -m worker`` spends about 3 s of CPU importing torch and gymnasium before it does anything, and holds
its own copy of them in memory. A launcher of N workers on one machine pays that N times. Here a ``multiprocessing``
fork server imports the worker's modules once; each worker is a fork of it and runs ``python -m worker``'s main
exactly as a process of its own would: its environment (the launcher's, with its FEDRL_* settings), its output
appended to its log, its own process group (a Ctrl-C in the terminal reaches the launcher only), its exit code.
``ForkedProcess`` answers what the launcher asks of a ``subprocess.Popen`` (poll, wait, terminate, kill,
send_signal, pid, returncode).

What differs from a process of its own: ``ps`` shows the fork server's command line for it, and it shares the fork
server's hash seed.
"""

from __future__ import annotations

import multiprocessing
import os
import runpy
import signal
import subprocess
import sys
from pathlib import Path

#: Modules the fork server imports before it forks (the worker's whole import graph: torch, gymnasium, paho).
PRELOAD = ["worker.service", "worker.settings", "runtime.cli"]

_CONTEXT = multiprocessing.get_context("forkserver")
_CONTEXT.set_forkserver_preload(PRELOAD)


def _run_module(module: str, env: dict[str, str], log_path: str) -> None:
    """In the fork: become ``python -m module`` with environment ``env``, writing to ``log_path``."""
    os.setpgid(0, 0)
    os.environ.clear()  # the fork server's is the launcher's environment when it started, not now
    os.environ.update(env)
    fd = os.open(log_path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)
    # Line-buffered, so that the log keeps up as with PYTHONUNBUFFERED (which only a starting interpreter reads).
    sys.stdout = open(1, "w", buffering=1, closefd=False, encoding="utf-8", errors="backslashreplace")
    sys.stderr = open(2, "w", buffering=1, closefd=False, encoding="utf-8", errors="backslashreplace")
    sys.argv = [module]
    runpy.run_module(module, run_name="__main__", alter_sys=True)


class ForkedProcess:
    """A forked ``python -m module``, with the part of ``subprocess.Popen``'s interface the launcher uses."""

    def __init__(self, module: str, env: dict[str, str], log_path: Path) -> None:
        self._process = _CONTEXT.Process(target=_run_module, args=(module, env, str(log_path)), name=module)
        self._process.start()
        self.args = [sys.executable, "-m", module]

    @property
    def pid(self) -> int:
        assert self._process.pid is not None
        return self._process.pid

    @property
    def returncode(self) -> int | None:
        return self._process.exitcode

    def poll(self) -> int | None:
        return self._process.exitcode

    def wait(self, timeout: float | None = None) -> int:
        self._process.join(timeout)
        code = self._process.exitcode
        if code is None:
            raise subprocess.TimeoutExpired(self.args, timeout or 0.0)
        return code

    def send_signal(self, sig: int) -> None:
        if self._process.exitcode is None:
            os.kill(self.pid, sig)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)
