"""``python -m services.dashboard.screenshot --out docs/dashboard.png``: run a short federation, watch it in the
dashboard with headless Chromium and save a picture of the page (the README's screenshot).

It starts the embedded broker, the dashboard and ``python -m deploy.run_local`` (chief, workers and, for ``qube``,
simulated rigs), opens the page before the run starts, and reports how long the page took to show the first point
of a curve after the launch and after the chief's RunStart. The picture is taken when the run ends or after
``--seconds``, whichever comes first. Needs ``apt-get install chromium chromium-driver`` and the ``dev`` extra.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any

from services.broker.embedded import start_broker_process, stop_process
from services.dashboard.browser import chromium, missing, page_state
from services.dashboard.service import wait_for_url


def interrupt(proc: subprocess.Popen, timeout: float = 30.0) -> None:
    """Ctrl-C for the launcher (it then stops its own children), a hard stop if that does not end it."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            stop_process(proc)


def capture(driver: Any, out: Path, width: int) -> Path:
    """Save the whole page (not just the window) as a PNG."""
    for _ in range(5):  # the window's outer size is not the page's: grow it until nothing scrolls
        inner, full = driver.execute_script(
            "return [window.innerHeight, document.documentElement.scrollHeight]")
        if full <= inner:
            break
        driver.set_window_size(width, driver.get_window_size()["height"] + full - inner)
        time.sleep(0.3)  # one more render at the new size
    out.parent.mkdir(parents=True, exist_ok=True)
    if not driver.save_screenshot(str(out)):
        raise RuntimeError(f"Chromium could not save {out}")
    return out


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m services.dashboard.screenshot", description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("docs/dashboard.png"), help="PNG to write")
    parser.add_argument("--env", default="CartPole-v0", help="task of the run (default CartPole-v0)")
    parser.add_argument("--workers", type=int, default=4)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--policy", help="federation strategy (default: the launcher's)")
    parser.add_argument("--seconds", type=float, default=300.0, help="take the picture after this long at the latest")
    parser.add_argument("--width", type=int, default=1400, help="browser window width in CSS pixels")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    problem = missing()
    if problem:
        print(f"screenshot: {problem}", file=sys.stderr)
        return 2
    run_id = "shot-" + dt.datetime.now().strftime("%H%M%S")
    work = Path(tempfile.mkdtemp(prefix="fedrl-shot-"))
    procs: list[subprocess.Popen] = []
    broker_proc, port = start_broker_process(stdout=(work / "broker.log").open("wb"), stderr=subprocess.STDOUT)
    broker = f"mqtt://127.0.0.1:{port}"
    try:
        url_file = work / "dashboard.url"
        dashboard = subprocess.Popen(
            [sys.executable, "-m", "services.dashboard", "--broker", broker, "--run-id", run_id, "--port", "0",
             "--url-file", str(url_file)], stdout=(work / "dashboard.log").open("wb"), stderr=subprocess.STDOUT)
        procs.append(dashboard)
        url = wait_for_url(dashboard, url_file)
        if url is None:
            print(f"screenshot: the dashboard did not start; see {work / 'dashboard.log'}", file=sys.stderr)
            return 1
        with chromium(args.width, 1000) as driver:
            driver.get(url)
            launched = time.time()
            run = subprocess.Popen(
                [sys.executable, "-m", "deploy.run_local", "--broker", broker, "--run-id", run_id, "--env", args.env,
                 "--workers", str(args.workers), "--seed", str(args.seed), "--dashboard-port", "off",
                 "--run-dir", str(work / "run"), *(["--policy", args.policy] if args.policy else [])],
                stdout=(work / "run.log").open("wb"), stderr=subprocess.STDOUT)
            procs.append(run)
            first_point: float | None = None
            while time.time() - launched < args.seconds:
                state = page_state(driver)
                if first_point is None and state["drawn"] > 0:
                    first_point = state["probe"]["firstPointAt"] / 1000.0
                if state["phase"] == "stopped" or run.poll() is not None:
                    break
                time.sleep(0.2)
            time.sleep(1.5)  # the last events and one render
            capture(driver, args.out, args.width)
            state = page_state(driver)
        snapshot = json.load(urllib.request.urlopen(url + "api/snapshot", timeout=10))
        started = snapshot["run"]["started_at"]
        print(f"wrote {args.out}: run {run_id}, {args.env}, {args.workers} workers, phase {state['phase']}, "
              f"{state['drawn']} points, {state['rounds']} round rows, {len(state['rigs'])} rigs")
        if first_point is not None:
            after_start = f", {first_point - started:.1f} s after the chief's RunStart" if started else ""
            print(f"first curve point on the page {first_point - launched:.1f} s after the launch{after_start}")
        else:
            print("no curve point was shown")
        return 0
    finally:
        for proc in reversed(procs):
            interrupt(proc)
        stop_process(broker_proc)


if __name__ == "__main__":
    sys.exit(main())
