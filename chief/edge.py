"""``python -m chief --role edge --edge-id <edge>``: an edge chief of a tiered run (docs/explanation/tiered.md).

The adapter between an edge's workers and the root chief. It decides nothing itself: its RoundKeeper (tier
``edge``, chief/rounds.py) counts its workers' submissions with the chief's own checks and closes their part of each
round into one partial (chief/tiers.py), which goes to the root as an EdgePartial (each submission as a
Contribution, a finisher's actor whole, one unnormalised Eq. 9 sum). Every answer of the root (RunStart, aggregate,
transfer, acknowledgement, RunStop) it passes on verbatim to its workers on fedrl/<run>/edge/<edge>/..., so the
root's tag stays valid and a transfer (Eq. 10-11) fans out through the edges.

Under a quorum k of n (RunStart ``quorum``) the edge closes its part of a round with its share of k
(chief/tiers.py ``edge_quorum``), and forwards a submission that comes after that in a partial of its own: the root
counts k across all partials, and takes it or refuses it as late (docs/explanation/tiered.md, "k of n across
edges").

A worker that sends a closed round again missed something: the edge passes on the root's answer and acknowledgement
it holds for that round, and sends the round's partial again when it holds none (a broker lost the partial or the
answer; the root counts it once and answers again).

It learns the run from the root's RunStart (task, strategy, round shape, which workers are its: ``edges``) and its
workers' tensor shapes from their hellos (subscribing to a worker's updates from its first hello on).

It keeps its workers' records: every submission it counted, as a flat chief records it (runtime.records
EpisodeRecord, StepRecord), appended to RUN/edges/<edge>/metrics.jsonl (``--run-dir``). Its partial carries each one
to the root as a Contribution (protocol/messages.py: the few fields the root's round needs and the digest of that
record line); the root keeps one record per partial (runtime.records.EdgeRecord) and the audit reads both levels.

It says ``online`` every second (EdgeStatus; its last will says ``offline``). When the root finds another edge dead,
its RunStart may name this edge the dead one's stand-in (``stand_ins``, chief/failover.py): the edge then takes that
edge's workers as a group of their own, with a keeper from the root's open round (RunStart ``round``) on, and sums
them in partials of their own (EdgePartial ``group``), keeping their records in its own file. Started again mid-run,
it serves the groups the root's RunStart gives it, from that round on.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from pathlib import Path
from typing import Any, TextIO

from chief import failover, tiers
from chief.rounds import RoundKeeper, RoundOutcome, Verdict
from chief.settings import ChiefSettings
from chief.wire import submission_of
from protocol import topics
from protocol.auth import WorkerKeys, admitted, chief_key_of, signed
from protocol.codec import DecodeError, RejectCounter, decode, encode
from protocol.messages import (
    ChiefAck,
    ChiefAggregate,
    ChiefTransfer,
    Contribution,
    EdgePartial,
    EdgeStatus,
    MatureParams,
    RunStart,
    RunStop,
    WorkerHello,
    WorkerStatus,
    WorkerUpdate,
)
from protocol.rounds import RoundShape
from protocol.routes import WORKER, route_for
from protocol.tasks import task
from protocol.tensors import pack_arrays
from protocol.topics import ROOT_EDGE
from protocol.transport import Connect, Handler, Published, Transport
from runtime.records import EDGES, METRICS, line, parse_record, record_digest
from runtime.storage import storage_errors

log = logging.getLogger("edge")

EXIT_OK, EXIT_NOT_STARTED, EXIT_INTERRUPTED = 0, 3, 130
#: Closed rounds whose root answers an edge keeps, to answer a worker again that missed one.
ANSWERS_KEPT = 32
#: Seconds between two further copies of one round's partial: the workers of an edge that send a round again (all at
#: once after their broker came back, or each every resend_interval while the round waits) cost the root one copy.
RESEND_GAP = 2.0

Root = RunStart | RunStop | ChiefAggregate | ChiefTransfer | ChiefAck


class EdgeService:
    """One edge chief, from the root's RunStart to its RunStop."""

    def __init__(self, cfg: ChiefSettings, connect: Connect | None = None) -> None:
        assert cfg.edge_id is not None
        self.cfg = cfg
        self.edge = cfg.edge_id
        # protocol/auth.py: the run's key tags its partials, the chief key the root's answers it passes on (and its
        # own refusals in the root's name), each worker's own key what that worker sends.
        self.key = cfg.key()
        self.chief_key = chief_key_of(self.key)
        self.worker_keys = WorkerKeys(self.key)
        self.rejects = RejectCounter(log)
        self.events: queue.Queue[tuple[str, Any, bytes]] = queue.Queue()
        self.specs: dict[str, tuple[dict[str, tuple[int, ...]], dict[str, tuple[int, ...]]]] = {}
        self.keepers: dict[str, RoundKeeper] = {}  # group (chief/failover.py) -> its keeper
        self.group_of: dict[str, str] = {}  # a worker it serves -> its group
        self.first_round: dict[str, int] = {}  # group -> the round its keeper started at (>1: it joined mid-run)
        self.watched: set[str] = set()  # workers whose updates and statuses it subscribed to
        self.start: RunStart | None = None
        self.held: dict[tuple[str, int], WorkerUpdate | MatureParams] = {}  # accepted, not yet in a partial
        self.unreached: dict[tuple[str, int], WorkerUpdate | MatureParams] = {}  # held by the keeper (beyond reach)
        self.answers: dict[int, tuple[str, bytes]] = {}  # round -> the root's answer (leaf, payload)
        self.sent: dict[tuple[str, int], list[bytes]] = {}  # (group, round) -> its partials (the last ANSWERS_KEPT)
        self.resent: dict[tuple[str, int], float] = {}  # (group, round) -> when its partial last went again
        self.acks: dict[tuple[str, int], bytes] = {}  # (worker, round) -> the root's acknowledgement of its actor
        self.partials = 0
        self._beat = -math.inf  # when its last ``online`` status went out
        self.digests: dict[tuple[str, int], str] = {}  # (worker, round) -> its record's digest, until in a partial
        self.records: TextIO | None = None  # RUN/edges/<edge>/metrics.jsonl, from the RunStart on
        self.t0 = time.monotonic()
        self._interrupt = threading.Event()  # set by ``interrupt`` (a signal handler, another thread)
        self._offline = encode(signed(EdgeStatus(edge_id=self.edge, state="offline"), self.key))  # its last will
        self.conn: Transport = (connect or cfg.connector())(f"fedrl-{cfg.run_id}-edge-{self.edge}",
                                                           (self._status_topic, self._offline), self.rejects)

    @property
    def _status_topic(self) -> str:
        return topics.edge(self.cfg.run_id, self.edge, topics.STATUS)

    def interrupt(self) -> None:
        """Stop within a tenth of a second (SIGTERM, SIGINT, SIGHUP): the root goes on, and this edge's workers
        are lagging until an edge speaks for them again. Safe from any thread or a signal handler."""
        self._interrupt.set()

    # -- network thread: decode, enqueue -----------------------------------------------------------------------

    def _on_root(self, topic: str, payload: bytes) -> None:
        msg = admitted(payload, RunStart, RunStop, ChiefAggregate, ChiefTransfer, ChiefAck, topic=topic,
                       key=self.chief_key, rejects=self.rejects)
        if msg is None:
            return
        self.events.put((topic, msg, payload))

    def _on_worker(self, topic: str, payload: bytes) -> None:
        try:
            msg = decode(payload, WorkerHello, WorkerStatus, WorkerUpdate, MatureParams, topic=topic)
        except DecodeError as err:
            self.rejects.reject_error(topic, err)
            return
        refused = self.worker_keys.refusal(msg)
        if refused is not None:  # not its worker's
            self.rejects.reject(topic, *refused)
            return
        self.events.put((topic, msg, payload))

    # -- main thread -------------------------------------------------------------------------------------------

    def run(self) -> int:
        run = self.cfg.run_id
        self.conn.start()
        try:
            if self.edge != ROOT_EDGE:  # the root hands its own edge its RunStarts, and knows its workers' shapes
                self.conn.subscribe(topics.chief(run, "+"), self._on_root, qos=1)
                self.conn.subscribe(route_for(WORKER, "hello").filter(run=run), self._on_worker, qos=1)
            log.info("edge %s of run %s: waiting for the root's RunStart", self.edge, run)
            deadline = time.monotonic() + self.cfg.start_timeout
            while not self._interrupt.is_set():
                self._heartbeat(time.monotonic())
                try:
                    topic, msg, payload = self.events.get(timeout=0.1)
                except queue.Empty:
                    if self.start is None and time.monotonic() > deadline:
                        log.error("edge %s: no RunStart of the root within %.0f s", self.edge, self.cfg.start_timeout)
                        return EXIT_NOT_STARTED
                else:
                    if isinstance(msg, threading.Event):  # RootStandIn.take's mark: what came before it is handled
                        msg.set()
                        continue
                    if isinstance(msg, RunStop):
                        self._pass_on(topics.STOP, payload)
                        log.info("edge %s: the run is over (%s); %d partials sent", self.edge, msg.reason,
                                 self.partials)
                        return EXIT_OK
                    try:
                        self._handle(msg, payload)
                    except Exception as exc:  # one message never ends the edge
                        log.exception("handling %s from %s failed", msg.kind, topic)
                        self.rejects.reject(topic, "handler_error", f"{type(exc).__name__}: {exc}")
                for group, keeper in list(self.keepers.items()):
                    self._forward(group, keeper.tick(time.monotonic()))
            if self.edge == ROOT_EDGE:
                log.info("the root's own edge: stopped with the root after %d partials", self.partials)
                return EXIT_INTERRUPTED
            log.warning("edge %s: interrupted after %d partials; the root goes on, and moves this edge's workers to "
                        "another edge", self.edge, self.partials)
            self.conn.publish(self._status_topic, self._offline, qos=1)  # a clean stop sends no will: say it
            return EXIT_INTERRUPTED
        finally:
            self.conn.stop()
            if self.records is not None:
                with storage_errors(self.records.name):
                    self.records.close()

    def _heartbeat(self, now: float) -> None:
        """Say ``online`` every failover.HEARTBEAT seconds (the root finds a silent edge dead; standing in, the root
        needs no word from itself)."""
        if now - self._beat < failover.HEARTBEAT or self.edge == ROOT_EDGE:
            return
        self._beat = now
        status = EdgeStatus(edge_id=self.edge, state="online", started=self.start is not None, site=self.cfg.site)
        self.conn.publish(self._status_topic, encode(signed(status, self.key)), qos=1)

    def _handle(self, msg: Any, payload: bytes) -> None:
        if isinstance(msg, WorkerHello):
            if msg.edge == self.edge:
                # From its first hello on (before the root's RunStart lets it submit), so nothing it sends is missed.
                self._watch([msg.worker_id])
            self.specs[msg.worker_id] = (dict(msg.actor_spec), dict(msg.critic_spec))
            return
        if isinstance(msg, RunStart):
            self._adopt(msg)
            self._pass_on(topics.START, payload)
            return
        if isinstance(msg, ChiefAck):
            if msg.worker_id in self.group_of:
                self.acks = {k: v for k, v in self.acks.items() if k[1] > msg.round - ANSWERS_KEPT}
                self.acks[(msg.worker_id, msg.round)] = payload
                self._pass_on(topics.ACK, payload)
            return
        if isinstance(msg, ChiefAggregate | ChiefTransfer):
            leaf = topics.AGGREGATE if isinstance(msg, ChiefAggregate) else topics.TRANSFER
            self.answers[msg.round] = (leaf, payload)
            self.answers.pop(msg.round - ANSWERS_KEPT, None)
            self._pass_on(leaf, payload)
            return
        group = self.group_of.get(msg.worker_id)
        keeper = self.keepers.get(group) if group is not None else None
        if keeper is None or group is None:
            return
        now = time.monotonic()
        if isinstance(msg, WorkerStatus):
            self._forward(group, keeper.note_status(msg.worker_id, msg.state, now))
            return
        verdict = keeper.submit(submission_of(msg), now)
        self._count(group, verdict, msg)
        self._forward(group, verdict.outcomes)

    def _watch(self, workers: list[str]) -> None:
        """Subscribe to these workers' updates and statuses (once each)."""
        for w in workers:
            if w not in self.watched:
                self.watched.add(w)
                for leaf in (topics.UPDATE, topics.STATUS):
                    self.conn.subscribe(topics.worker(self.cfg.run_id, w, leaf), self._on_worker, qos=1)

    def _adopt(self, start: RunStart) -> None:
        """The root's RunStart: serve the groups it gives this edge (its own workers, and a dead edge's it stands in
        for: chief/failover.py), each with a keeper from the root's open round on; let go of those it does not."""
        self.start = start
        if self.records is None:
            path = records_path(self.cfg.run_dir, self.edge)
            with storage_errors(path):  # appended to: an edge started again goes on with its file
                path.parent.mkdir(parents=True, exist_ok=True)
                self.records = path.open("a", encoding="utf-8")
        named = {w: e for w, e in start.edges.items() if w in start.workers}
        groups = failover.groups_of(self.edge, named, start.stand_ins)
        for group in [g for g in self.keepers if g not in groups]:
            log.warning("edge %s: the workers of %s go through %s now", self.edge, group,
                        failover.serving(group, start.stand_ins))
            del self.keepers[group]
            for w in [w for w, g in self.group_of.items() if g == group]:
                del self.group_of[w]
        for group, mine in groups.items():
            if group not in self.keepers:
                self._keeper(group, mine, start)
        if not groups and not self.keepers:
            log.info("edge %s: the run names no worker it serves (now)", self.edge)

    def _keeper(self, group: str, mine: list[str], start: RunStart) -> None:
        """A keeper for one group's rounds, from the root's open round on."""
        known = [w for w in mine if w in self.specs] or list(self.specs)
        actor, critic = self.specs[known[0]] if known else (None, None)
        share = tiers.edge_quorum(start.quorum, len(start.workers), len(mine))
        keeper = RoundKeeper(mine, start.policy, task(start.env_id), start.max_episodes, self.cfg.round_timeout,
                             actor_spec=actor, critic_spec=critic or None,
                             shape=RoundShape(per_episode=start.rounds_per_episode),
                             max_staleness=start.max_staleness, tier="edge", quorum=share)
        if start.round > 1:
            keeper.join_at(start.round)
        self.keepers[group], self.first_round[group] = keeper, start.round
        self.group_of.update(dict.fromkeys(mine, group))
        self._watch(mine)
        what = "its" if group == self.edge else f"edge {group}'s (standing in)"
        log.info("edge %s: %s %d workers (%s) from round %d, policy %s%s", self.edge, what, len(mine),
                 ", ".join(mine), start.round, start.policy,
                 f", its share of the quorum {start.quorum} of {len(start.workers)}: {share}" if share else "")

    def _count(self, group: str, verdict: Verdict, msg: WorkerUpdate | MatureParams) -> None:
        """Hold what counts for its partial; answer again a round a worker missed; refuse the rest (a refused
        mature actor with the root's session, as the root would)."""
        if verdict.status == "accepted":
            self.held[(msg.worker_id, verdict.round)] = msg
            self._record(verdict)
            return
        if verdict.status == "held":  # beyond reach: it counts, or is refused, when its round opens (_forward)
            self.unreached[(msg.worker_id, verdict.round)] = msg
            return
        if verdict.status == "rejected":
            topic = topics.worker(self.cfg.run_id, msg.worker_id, topics.UPDATE)
            self.rejects.reject(topic, verdict.reason, f"{msg.kind} for episode {msg.episode}: {verdict.detail}")
            if verdict.ack is not None and self.start is not None:
                ack = verdict.ack
                self._relay(topics.ACK, encode(signed(ChiefAck(
                    worker_id=ack.worker_id, round=ack.round, episode=ack.episode, accepted=False,
                    reason=ack.reason[:2000], session=self.start.session), self.chief_key)))
        if verdict.reason not in ("duplicate", "stale"):
            return
        r, now = verdict.round, time.monotonic()
        answer = self.answers.get(r)
        if answer is not None:
            self._relay(*answer)
        acked = self.acks.get((msg.worker_id, r)) if isinstance(msg, MatureParams) else None
        if acked is not None:
            self._relay(topics.ACK, acked)
        if answer is not None and (acked is not None or not isinstance(msg, MatureParams)):
            return
        if now - self.resent.get((group, r), -math.inf) < RESEND_GAP:
            return
        if (group, r) in self.sent:
            # What the worker waits for never came though the partial went out: the partial or the root's answer was
            # lost on the way (a broker that died holding it). The root counts the partial once and answers again.
            log.info("edge %s: %s sent round %d again, unanswered: sending its partial again", self.edge,
                     msg.worker_id, r)
            self.resent[(group, r)] = now
            for payload in self.sent[(group, r)]:
                self._publish_partial(payload)
        elif verdict.reason == "stale" and r < self.first_round.get(group, 1):
            # A round closed before this edge took the group (the edge it went through died before passing the
            # answer on): the submission alone, for the root to answer the closed round again (no part of a sum).
            log.info("edge %s: %s sent round %d, closed before this edge took it: asking the root to answer again",
                     self.edge, msg.worker_id, r)
            self.resent[(group, r)] = now
            bare = msg.model_copy(update={"gradient": {}, "critic_gradient": None}) \
                if isinstance(msg, WorkerUpdate) else msg
            self._publish_partial(encode(signed(EdgePartial(
                edge_id=self.edge, round=r, episode=msg.episode, step=getattr(msg, "step", 0),
                updates=(bare,) if isinstance(bare, WorkerUpdate) else (),
                matures=(bare,) if isinstance(bare, MatureParams) else (),
                group=None if group == self.edge else group, again=True), self.key)))

    def _forward(self, group: str, outcomes: list[RoundOutcome]) -> None:
        """Each of a group's closed rounds as one EdgePartial to the root."""
        for outcome in outcomes:
            part = outcome.partial
            assert part is not None
            subs = [self.held.pop((w, outcome.round)) for w in outcome.contributors]
            contributions = tuple(self._contribution(s, outcome.round) for s in subs)
            if outcome.round in self.answers:  # a late worker's, and the root answered: it refuses it as late
                part = tiers.Partial(None, 0.0, part.count)  # ... so its tensors need not travel
            msg = EdgePartial(
                edge_id=self.edge, round=outcome.round, episode=outcome.episode, step=outcome.step,
                contributions=contributions,
                matures=tuple(s for s in subs if isinstance(s, MatureParams)),
                gradient=None if part.gradient is None else pack_arrays(part.gradient),
                critic_gradient=None if part.critic is None else pack_arrays(part.critic),
                total=part.total, count=part.count, uniform=part.uniform, clipped=outcome.clipped,
                critic_clipped=outcome.critic_clipped, timed_out=tuple(outcome.timed_out),
                group=None if group == self.edge else group)
            self._partial(group, signed(msg, self.key))
            self.partials += 1
            for verdict in outcome.taken_up:  # what the next round made of the submissions its keeper held
                sub = verdict.submission
                held = self.unreached.pop((sub.worker_id, verdict.round), None) if sub is not None else None
                if held is not None:
                    self._count(group, verdict, held)

    def _record(self, verdict: Verdict) -> None:
        """Keep a counted submission's record (RUN/edges/<edge>/metrics.jsonl) and its digest for the partial."""
        record = parse_record(verdict.record(time.monotonic() - self.t0))
        assert verdict.submission is not None
        self.digests[(verdict.submission.worker_id, verdict.round)] = record_digest(record)
        if self.records is not None:
            with storage_errors(self.records.name):
                self.records.write(line(record) + "\n")
                self.records.flush()

    def _contribution(self, sub: WorkerUpdate | MatureParams, r: int) -> Contribution:
        """A counted submission as its partial carries it: what the root's round needs, and its record's digest."""
        rig = None if sub.balance_steps is None else (sub.balance_steps, sub.balance_s or 0.0, sub.reset_s or 0.0,
                                                      sub.idle_s)
        return Contribution(sub.worker_id, sub.episode, sub.step if isinstance(sub, WorkerUpdate) else 0, sub.pi,
                            sub.episode_return, sub.steps, self.digests.pop((sub.worker_id, r)), sub.played, rig)

    def _partial(self, group: str, msg: EdgePartial) -> None:
        """Send a round's partial to the root, and keep it to send again (the last ANSWERS_KEPT rounds')."""
        payload = encode(msg)
        self.sent.setdefault((group, msg.round), []).append(payload)
        self.sent.pop((group, msg.round - ANSWERS_KEPT), None)
        self.resent.pop((group, msg.round - ANSWERS_KEPT), None)
        self._publish_partial(payload)

    def _publish_partial(self, payload: bytes) -> None:
        self.conn.publish(topics.edge(self.cfg.run_id, self.edge, topics.PARTIAL), payload, qos=1)

    def _pass_on(self, leaf: str, payload: bytes) -> None:
        """A root's message to this edge's workers, as it came (standing in, the root published it for them
        itself)."""
        if self.edge != ROOT_EDGE:
            self._relay(leaf, payload)

    def _relay(self, leaf: str, payload: bytes) -> None:
        """A root's message (or an edge's refusal in the root's name) to this edge's workers, as it came."""
        self.conn.publish(topics.answers(self.cfg.run_id, self.edge, leaf), payload, qos=1)


