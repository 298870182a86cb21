"""A worker's resumable state: saved when the chief interrupts the run (a RunStop with reason INTERRUPTED), loaded
when the resumed run's RunStart names the worker again, so that its learning goes on exactly where it stopped.

The file is ``<state dir>/<run id>.<worker id>.state.pt``. It holds the run it belongs to (run id, worker id, the
chief's session and epoch), the task and the networks' shapes (checked when it is loaded), Algorithm 2's state
(worker/federated.py ``Algorithm2.state``: its bookkeeping, the learner, the env's RNGs), the submission the chief
had not answered yet (sent again first), the rounds whose answers were applied, and the process-wide RNGs (torch,
numpy, Python's). It is ``torch.save`` of tensors and plain data, read with ``weights_only``: loading one runs no
code. It is written atomically (runtime/storage.py: a storage fault is one line and exit 5) and removed once taken
up, so a worker that is started again later does not go back to it.
"""

from __future__ import annotations

import io
import logging
import random
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from protocol.codec import DecodeError, decode, encode
from protocol.messages import MatureParams, RunStart, WorkerUpdate
from runtime.storage import atomic_write, storage_errors

log = logging.getLogger("worker")

VERSION = 1


class UnfitState(ValueError):
    """A state file that is unreadable or belongs to another run, task or network (the worker refuses to start)."""


def state_file(folder: Path, run_id: str, worker_id: str) -> Path:
    """Where a worker keeps its resumable state (ids hold no path separators: protocol.topics.check_id)."""
    return folder / f"{run_id}.{worker_id}.state.pt"


@dataclass(frozen=True)
class Identity:
    """What a state must match to be taken up: the run, the worker, its task and its networks' shapes."""

    run_id: str
    worker_id: str
    env: str
    actor_spec: dict[str, tuple[int, ...]]
    critic_spec: dict[str, tuple[int, ...]]

    def fields(self) -> dict[str, Any]:
        return {"run_id": self.run_id, "worker_id": self.worker_id, "env": self.env,
                "actor_spec": {k: list(v) for k, v in self.actor_spec.items()},
                "critic_spec": {k: list(v) for k, v in self.critic_spec.items()}}


def save(path: Path, who: Identity, start: RunStart, epoch: int, algorithm: dict[str, Any],
         pending: WorkerUpdate | MatureParams | None, answered: set[int]) -> None:
    """Write the state file atomically (a storage fault: StorageError, one line and exit 5)."""
    state = {"version": VERSION, **who.fields(), "session": start.session, "epoch": epoch,
             "algorithm": algorithm, "pending": encode(pending) if pending is not None else None,
             "answered": sorted(answered), "rngs": _global_rngs()}
    data = io.BytesIO()  # torch.save reports a full disk as a RuntimeError: serialise first, then write
    torch.save(state, data)
    with storage_errors(path):
        path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, data.getvalue())


@dataclass(frozen=True)
class Resumed:
    """A loaded state: Algorithm 2's, the submission to send again (if any) and the rounds whose answers were
    applied. Loading it restored the process-wide RNGs."""

    algorithm: dict[str, Any]
    pending: WorkerUpdate | MatureParams | None
    answered: set[int]


def load(path: Path, who: Identity, start: RunStart) -> Resumed:
    """Read and check a state file for the run of ``start`` (``discard`` it once taken up); UnfitState, nothing
    restored, when it cannot be read or does not belong to this run, worker, task and networks, or to this chief's
    run (its session, and an epoch before the chief's)."""
    try:
        state = torch.load(path, weights_only=True)
    except Exception as exc:  # a truncated, foreign or corrupt file: whatever torch raises
        raise UnfitState(f"{path} is not a readable worker state ({type(exc).__name__}: {exc})") from exc
    if not isinstance(state, dict) or state.get("version") != VERSION:
        raise UnfitState(f"{path} is not a worker state of version {VERSION}")
    for key, want in who.fields().items():
        if state.get(key) != want:
            raise UnfitState(f"{path} holds the state of {key} {state.get(key)!r}, this worker's is {want!r}")
    if state["session"] != start.session or not state["epoch"] < start.epoch:
        raise UnfitState(f"{path} was saved in session {state['session']!r} epoch {state['epoch']}, and the chief "
                         f"runs session {start.session!r} epoch {start.epoch}: it is not this run's last interruption")
    try:
        pending = (decode(state["pending"], WorkerUpdate, MatureParams)
                   if state["pending"] is not None else None)
    except DecodeError as exc:
        raise UnfitState(f"{path}: its pending submission does not decode ({exc})") from exc
    _set_global_rngs(state["rngs"])
    return Resumed(state["algorithm"], pending, set(state["answered"]))


def discard(path: Path) -> None:
    """Remove a state once taken up: the worker's learning is in memory again, and a later start must not go back."""
    with storage_errors(path):
        path.unlink(missing_ok=True)


def _global_rngs() -> dict[str, Any]:
    """The process-wide RNGs (the learner keeps its own, but a library may draw from these)."""
    name, key, pos, has_gauss, gauss = np.random.get_state(legacy=True)
    return {"torch": torch.get_rng_state(), "numpy": [name, torch.from_numpy(np.asarray(key, np.int64)), pos,
                                                       has_gauss, gauss], "python": random.getstate()}


def _set_global_rngs(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    name, key, pos, has_gauss, gauss = state["numpy"]
    np.random.set_state((name, key.numpy().astype(np.uint32), pos, has_gauss, gauss))
    random.setstate(state["python"])
