"""Algorithm 1's round state machine: pure code, no MQTT, time passed in explicitly.

Every federation decision of the chief is made here (and in the strategies it calls); the MQTT adapter only
translates.

**Rounds.** The paper's strategies have one round per episode: a worker plays an episode, runs its K PPO steps and
submits the episode's gradient. A strategy that shares every mini-batch step (``Strategy.rounds``, e.g. ``sync``)
has K rounds per episode: round (e, s) carries step s of episode e, and the workers apply each round's answer before
computing the next step. Rounds are numbered 1, 2, ... over (episode, step) by the run's ``RoundShape``
(protocol/rounds.py); with one round per episode the round is the episode.

**Bounded staleness** (``max_staleness`` S, per-episode strategies only): a worker may play on while up to S of its
own rounds are unanswered (worker/federated.py decides when it waits). The keeper decides nothing differently: a
submission for a round ahead of the open one is filed for its round (the window is ``AHEAD_WINDOW`` > S), and the
round still closes when every waited-on worker's submission for it is in. S travels to the workers in RunStart, is
saved with the keeper and written to summary.json, where the audit finds it.

``submit`` decides whether a worker's submission counts:

- it must come from a worker of the run, for a round in the open round's window (the open round up to
  ``AHEAD_WINDOW`` episodes ahead, never past ``max_episodes``), with the run's tensor shapes;
- one for a round beyond its worker's reach (more than S rounds past the open round, ``reachable``) is held,
  counting nothing, until its round opens; it counts then only if it displaces nothing of the worker's own
  (``displaces``: the chief heard nothing of the worker in the round before, and has not counted that round from it
  since), so a forged update for a round ahead never makes the worker's real ones duplicates or ``inconsistent``;
- its returns must lie within the task's bounds, agree with the returns the worker reported before, and its PI must be
  their mean (the chief uses its own mean from then on); a later step of an episode must repeat that episode's
  counted return and PI;
- its tensors must be float32 with a finite L2 norm below NORM_LIMIT (so no sum of them can overflow float32);
- a MatureParams (the worker's finish, always at step 0) counts only when PI >= TC over at least PI_WINDOW episodes;
- a submission already counted for that worker and round is a duplicate: it changes nothing (a repeated
  MatureParams is acknowledged again). A duplicate or late submission for a closed round gets that round's answer
  again (the worker missed it: a broker restart, a chief restart), so nobody waits out a reply timeout.

A round collects one submission per waited-on worker. It closes when all of them are in, or ``round_timeout``
seconds after its first submission arrived (silent workers are then marked lagging and not waited on until they
submit again). With a quorum k it closes once k of them are in; an edge's keeper (its share of k) forwards a
submission for a round it closed without that worker in a partial of its own (``_late``), for the root to count.
A status message never removes a submission, and a ``finished`` status means nothing until its
MatureParams is in. A worker's last will (``offline``) does not stop the round from waiting for it: a broker restart
delivers every client's will, and workers that merely reconnected must not lose their place (the round's timeout
still ends the wait for one that really died); a worker that says it stopped or failed is not waited for at once.
Closing a round yields a RoundOutcome for the service to publish:

- some submissions are mature and the strategy transfers -> the best one's actor goes to every worker still
  learning, each with the strategy's keep weight w_T of its own progress at that round (Eq. 10-11); the finished
  leave (Algorithm 1: the round's gradients are not shared). A learner the keeper knows is offline (it timed out,
  or said it stopped or failed, and has not submitted since) is no recipient: the round records it as ``offline``;
- otherwise -> the strategy's aggregate of the round's gradients (Eq. 8-9 for ``weighted``; actor and critic for
  per-step strategies), or nothing to share; finishers of a strategy that does not transfer simply leave.
  Before aggregating, a gradient whose norm exceeds NORM_FACTOR times the round's median norm is scaled down to that
  bound, so one worker cannot blow up a linear mean; honest workers' norms stay within 6x of the median (measured on
  CartPole-v0 and Acrobot-v1, per episode and per mini-batch step).

The run is done when every worker has finished or after the last round of ``max_episodes`` episodes; the service may
``abort`` it (it ended for good) or ``interrupt`` it (Ctrl-C, SIGTERM: it ended early, and ``resume`` takes it up
again from its saved state).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from chief import federation, strategies, tiers
from protocol.messages import INTERRUPTED
from protocol.rounds import PER_EPISODE, STALENESS_LIMIT, RoundShape
from protocol.tasks import PI_WINDOW, TaskSpec, performance_index
from protocol.tensors import NORM_LIMIT, answer_digest, digest, l2_norm

log = logging.getLogger(__name__)

WorkerState = Literal["active", "lagging", "offline", "finished"]
#: Where a keeper sits in a tiered run (docs/explanation/tiered.md): ``flat`` (the one chief), ``root`` (its
#: workers' gradients arrive summed, in the edges' partials) or ``edge`` (closes its workers' part of each round
#: into a partial, chief/tiers.py, and leaves the answer to the root).
Tier = Literal["flat", "root", "edge"]
Arrays = dict[str, np.ndarray]

#: How many episodes ahead of the open round a submission may be (a worker that went on without an answer, or one
#: playing on under a bounded staleness: at most STALENESS_LIMIT ahead).
AHEAD_WINDOW = 10
assert AHEAD_WINDOW > STALENESS_LIMIT
#: Reported returns may exceed the task's bounds by this share of (ceiling - floor): device noise can push an action
#: slightly past its nominal range (MountainCarContinuous's action cost), but not a return of 1e9.
RETURN_MARGIN = 0.1
#: A gradient above this many times the round's median norm is scaled down to it.
NORM_FACTOR = 10.0
#: Closed rounds whose answers are kept for workers that missed them.
ANSWERS_KEPT = 32
#: Episodes of each worker's returns and PIs a keeper keeps behind the open round's episode: the furthest back a
#: submission it checks can reach (one of the open round or later, its PI_WINDOW returns; at an edge with a quorum,
#: one for an answered round up to ANSWERS_KEPT rounds back, ``_late``). Older ones are forgotten as the episodes go
#: by (the latest older PI kept, for Eq. 10), and every FORGET_EVERY rounds the counted (worker, round) pairs of
#: rounds older than ANSWERS_KEPT too, so a long run's keeper (and its saved state, chief/checkpoint.py) stays the
#: same size.
HISTORY = PI_WINDOW
LATE_HISTORY = ANSWERS_KEPT + PI_WINDOW
FORGET_EVERY = 16


@dataclass(frozen=True)
class Submission:
    """What a worker sent for one round: a gradient (still learning) or, at step 0, its mature actor (finished).

    ``recent_returns`` are the returns its PI is the mean of, oldest first, ending with this episode's.
    ``receipt`` is what it did with the last answer it applied (see protocol.messages.Receipt), ``earlier_receipts``
    the answers it applied before that one since its last submission (only under a bounded staleness).
    ``step`` is the mini-batch step of a per-step strategy (0 otherwise); ``critic_gradient`` its critic's gradient.
    ``stats`` are the learner's update statistics it reported (protocol.messages.STAT_BOUNDS, None where not usable):
    they decide nothing and are only recorded. ``rig`` is the episode's rig time (protocol/rigtime.py: balance steps
    and seconds, reset seconds, measured idle seconds; None for the gymnasium tasks): recorded and summed, deciding
    nothing.
    ``played`` is what the worker has played so far (protocol.messages.Played: life, episodes, env steps), counted
    or not: recorded, even when the submission is refused, deciding nothing.
    """

    worker_id: str
    episode: int
    pi: float
    episode_return: float
    recent_returns: tuple[float, ...] = ()
    steps: int = 0
    gradient: Arrays | None = None
    params: Arrays | None = None
    receipt: dict[str, Any] | None = None
    step: int = 0
    critic_gradient: Arrays | None = None
    stats: dict[str, float | None] | None = None
    rig: dict[str, float | int | None] | None = None
    played: dict[str, Any] | None = None
    earlier_receipts: tuple[dict[str, Any], ...] = ()

    @property
    def mature(self) -> bool:
        return self.params is not None

    @property
    def kind(self) -> str:
        return "mature" if self.mature else "update"


@dataclass(frozen=True)
class Ack:
    """The answer to a MatureParams (of round ``round``, step 0 of ``episode``): accepted (the chief holds it) or
    refused, with the reason."""

    worker_id: str
    round: int
    episode: int
    accepted: bool
    reason: str = ""


@dataclass
class RoundOutcome:
    """The chief's answer to one round, with everything the audit needs to re-check it."""

    round: int
    episode: int
    kind: Literal["aggregate", "transfer", "partial"]
    strategy: str
    contributors: list[str]
    step: int = 0
    pis: dict[str, float] = field(default_factory=dict)
    weights: dict[str, float] = field(default_factory=dict)
    gradient: Arrays | None = None
    critic_gradient: Arrays | None = None
    source_worker: str | None = None
    source_pi: float | None = None
    params: Arrays | None = None
    keep_weights: dict[str, float] = field(default_factory=dict)
    recipient_pis: dict[str, float | None] = field(default_factory=dict)
    finished: list[str] = field(default_factory=list)
    timed_out: list[str] = field(default_factory=list)
    clipped: dict[str, float] = field(default_factory=dict)  # worker -> factor its gradient was scaled by
    critic_clipped: dict[str, float] = field(default_factory=dict)  # the same for its critic's (per-step strategies)
    offline: list[str] = field(default_factory=list)  # learners left out of a finishing round's transfer: offline
    edges: dict[str, list[str]] = field(default_factory=dict)  # a root's round: edge -> its partial's contributors
    late: list[str] = field(default_factory=list)  # a quorum's round: the waited-on workers it closed without
    partial: tiers.Partial | None = None  # an edge's round: its part of Eq. 9, for the root
    parts: int = 0  # a root's round: how many partials it summed (more than its edges: an edge's late ones)
    norms: dict[str, float] = field(default_factory=dict)  # an edge's quorum round: its learners' gradient norms
    taken_up: list[Verdict] = field(default_factory=list)  # held submissions the next round took up (or refused)

    @property
    def digest(self) -> str:
        """Fingerprint of the tensors sent (the aggregate gradients or the mature actor); '' when none."""
        if self.kind == "transfer":
            return digest(self.params) if self.params is not None else ""
        return answer_digest(self.gradient, self.critic_gradient)

    def record(self) -> dict[str, Any]:
        """The round's line in metrics.jsonl (without the tensors)."""
        return {"type": "round", "round": self.round, "episode": self.episode, "step": self.step, "kind": self.kind,
                "strategy": self.strategy, "contributors": self.contributors, "pis": self.pis,
                "weights": self.weights, "digest": self.digest, "source": self.source_worker,
                "source_pi": self.source_pi, "keep_weights": self.keep_weights, "recipient_pis": self.recipient_pis,
                "finished": self.finished, "timed_out": self.timed_out, "clipped": self.clipped,
                **({"critic_clipped": self.critic_clipped} if self.critic_clipped else {}),
                **({"offline": self.offline} if self.offline else {}),
                **({"edges": self.edges} if self.edges else {}),
                **({"partials": self.parts} if self.parts > len(self.edges) else {}),
                **({"late": self.late} if self.late else {})}