def records_path(run_dir: Path, edge: str) -> Path:
    """Where edge ``edge`` of a run in ``run_dir`` keeps its workers' records."""
    return run_dir / EDGES / edge / METRICS


#: Seconds the root waits for its own edge to serve the groups of a RunStart before it announces it anyway.
TAKE_TIMEOUT = 10.0


class RootStandIn:
    """The root itself as an edge (ROOT_EDGE, chief/failover.py): an EdgeService in a thread of the root's process,
    started the first time a dead edge's group has no live edge of its site left (one edge per site: site brokers,
    Swarm, Kubernetes). It serves those groups as their edge would have: a keeper per group from the root's open
    round, the same partials (to the root over the broker, as any edge's), their records in RUN/edges/root/.

    It talks over the root's own connection (``_Lent``: a secured broker allows one connection per login), hears
    from the root only the RunStarts the root hands it (``take``, before publishing each), and says nothing of its
    own life. The workers it serves read the root's own topics: it passes nothing on, and a worker that missed an
    answer gets it from the root, to which the edge sends that round's partial again."""

    def __init__(self, cfg: ChiefSettings, conn: Transport,
                 specs: dict[str, tuple[dict[str, tuple[int, ...]], dict[str, tuple[int, ...]]]]) -> None:
        """``conn``: the root's started connection; ``specs``: each worker's actor and critic shapes, as the root
        knows them (its workers said hello long before this edge started)."""
        def lend(client_id: str, will: tuple[str, bytes] | None = None,
                 rejects: RejectCounter | None = None) -> Transport:
            return _Lent(conn)  # no will: the root's own edge dies only with the root

        self.edge = EdgeService(cfg.model_copy(update={"role": "edge", "edge_id": ROOT_EDGE, "edges": 0,
                                                       "site": None}), lend)
        self.edge.specs.update(specs)
        self.exit: int | None = None
        self._thread: threading.Thread | None = None

    def _run(self) -> None:
        try:
            self.exit = self.edge.run()
        except Exception:  # the root goes on; its groups' rounds time out, as a dead edge's would
            log.exception("the root's own edge failed")

    def take(self, start: RunStart, timeout: float = TAKE_TIMEOUT) -> bool:
        """Hand the edge the RunStart the root is about to publish, and wait until it serves the groups it gives it
        (subscribed to their workers, on the root's connection: before the RunStart that has them send their round
        again); False if it did not within ``timeout``."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="root-stand-in", daemon=True)
            self._thread.start()
        done = threading.Event()
        self.edge.events.put((topics.chief(self.edge.cfg.run_id, topics.START), start, b""))
        self.edge.events.put(("", done, b""))
        deadline = time.monotonic() + timeout
        while not done.wait(0.05):
            if not self._thread.is_alive() or time.monotonic() > deadline:  # ended (logged): the root goes on
                return False
        return True

    def stop(self, timeout: float = 5.0) -> None:
        """End the edge with the root (its records closed)."""
        if self._thread is not None:
            self.edge.interrupt()
            self._thread.join(timeout)


class _Lent:
    """The root's connection as its own edge uses it: subscribe and publish on it; connecting and disconnecting it
    stay the root's."""

    def __init__(self, conn: Transport) -> None:
        self._conn = conn
        self.connected, self.rejects = conn.connected, conn.rejects

    @property
    def connects(self) -> int:
        return self._conn.connects

    @connects.setter
    def connects(self, value: int) -> None:
        self._conn.connects = value

    @property
    def session_present(self) -> bool:
        return self._conn.session_present

    def start(self, timeout: float = 10.0, stop: threading.Event | None = None) -> _Lent:
        return self

    def stop(self) -> None:
        return None

    def subscribe(self, topic_filter: str, handler: Handler, qos: int = 1) -> None:
        self._conn.subscribe(topic_filter, handler, qos)

    def unsubscribe(self, topic_filter: str) -> None:
        self._conn.unsubscribe(topic_filter)

    def publish(self, topic: str, payload: bytes, qos: int = 1, retain: bool = False) -> Published:
        return self._conn.publish(topic, payload, qos, retain)
