"""Algorithm 1's round state machine, keyed by episode: pure code, no MQTT, time passed in explicitly.

A round collects one submission per waited-on worker for the current episode. It closes when all of them are in,
or ``round_timeout`` seconds after its first submission arrived (silent workers are then marked lagging and no
longer waited on; a lagging worker that submits for the open round is waited on again). A worker that goes offline
is dropped from the round at once. Closing a round yields a RoundOutcome for the service to publish:

- some submissions carry mature parameters -> transfer the best one (Eq. 10-11), the finished leave the active set;
- otherwise -> the weighted mean gradient (Eq. 8-9), or nothing to share under the ``independent`` policy.

The run is done when every worker has finished or after ``max_episodes`` rounds; the service may ``abort`` it
(e.g. when every worker stayed offline too long).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from chief import federation
from chief.federation import Policy

log = logging.getLogger(__name__)

WorkerState = Literal["active", "lagging", "offline", "finished"]


@dataclass(frozen=True)
class Submission:
    """What a worker sent for one episode: a gradient (still learning) or its mature actor (finished)."""

    worker_id: str
    episode: int
    pi: float
    episode_return: float
    gradient: dict[str, np.ndarray] | None = None
    params: dict[str, np.ndarray] | None = None

    @property
    def mature(self) -> bool:
        return self.params is not None


@dataclass
class RoundOutcome:
    """The chief's answer to one round."""

    episode: int
    kind: Literal["aggregate", "transfer"]
    contributors: list[str]
    weights: dict[str, float] = field(default_factory=dict)
    gradient: dict[str, np.ndarray] | None = None
    source_worker: str | None = None
    source_pi: float | None = None
    params: dict[str, np.ndarray] | None = None
    keep_weights: dict[str, float] = field(default_factory=dict)
    finished: list[str] = field(default_factory=list)
    timed_out: list[str] = field(default_factory=list)


@dataclass
class WorkerRecord:
    """What the chief knows about one worker."""

    worker_id: str
    state: WorkerState = "active"
    pi: float | None = None
    last_episode: int = 0
    solved_episode: int | None = None