@dataclass(frozen=True)
class HeldPartial:
    """An edge's part of a round as a root holds it until the round closes: its partial sum, its contributors, and
    the factors the edge scaled their actors' and (per-step strategies) critics' gradients by. Under a quorum an edge
    may send a round more than one partial (its late workers' own), with disjoint contributors: a root holds each
    under ``PartKey`` (edge, contributors), so a copy of one sent again replaces itself."""

    partial: tiers.Partial
    contributors: list[str]
    clipped: dict[str, float]
    critic_clipped: dict[str, float] = field(default_factory=dict)


@dataclass
class Verdict:
    """What ``submit`` decided: ``accepted`` (counted), ``duplicate`` (already counted) or ``rejected``.
    ``replay`` is a closed round's answer to send again to a worker that evidently missed it."""

    status: Literal["accepted", "duplicate", "rejected", "held"]
    reason: str = ""
    detail: str = ""
    submission: Submission | None = None
    round: int = 0
    ack: Ack | None = None
    outcomes: list[RoundOutcome] = field(default_factory=list)
    replay: RoundOutcome | None = None

    def record(self, t: float) -> dict[str, Any]:
        """An accepted submission's line in metrics.jsonl: the episode (at its step 0) or one later step, with the
        learner's update statistics it carried (``stats``, null where not sent; absent for a mature actor, which had no
        update)."""
        sub = self.submission
        assert sub is not None and self.status == "accepted"
        line: dict[str, Any]
        if sub.step > 0:
            line = {"type": "step", "worker": sub.worker_id, "round": self.round, "episode": sub.episode,
                    "step": sub.step, "receipt": sub.receipt, "t": round(t, 3)}
        else:
            line = {"type": "episode", "worker": sub.worker_id, "round": self.round, "episode": sub.episode,
                    "return": sub.episode_return, "pi": sub.pi, "steps": sub.steps, "kind": sub.kind,
                    "receipt": sub.receipt, "t": round(t, 3)}
        if sub.earlier_receipts:
            line["earlier_receipts"] = list(sub.earlier_receipts)
        if sub.mature:
            line["recent_returns"] = list(sub.recent_returns)
        elif sub.stats is not None:
            line["stats"] = dict(sub.stats)
        if sub.step == 0 and sub.played is not None:
            line["played"] = dict(sub.played)
        if sub.step == 0 and sub.rig is not None:
            line.update({k: v for k, v in sub.rig.items() if v is not None})
        return line

    def refusal(self, t: float) -> dict[str, Any] | None:
        """A refused submission's line in metrics.jsonl (``type: refused``), so what its worker played is on record
        though the chief did not count it; None when there is nothing to record (no ``played`` counts, or not a
        worker of the run)."""
        sub = self.submission
        if self.status != "rejected" or sub is None or sub.played is None or self.reason == "unknown_worker":
            return None
        return {"type": "refused", "worker": sub.worker_id, "round": self.round, "episode": sub.episode,
                "step": sub.step, "kind": sub.kind, "reason": self.reason, "steps": sub.steps,
                "played": dict(sub.played), "t": round(t, 3)}


