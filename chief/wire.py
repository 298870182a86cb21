"""Translation between the wire (protocol/messages.py) and the round state machine (chief/rounds.py), for the root
or flat chief (chief/service.py) and the edge chiefs (chief/edge.py) alike: pure, deciding nothing."""

from __future__ import annotations

from chief.rounds import Ack, RoundOutcome, Submission
from chief.tiers import Partial
from protocol.messages import (
    STAT_BOUNDS,
    ChiefAck,
    ChiefAggregate,
    ChiefTransfer,
    Contribution,
    EdgePartial,
    MatureParams,
    WorkerUpdate,
)
from protocol.rigtime import RIG_FIELDS
from protocol.tensors import pack_arrays, unpack_arrays


def submission_of(msg: WorkerUpdate | MatureParams) -> Submission:
    """A worker's message as the RoundKeeper takes it."""
    mature = isinstance(msg, MatureParams)
    arrays = unpack_arrays(msg.params if mature else msg.gradient)  # type: ignore[union-attr]
    critic = None if mature or msg.critic_gradient is None else unpack_arrays(msg.critic_gradient)  # type: ignore[union-attr]
    return Submission(msg.worker_id, msg.episode, msg.pi, msg.episode_return, recent_returns=tuple(msg.recent_returns),
                      steps=msg.steps, gradient=None if mature else arrays, params=arrays if mature else None,
                      receipt=msg.receipt.model_dump() if msg.receipt is not None else None,
                      earlier_receipts=tuple(r.model_dump() for r in msg.earlier_receipts),
                      step=0 if mature else msg.step, critic_gradient=critic,  # type: ignore[union-attr]
                      stats=None if mature else {k: getattr(msg, k) for k in STAT_BOUNDS},
                      rig=None if msg.balance_steps is None else {k: getattr(msg, k) for k in RIG_FIELDS},
                      played=msg.played.model_dump() if msg.played is not None else None)


def contributed(c: Contribution) -> Submission:
    """An edge's Contribution as the root's RoundKeeper takes it: an update its edge checked, with no tensors and
    its episode's return as its only recent return (chief/rounds.py: a root checks no edge-checked returns again)."""
    return Submission(c.worker_id, c.episode, c.pi, c.episode_return, recent_returns=(c.episode_return,),
                      steps=c.steps, gradient={}, step=c.step,
                      rig=None if c.rig is None else dict(zip(RIG_FIELDS, c.rig, strict=True)),
                      played=c.played.model_dump() if c.played is not None else None)


def partial_of(msg: EdgePartial) -> Partial:
    """An edge's partial as the root's RoundKeeper takes it."""
    return Partial(None if msg.gradient is None else unpack_arrays(msg.gradient), msg.total, msg.count, msg.uniform,
                   None if msg.critic_gradient is None else unpack_arrays(msg.critic_gradient))


def answer_of(outcome: RoundOutcome, session: str) -> ChiefAggregate | ChiefTransfer:
    """A closed round's answer to the workers, from the chief of ``session``."""
    if outcome.kind == "transfer":
        assert outcome.params is not None and outcome.source_worker is not None
        return ChiefTransfer(round=outcome.round, episode=outcome.episode, source_worker=outcome.source_worker,
                             source_pi=float(outcome.source_pi or 0), params=pack_arrays(outcome.params),
                             keep_weights=outcome.keep_weights, finished=outcome.finished, session=session)
    return ChiefAggregate(round=outcome.round, episode=outcome.episode, step=outcome.step,
                          gradient=pack_arrays(outcome.gradient) if outcome.gradient is not None else None,
                          critic_gradient=(pack_arrays(outcome.critic_gradient)
                                           if outcome.critic_gradient is not None else None),
                          weights=outcome.weights, contributors=outcome.contributors, session=session)


def ack_of(ack: Ack, session: str) -> ChiefAck:
    """An acknowledgement as the workers take it, from the chief of ``session``."""
    return ChiefAck(worker_id=ack.worker_id, round=ack.round, episode=ack.episode, accepted=ack.accepted,
                    reason=ack.reason, session=session)