class RoundKeeper:
    """Rounds keyed by episode for a fixed set of workers (Algorithm 1)."""

    def __init__(
        self,
        workers: list[str],
        policy: Policy,
        tc: float,
        r_floor: float,
        max_episodes: int,
        round_timeout: float,
    ) -> None:
        if not workers:
            raise ValueError("a federation needs at least one worker")
        if policy not in federation.POLICIES:
            raise ValueError(f"unknown policy {policy!r}; choose one of {federation.POLICIES}")
        federation.progress(tc, tc, r_floor)  # validates tc > r_floor
        self.policy: Policy = policy
        self.tc = tc
        self.r_floor = r_floor
        self.max_episodes = max_episodes
        self.round_timeout = round_timeout
        self.workers = {w: WorkerRecord(w) for w in sorted(workers)}
        self.episode = 1
        self.pending: dict[str, Submission] = {}
        self.ahead: dict[int, dict[str, Submission]] = {}  # submissions for rounds not open yet
        self.round_opened_at: float | None = None  # time of the round's first submission
        self.stale = 0
        self.done_reason: str | None = None

    # -- queries ---------------------------------------------------------------------------------------------

    @property
    def done(self) -> bool:
        return self.done_reason is not None

    def ids_in(self, *states: WorkerState) -> list[str]:
        return [w for w, r in self.workers.items() if r.state in states]

    def waiting_for(self) -> list[str]:
        """Active workers whose submission for the current round is still missing (not those already past it)."""
        return [w for w in self.ids_in("active")
                if w not in self.pending and self.workers[w].last_episode <= self.episode]

    # -- events ----------------------------------------------------------------------------------------------

    def submit(self, sub: Submission, now: float) -> list[RoundOutcome]:
        """Take one worker's submission; returns the outcomes of any round it closes."""
        rec = self.workers.get(sub.worker_id)
        if rec is None:
            raise KeyError(f"unknown worker {sub.worker_id!r}")
        if self.done or rec.state == "finished":
            self.stale += 1
            return []
        rec.pi = sub.pi
        rec.last_episode = max(rec.last_episode, sub.episode)
        if sub.episode < self.episode:
            # A late answer to a closed round: its PI is noted, the rest dropped.
            self.stale += 1
            log.info("stale submission from %s for episode %d (round %d)", sub.worker_id, sub.episode, self.episode)
            return []
        if rec.state in ("lagging", "offline"):
            log.info("worker %s is back (state was %s)", sub.worker_id, rec.state)
            rec.state = "active"
        if sub.episode > self.episode:
            # The worker went on without an answer (e.g. the chief missed its submissions while the broker
            # restarted): keep this for its round, and stop waiting for the worker in the rounds it skipped.
            self.ahead.setdefault(sub.episode, {})[sub.worker_id] = sub
            if self.round_opened_at is None:
                self.round_opened_at = now
            return self._maybe_close(now)
        self.pending[sub.worker_id] = sub
        if self.round_opened_at is None:
            self.round_opened_at = now
        return self._maybe_close(now)

    def mark_finished(self, worker_id: str, episode: int, pi: float, now: float) -> list[RoundOutcome]:
        """A worker says it solved the task but its mature actor never arrived: it leaves without a transfer."""
        rec = self.workers.get(worker_id)
        if rec is None or rec.state == "finished":
            return []
        rec.state, rec.solved_episode, rec.pi = "finished", episode, pi
        rec.last_episode = max(rec.last_episode, episode)
        self.pending.pop(worker_id, None)
        for subs in self.ahead.values():
            subs.pop(worker_id, None)
        outcomes = self._maybe_close(now)
        if not outcomes and not self.done and not self.ids_in("active", "lagging", "offline"):
            self.done_reason = "all workers solved"
        return outcomes

    def mark_offline(self, worker_id: str, now: float) -> list[RoundOutcome]:
        """A worker's last will arrived: stop waiting for it."""
        rec = self.workers.get(worker_id)
        if rec is None or rec.state == "finished":
            return []
        rec.state = "offline"
        self.pending.pop(worker_id, None)
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
        self.pending = self.ahead.pop(self.episode, {})
        self.round_opened_at = now if (self.pending or self.ahead) else None
        return first + self._maybe_close(now)

    def abort(self, reason: str) -> None:
        """End the run early (e.g. every worker stayed offline past the service's idle limit)."""
        if not self.done:
            self.done_reason = reason

    # -- internals -------------------------------------------------------------------------------------------

    def _maybe_close(self, now: float) -> list[RoundOutcome]:
        outcomes: list[RoundOutcome] = []
        while not self.done and (self.pending or self.ahead) and not self.waiting_for():
            outcomes += self._close()
            self.pending = self.ahead.pop(self.episode, {})
            if self.pending or self.ahead:
                self.round_opened_at = now
        return outcomes

    def _close(self) -> list[RoundOutcome]:
        subs = self.pending
        episode = self.episode
        mature = {w: s for w, s in subs.items() if s.mature}
        if mature:
            outcome = self._transfer(episode, subs, mature)
        else:
            outcome = self._aggregate(episode, subs)
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
        if self.policy == "independent" or not contributors:
            return RoundOutcome(episode=episode, kind="aggregate", contributors=contributors)
        weights = federation.gradient_weights({w: subs[w].pi for w in contributors}, self.tc, self.r_floor, self.policy)
        grads = {w: subs[w].gradient for w in contributors}
        gradient = federation.weighted_gradient(grads, weights)  # type: ignore[arg-type]
        return RoundOutcome(episode=episode, kind="aggregate", contributors=contributors, weights=weights,
                            gradient=gradient)

    def _transfer(self, episode: int, subs: dict[str, Submission], mature: dict[str, Submission]) -> RoundOutcome:
        for w, s in mature.items():
            rec = self.workers[w]
            rec.state = "finished"
            rec.solved_episode = s.episode
        finished = sorted(mature)
        best = federation.best_mature({w: s.pi for w, s in mature.items()})
        if self.policy == "independent":
            return RoundOutcome(episode=episode, kind="aggregate", contributors=sorted(subs), finished=finished)
        recipients = self.ids_in("active", "lagging", "offline")
        keep = {
            w: federation.transfer_weight(self._pi_or_floor(w), self.tc, self.r_floor, self.policy) for w in recipients
        }
        return RoundOutcome(
            episode=episode,
            kind="transfer",
            contributors=sorted(subs),
            source_worker=best,
            source_pi=mature[best].pi,
            params=mature[best].params,
            keep_weights=keep,
            finished=finished,
        )

    def _pi_or_floor(self, worker_id: str) -> float:
        pi = self.workers[worker_id].pi
        return self.r_floor if pi is None else pi
