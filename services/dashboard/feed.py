"""The dashboard's MQTT adapter: subscribe to one run's topics and the rigs' status and telemetry, decode, enqueue.

paho's network thread only decodes and enqueues (a bounded queue: when it is full the message is counted as dropped,
never waited for); the pump thread applies batches to the Hub. Bad payloads are logged and counted, messages of
kinds this build does not know are counted and ignored, and the rigs' 143 Hz ``state`` topic is never subscribed.
In a tiered run (its RunStart names edges) the workers' updates are not read: each worker's progress comes from its
edge's partials, the submissions the root counts without their tensors (services/dashboard/view.py), so the
dashboard does not decode a gradient per worker and round; a flat run under the same id reads them again.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import Counter
from typing import Any

from protocol import topics
from protocol.codec import DecodeError, RejectCounter, decode
from protocol.messages import Message
from protocol.routes import DASHBOARD, qos_of, received_by
from protocol.transport import Connect
from services.dashboard.hub import Hub

log = logging.getLogger("dashboard")


def subscriptions(run_id: str, rigs: list[str] | None) -> list[tuple[str, int]]:
    """Topic filters and QoS: the run's topics the contract names the dashboard a reader of (protocol/routes.py),
    and status + telemetry of the given rigs (None = all)."""
    run = topics.check_id(run_id, "run id")
    filters = [r.filter(run=run) for r in received_by(DASHBOARD) if "run" in r.parameters]
    for rig in rigs if rigs else ["+"]:
        name = rig if rig == "+" else topics.check_id(rig, "rig id")
        filters += [f"{topics.QUBE}/{name}/{topics.STATUS}", f"{topics.QUBE}/{name}/{topics.TELEMETRY}"]
    return [(f, qos_of(f)) for f in filters]


def updates_filter(run_id: str) -> str:
    """The topic filter of every worker's updates (and mature actors) in run ``run_id``."""
    return f"{topics.FEDRL}/{topics.check_id(run_id, 'run id')}/worker/+/{topics.UPDATE}"


class MqttFeed:
    """Decoded messages of one run into a Hub."""

    def __init__(self, connect: Connect, run_id: str, hub: Hub, rigs: list[str] | None = None,
                 max_queue: int = 50_000, where: str = "the broker") -> None:
        """``connect`` makes its connection (protocol.transport.Connect); ``where`` names it in the log."""
        self.run_id = topics.check_id(run_id, "run id")
        self.hub = hub
        self.subs = subscriptions(run_id, rigs)
        self.rejects = RejectCounter(log)
        self.unknown: Counter[str] = Counter()
        self.received = 0
        self.dropped = 0
        self.inbox: queue.Queue[tuple[str, Message, float]] = queue.Queue(maxsize=max_queue)
        self.conn = connect(f"fedrl-{run_id}-dashboard", None, self.rejects)
        self.where = where
        self.updates = updates_filter(self.run_id)  # the workers' updates: not read in a tiered run
        self.reading_updates = True
        self._stop = threading.Event()
        self._pump = threading.Thread(target=self._run_pump, name="dashboard-pump", daemon=True)

    # -- network thread ----------------------------------------------------------------------------------------

    def on_message(self, topic: str, payload: bytes) -> None:
        self.received += 1
        if not payload:  # the chief's claim of the run, cleared at its end (chief/claim.py)
            return
        try:
            msg: Message = decode(payload, topic=topic)
        except DecodeError as err:
            if err.reason == "unknown_kind":  # a newer peer's message: not ours to judge
                self.unknown[err.detail.removeprefix("unknown message kind ")] += 1
                log.debug("ignored message on %s: %s", topic, err.detail)
            else:
                self.rejects.reject_error(topic, err)
            return
        try:
            self.inbox.put_nowait((topic, msg, time.time()))
        except queue.Full:
            self.dropped += 1

    # -- pump thread -------------------------------------------------------------------------------------------

    def _run_pump(self) -> None:
        while not self._stop.is_set():
            try:
                batch = [self.inbox.get(timeout=0.2)]
            except queue.Empty:
                continue
            try:
                while len(batch) < 1000:
                    batch.append(self.inbox.get_nowait())
            except queue.Empty:
                pass
            try:
                self.hub.apply(batch)
                self.follow_tier(self.hub.view.tiered)
            except Exception:  # a bug in the view must not stop the dashboard
                log.exception("could not apply %d messages", len(batch))

    def follow_tier(self, tiered: bool) -> None:
        """Stop reading the workers' updates once the run is tiered (its edges' partials carry them); read them
        again when a flat run follows under the same id."""
        if tiered != self.reading_updates:
            return
        if tiered:
            self.conn.unsubscribe(self.updates)
        else:
            self.conn.subscribe(self.updates, self.on_message, qos=qos_of(self.updates))
        self.reading_updates = not tiered
        log.info("a tiered run: each worker's progress from its edge's partials, not from its updates" if tiered
                 else "a flat run: reading the workers' updates")

    # -- lifecycle ---------------------------------------------------------------------------------------------

    def start(self, timeout: float = 10.0, stop: threading.Event | None = None) -> MqttFeed:
        self._pump.start()
        self.conn.start(timeout, stop)
        for topic_filter, qos in self.subs:
            self.conn.subscribe(topic_filter, self.on_message, qos=qos)
        log.info("dashboard following run %s on %s (%s)", self.run_id, self.where,
                 ", ".join(t for t, _ in self.subs))
        return self

    def stop(self) -> None:
        self._stop.set()
        try:
            self.conn.stop()
        finally:
            if self._pump.is_alive():
                self._pump.join(timeout=2)

    def stats(self) -> dict[str, Any]:
        return {"received": self.received, "rejected": self.rejects.as_dict(), "unknown": dict(self.unknown),
                "dropped": self.dropped, "connected": self.conn.connected.is_set()}