@dataclass
class WorkerRecord:
    """What the chief knows about one worker, from the submissions it accepted."""

    worker_id: str
    state: WorkerState = "active"
    pi: float | None = None
    last_episode: int = 0
    solved_episode: int | None = None
    steps: int = 0
    steps_at_solve: int | None = None
    returns: dict[int, float] = field(default_factory=dict)
    pis: dict[int, float] = field(default_factory=dict)
    last_round: int = 0
    excused: bool = False  # not waited for (timed out, or said it stopped) until it submits again
    helping: bool = False  # finished, and still playing and sharing (a strategy whose finishers help)
    detail: str = ""  # why it stopped learning, in its own words (its last ``error`` or ``stopped`` status)

    def pi_at(self, episode: int) -> float | None:
        """The PI of this worker's latest accepted submission for an episode <= ``episode``."""
        known = [e for e in self.pis if e <= episode]
        return self.pis[max(known)] if known else None

    def forget(self, before: int) -> None:
        """Forget the returns and PIs of episodes before ``before``, but the latest PI among them (``pi_at`` of a
        later episode may still need it)."""
        self.returns = {e: v for e, v in self.returns.items() if e >= before}
        older = [e for e in self.pis if e < before]
        if older:
            keep = max(older)
            self.pis = {e: v for e, v in self.pis.items() if e >= before or e == keep}


