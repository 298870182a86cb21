"""Each rig's time, summed from the run's records (summary.json, chief/audit.py): protocol/rigtime.py's model.

Balance steps and seconds and reset seconds are the sums over the rig's counted episodes. Idle seconds are the sum of
what its worker measured when it measured them (a realtime or delayed rig), else modelled from the rounds
(protocol.rigtime.IdleModel: a round closes when its slowest contributor's rig time has passed on the simulated
clock). A run of the gymnasium tasks has no rig time: every function here then gives nothing.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Literal

from protocol.rigtime import EpisodeTime, IdleModel, RigTotals
from runtime.records import EpisodeRecord, LastRig, RigTime, RoundRecord, StepRecord


def rig_times(records: Iterable[EpisodeRecord | StepRecord | RoundRecord], staleness: int = 0) -> dict[str, RigTime]:
    """Each rig's time (by worker id, in order of first appearance) from metrics.jsonl's records of a run whose
    workers could leave ``staleness`` rounds unanswered; {} when no record carries rig time."""
    totals: dict[str, RigTotals] = {}
    measured: set[str] = set()
    rounds: dict[int, dict[str, float]] = {}  # round -> contributor -> rig seconds spent for it
    for rec in records:
        if isinstance(rec, EpisodeRecord) and rec.balance_steps is not None:
            spent = EpisodeTime(rec.balance_steps, rec.balance_s or 0.0, rec.reset_s or 0.0, rec.idle_s)
            totals.setdefault(rec.worker, RigTotals()).add(spent)
            if rec.idle_s is not None:
                measured.add(rec.worker)
            rounds.setdefault(rec.round, {})[rec.worker] = spent.rig_s
        elif isinstance(rec, StepRecord):  # a later step of a per-step strategy: a round with no rig time spent
            rounds.setdefault(rec.round, {})[rec.worker] = 0.0
    if not totals:
        return {}
    model = IdleModel(staleness=staleness)
    for number in sorted(rounds):
        model.close({w: s for w, s in rounds[number].items() if w in totals})
    out = {}
    for worker, total in totals.items():
        idle: Literal["measured", "modelled"] = "measured" if worker in measured else "modelled"
        if idle == "modelled":
            total.idle_s = model.idle.get(worker, 0.0)
        out[worker] = RigTime(**total.fields(), idle=idle)
    return out


def last_rig(rigs: dict[str, RigTime]) -> LastRig | None:
    """The rig that finished last: the most rig time plus idle (ties: the most rig time); None without rigs."""
    if not rigs:
        return None
    worker = max(rigs, key=lambda w: (rigs[w].rig_s + rigs[w].idle_s, rigs[w].rig_s))
    return LastRig(id=worker, **rigs[worker].model_dump())
