"""A tiered run's witness (docs/explanation/tiered.md): an observer of the wire that keeps every worker's actor
gradient and every aggregate the root chief sent, and saves them as the run folder's GRADIENTS (runtime/records.py)
for the audit's ``tiered-exact`` check. It reads what a dashboard may read (the observer's login) and decides
nothing; the root chief never sees a worker's gradient, this observer does, so it is for checking runs, not for
production (deploy.inprocess --edges always has one; deploy.run_local --edges N --witness).

A broker that comes back without the witness's session (one restarted empty) drops what was published before the
witness subscribed again: the witness saves each such stretch as a gap (``gaps``), so that the audit counts the
rounds it lacks there as unwitnessed rather than failing a run that was right."""

from __future__ import annotations

import logging
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from protocol.codec import DecodeError, RejectCounter, decode
from protocol.messages import ChiefAggregate, MatureParams, WorkerUpdate
from protocol.routes import CHIEF, WORKER, route_for
from protocol.tensors import unpack_arrays
from protocol.transport import Connect, Transport
from runtime.records import GRADIENTS, ROOT, Place, WitnessGap, gradient_key, write_gradients

log = logging.getLogger("witness")


@dataclass(frozen=True)
class Link:
    """The witness's connection at one moment: its successful connects so far (Transport.connects) and whether the
    broker still held its session at the last of them (Transport.session_present)."""

    connects: int
    resumed: bool

    @classmethod
    def of(cls, conn: Transport) -> Link:
        return cls(conn.connects, conn.session_present)


def lost(before: Link, after: Link) -> bool:
    """Whether what was published between two moments of the connection may never have reached it: it connected
    again and the broker no longer held its session, or it connected more than once (only the last connect's
    session is known)."""
    again = after.connects - before.connects
    return again > 1 or (again == 1 and not after.resumed)


def gaps(seen: Sequence[tuple[Place, Link]], subscribed: Link, stopped: Link | None) -> list[WitnessGap]:
    """The witness's gaps: ``seen`` is the place of each message it witnessed and its connection then, in the order
    they came; ``subscribed`` its connection when it subscribed, ``stopped`` when it stopped (None: it was down,
    so whatever came after its last message may be missing). A gap wherever the connection was ``lost`` between two
    messages (bounded by their places), before the first (from the beginning) or after the last (to the end)."""
    out: list[WitnessGap] = []
    last: Place | None = None
    link = subscribed
    for place, now in seen:
        if lost(link, now):
            out.append(WitnessGap(last, place))
        last, link = place, now
    if stopped is None or lost(link, stopped):
        out.append(WitnessGap(last, None))
    return out


class Witness:
    """Started on a connection (``connect``, protocol.transport.Connect) before the workers send; ``save`` writes
    ``run_dir``/GRADIENTS."""

    def __init__(self, connect: Connect, run_id: str, run_dir: Path) -> None:
        self.path = run_dir / GRADIENTS
        self.tensors: dict[str, np.ndarray] = {}
        self.seen: list[tuple[Place, Link]] = []  # each witnessed message's place and the connection then
        self._lock = threading.Lock()
        self.conn = connect(f"fedrl-{run_id}-witness", None, RejectCounter(log))
        self.conn.start()
        self.subscribed = Link.of(self.conn)  # before subscribing: a session lost meanwhile counts as a gap
        for publisher, kind in ((WORKER, "update"), (CHIEF, "aggregate")):
            self.conn.subscribe(route_for(publisher, kind).filter(run=run_id), self._note, qos=1)

    def _note(self, topic: str, payload: bytes) -> None:
        """On the connection's delivery thread, where its connects are counted too: the link is the message's."""
        try:
            msg = decode(payload, WorkerUpdate, MatureParams, ChiefAggregate, topic=topic)
        except DecodeError:
            return  # a bad payload: nothing to witness
        link = Link.of(self.conn)
        with self._lock:
            if isinstance(msg, MatureParams):  # a finisher's actor: a place witnessed, no gradient
                self.seen.append(((msg.episode, 0), link))
                return
            self.seen.append(((msg.episode, msg.step), link))
            who = msg.worker_id if isinstance(msg, WorkerUpdate) else ROOT
            for name, array in unpack_arrays(msg.gradient or {}).items():
                self.tensors[gradient_key(msg.episode, msg.step, who, name)] = array

    def save(self) -> Path:
        up = self.conn.connected.is_set()
        self.conn.stop()
        with self._lock:
            found = gaps(self.seen, self.subscribed, Link.of(self.conn) if up else None)
            for gap in found:
                log.warning("the witness's broker lost its session: it may lack the rounds from %s to %s",
                            gap.start or "the beginning", gap.end or "the end")
            return write_gradients(self.path, self.tensors, found)
