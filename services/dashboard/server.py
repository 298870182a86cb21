"""The dashboard's HTTP adapter (standard library only): the page, a JSON snapshot and a server-sent event stream.

| path | what |
| --- | --- |
| ``/`` | the page (``static/index.html`` with ``app.js`` and ``style.css``; nothing is fetched from elsewhere) |
| ``/api/snapshot`` | the run's whole state as JSON |
| ``/events`` | ``text/event-stream``: ``snapshot`` first, then ``delta`` (a list of events), ``stats`` every second |
| ``/healthz`` | ``ok`` |
"""

from __future__ import annotations

import json
import logging
import sys
import threading
import time
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from services.dashboard.hub import Hub

log = logging.getLogger("dashboard.http")

STATIC_DIR = Path(__file__).resolve().parent / "static"
STATIC_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
                ".css": "text/css; charset=utf-8"}
#: Host names a browser uses for a server bound to loopback; any other name there is a DNS-rebinding attempt.
LOOPBACK_NAMES = frozenset({"127.0.0.1", "localhost", "[::1]", "::1"})
#: The page may load its own files and talk to this server, nothing else.
CSP = ("default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data:; connect-src 'self'; "
       "base-uri 'none'; form-action 'none'; frame-ancestors 'none'")


def _json(obj: Any) -> bytes:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


def load_static(directory: Path = STATIC_DIR) -> dict[str, tuple[str, bytes]]:
    """URL path -> (content type, body) for the page's files, read once."""
    files = {f"/{p.name}": (STATIC_TYPES[p.suffix], p.read_bytes())
             for p in sorted(directory.iterdir()) if p.suffix in STATIC_TYPES}
    files["/"] = files["/index.html"]
    return files


class DashboardServer(ThreadingHTTPServer):
    """One thread per request; an event stream holds its thread until the page goes or the server stops."""

    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, address: tuple[str, int], hub: Hub, stats: Callable[[], dict[str, Any]],
                 stats_interval: float = 1.0) -> None:
        super().__init__(address, DashboardHandler)
        self.hub = hub
        self.stats = stats
        self.stats_interval = stats_interval
        self.static = load_static()
        self.stopping = threading.Event()
        self.loopback_only = address[0] in LOOPBACK_NAMES or address[0].startswith("127.")

    @property
    def url(self) -> str:
        host, port = self.server_address[:2]
        shown = "127.0.0.1" if host in ("0.0.0.0", "") else str(host)
        return f"http://{shown}:{port}/"

    def full_stats(self) -> dict[str, Any]:
        return {**self.stats(), "pages": self.hub.clients, "dropped_pages": self.hub.dropped_clients,
                "ignored": dict(self.hub.view.ignored), "refused": dict(self.hub.view.refused),
                "t": round(time.time(), 3)}

    def host_allowed(self, header: str | None) -> bool:
        """Served on loopback, only pages that asked for a loopback name get an answer (DNS rebinding)."""
        if not self.loopback_only or not header:
            return True
        name = header.strip().lower()
        name = name[: name.index("]") + 1] if name.startswith("[") else name.rsplit(":", 1)[0]
        return name in LOOPBACK_NAMES or name.startswith("127.")

    def handle_error(self, request: Any, client_address: Any) -> None:
        """A browser that went away mid-request is normal; anything else is logged with its traceback."""
        exc = sys.exc_info()[1]
        if isinstance(exc, (ConnectionError, TimeoutError)):
            log.debug("%s went away: %s", client_address, exc)
        else:
            log.exception("request from %s failed", client_address)

    def shutdown(self) -> None:
        self.stopping.set()
        super().shutdown()


class DashboardHandler(BaseHTTPRequestHandler):
    server: DashboardServer
    server_version = "fedrl-dashboard"
    protocol_version = "HTTP/1.1"

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("%s %s", self.address_string(), format % args)

    def _send(self, status: int, content_type: str, body: bytes) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Content-Security-Policy", CSP)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def do_HEAD(self) -> None:
        self.do_GET()

    def do_GET(self) -> None:
        path = urlsplit(self.path).path
        if not self.server.host_allowed(self.headers.get("Host")):
            self._send(403, "text/plain; charset=utf-8", b"this dashboard answers to 127.0.0.1 and localhost only\n")
        elif path in self.server.static:
            self._send(200, *self.server.static[path])
        elif path == "/api/snapshot":
            self._send(200, "application/json", _json({**self.server.hub.snapshot(),
                                                       "stats": self.server.full_stats()}))
        elif path == "/events" and self.command == "GET":
            self._stream()
        elif path == "/healthz":
            self._send(200, "text/plain; charset=utf-8", b"ok\n")
        else:
            self._send(404, "text/plain; charset=utf-8", b"not found\n")

    def _event(self, name: str, data: Any) -> None:
        self.wfile.write(b"event: " + name.encode() + b"\ndata: " + _json(data) + b"\n\n")
        self.wfile.flush()

    def _stream(self) -> None:
        server = self.server
        snapshot, client = server.hub.connect()
        try:
            self.send_response(200)
            self.send_header("Content-Type", "text/event-stream; charset=utf-8")
            self.send_header("Cache-Control", "no-store")
            self.send_header("X-Accel-Buffering", "no")
            self.send_header("Connection", "close")
            self.end_headers()
            self.close_connection = True
            self.wfile.write(b"retry: 1000\n\n")
            self._event("snapshot", {**snapshot, "stats": server.full_stats()})
            last_stats = time.monotonic()
            while not server.stopping.is_set() and not client.overflowed.is_set():
                events = client.next_batch(timeout=0.25)
                if events:
                    self._event("delta", events)
                if time.monotonic() - last_stats >= server.stats_interval:
                    self._event("stats", server.full_stats())
                    last_stats = time.monotonic()
        except (BrokenPipeError, ConnectionResetError, TimeoutError):
            pass  # the page went away
        finally:
            server.hub.disconnect(client)
