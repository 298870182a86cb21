"""The dashboard in a real headless browser during a real federation: ``python -m deploy.run_local`` (embedded broker,
chief, 2 PPO workers on CartPole-v0, the dashboard) with the page open in Debian's Chromium from before the run
starts. Every worker must appear and the curves must grow while the run goes on.

Skipped where Chromium or chromedriver is missing: ``apt-get install chromium chromium-driver`` (as root).
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from services.dashboard import browser
from services.dashboard.screenshot import capture, interrupt

REASON = browser.missing()
pytestmark = [pytest.mark.slow, pytest.mark.skipif(REASON is not None, reason=f"no headless browser: {REASON}")]


class Launcher:
    """run_local as a child process whose output is collected by a thread."""

    def __init__(self, argv: list[str]) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", "deploy.run_local", *argv], stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True)
        self.lines: list[str] = []
        self.url = threading.Event()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line)
            if line.startswith("dashboard: http"):
                self.dashboard = line.split()[1]
                self.url.set()

    @property
    def output(self) -> str:
        return "".join(self.lines)


def test_page_shows_every_worker_and_growing_curves_during_a_run(tmp_path: Path) -> None:
    run = Launcher(["--workers", "2", "--env", "CartPole-v0", "--seed", "3", "--max-episodes", "600",
                    "--run-dir", str(tmp_path / "run"), "--run-id", "browser", "--dashboard-port", "0"])
    try:
        assert run.url.wait(60), f"run_local printed no dashboard URL:\n{run.output}"
        with browser.chromium(1280, 900) as driver:
            driver.get(run.dashboard)
            drawn: list[int] = []  # points on the chart, sampled while the run goes on
            workers: dict = {}
            deadline = time.monotonic() + 300
            while time.monotonic() < deadline:
                state = browser.page_state(driver)
                workers = state["workers"]
                if state["phase"] == "running" and state["connected"]:
                    drawn.append(state["drawn"])
                if state["phase"] == "stopped" or run.proc.poll() is not None:
                    break
                time.sleep(0.2)
            time.sleep(0.5)
            final = browser.page_state(driver)
            js_errors = [e for e in driver.get_log("browser") if e.get("source") == "javascript"]
            shot = capture(driver, tmp_path / "page.png", 1280)
        assert run.proc.wait(120) == 0, run.output[-3000:]
    finally:
        interrupt(run.proc)
    growth = sorted({d for d in drawn if d > 0})
    assert len(growth) >= 3, f"the curves did not grow while the run went on (points seen: {growth})"
    assert drawn == sorted(drawn), "points disappeared"
    assert set(workers) == {"w0", "w1"} and all(w["points"] > 0 for w in final["workers"].values())
    assert final["rounds"] > 0 and final["probe"]["firstPointAt"] is not None
    assert "all workers solved" in run.output
    assert final["phase"] == "stopped" and all(w["state"] == "finished" for w in final["workers"].values())
    assert shot.stat().st_size > 10_000
    assert not js_errors, js_errors
