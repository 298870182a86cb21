"""A tiered run's witness (docs/explanation/tiered.md): an observer of the wire that keeps every worker's actor
gradient and every aggregate the root chief sent, and saves them as the run folder's GRADIENTS (runtime/records.py)
for the audit's ``tiered-exact`` check. It reads what a dashboard may read (the observer's login) and decides
nothing; the root chief never sees a worker's gradient, this observer does, so it is for checking runs, not for
production (deploy.inprocess --edges always has one; deploy.run_local --edges N --witness)."""

from __future__ import annotations

import logging
import threading
from pathlib import Path

import numpy as np

from protocol.codec import DecodeError, RejectCounter, decode
from protocol.messages import ChiefAggregate, WorkerUpdate
from protocol.routes import CHIEF, WORKER, route_for
from protocol.tensors import unpack_arrays
from protocol.transport import Connect
from runtime.records import GRADIENTS, ROOT, gradient_key

log = logging.getLogger("witness")


class Witness:
    """Started on a connection (``connect``, protocol.transport.Connect) before the workers send; ``save`` writes
    ``run_dir``/GRADIENTS."""

    def __init__(self, connect: Connect, run_id: str, run_dir: Path) -> None:
        self.path = run_dir / GRADIENTS
        self.tensors: dict[str, np.ndarray] = {}
        self._lock = threading.Lock()
        self.conn = connect(f"fedrl-{run_id}-witness", None, RejectCounter(log))
        self.conn.start()
        for publisher, kind in ((WORKER, "update"), (CHIEF, "aggregate")):
            self.conn.subscribe(route_for(publisher, kind).filter(run=run_id), self._note, qos=1)

    def _note(self, topic: str, payload: bytes) -> None:
        try:
            msg = decode(payload, WorkerUpdate, ChiefAggregate, topic=topic)
        except DecodeError:
            return  # a finisher's actor (MatureParams) or a bad payload: nothing to witness
        who = msg.worker_id if isinstance(msg, WorkerUpdate) else ROOT
        with self._lock:
            for name, array in unpack_arrays(msg.gradient or {}).items():
                self.tensors[gradient_key(msg.episode, msg.step, who, name)] = array

    def save(self) -> Path:
        self.conn.stop()
        with self._lock:
            np.savez_compressed(self.path, **self.tensors)  # type: ignore[arg-type]
        return self.path
