"""Wires the dashboard together: RunView + Hub (core), MqttFeed (broker side), DashboardServer (browser side)."""

from __future__ import annotations

import logging
import signal
import subprocess
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from protocol.mqtt import BrokerAddress, Stopped
from protocol.transport import Connect, connector
from runtime.cli import STOP_SIGNALS
from services.dashboard.feed import MqttFeed
from services.dashboard.hub import Hub
from services.dashboard.server import DashboardServer
from services.dashboard.view import RunView

log = logging.getLogger("dashboard")


@dataclass
class DashboardConfig:
    broker: BrokerAddress
    run_id: str = "default"
    host: str = "127.0.0.1"
    port: int = 8050  # 0 = any free port
    rigs: list[str] | None = None  # None = every rig's status and telemetry
    max_points: int = 4000  # per worker curve kept for new pages (older points are thinned)
    url_file: Path | None = None  # written with the page's URL once it is served
    key: bytes | None = None  # the run's key: messages without their sender's tag are refused (None: all trusted)


class DashboardService:
    """A live web view of one run; ``start()``/``stop()`` for tests, ``run()`` for the command line."""

    def __init__(self, cfg: DashboardConfig, connect: Connect | None = None) -> None:
        """``connect`` makes its connection (protocol.transport.Connect; default: to ``cfg.broker``)."""
        self.cfg = cfg
        self.hub = Hub(RunView(cfg.run_id, max_points=cfg.max_points, key=cfg.key))
        self.feed = MqttFeed(connect or connector(cfg.broker), cfg.run_id, self.hub, cfg.rigs, where=str(cfg.broker))
        try:
            self.server = DashboardServer((cfg.host, cfg.port), self.hub, self.feed.stats)
        except OSError as err:
            raise ValueError(f"cannot serve on {cfg.host}:{cfg.port}: {err.strerror or err}") from None
        self._http = threading.Thread(target=self.server.serve_forever, kwargs={"poll_interval": 0.2},
                                      name="dashboard-http", daemon=True)
        self.stop_event = threading.Event()

    @property
    def url(self) -> str:
        return self.server.url

    def start(self) -> DashboardService:
        """Serve the page, then connect to the broker (ConnectionError if it cannot be reached)."""
        self._http.start()
        try:
            self.feed.start(stop=self.stop_event)
        except (ConnectionError, Stopped):
            self.stop()
            raise
        if self.cfg.url_file is not None:
            tmp = self.cfg.url_file.with_name(self.cfg.url_file.name + ".tmp")
            tmp.write_text(self.url + "\n")
            tmp.replace(self.cfg.url_file)
        return self

    def stop(self) -> None:
        self.stop_event.set()
        self.feed.stop()
        if self._http.is_alive():
            self.server.shutdown()
        self.server.server_close()

    def run(self) -> int:
        try:
            self.start()
        except Stopped:
            return 0
        print(f"dashboard for run {self.cfg.run_id}: {self.url}", flush=True)
        try:
            self.stop_event.wait()
        finally:
            self.stop()
        return 0

    def install_signal_handlers(self) -> None:
        for sig in STOP_SIGNALS:
            signal.signal(sig, lambda *_: self.stop_event.set())


def wait_for_url(proc: subprocess.Popen, url_file: Path, timeout: float = 20.0) -> str | None:
    """The URL the dashboard wrote once it served its page, or None when it exited or took too long."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if url_file.exists():
            return url_file.read_text().strip()
        if proc.poll() is not None:
            return None
        time.sleep(0.05)
    return None
