"""The chief's state on disk, so a chief that died can resume its run (``python -m chief`` with the same run id and
run folder finds ``chief-state.msgpack`` and carries on from it).

What is kept: the round state machine (open round, every worker's record with its recent returns and PIs, the
pending and early submissions, which recent rounds were counted, the answers of the last few rounds: what the keeper
still holds, chief/rounds.py HISTORY, so the file stays the same size however long the run), the roster, the
reject counters, the run's session id, and how far ``metrics.jsonl`` had been written. It is written atomically
(temporary file, fsync, rename) whenever a round closes and before a mature actor is acknowledged, so what the chief
confirmed to a worker is never lost. Tensors are stored as raw float32 bytes in msgpack, never pickled: a state file
is data, and loading one runs no code. Its layout is chief.records.ChiefState (validated when written and read);
workers' records are restored field by field, by name.

A root of edges (docs/explanation/tiered.md) also keeps the edges' partial sums of its open rounds and which edge
each worker is behind. What is not kept (and need not be): gradients accepted since the last write. Workers send a
submission again when the chief comes back (they see its RunStart), and everything is idempotent by worker and
episode, so the resumed chief counts each episode once and records it once (``metrics.jsonl`` is cut back to the
written position). Behind an edge, the worker's edge sends its partial of that round again (chief/edge.py).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from chief import tiers
from chief.records import ChiefState, KeeperState, SavedWorker, ServiceState
from chief.rounds import HeldPartial, RoundKeeper, RoundOutcome, Submission, WorkerRecord
from protocol.rounds import RoundShape
from protocol.tasks import TaskSpec
from protocol.tensors import TensorBlob
from runtime.storage import atomic_write

FILENAME = "chief-state.msgpack"
VERSION = 1
#: Closed rounds whose answers a state file keeps (a waiting worker waits for one of the last ones).
ANSWERS_SAVED = 3


def _arrays(arrays: dict[str, np.ndarray] | None) -> dict[str, Any] | None:
    if arrays is None:
        return None
    return {k: TensorBlob.from_array(np.asarray(v)).model_dump() for k, v in arrays.items()}


def _unarrays(blobs: dict[str, Any] | None) -> dict[str, np.ndarray] | None:
    if blobs is None:
        return None
    return {k: TensorBlob.model_validate(v).to_array().copy() for k, v in blobs.items()}


TENSORS = ("gradient", "params", "critic_gradient")


def _submission(s: Submission) -> dict[str, Any]:
    fields = {k: v for k, v in vars(s).items() if k not in TENSORS}
    return {**fields, "recent_returns": list(s.recent_returns), "earlier_receipts": list(s.earlier_receipts),
            **{k: _arrays(getattr(s, k)) for k in TENSORS}}


def _unsubmission(d: dict[str, Any]) -> Submission:
    return Submission(**{**d, "recent_returns": tuple(d["recent_returns"]),
                         "earlier_receipts": tuple(d.get("earlier_receipts", ())),
                         **{k: _unarrays(d[k]) for k in TENSORS}})


def _outcome(o: RoundOutcome) -> dict[str, Any]:
    fields = {k: v for k, v in vars(o).items() if k not in TENSORS}
    return {**fields, **{k: _arrays(getattr(o, k)) for k in TENSORS}}


def _unoutcome(d: dict[str, Any]) -> RoundOutcome:
    return RoundOutcome(**{**d, **{k: _unarrays(d[k]) for k in TENSORS}})


def keeper_state(k: RoundKeeper) -> dict[str, Any]:
    """Everything a RoundKeeper needs to go on, as plain data: ``KeeperState(...).model_dump()``, built directly.
    A 1,024-worker root saves every round, and building its workers' models and dumping them again was most of it;
    their fields have their types already, ``load`` checks them all, and a test holds both ways to the same bytes."""
    last = sorted(k.answers)[-ANSWERS_SAVED:]
    # The counted rounds a resumed keeper needs: those whose answers it keeps (an older one sent again is refused as
    # stale instead of a duplicate: it counts nothing either way, and no answer of it is kept), and the open
    # episode's (a later step checks its step 0).
    since = min([k.round - k.shape.per_episode, *last[:1]])
    base, masks = counted_masks({(w, r) for w, r in k.counted if r >= since})
    values = dict(
        policy=k.policy, env_id=k.task.env_id, max_episodes=k.max_episodes, round_timeout=k.round_timeout,
        actor_spec=_spec(k.actor_spec), critic_spec=_spec(k.critic_spec), rounds_per_episode=k.shape.per_episode,
        max_staleness=k.max_staleness, quorum=k.quorum, round=k.round,
        workers=[saved_worker(rec) for rec in k.workers.values()],
        pending=[_submission(s) for s in k.pending.values()],
        ahead=[_submission(s) for subs in k.ahead.values() for s in subs.values()],
        counted=[], counted_from=base, counted_rounds=masks, answers=[_outcome(k.answers[e]) for e in last],
        done_reason=k.done_reason, aborted=k.aborted, interrupted=k.interrupted, tier=k.tier,
        partials=[_partial(r, e, held) for r, by_edge in sorted(k.partials.items())
                  for (e, _), held in sorted(by_edge.items())])
    return {name: values[name] for name in KeeperState.model_fields}


def saved_worker(rec: WorkerRecord) -> dict[str, Any]:
    """A WorkerRecord as ``SavedWorker(...).model_dump()`` gives it: its fields in SavedWorker's order, its
    per-episode maps as sorted pairs."""
    return {name: sorted(getattr(rec, name).items()) if name in _PAIRS else getattr(rec, name) for name in _SAVED}


def counted_masks(counted: set[tuple[str, int]]) -> tuple[int, dict[str, bytes]]:
    """The counted (worker, round) pairs as (first round, worker -> little-endian bit mask of its rounds from it)."""
    if not counted:
        return 0, {}
    base = min(r for _, r in counted)
    bits: dict[str, int] = {}
    for w, r in counted:
        bits[w] = bits.get(w, 0) | (1 << (r - base))
    return base, {w: b.to_bytes((b.bit_length() + 7) // 8, "little") for w, b in sorted(bits.items())}


def uncounted_masks(base: int, masks: dict[str, bytes]) -> set[tuple[str, int]]:
    """``counted_masks`` undone: the (worker, round) pairs."""
    out: set[tuple[str, int]] = set()
    for w, raw in masks.items():
        b = int.from_bytes(raw, "little")
        out.update((w, base + i) for i in range(b.bit_length()) if b >> i & 1)
    return out


def _partial(r: int, edge: str, held: HeldPartial) -> dict[str, Any]:
    p = held.partial
    return {"round": r, "edge": edge, "gradient": _arrays(p.gradient), "critic": _arrays(p.critic), "total": p.total,
            "count": p.count, "uniform": p.uniform, "contributors": held.contributors, "clipped": held.clipped,
            "critic_clipped": held.critic_clipped}


def _unpartial(d: dict[str, Any]) -> HeldPartial:
    """A held partial (a state saved before critics' factors travelled has none)."""
    return HeldPartial(tiers.Partial(_unarrays(d["gradient"]), d["total"], d["count"], d["uniform"],
                                     _unarrays(d["critic"])),
                       list(d["contributors"]), dict(d["clipped"]), dict(d.get("critic_clipped", {})))


#: WorkerRecord's per-episode maps, saved as sorted (episode, value) pairs.
_PAIRS = ("returns", "pis")
#: SavedWorker's fields, in its order.
_SAVED = tuple(SavedWorker.model_fields)


def _spec(spec: dict[str, tuple[int, ...]] | None) -> dict[str, list[int]] | None:
    return None if spec is None else {name: list(shape) for name, shape in spec.items()}


def _unspec(spec: dict[str, list[int]] | None) -> dict[str, tuple[int, ...]] | None:
    return None if spec is None else {name: tuple(shape) for name, shape in spec.items()}


def restore_worker(saved: SavedWorker) -> WorkerRecord:
    """The WorkerRecord a saved one describes, field by field."""
    return WorkerRecord(**{**{f: getattr(saved, f) for f in SavedWorker.model_fields if f not in _PAIRS},
                           **{f: dict(getattr(saved, f)) for f in _PAIRS}})


def restore_keeper(state: KeeperState, task: TaskSpec) -> RoundKeeper:
    """The RoundKeeper a state describes (its round timer starts afresh)."""
    if state.env_id != task.env_id:
        raise ValueError(f"the saved run learns {state.env_id!r}, not {task.env_id!r}")
    k = RoundKeeper([w.worker_id for w in state.workers], state.policy, task, state.max_episodes,
                    state.round_timeout, actor_spec=_unspec(state.actor_spec), critic_spec=_unspec(state.critic_spec),
                    shape=RoundShape(per_episode=state.rounds_per_episode), max_staleness=state.max_staleness,
                    tier=state.tier, quorum=state.quorum)
    k.workers.update((w.worker_id, restore_worker(w)) for w in state.workers)
    k.round = state.round
    k.pending = {s["worker_id"]: _unsubmission(s) for s in state.pending}
    for s in state.ahead:
        sub = _unsubmission(s)
        k.ahead.setdefault(k.shape.number(sub.episode, sub.step), {})[sub.worker_id] = sub
    k.counted = {(w, e) for w, e in state.counted} | uncounted_masks(state.counted_from, state.counted_rounds)
    k.answers = {o.round: o for o in map(_unoutcome, state.answers)}
    k.done_reason, k.aborted, k.interrupted = state.done_reason, state.aborted, state.interrupted
    for d in state.partials:
        k.partials.setdefault(d["round"], {})[(d["edge"], tuple(d["contributors"]))] = _unpartial(d)
    return k


def save(run_dir: Path, keeper: RoundKeeper, service: ServiceState | Mapping[str, Any]) -> Path:
    """Write the state atomically; ``service`` holds the service's own part (roster, counters, records offset: a
    chief.records.ServiceState or its fields)."""
    path = run_dir / FILENAME
    return atomic_write(path, encoded(keeper, service), tmp=path.with_suffix(".tmp"))  # StorageError: disk full...


def encoded(keeper: RoundKeeper, service: ServiceState | Mapping[str, Any]) -> bytes:
    """The state file's bytes (``save`` writes them)."""
    state = {"version": VERSION, "keeper": keeper_state(keeper),
             "service": ServiceState.model_validate(service).model_dump()}  # ChiefState's fields, in its order
    return msgpack.packb(state, use_bin_type=True)


def load(run_dir: Path, task: TaskSpec) -> tuple[RoundKeeper, dict[str, Any]] | None:
    """The saved keeper and the service's part (ServiceState's fields), or None when the folder holds none;
    ValueError for a bad file."""
    path = run_dir / FILENAME
    if not path.exists():
        return None
    try:
        state = msgpack.unpackb(path.read_bytes(), raw=False, strict_map_key=False)
        if state.get("version") != VERSION:
            raise ValueError(f"version {state.get('version')!r}, this build reads {VERSION}")
        saved = ChiefState.model_validate(state)
        return restore_keeper(saved.keeper, task), saved.service.model_dump()
    except (ValueError, KeyError, TypeError, msgpack.UnpackException) as err:
        raise ValueError(f"cannot resume from {path}: {type(err).__name__}: {err}") from None
