"""``make run`` against a broker nobody can reach ends at once: one line and exit code 1, no processes started."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path


def _closed_port() -> int:
    """A port on 127.0.0.1 with nothing listening (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_an_unreachable_broker_is_one_line_and_exit_1(tmp_path: Path) -> None:
    env = {**os.environ, "FEDRL_BROKER": f"mqtt://127.0.0.1:{_closed_port()}", "FEDRL_RUN_DIR": str(tmp_path / "run")}
    start = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "deploy.run_local"], env=env, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 1
    assert time.monotonic() - start < 15
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "cannot reach the MQTT broker" in lines[0], done.stderr
    assert not (tmp_path / "run" / "logs" / "chief.log").exists()