class RoundKeeper:
    """Rounds for a fixed set of workers (Algorithm 1), shaped by ``shape`` (its strategy's ``rounds(K)``)."""

    def __init__(
        self,
        workers: list[str],
        policy: str,
        task: TaskSpec,
        max_episodes: int,
        round_timeout: float,
        actor_spec: dict[str, tuple[int, ...]] | None = None,
        critic_spec: dict[str, tuple[int, ...]] | None = None,
        shape: RoundShape = PER_EPISODE,
        max_staleness: int = 0,
        tier: Tier = "flat",
        quorum: int = 0,
    ) -> None:
        if not workers:
            raise ValueError("a federation needs at least one worker")
        self.strategy = strategies.get(policy)
        if self.strategy.rounds(shape.per_episode) != shape:
            raise ValueError(f"policy {policy!r} has other rounds than {shape.per_episode} per episode")
        if not 0 <= max_staleness <= STALENESS_LIMIT or (max_staleness and not self.strategy.allows_staleness):
            raise ValueError(f"policy {policy!r} cannot run with a staleness of {max_staleness} "
                             f"(0..{STALENESS_LIMIT}, and 0 for a per-step strategy)")
        federation.progress(task.tc, task.tc, task.r_floor)  # validates tc > r_floor
        if tier != "flat" and not tiers.decomposable(self.strategy):
            raise ValueError(tiers.why_flat(self.strategy))
        if quorum and not (self.strategy.allows_staleness and 1 <= quorum <= len(workers)):
            raise ValueError(f"a quorum of {quorum}: 1..{len(workers)} workers and a per-episode strategy (not "
                             f"{policy!r}: every worker must apply each step's mean with its own)")
        self.quorum = quorum  # k: a round closes when k of its waited-on workers submitted (0: all of them)
        self.tier = tier
        #: A root's partials: round -> edge -> what it sent.
        self.partials: dict[int, dict[PartKey, HeldPartial]] = {}
        self.policy = policy
        self.task = task
        self.max_episodes = max_episodes
        self.round_timeout = round_timeout
        self.actor_spec = actor_spec
        self.critic_spec = critic_spec
        self.shape = shape
        self.max_staleness = max_staleness  # S: a worker plays on with up to S of its rounds unanswered (RunStart)
        self.workers = {w: WorkerRecord(w) for w in sorted(workers)}
        self.round = 1
        self.joined = 1  # the round it started at (``join_at``)
        self.pending: dict[str, Submission] = {}
        self.ahead: dict[int, dict[str, Submission]] = {}  # submissions for rounds not open yet
        self.held: dict[int, dict[str, Submission]] = {}  # submissions beyond reach, not counted (``_hold``)
        self.counted: set[tuple[str, int]] = set()  # (worker, round) of every accepted submission (recent rounds')
        self._forgotten = 1  # the episodes before it are forgotten (``_forget``)
        self.answers: dict[int, RoundOutcome] = {}  # the last ANSWERS_KEPT closed rounds' answers
        self.round_opened_at: float | None = None  # time of the round's first submission
        self._blocker: str | None = None  # the last waited-on worker found missing from the open round (a cache)
        self.done_reason: str | None = None
        self.aborted = False
        self.interrupted = False  # ended early by ``interrupt``: resumable

    def join_at(self, round_: int) -> None:
        """Start at round ``round_`` (an edge that joins a run mid-way, chief/failover.py): a later step of an
        episode whose step 0 came before is checked against nothing of that episode (the root checks it)."""
        self.round = self.joined = round_

    # -- rounds and episodes ---------------------------------------------------------------------------------

    @property
    def rounds_per_episode(self) -> int:
        """K of the run's round shape (as RunStart and summary.json carry it)."""
        return self.shape.per_episode

    @property
    def episode(self) -> int:
        """The open round's episode."""
        return self.shape.episode_of(self.round)

    @property
    def next_episode(self) -> int:
        """The first episode a worker joining now can take part in from its first step."""
        return self.episode + (1 if self.shape.step_of(self.round) else 0)

    # -- queries ---------------------------------------------------------------------------------------------

    @property
    def done(self) -> bool:
        return self.done_reason is not None

    @property
    def resumable(self) -> bool:
        """Whether a chief may go on with this run: it is not over, or it was only interrupted."""
        return not self.done or self.interrupted

    @property
    def tc(self) -> float:
        return self.task.tc

    @property
    def r_floor(self) -> float:
        return self.task.r_floor

    def ids_in(self, *states: WorkerState) -> list[str]:
        return [w for w, r in self.workers.items() if r.state in states]

    def any_in(self, *states: WorkerState) -> bool:
        """Whether some worker is in one of ``states`` (stops at the first: the chief asks after every message)."""
        return any(r.state in states for r in self.workers.values())

    def waiting_for(self) -> list[str]:
        """Active workers whose submission for the current round is still missing (not those already past it)."""
        return [w for w in self.workers if w not in self.pending and self._waits_for(self.workers[w])]

    def _waits_for(self, rec: WorkerRecord) -> bool:
        """Whether the open round waits for this worker (if its submission is not in yet)."""
        return ((rec.state in ("active", "offline") or rec.helping) and not rec.excused
                and rec.last_round <= self.round)

    def progress(self, pi: float | None) -> float:
        """Sign-safe progress of a PI (the floor when the worker has none yet)."""
        return federation.progress(self.r_floor if pi is None else pi, self.tc, self.r_floor)

    # -- events ----------------------------------------------------------------------------------------------

    def submit(self, sub: Submission, now: float) -> Verdict:
        """Decide whether a worker's submission counts; returns the verdict and the outcomes of rounds it closes."""
        rec = self.workers.get(sub.worker_id)
        if rec is None:
            return self._reject(sub, 0, "unknown_worker", "not part of this run")
        if not 0 <= sub.step < self.shape.per_episode or (sub.mature and sub.step):
            return self._reject(sub, 0, "invalid", f"step {sub.step} of a {sub.kind} (this run has "
                                f"{self.shape.per_episode} rounds per episode, a finish comes at step 0)")
        r = self.shape.number(sub.episode, sub.step)
        if (sub.worker_id, r) in self.counted:
            ack = None
            if sub.mature:
                same = rec.solved_episode == sub.episode or self._held_mature(sub.worker_id) == sub.episode
                ack = Ack(sub.worker_id, r, sub.episode, same, "" if same else "episode already counted as an update")
            return Verdict("duplicate", "duplicate", f"round {r} of {sub.worker_id} already counted",
                           submission=sub, round=r, ack=ack, replay=self.answers.get(r))
        late = self.answers.get(r) if self.tier == "edge" and r < self.round and not sub.mature else None
        if late is not None and sub.worker_id in late.late and not self.aborted:
            return self._late(sub, r, rec, late)  # the root decides whether it is late (its own partial)
        if self.done:
            return self._reject(sub, r, "run_over", f"the run is over ({self.done_reason})")
        if rec.state == "finished" and (sub.mature or not rec.helping):
            return self._reject(sub, r, "finished", f"{sub.worker_id} finished at episode {rec.solved_episode}")
        if r < self.round:
            answer = self.answers.get(r)
            if answer is not None and sub.worker_id in answer.late:  # dropped: its round closed with a quorum
                verdict = self._reject(sub, r, "late", f"round {r} closed with its quorum of {self.quorum} before "
                                       "this submission came")
            else:
                verdict = self._reject(sub, r, "stale", f"round {r} is closed (open round {self.round})")
            verdict.replay = answer
            return verdict
        last = min(self.round + AHEAD_WINDOW * self.shape.per_episode, self.shape.last_of(self.max_episodes))
        if r > last:
            return self._reject(sub, r, "out_of_window",
                                f"round {r} (episode {sub.episode}) is outside the open round's window "
                                f"{self.round}..{last}")
        if self.tier != "root" and r > self.reach:
            return self._hold(sub, r, now)
        problem = self._check(sub, rec)
        if problem is not None:
            return self._reject(sub, r, *problem)
        return self._accept(sub, r, rec, now)

    @property
    def reach(self) -> int:
        """The last round a worker can have reached while the chief heard it: S rounds past the open one (it plays
        on with up to S rounds unanswered), or the first round of ``next_episode`` (a worker that starts now)."""
        return reachable(self.round, self.max_staleness, self.shape.number(self.next_episode))

    def _hold(self, sub: Submission, r: int, now: float) -> Verdict:
        """Hold a submission beyond ``reach`` until its round opens, counting nothing yet (``_take_up``): only a
        worker that went on without an answer sends one, or a forger in its name. The first one held for a worker
        and round stays; another is a duplicate. It starts the open round's timeout, so a round whose submissions
        were all lost still closes."""
        held = self.held.setdefault(r, {})
        if sub.worker_id in held:
            return Verdict("duplicate", "duplicate", f"round {r} of {sub.worker_id} already held", submission=sub,
                           round=r)
        held[sub.worker_id] = sub
        if self.round_opened_at is None:
            self.round_opened_at = now
        return Verdict("held", submission=sub, round=r)

    def _take_up(self) -> list[Verdict]:
        """The open round's held submissions (``_hold``), each counted as if it came now, unless ``displaces``
        says it is not its worker's: what each became."""
        verdicts = []
        for w, sub in sorted(self.held.pop(self.round, {}).items()):
            r, rec = self.round, self.workers[w]
            why = displaces(r, (w, r - 1) in self.counted, (w, r) in self.counted)
            problem = (("unreachable", why) if why is not None else
                       ("finished", f"{w} finished at episode {rec.solved_episode}")
                       if rec.state == "finished" and (sub.mature or not rec.helping) else self._check(sub, rec))
            if problem is not None:
                verdicts.append(self._reject(sub, r, *problem))
            else:
                self._file(sub, r, rec, self.round_opened_at or 0.0)
                verdicts.append(Verdict("accepted", submission=sub, round=r,
                                        ack=Ack(w, r, sub.episode, True) if sub.mature else None))
        return verdicts

    def note_status(self, worker_id: str, state: str, now: float, detail: str = "") -> list[RoundOutcome]:
        """A worker's status message. Its last will (``offline``) marks it offline, still waited for until the
        round times out; ``error`` or ``stopped`` (it said so itself) stops the wait at once. A ``finished`` status
        is only news: the worker's MatureParams is its finish. What a worker sent always still counts."""
        rec = self.workers.get(worker_id)
        said, state = state, "error" if state == "storage" else state  # a storage fault: excused as an error
        if rec is None or rec.state == "finished" or state not in ("offline", "error", "stopped"):
            return []
        rec.state = "offline"
        if state != "offline":
            rec.excused, rec.detail = True, f"{said}: {detail}" if detail else said
        return self._maybe_close(now)

    def restart_clock(self, now: float) -> None:
        """Give the open round a full timeout from ``now``: workers that moved to another edge send it again
        (chief/failover.py), and the time their edge spent dying is not theirs to lose."""
        if self.round_opened_at is not None:
            self.round_opened_at = now

    def tick(self, now: float) -> list[RoundOutcome]:
        """Close the round if its timeout expired; call this periodically."""
        if self.done or self.round_opened_at is None:
            return []
        if now - self.round_opened_at < self.round_timeout:
            return []
        silent = self.waiting_for()
        for w in silent:
            rec = self.workers[w]
            rec.excused = True
            if rec.state == "active":
                rec.state = "lagging"
        log.warning("round %d timed out after %.1f s waiting for %s", self.round, self.round_timeout, silent)
        first = self._close()
        first[0].timed_out = silent
        self._open_next(now, first[0])
        return first + self._maybe_close(now)

    def abort(self, reason: str) -> None:
        """End the run early (e.g. every worker stayed offline past the service's idle limit)."""
        if not self.done:
            self.done_reason, self.aborted = reason, True

    def interrupt(self) -> None:
        """End the run now, resumably (the operator stopped the chief): the open round stays open, with what was
        submitted for it, and ``resume`` takes the run up again where it stopped."""
        if not self.done:
            self.done_reason, self.interrupted = INTERRUPTED, True

    def resume(self) -> None:
        """Take up an interrupted run again (a run that ended for good stays over). Every worker the stop left
        ``offline`` is waited for again: the command that resumes the run starts them all, and what one said about
        its stop (a storage fault, its ``stopped`` on the RunStop) does not excuse it from a run that goes on. A
        worker that had timed out (``lagging``) stays excused until it submits, as in a run that never stopped."""
        if self.interrupted:
            self.done_reason, self.interrupted = None, False
            for rec in self.workers.values():
                if rec.state == "offline":
                    rec.state, rec.excused, rec.detail = "active", False, ""

    # -- internals -------------------------------------------------------------------------------------------

    def _reject(self, sub: Submission, round_: int, reason: str, detail: str) -> Verdict:
        ack = Ack(sub.worker_id, self.shape.number(sub.episode), sub.episode, False,
                  f"{reason}: {detail}") if sub.mature else None
        return Verdict("rejected", reason, detail, submission=sub, round=round_, ack=ack)

    def _held_mature(self, worker_id: str) -> int | None:
        """The episode of this worker's accepted MatureParams still waiting for its round to close."""
        for subs in (self.pending, *self.ahead.values()):
            s = subs.get(worker_id)
            if s is not None and s.mature:
                return s.episode
        return None

    def _check(self, sub: Submission, rec: WorkerRecord) -> tuple[str, str] | None:
        """(reason, detail) when the submission must not count, else None."""
        tensors = sub.params if sub.mature else sub.gradient
        if self.tier == "root" and not sub.mature:
            # Its gradient is in its edge's partial (checked there): only an empty placeholder travels here.
            if tensors or sub.critic_gradient:
                return "invalid", "a root takes a worker's gradient only summed in its edge's partial"
            tensors = None
        elif tensors is None:
            return "invalid", "no tensors"
        wants_critic = self.shape.per_step and not sub.mature and self.tier != "root"
        if (sub.critic_gradient is not None) != wants_critic:
            return "invalid", (f"a critic gradient is {'required' if wants_critic else 'not expected'} under policy "
                               f"{self.policy!r}")
        for what, arrays, spec in (("actor", tensors, self.actor_spec), ("critic", sub.critic_gradient or None,
                                                                          self.critic_spec)):
            if arrays is None:
                continue
            if spec is not None:
                got = {k: tuple(np.shape(v)) for k, v in arrays.items()}
                if got != {k: tuple(v) for k, v in spec.items()}:
                    return "wrong_shape", f"{sub.kind} {what} tensors {got} differ from the run's {spec}"
            odd = sorted(k for k, v in arrays.items() if np.asarray(v).dtype != np.float32)
            if odd:
                return "wrong_dtype", f"{sub.kind} {what} tensors {odd} are not float32"
            norm = l2_norm(arrays)
            if not norm <= NORM_LIMIT:
                return "absurd_norm", f"{sub.kind} {what} tensors have an L2 norm of {norm:.3g} (limit {NORM_LIMIT:g})"
        if sub.step > 0 and self.shape.number(sub.episode) < self.joined:
            return None  # its episode's step 0 came before this keeper joined the run (join_at): the root checks it
        if sub.step > 0:
            # A later step of an episode whose step 0 was counted: it must repeat that episode's return and PI.
            if (sub.worker_id, self.shape.number(sub.episode)) not in self.counted:
                return "out_of_order", f"step {sub.step} of episode {sub.episode} before its step 0 was counted"
            if rec.returns.get(sub.episode) != sub.episode_return or rec.pis.get(sub.episode) != sub.pi:
                return "inconsistent", f"step {sub.step} of episode {sub.episode} reports another return or PI"
            return None
        if self.tier == "root" and not sub.mature:
            return None  # its edge checked its returns and PI as above (it sends its episode's return alone)
        returns = sub.recent_returns
        if not returns or len(returns) > PI_WINDOW:
            return "invalid", f"{len(returns)} recent returns (1..{PI_WINDOW} expected)"
        margin = RETURN_MARGIN * (self.task.r_ceiling - self.r_floor)
        low, high = self.r_floor - margin, self.task.r_ceiling + margin
        bad = [r for r in returns if not (math.isfinite(r) and low <= r <= high)]
        if bad:
            return "absurd_return", f"return {bad[0]} outside {self.task.env_id}'s range [{low:g}, {high:g}]"
        if returns[-1] != sub.episode_return:
            return "inconsistent", f"episode return {sub.episode_return} is not the last recent return {returns[-1]}"
        for back, value in enumerate(reversed(returns)):
            known = rec.returns.get(sub.episode - back)
            if known is not None and known != value:
                return "inconsistent", f"episode {sub.episode - back}'s return was reported as {known}, now {value}"
        pi = performance_index(list(returns))
        if not math.isclose(sub.pi, pi, rel_tol=1e-9, abs_tol=1e-9):
            return "pi_mismatch", f"PI {sub.pi} is not the mean {pi} of its {len(returns)} recent returns"
        if sub.mature and (len(returns) < PI_WINDOW or pi < self.tc):
            return "not_mature", (f"PI {pi:g} over {len(returns)} episodes; a mature actor needs PI >= TC "
                                  f"{self.tc:g} over {PI_WINDOW}")
        return None

    def _accept(self, sub: Submission, r: int, rec: WorkerRecord, now: float) -> Verdict:
        self._file(sub, r, rec, now)
        ack = Ack(sub.worker_id, r, sub.episode, True) if sub.mature else None
        return Verdict("accepted", submission=sub, round=r, ack=ack, outcomes=self._maybe_close(now))

    def _file(self, sub: Submission, r: int, rec: WorkerRecord, now: float) -> None:
        """Count a checked submission for round ``r``: the worker's record, and the round it waits in."""
        self._book(sub, r, rec)
        if r == self.round:
            self.pending[sub.worker_id] = sub
        else:
            # The worker went on without an answer (e.g. the chief missed its submissions while the broker
            # restarted): keep this for its round, and stop waiting for the worker in the rounds it skipped.
            self.ahead.setdefault(r, {})[sub.worker_id] = sub
        if self.round_opened_at is None:
            self.round_opened_at = now

    def _book(self, sub: Submission, r: int, rec: WorkerRecord) -> None:
        """Count a submission: its worker's returns, PI, steps and rounds, and its return from lagging."""
        self.counted.add((sub.worker_id, r))
        if sub.step == 0:
            for back, value in enumerate(reversed(sub.recent_returns)):
                rec.returns.setdefault(sub.episode - back, value)
            rec.pis[sub.episode] = sub.pi
            rec.pi = rec.pis[max(rec.pis)]
            rec.steps += sub.steps
        rec.last_episode = max(rec.last_episode, sub.episode)
        rec.last_round = max(rec.last_round, r)
        if rec.state in ("lagging", "offline") or rec.excused:
            log.info("worker %s is back (state was %s)", sub.worker_id, rec.state)
            rec.state, rec.excused = "active" if rec.state != "finished" else "finished", False

    def _open_next(self, now: float, closed: RoundOutcome) -> None:
        """Open the next round with what was filed ahead for it and the held submissions it takes up (their verdicts
        travel with the round just ``closed``, for the service to record)."""
        self.pending = self.ahead.pop(self.round, {})
        self.round_opened_at = now if (self.pending or self.ahead or self.held) else None
        if not self.done:
            closed.taken_up = self._take_up()

    def _maybe_close(self, now: float) -> list[RoundOutcome]:
        outcomes: list[RoundOutcome] = []
        while not self.done and (self.pending or self.ahead or self.held) and self._complete():
            outcomes += self._close()
            self._open_next(now, outcomes[-1])
        return outcomes

    def _complete(self) -> bool:
        """Whether the open round has what it waits for: every waited-on worker's submission or, with a quorum k,
        k of them (all of them when fewer than k are left to wait for)."""
        if self.quorum > 0 and len(self.pending) >= self.quorum:
            return True
        # One missing waited-on worker keeps the round open. The last one found is checked first; only once it is in
        # is another looked for, among the workers not in yet (a set difference, one pass in C). It is found in an
        # arbitrary order, so a round of N submissions makes O(log N) such passes on average, not N.
        b = self._blocker
        if b is not None and b not in self.pending and b in self.workers and self._waits_for(self.workers[b]):
            return False
        self._blocker = next((w for w in self.workers.keys() - self.pending.keys() if self._waits_for(self.workers[w])),
                             None)
        return self._blocker is None

    def _close(self) -> list[RoundOutcome]:
        subs, r = self.pending, self.round
        late = self.waiting_for() if self.quorum else []  # the round closes without them (a quorum's)
        mature = {w: s for w, s in subs.items() if s.mature}
        outcome = self._partial(r, subs, sorted(mature)) if self.tier == "edge" else None
        if outcome is None and mature:
            outcome = self._transfer(r, subs, mature)
        if outcome is None:
            outcome = self._aggregate(r, subs, finished=sorted(mature))
            if mature:
                outcome.offline = self._offline_learners(mature)
        if self.tier == "root":
            held = self.partials.get(r, {})
            outcome.edges = {e: sorted(w for (f, _), h in held.items() if f == e for w in h.contributors)
                             for e in sorted({e for e, _ in held})}
            outcome.parts = len(held)
        outcome.late = late
        self.answers[r] = outcome
        self.answers.pop(r - ANSWERS_KEPT, None)
        self.partials.pop(r, None)
        self.pending = {}
        self.round_opened_at = None
        self.round += 1
        self._forget(full=self.round % FORGET_EVERY == 0)
        if not self.any_in("active", "lagging", "offline"):
            self.done_reason = "all workers solved"
        elif r >= self.shape.last_of(self.max_episodes):
            self.done_reason = f"reached the maximum of {self.max_episodes} episodes"
        return [outcome]

    @property
    def history(self) -> int:
        """Episodes of returns and PIs kept behind the open round's (HISTORY; LATE_HISTORY at an edge with a
        quorum)."""
        return LATE_HISTORY if self.tier == "edge" and self.quorum else HISTORY

    def _forget(self, full: bool) -> None:
        """Drop the history no submission can be checked against any more (``history``): each episode that falls
        out of it and the counted round whose answer was just dropped (a few dict lookups per worker), and, when
        ``full``, everything older and every counted round older than ANSWERS_KEPT. The keeper's size, and its saved
        state's, stays bounded however long the run."""
        before = self.episode - self.history
        full = full or before - self._forgotten > FORGET_EVERY  # a keeper restored from an older, longer state
        for e in range(self._forgotten, before) if not full else ():
            for rec in self.workers.values():
                rec.returns.pop(e, None)
                if rec.last_episode > e:  # a later PI of it is on record: this one is nobody's latest
                    rec.pis.pop(e, None)
        self._forgotten = max(self._forgotten, before)
        # The counted rounds still needed: those whose answers are kept, and every round of the open episode (a
        # per-step strategy's later step is checked against its episode's step 0, maybe more rounds back).
        oldest = min(self.round - ANSWERS_KEPT, self.shape.number(self.episode))
        if not full:
            old = self.round - ANSWERS_KEPT - 1  # the round whose answer was just dropped
            for w in self.workers if 1 <= old < oldest else ():
                self.counted.discard((w, old))
            return
        if before > 1:
            for rec in self.workers.values():
                rec.forget(before)
        if oldest > 1:
            self.counted = {(w, r) for w, r in self.counted if r >= oldest}

    def _outcome(self, r: int, kind: Literal["aggregate", "transfer", "partial"],
                 subs: dict[str, Submission]) -> RoundOutcome:
        contributors = sorted(subs)
        episode, step = self.shape.of(r)
        return RoundOutcome(round=r, episode=episode, step=step, kind=kind,
                            strategy=self.policy, contributors=contributors,
                            pis={w: subs[w].pi for w in contributors})

    def _aggregate(self, r: int, subs: dict[str, Submission], finished: list[str]) -> RoundOutcome:
        outcome = self._outcome(r, "aggregate", subs)
        outcome.finished = finished
        learners = sorted(w for w in subs if not subs[w].mature)
        if learners and self.tier == "root":
            self._combine(outcome, r, learners)
        elif learners:
            progress = {w: self.progress(subs[w].pi) for w in learners}
            grads, outcome.clipped = self._bounded({w: subs[w].gradient for w in learners})  # type: ignore[misc]
            agg = self.strategy.aggregate(grads, progress)
            outcome.gradient, outcome.weights = agg.gradient, agg.weights or {}
            if self.shape.per_step and agg.gradient is not None:
                critics, outcome.critic_clipped = self._bounded(
                    {w: subs[w].critic_gradient for w in learners})  # type: ignore[misc]
                outcome.critic_gradient = self.strategy.aggregate(critics, progress).gradient
        for w in finished:
            self._finish(self.workers[w], subs[w].episode)
        return outcome

    def _bounded(self, gradients: Gradients, others: list[float] | None = None) -> tuple[Gradients, dict[str, float]]:
        """``bound_norms`` for a strategy that shares; a strategy that shares nothing (``independent``) bounds
        nothing: no gradient of its reaches anyone."""
        return bound_norms(gradients, others or []) if self.strategy.shares else (dict(gradients), {})

    def _combine(self, outcome: RoundOutcome, r: int, learners: list[str]) -> None:
        """A root's Eq. 9: the edges' partials of round ``r`` combined (chief/tiers.py), in edge order; Eq. 8's
        weights over all of the round's learners."""
        held = self.partials.get(r, {})
        keys = sorted(held)  # canonical order: by edge, then contributors
        outcome.gradient, outcome.critic_gradient = tiers.combine([held[key].partial for key in keys])
        if outcome.gradient is not None:
            outcome.weights = tiers.weights(tiers.shares(self.strategy, {w: self.progress(self.pending[w].pi)
                                                                          for w in learners}))
        for key in keys:
            outcome.clipped.update(held[key].clipped)
            outcome.critic_clipped.update(held[key].critic_clipped)

    def add_partial(self, r: int, edge: str, partial: tiers.Partial, contributors: list[str],
                    clipped: dict[str, float], critic_clipped: dict[str, float] | None = None) -> None:
        """A root keeps an edge's partial of round ``r`` (before its contributors' submissions, whose last closes
        the round), and notes which of the round's contributors it holds and the factors the edge scaled by."""
        key = (edge, tuple(sorted(contributors)))
        held, new = self.partials.setdefault(r, {}), set(contributors)
        for other in [k for k in held if k[0] == edge and k != key and new & set(k[1])]:
            # Two partials of one edge's workers that overlap (a dead edge's and its stand-in's, chief/failover.py):
            # the one that holds the other supersedes it; neither sums a worker twice.
            if not new >= set(other[1]):
                log.warning("round %d: a partial of edge %s's workers %s overlaps the held %s: not summed", r,
                            edge, sorted(new), list(other[1]))
                return
            del held[other]
        held[key] = HeldPartial(partial, sorted(contributors), clipped, dict(critic_clipped or {}))

    def _partial(self, r: int, subs: dict[str, Submission], finished: list[str]) -> RoundOutcome:
        """An edge's round: its learners' (bounded) gradients summed into one Partial for the root (chief/tiers.py);
        its finishers leave, as the root will decide (a mature actor always ends its worker's learning)."""
        outcome = self._outcome(r, "partial", subs)
        outcome.finished = finished
        learners = sorted(w for w in subs if not subs[w].mature)
        grads, outcome.clipped = self._bounded({w: subs[w].gradient for w in learners})  # type: ignore[misc]
        critics = None
        if self.shape.per_step and learners:
            critics, outcome.critic_clipped = self._bounded(
                {w: subs[w].critic_gradient for w in learners})  # type: ignore[misc]
        outcome.partial = tiers.partial(self.strategy, grads, {w: self.progress(subs[w].pi) for w in learners},
                                        critics)
        if self.quorum:  # the reference a late worker's gradient is bounded against (``_late``)
            outcome.norms = {w: l2_norm(subs[w].gradient) for w in learners}  # type: ignore[arg-type]
        for w in finished:
            self._finish(self.workers[w], subs[w].episode)
        return outcome

    def _late(self, sub: Submission, r: int, rec: WorkerRecord, answer: RoundOutcome) -> Verdict:
        """An edge's quorum round closed without this worker, but the root's may still be open (it counts k across
        all edges): the edge checks and counts the submission and forwards it in a partial of its own, bounded
        against the round's norms; the root takes it into the round, or refuses it as late."""
        problem = self._check(sub, rec)
        if problem is not None:
            return self._reject(sub, r, *problem)
        self._book(sub, r, rec)
        outcome = self._outcome(r, "partial", {sub.worker_id: sub})
        assert sub.gradient is not None
        grads, outcome.clipped = self._bounded({sub.worker_id: sub.gradient}, list(answer.norms.values()))
        answer.norms[sub.worker_id] = l2_norm(sub.gradient)
        outcome.partial = tiers.partial(self.strategy, grads, {sub.worker_id: self.progress(sub.pi)})
        return Verdict("accepted", submission=sub, round=r, outcomes=[outcome])

    def excuse(self, r: int, workers: list[str], now: float) -> list[RoundOutcome]:
        """A root stops waiting in round ``r`` for workers their edge timed out in it (marked lagging, as ``tick``
        does), when ``r`` is the open round (a late copy of an earlier round's partial, which an edge sends again,
        excuses nobody now); the outcomes of the rounds that closes."""
        if r != self.round:
            return []
        for w in workers:
            rec = self.workers.get(w)
            if rec is not None and w not in self.pending:
                rec.excused = True
                if rec.state == "active":
                    rec.state = "lagging"
        return self._maybe_close(now)

    def _finish(self, rec: WorkerRecord, episode: int) -> None:
        rec.state, rec.solved_episode, rec.steps_at_solve = "finished", episode, rec.steps
        rec.helping = self.strategy.finishers_help
        # Not waited for in the rest of its finishing episode's rounds; a helper is from the next episode on.
        rec.last_round = max(rec.last_round, self.shape.number(episode + 1))

    def _transfer(self, r: int, subs: dict[str, Submission], mature: dict[str, Submission]) -> RoundOutcome | None:
        """The transfer of the best finisher's actor (Eq. 10-11), or None when nobody is left to receive it or the
        strategy transfers nothing."""
        episode = self.shape.episode_of(r)
        offline = self._offline_learners(mature)
        recipients = [w for w in self.ids_in("active", "lagging", "offline") if w not in mature and w not in offline]
        recipient_pis = {w: self.workers[w].pi_at(episode) for w in recipients}
        keep = {w: self.strategy.keep_weight(self.progress(pi)) for w, pi in recipient_pis.items()}
        if not recipients or any(k is None for k in keep.values()):
            return None
        for w, s in mature.items():
            self._finish(self.workers[w], s.episode)
        best = federation.best_mature({w: s.pi for w, s in mature.items()})
        outcome = self._outcome(r, "transfer", subs)
        outcome.source_worker, outcome.source_pi, outcome.params = best, mature[best].pi, mature[best].params
        outcome.keep_weights = {w: float(k) for w, k in keep.items() if k is not None}
        outcome.recipient_pis, outcome.finished, outcome.offline = recipient_pis, sorted(mature), offline
        return outcome

    def why_no_transfer(self) -> str:
        """Why a round in which workers finished transferred nothing (for the log): nobody left to learn, every
        learner left excused (lagging, offline: no transfer is addressed to them), or the strategy's rule."""
        learning = self.ids_in("active", "lagging", "offline")
        if not learning:
            return "nobody left to learn"
        if all(self.workers[w].excused for w in learning):
            return ", ".join(f"{w} {self.workers[w].state}" for w in learning) + " (not answering: no transfer is " \
                "addressed to a worker that is not)"
        return f"policy {self.policy}"

    def _offline_learners(self, mature: dict[str, Submission]) -> list[str]:
        """The workers still learning that the keeper knows are offline: excused (timed out, or said it stopped or
        failed) and silent since. No transfer is addressed to them."""
        return [w for w in self.ids_in("active", "lagging", "offline") if w not in mature and self.workers[w].excused]


