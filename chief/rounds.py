"""Algorithm 1's round state machine, keyed by episode: pure code, no MQTT, time passed in explicitly.

Every federation decision of the chief is made here (and in the strategies it calls); the MQTT adapter only
translates. ``submit`` decides whether a worker's submission counts:

- it must come from a worker of the run, for an episode in the open round's window (the open round up to
  ``AHEAD_WINDOW`` rounds ahead, never past ``max_episodes``), with the run's tensor shapes;
- its returns must lie within the task's bounds, agree with the returns the worker reported before, and its PI must be
  their mean (the chief uses its own mean from then on);
- its tensors must be float32 with a finite L2 norm below NORM_LIMIT (so no sum of them can overflow float32);
- a MatureParams (the worker's finish) counts only when PI >= TC over at least PI_WINDOW episodes;
- a submission already counted for that worker and episode is a duplicate: it changes nothing (a repeated
  MatureParams is acknowledged again). A duplicate or late submission for a closed round gets that round's answer
  again (the worker missed it: a broker restart, a chief restart), so nobody waits out a reply timeout.

A round collects one submission per waited-on worker for the current episode. It closes when all of them are in, or
``round_timeout`` seconds after its first submission arrived (silent workers are then marked lagging and not waited
on until they submit again). A status message never removes a submission: a worker that goes offline is no longer
waited for, but what it sent still counts, and a ``finished`` status means nothing until its MatureParams is in.
Closing a round yields a RoundOutcome for the service to publish:

- some submissions are mature -> the best one's actor goes to every worker still learning, each with the strategy's
  keep weight w_T of its own progress at that round (Eq. 10-11); the finished leave;
- otherwise -> the strategy's aggregate of the round's gradients (Eq. 8-9 for ``weighted``), or nothing to share.
  Before aggregating, a gradient whose norm exceeds NORM_FACTOR times the round's (lower) median norm is scaled down
  to that bound, so one worker cannot blow up a linear mean; honest workers' norms stay within about 3.5x of each
  other (measured on CartPole-v0 and Acrobot-v1).

The run is done when every worker has finished or after ``max_episodes`` rounds; the service may ``abort`` it.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from chief import federation, strategies
from protocol.tasks import PI_WINDOW, TaskSpec, performance_index
from protocol.tensors import NORM_LIMIT, digest, l2_norm

log = logging.getLogger(__name__)

WorkerState = Literal["active", "lagging", "offline", "finished"]

#: How many rounds ahead of the open one a submission may be (a worker that went on without an answer).
AHEAD_WINDOW = 10
#: Reported returns may exceed the task's bounds by this share of (ceiling - floor): device noise can push an action
#: slightly past its nominal range (MountainCarContinuous's action cost), but not a return of 1e9.
RETURN_MARGIN = 0.1
#: A gradient above this many times the round's lower median norm is scaled down to it.
NORM_FACTOR = 10.0
#: Closed rounds whose answers are kept for workers that missed them.
ANSWERS_KEPT = 32


@dataclass(frozen=True)
class Submission:
    """What a worker sent for one episode: a gradient (still learning) or its mature actor (finished).

    ``recent_returns`` are the returns its PI is the mean of, oldest first, ending with this episode's.
    ``receipt`` is what it did with the answer to the round before (see protocol.messages.Receipt).
    """

    worker_id: str
    episode: int
    pi: float
    episode_return: float
    recent_returns: tuple[float, ...] = ()
    steps: int = 0
    gradient: dict[str, np.ndarray] | None = None
    params: dict[str, np.ndarray] | None = None
    receipt: dict[str, Any] | None = None

    @property
    def mature(self) -> bool:
        return self.params is not None

    @property
    def kind(self) -> str:
        return "mature" if self.mature else "update"


@dataclass(frozen=True)
class Ack:
    """The answer to a MatureParams: accepted (the chief holds it) or refused, with the reason."""

    worker_id: str
    episode: int
    accepted: bool
    reason: str = ""


@dataclass
class RoundOutcome:
    """The chief's answer to one round, with everything the audit needs to re-check it."""

    episode: int
    kind: Literal["aggregate", "transfer"]
    strategy: str
    contributors: list[str]
    pis: dict[str, float] = field(default_factory=dict)
    weights: dict[str, float] = field(default_factory=dict)
    gradient: dict[str, np.ndarray] | None = None
    source_worker: str | None = None
    source_pi: float | None = None
    params: dict[str, np.ndarray] | None = None
    keep_weights: dict[str, float] = field(default_factory=dict)
    recipient_pis: dict[str, float | None] = field(default_factory=dict)
    finished: list[str] = field(default_factory=list)
    timed_out: list[str] = field(default_factory=list)
    clipped: dict[str, float] = field(default_factory=dict)  # worker -> factor its gradient was scaled by

    @property
    def digest(self) -> str:
        """Fingerprint of the tensors sent (the aggregate gradient or the mature actor); '' when none."""
        tensors = self.params if self.kind == "transfer" else self.gradient
        return digest(tensors) if tensors is not None else ""

    def record(self) -> dict[str, Any]:
        """The round's line in metrics.jsonl (without the tensors)."""
        return {"type": "round", "round": self.episode, "kind": self.kind, "strategy": self.strategy,
                "contributors": self.contributors, "pis": self.pis, "weights": self.weights,
                "digest": self.digest, "source": self.source_worker, "source_pi": self.source_pi,
                "keep_weights": self.keep_weights, "recipient_pis": self.recipient_pis, "finished": self.finished,
                "timed_out": self.timed_out, "clipped": self.clipped}


