"""Between the MQTT feed and the pages: applies batches of decoded messages to the RunView under one lock and
hands the resulting events to every connected page through its own bounded queue.

A page that falls behind (its queue is full) is cut off rather than slowing anyone down; its browser reconnects and
starts again from a fresh snapshot.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterable
from typing import Any

from protocol.messages import Message
from services.dashboard.view import Event, RunView


class Client:
    """One connected page: a queue of event batches and a flag set when it fell too far behind."""

    def __init__(self, max_batches: int) -> None:
        self.batches: queue.Queue[list[Event]] = queue.Queue(maxsize=max_batches)
        self.overflowed = threading.Event()

    def next_batch(self, timeout: float) -> list[Event]:
        """Every event waiting (possibly none after ``timeout`` s)."""
        out: list[Event] = []
        try:
            out.extend(self.batches.get(timeout=timeout))
            while True:
                out.extend(self.batches.get_nowait())
        except queue.Empty:
            pass
        return out


class Hub:
    """Thread-safe owner of the RunView and of the connected pages."""

    def __init__(self, view: RunView, client_batches: int = 2000) -> None:
        self.view = view
        self.client_batches = client_batches
        self.dropped_clients = 0
        self._lock = threading.Lock()
        self._clients: set[Client] = set()

    def apply(self, items: Iterable[tuple[str, Message, float]]) -> list[Event]:
        """Apply ``(topic, message, time)`` items in order and send their events to every page."""
        with self._lock:
            events: list[Event] = []
            for topic, msg, now in items:
                events.extend(self.view.apply(topic, msg, now))
            if events:
                for client in list(self._clients):
                    try:
                        client.batches.put_nowait(events)
                    except queue.Full:
                        client.overflowed.set()
                        self._clients.discard(client)
                        self.dropped_clients += 1
        return events

    def connect(self) -> tuple[dict[str, Any], Client]:
        """A snapshot and a client whose queue receives every event after it (nothing lost in between)."""
        client = Client(self.client_batches)
        with self._lock:
            snapshot = self.view.snapshot()
            self._clients.add(client)
        return snapshot, client

    def disconnect(self, client: Client) -> None:
        with self._lock:
            self._clients.discard(client)

    def snapshot(self) -> dict[str, Any]:
        with self._lock:
            return self.view.snapshot()

    @property
    def clients(self) -> int:
        with self._lock:
            return len(self._clients)