Gradients = dict[str, Arrays]
#: A held partial's key: (edge, its contributors).
PartKey = tuple[str, tuple[str, ...]]


def reachable(open_round: int, staleness: int, first_of_next_episode: int) -> int:
    """The last round a worker the chief hears can have reached: the open round plus the S rounds it may play
    unanswered, or a joining worker's first round (the next episode's, when the open round is a later step)."""
    return max(open_round + staleness, first_of_next_episode)


def displaces(r: int, previous_counted: bool, already_counted: bool) -> str | None:
    """Why a submission held for round ``r`` (it came while ``r`` was beyond reach) is not its worker's, when
    ``r`` opens; None when it counts. A worker sends its rounds in order: if the chief counted the worker's round
    ``r - 1``, or its round ``r`` itself came in reach since, the worker was in step with the chief, and this one
    came before the answer to round ``r - 1 - S`` that the worker needed to play round ``r``: counting it would
    displace the worker's real one (counted twice, or its returns made ``inconsistent``). Only a worker the chief did
    not hear in round ``r - 1`` (its submission lost, it went on without an answer) has its held submission
    counted. The price: a worker that went on without an answer although its round ``r - 1`` was counted (its
    answer was late, not lost) loses round ``r``, and is counted again from its next round in reach."""
    if already_counted:
        return f"round {r} was counted from its worker since this one was held"
    if previous_counted:
        return (f"came before its worker could have played round {r} (the chief heard it in round {r - 1} and had "
                "not answered the round it needed)")
    return None