@dataclass
class Verdict:
    """What ``submit`` decided: ``accepted`` (counted), ``duplicate`` (already counted) or ``rejected``.
    ``replay`` is a closed round's answer to send again to a worker that evidently missed it."""

    status: Literal["accepted", "duplicate", "rejected"]
    reason: str = ""
    detail: str = ""
    submission: Submission | None = None
    ack: Ack | None = None
    outcomes: list[RoundOutcome] = field(default_factory=list)
    replay: RoundOutcome | None = None

    def record(self, t: float) -> dict[str, Any]:
        """An accepted submission's line in metrics.jsonl."""
        sub = self.submission
        assert sub is not None and self.status == "accepted"
        line: dict[str, Any] = {"type": "episode", "worker": sub.worker_id, "episode": sub.episode,
                                "return": sub.episode_return, "pi": sub.pi, "steps": sub.steps, "kind": sub.kind,
                                "receipt": sub.receipt, "t": round(t, 3)}
        if sub.mature:
            line["recent_returns"] = list(sub.recent_returns)
        return line


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

    def pi_at(self, episode: int) -> float | None:
        """The PI of this worker's latest accepted submission for an episode <= ``episode``."""
        known = [e for e in self.pis if e <= episode]
        return self.pis[max(known)] if known else None


class RoundKeeper:
    """Rounds keyed by episode for a fixed set of workers (Algorithm 1)."""

    def __init__(
        self,
        workers: list[str],
        policy: str,
        task: TaskSpec,
        max_episodes: int,
        round_timeout: float,
        actor_spec: dict[str, tuple[int, ...]] | None = None,
    ) -> None:
        if not workers:
            raise ValueError("a federation needs at least one worker")
        self.strategy = strategies.get(policy)
        federation.progress(task.tc, task.tc, task.r_floor)  # validates tc > r_floor
        self.policy = policy
        self.task = task
        self.max_episodes = max_episodes
        self.round_timeout = round_timeout
        self.actor_spec = actor_spec
        self.workers = {w: WorkerRecord(w) for w in sorted(workers)}
        self.episode = 1
        self.pending: dict[str, Submission] = {}
        self.ahead: dict[int, dict[str, Submission]] = {}  # submissions for rounds not open yet
        self.counted: set[tuple[str, int]] = set()  # (worker, episode) of every accepted submission
        self.answers: dict[int, RoundOutcome] = {}  # the last ANSWERS_KEPT closed rounds' answers
        self.round_opened_at: float | None = None  # time of the round's first submission
        self.done_reason: str | None = None
        self.aborted = False

    # -- queries ---------------------------------------------------------------------------------------------

    @property
    def done(self) -> bool:
        return self.done_reason is not None

    @property
    def tc(self) -> float:
        return self.task.tc

    @property
    def r_floor(self) -> float:
        return self.task.r_floor

    def ids_in(self, *states: WorkerState) -> list[str]:
        return [w for w, r in self.workers.items() if r.state in states]

    def waiting_for(self) -> list[str]:
        """Active workers whose submission for the current round is still missing (not those already past it)."""
        return [w for w in self.ids_in("active")
                if w not in self.pending and self.workers[w].last_episode <= self.episode]

    def progress(self, pi: float | None) -> float:
        """Sign-safe progress of a PI (the floor when the worker has none yet)."""
        return federation.progress(self.r_floor if pi is None else pi, self.tc, self.r_floor)

    # -- events ----------------------------------------------------------------------------------------------

    def submit(self, sub: Submission, now: float) -> Verdict:
        """Decide whether a worker's submission counts; returns the verdict and the outcomes of rounds it closes."""
        rec = self.workers.get(sub.worker_id)
        if rec is None:
            return self._reject(sub, "unknown_worker", "not part of this run")
        key = (sub.worker_id, sub.episode)
        if key in self.counted:
            ack = None
            if sub.mature:
                same = rec.solved_episode == sub.episode or self._held_mature(sub.worker_id) == sub.episode
                ack = Ack(sub.worker_id, sub.episode, same, "" if same else "episode already counted as an update")
            return Verdict("duplicate", "duplicate", f"episode {sub.episode} of {sub.worker_id} already counted",
                           submission=sub, ack=ack, replay=self.answers.get(sub.episode))
        if self.done:
            return self._reject(sub, "run_over", f"the run is over ({self.done_reason})")
        if rec.state == "finished":
            return self._reject(sub, "finished", f"{sub.worker_id} finished at episode {rec.solved_episode}")
        if sub.episode < self.episode:
            verdict = self._reject(sub, "stale", f"round {sub.episode} is closed (open round {self.episode})")
            verdict.replay = self.answers.get(sub.episode)
            return verdict
        last = min(self.episode + AHEAD_WINDOW, self.max_episodes)
        if sub.episode > last:
            return self._reject(sub, "out_of_window",
                                f"episode {sub.episode} is outside the open round's window {self.episode}..{last}")
        problem = self._check(sub, rec)
        if problem is not None:
            return self._reject(sub, *problem)
        return self._accept(sub, rec, now)

    def note_status(self, worker_id: str, state: str, now: float) -> list[RoundOutcome]:
        """A worker's status message. Only going away changes anything: the worker is not waited for any more.
        A ``finished`` status is only news: the worker's MatureParams is its finish."""
        if state in ("offline", "error", "stopped"):
            return self.mark_offline(worker_id, now)
        return []

    def mark_offline(self, worker_id: str, now: float) -> list[RoundOutcome]:
        """A worker's last will (or error/stopped status) arrived: stop waiting for it; what it sent still counts."""
        rec = self.workers.get(worker_id)
        if rec is None or rec.state == "finished":
            return []
        rec.state = "offline"
        return self._maybe_close(now)

    def tick(self, now: float) -> list[RoundOutcome]:
        """Close the round if its timeout expired; call this periodically."""
        if self.done or self.round_opened_at is None:
            return []
        if now - self.round_opened_at < self.round_timeout:
            return []
        silent = self.waiting_for()
        for w in silent:
            self.workers[w].state = "lagging"
        log.warning("round %d timed out after %.1f s waiting for %s", self.episode, self.round_timeout, silent)
        first = self._close()
        first[0].timed_out = silent
        self._open_next(now)
        return first + self._maybe_close(now)

    def abort(self, reason: str) -> None:
        """End the run early (e.g. every worker stayed offline past the service's idle limit)."""
        if not self.done:
            self.done_reason, self.aborted = reason, True

    # -- internals -------------------------------------------------------------------------------------------

    def _reject(self, sub: Submission, reason: str, detail: str) -> Verdict:
        ack = Ack(sub.worker_id, sub.episode, False, f"{reason}: {detail}") if sub.mature else None
        return Verdict("rejected", reason, detail, submission=sub, ack=ack)

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
        if tensors is None:
            return "invalid", "no tensors"
        if self.actor_spec is not None:
            got = {k: tuple(np.shape(v)) for k, v in tensors.items()}
            if got != {k: tuple(v) for k, v in self.actor_spec.items()}:
                return "wrong_shape", f"{sub.kind} tensors {got} differ from the run's actor {self.actor_spec}"
        odd = sorted(k for k, v in tensors.items() if np.asarray(v).dtype != np.float32)
        if odd:
            return "wrong_dtype", f"{sub.kind} tensors {odd} are not float32"
        norm = l2_norm(tensors)
        if not norm <= NORM_LIMIT:
            return "absurd_norm", f"{sub.kind} tensors have an L2 norm of {norm:.3g} (limit {NORM_LIMIT:g})"
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

    def _accept(self, sub: Submission, rec: WorkerRecord, now: float) -> Verdict:
        self.counted.add((sub.worker_id, sub.episode))
        for back, value in enumerate(reversed(sub.recent_returns)):
            rec.returns.setdefault(sub.episode - back, value)
        rec.pis[sub.episode] = sub.pi
        rec.pi = rec.pis[max(rec.pis)]
        rec.last_episode = max(rec.last_episode, sub.episode)
        rec.steps += sub.steps
        if rec.state in ("lagging", "offline"):
            log.info("worker %s is back (state was %s)", sub.worker_id, rec.state)
            rec.state = "active"
        if sub.episode == self.episode:
            self.pending[sub.worker_id] = sub
        else:
            # The worker went on without an answer (e.g. the chief missed its submissions while the broker
            # restarted): keep this for its round, and stop waiting for the worker in the rounds it skipped.
            self.ahead.setdefault(sub.episode, {})[sub.worker_id] = sub
        if self.round_opened_at is None:
            self.round_opened_at = now
        ack = Ack(sub.worker_id, sub.episode, True) if sub.mature else None
        return Verdict("accepted", submission=sub, ack=ack, outcomes=self._maybe_close(now))

    def _open_next(self, now: float) -> None:
        self.pending = self.ahead.pop(self.episode, {})
        self.round_opened_at = now if (self.pending or self.ahead) else None

    def _maybe_close(self, now: float) -> list[RoundOutcome]:
        outcomes: list[RoundOutcome] = []
        while not self.done and (self.pending or self.ahead) and not self.waiting_for():
            outcomes += self._close()
            self._open_next(now)
        return outcomes

    def _close(self) -> list[RoundOutcome]:
        subs = self.pending
        episode = self.episode
        mature = {w: s for w, s in subs.items() if s.mature}
        outcome = self._transfer(episode, subs, mature) if mature else self._aggregate(episode, subs)
        self.answers[episode] = outcome
        self.answers.pop(episode - ANSWERS_KEPT, None)
        self.pending = {}
        self.round_opened_at = None
        self.episode += 1
        if not self.ids_in("active", "lagging", "offline"):
            self.done_reason = "all workers solved"
        elif episode >= self.max_episodes:
            self.done_reason = f"reached the maximum of {self.max_episodes} episodes"
        return [outcome]

    def _aggregate(self, episode: int, subs: dict[str, Submission]) -> RoundOutcome:
        contributors = sorted(subs)
        pis = {w: subs[w].pi for w in contributors}
        outcome = RoundOutcome(episode=episode, kind="aggregate", strategy=self.policy, contributors=contributors,
                               pis=pis)
        if contributors:
            grads, outcome.clipped = bound_norms({w: subs[w].gradient for w in contributors})  # type: ignore[misc]
            agg = self.strategy.aggregate(grads, {w: self.progress(pi) for w, pi in pis.items()})
            outcome.gradient, outcome.weights = agg.gradient, agg.weights or {}
        return outcome

    def _transfer(self, episode: int, subs: dict[str, Submission], mature: dict[str, Submission]) -> RoundOutcome:
        for w, s in mature.items():
            rec = self.workers[w]
            rec.state, rec.solved_episode, rec.steps_at_solve = "finished", s.episode, rec.steps
        finished = sorted(mature)
        contributors = sorted(subs)
        pis = {w: subs[w].pi for w in contributors}
        recipients = self.ids_in("active", "lagging", "offline")
        recipient_pis = {w: self.workers[w].pi_at(episode) for w in recipients}
        keep = {w: self.strategy.keep_weight(self.progress(pi)) for w, pi in recipient_pis.items()}
        if not recipients or any(k is None for k in keep.values()):
            # Nobody left to learn, or a strategy that transfers nothing: the finished simply leave.
            return RoundOutcome(episode=episode, kind="aggregate", strategy=self.policy, contributors=contributors,
                                pis=pis, finished=finished)
        best = federation.best_mature({w: s.pi for w, s in mature.items()})
        return RoundOutcome(
            episode=episode, kind="transfer", strategy=self.policy, contributors=contributors, pis=pis,
            source_worker=best, source_pi=mature[best].pi, params=mature[best].params,
            keep_weights={w: float(k) for w, k in keep.items() if k is not None}, recipient_pis=recipient_pis,
            finished=finished,
        )


Gradients = dict[str, dict[str, np.ndarray]]


def bound_norms(gradients: Gradients) -> tuple[Gradients, dict[str, float]]:
    """Scale every gradient whose norm exceeds NORM_FACTOR times the lower median norm down to that bound.

    Returns the (possibly scaled) gradients and, per scaled worker, the factor applied. The lower median (the
    ((n-1)//2)-th smallest norm) is an honest worker's norm as long as fewer than half of them lie, also at n = 2.
    """
    norms = {w: l2_norm(g) for w, g in gradients.items()}
    reference = sorted(norms.values())[(len(norms) - 1) // 2]
    bound = NORM_FACTOR * reference
    if not bound > 0:
        return dict(gradients), {}
    out, clipped = dict(gradients), {}
    for w, norm in norms.items():
        if norm > bound:
            factor = bound / norm
            clipped[w] = factor
            out[w] = {k: (np.asarray(v, np.float64) * factor).astype(np.float32) for k, v in gradients[w].items()}
            log.warning("the gradient of %s (norm %.3g) is above %g x the round's median norm %.3g: scaled by %.3g",
                        w, norm, NORM_FACTOR, reference, factor)
    return out, clipped