def bound_norms(gradients: Gradients, others: list[float] | None = None) -> tuple[Gradients, dict[str, float]]:
    """Scale every gradient whose norm exceeds NORM_FACTOR times the round's median norm down to that bound
    (``others``: the norms of the round's gradients already bounded, when these come late).

    Returns the (possibly scaled) gradients and, per scaled worker, the factor applied. The median is bounded by
    honest workers' norms as long as fewer than half of them lie (at N = 2 it is the mean of both, so a single liar
    is not bounded relative to the other: no linear mean of two survives one liar). Honest norms stay within 3.5x of
    the median per episode and 6x per mini-batch step (CartPole-v0, Acrobot-v1); the lower median, tried first,
    clipped honest per-step gradients (up to 25x) and changed the runs.
    """
    norms = {w: l2_norm(g) for w, g in gradients.items()}
    if not norms:  # a round of finishers only (an edge's, say): nothing to bound
        return {}, {}
    reference = float(np.median(list(norms.values()) + list(others or [])))
    bound = NORM_FACTOR * reference
    if not bound > 0:
        return dict(gradients), {}
    out, clipped = dict(gradients), {}
    for w, norm in norms.items():
        if norm > bound:
            factor = bound / norm
            clipped[w] = factor
            out[w] = scaled(gradients[w], factor)
            log.warning("the gradient of %s (norm %.3g) is above %g x the round's median norm %.3g: scaled by %.3g",
                        w, norm, NORM_FACTOR, reference, factor)
    return out, clipped


def scaled(arrays: Arrays, factor: float) -> Arrays:
    """A gradient scaled down by ``bound_norms``'s factor (in float64, back to float32)."""
    return {k: (np.asarray(v, np.float64) * factor).astype(np.float32) for k, v in arrays.items()}
