"""The chief's adapter to its connection (MQTT, or deploy/inprocess.py's in-memory hub): decode what workers send,
hand it to the Roster and the RoundKeeper, publish their answers, print live progress and write the run folder. It
decides nothing: admission is roster.py's, every federation decision rounds.py's and the strategies'."""

from __future__ import annotations

import datetime as dt
import logging
import math
import os
import queue
import secrets
import socket
import threading
import time
from dataclasses import dataclass
from typing import Any

from chief import checkpoint, failover, tensorboard
from chief.claim import EXIT_CLAIMED, RunClaim
from chief.edge import TAKE_TIMEOUT, RootStandIn
from chief.report import MetricsLog, plot_learning_curves, run_summary, write_summary
from chief.roster import Roster
from chief.rounds import RoundKeeper, RoundOutcome, Verdict
from chief.settings import ChiefSettings
from chief.wire import ack_of, answer_of, contributed, partial_of, submission_of
from protocol import topics
from protocol.auth import WorkerKeys, chief_key_of, refusal, signed
from protocol.codec import DecodeError, RejectCounter, decode, encode
from protocol.messages import (
    ChiefAck,
    ChiefAggregate,
    ChiefClaim,
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
from protocol.mqtt import Stopped
from protocol.routes import CHIEF, chief_route, qos_of, received_by
from protocol.tasks import task
from protocol.topics import ROOT_EDGE
from protocol.transport import Connect, Published, Transport
from runtime.model_file import InitModel
from runtime.records import SUMMARY, EdgeRecord
from runtime.storage import EXIT_STORAGE

log = logging.getLogger("chief")

EXIT_OK, EXIT_NO_WORKERS, EXIT_ABORTED = 0, 3, 4
#: The exit code of a chief that was interrupted (SIGINT or SIGTERM): the run is saved and resumable.
EXIT_INTERRUPTED = 130


#: The kinds of a worker's submissions (a root takes them summed, in its edges' partials).
UPDATE_KINDS = frozenset({"update", "mature"})
#: The kinds only a root reads: its edges' partials and statuses.
EDGE_KINDS = frozenset({"partial", "edge_status"})

#: The fewest seconds between two RunStarts the chief sends again for workers' hellos.
ANNOUNCE_INTERVAL = 1.0

#: Seconds between two progress lines.
PROGRESS_INTERVAL = 2.0


@dataclass(frozen=True)
class Outputs:
    """What the chief writes besides metrics.jsonl and summary.json (an in-process sweep leaves some out)."""

    state: bool = True  # its state after every round, synced to disk, so that a restarted chief resumes the run
    tensorboard: bool = True  # the TensorBoard event files, live
    plot: bool = True  # learning_curve.png at the end
    progress: bool = True  # a progress line every PROGRESS_INTERVAL seconds (else only the last one)


class ChiefService:
    """Runs one federation from the first hello (or from its saved state) to the summary.

    ``connect`` makes its connection (protocol.transport.Connect; default: its settings', ``cfg.connector()``)."""

    def __init__(self, cfg: ChiefSettings, connect: Connect | None = None,
                 outputs: Outputs | None = None) -> None:
        """``cfg``: the chief's settings, already checked (the policy, the task and the run id among them)."""
        self.cfg = cfg
        self.outputs = outputs or Outputs()
        self.broker = cfg.where()
        self.spec = task(cfg.env)
        self.rejects = RejectCounter(log)
        self.events: queue.Queue[tuple[str, Any]] = queue.Queue()
        # The run's model, when the chief is told it (a ValueError, exit 2, for an unreadable one); else the first
        # worker's decides (chief/roster.py).
        model = InitModel.open(cfg.init_model) if cfg.init_model is not None else None
        self.roster = Roster(cfg.env, algo=cfg.algo, init_model=model.digest if model else None,
                             init_model_known=model is not None, init_model_path=model.given if model else "")
        self.keeper: RoundKeeper | None = None
        self.session = secrets.token_hex(8)
        # protocol/auth.py: the run's key tags this chief's claim and checks the edges' partials; the chief key tags
        # what it says to the workers; each worker's key, derived from the run's, checks what that worker sends.
        self.key = cfg.key()
        self.chief_key = chief_key_of(self.key)
        self.worker_keys = WorkerKeys(self.key)
        self.saved = checkpoint.load(cfg.run_dir, self.spec)  # ValueError (exit 2) for an unreadable state file
        if self.saved is not None:
            self._check_resumable(*self.saved)
        self.conn: Transport = (connect or cfg.connector())(f"fedrl-{cfg.run_id}-chief", None, self.rejects)
        self.metrics: MetricsLog | None = None
        self.t0 = time.monotonic()
        self._last_progress = 0.0
        self._last_line, self._last_printed = "", 0.0
        self._outbox: list[tuple[str, bytes]] = []  # held back until the state is saved
        self._must_save = False
        self.duplicates = 0
        self.edge_of: dict[str, str] = {}  # a root's workers: the edge each said it is behind (its group)
        self.stand_ins: dict[str, str] = {}  # a root's dead edges -> the edge standing in (chief/failover.py)
        self.moves = 0  # how often the edges changed (RunStart ``moves``)
        self.watch = failover.EdgeWatch()  # a root's edges: when each was heard, which are dead
        self.root_edge: RootStandIn | None = None  # the root standing in for a dead edge (chief/failover.py)
        self._announced = -math.inf  # when the last RunStart went out (time.monotonic)
        self.epoch = 0  # how often this run's chief has restarted
        self._interrupt = threading.Event()  # set by ``interrupt`` (a signal handler, another thread)
        self._storage_fault: str | None = None  # a worker's storage fault, which stopped the run (exit 5)
        session, since = ((self.saved[1]["session"], self.saved[1].get("claimed_since", 0.0)) if self.saved is not None
                          else (self.session, time.time()))  # a resumed chief is the same chief: its claim too
        self.claim = RunClaim(self.conn, ChiefClaim(run_id=cfg.run_id, session=session, since=since,
                                                    host=socket.gethostname()[:255], pid=os.getpid()),
                              self.key, self.rejects)

    def _check_resumable(self, keeper: RoundKeeper, service: dict[str, Any]) -> None:
        if service.get("run_id") != self.cfg.run_id:
            raise ValueError(f"{self.cfg.run_dir} holds run {service.get('run_id')!r}, not {self.cfg.run_id!r}: "
                             "use the same --run-id to resume it, or another --run-dir")
        if not keeper.resumable:
            raise ValueError(f"the run in {self.cfg.run_dir} is over ({keeper.done_reason}); choose another --run-dir")
        if keeper.tier != ("root" if self.cfg.edges else "flat"):
            raise ValueError(f"the saved run is {'tiered' if keeper.tier == 'root' else 'flat'}: resume it "
                             + ("with --edges (the same number of edges)" if keeper.tier == "root" else
                                "without --edges"))
        if keeper.policy != self.cfg.policy:
            raise ValueError(f"the saved run uses policy {keeper.policy!r}, not {self.cfg.policy!r}")

    def interrupt(self) -> None:
        """Ask the run to end early and resumably (SIGINT, SIGTERM): the main thread tells the RoundKeeper, then
        saves the state, tells the workers and writes the summary and the curve. Safe from any thread or a signal
        handler."""
        self._interrupt.set()

    # -- network thread: decode, validate, enqueue -------------------------------------------------------------

    def _on_message(self, topic: str, payload: bytes) -> None:
        try:
            msg = decode(payload, WorkerHello, WorkerStatus, WorkerUpdate, MatureParams, EdgePartial, EdgeStatus,
                         topic=topic)
        except DecodeError as err:
            self.rejects.reject_error(topic, err)
            return
        # An edge holds the run's key, a worker only its own (protocol/auth.py): a message without its sender's tag is
        # not its sender's.
        refused = (refusal(msg, self.key) if isinstance(msg, EdgePartial | EdgeStatus)
                   else self.worker_keys.refusal(msg))
        if refused is not None:
            self.rejects.reject(topic, *refused)
            return
        self.events.put((topic, msg))

    # -- main thread -------------------------------------------------------------------------------------------

    def run(self) -> int:
        cfg = self.cfg
        run = cfg.run_id
        try:
            self.conn.start(stop=self._interrupt)
        except Stopped:
            return EXIT_INTERRUPTED  # before the run was claimed: nothing to save
        try:
            other = self.claim.take()
            if other is not None:
                log.error("run %s is held by another chief (session %s on %s, pid %d, since %s): not starting a "
                          "second one (if that chief is gone for good, clear its claim: mosquitto_pub -r -n -t %s)",
                          run, other.session, other.host or "?", other.pid,
                          dt.datetime.fromtimestamp(other.since).isoformat(timespec="seconds"), self.claim.topic)
                return EXIT_CLAIMED
            for route in received_by(CHIEF):  # the workers' hello, status and update (a root: the edges' partials)
                if route.retain or (UPDATE_KINDS if cfg.edges else EDGE_KINDS) & route.kinds:
                    continue  # the claim is RunClaim's; a root's updates come summed in the partials
                self.conn.subscribe(route.filter(run=run), self._on_message, qos=route.qos)
            if self.saved is not None:
                self._resume(*self.saved)
            else:
                log.info("run %s: waiting for %d workers on %s (env %s, policy %s)", run, cfg.workers, self.broker,
                         cfg.env, cfg.policy)
                self.metrics = MetricsLog(cfg.run_dir)
                workers = self._gather_workers()
                if self._interrupt.is_set():
                    log.warning("interrupted before the run started: nothing to save")
                    self.claim.clear()  # nothing to resume: the next chief of this run id may start
                    return EXIT_INTERRUPTED
                if not workers:
                    log.error("no worker said hello within %.0f s; giving up", cfg.start_timeout)
                    self.claim.clear()  # nothing to resume
                    return EXIT_NO_WORKERS
                shape = cfg.strategy.rounds(self.roster.update_steps)  # ValueError if it cannot run
                self.keeper = RoundKeeper(workers, cfg.policy, self.spec, cfg.max_episodes, cfg.round_timeout,
                                          actor_spec=self.roster.actor_spec, critic_spec=self.roster.critic_spec,
                                          shape=shape, max_staleness=cfg.max_staleness,
                                          tier="root" if cfg.edges else "flat", quorum=cfg.quorum)
                self._save()
            assert self.metrics is not None and self.keeper is not None
            if self.outputs.tensorboard and tensorboard.live(cfg.workers):
                self.metrics.attach(tensorboard.open_board(  # the event files follow metrics.jsonl from here on
                    cfg.run_dir, self.keeper.shape.per_episode,
                    wall_start=time.time() - (time.monotonic() - self.t0)))
            elif self.outputs.tensorboard:
                log.info("%d workers: the TensorBoard event files are drawn at the end of the run, not live (more "
                         "than %d); python -m chief.tensorboard %s draws them at any time", cfg.workers,
                         tensorboard.LIVE_WORKERS, cfg.run_dir)
            self.watch.expect(set(self.edge_of.values()), time.monotonic())
            self._announce()
            if not self._federate():
                return EXIT_CLAIMED
            return self._finish()
        finally:
            if self.root_edge is not None:
                self.root_edge.stop()
            if self.metrics is not None:
                self.metrics.close()
            self.conn.stop()

    def _resume(self, keeper: RoundKeeper, service: dict[str, Any]) -> None:
        """Carry on a run from its saved state: the records are cut back to what the state had seen."""
        self.keeper = keeper
        if keeper.max_staleness != self.cfg.max_staleness:
            log.warning("run %s keeps its saved --max-staleness %d (given %d): a run's staleness does not change",
                        self.cfg.run_id, keeper.max_staleness, self.cfg.max_staleness)
        if keeper.interrupted:  # its summary told how it stopped; the run goes on and will write another
            log.warning("run %s was interrupted (%s): taking it up again", self.cfg.run_id,
                        self.cfg.run_dir / SUMMARY)
            keeper.resume()
            (self.cfg.run_dir / SUMMARY).unlink(missing_ok=True)
        self.session, self.epoch, self.duplicates = service["session"], service["epoch"] + 1, service["duplicates"]
        algo = service.get("algo", "ppo")
        if algo != self.cfg.algo:
            log.warning("run %s keeps its saved learner %s (given %s): a run's learner does not change",
                        self.cfg.run_id, algo, self.cfg.algo)
        self.roster = Roster(self.cfg.env, algo=algo, started=True, actor_spec=keeper.actor_spec,
                             critic_spec=keeper.critic_spec, update_steps=service["update_steps"],
                             hosts=service["hosts"], init_model_known=service["init_model_known"])
        if service["init_model"] is not None:
            self.roster.init_model = service["init_model"]["digest"]
            self.roster.init_model_path = service["init_model"]["path"]
        self.rejects.restore(service["rejects"])
        self.edge_of = dict(service.get("edges", {}))
        self.stand_ins, self.moves = dict(service.get("stand_ins", {})), service.get("moves", 0)
        self.metrics = MetricsLog(self.cfg.run_dir, resume_at=service["metrics_bytes"])
        self.t0 = time.monotonic() - service["elapsed_s"]
        log.warning("resuming run %s from %s at round %d (%d workers, %d finished)", self.cfg.run_id,
                    self.cfg.run_dir / checkpoint.FILENAME, keeper.round, len(keeper.workers),
                    len(keeper.ids_in("finished")))

    def _save(self) -> None:
        """Write the chief's state (after the records it covers are on disk)."""
        assert self.keeper is not None and self.metrics is not None
        self._must_save = False
        if not self.outputs.state:
            return
        checkpoint.save(self.cfg.run_dir, self.keeper, {
            "run_id": self.cfg.run_id, "session": self.session, "epoch": self.epoch, "duplicates": self.duplicates,
            "hosts": self.roster.hosts, "update_steps": self.roster.update_steps,
            "rejects": self.rejects.as_dict(), "metrics_bytes": self.metrics.offset,
            "elapsed_s": time.monotonic() - self.t0, "init_model": self._init_model(),
            "init_model_known": self.roster.init_model_known, "claimed_since": self.claim.claim.since,
            "algo": self.roster.algo, "edges": self.edge_of, "stand_ins": self.stand_ins, "moves": self.moves})

    def _init_model(self) -> dict[str, str] | None:
        """The run's model as the records name it (runtime.records.InitModelRecord), None from scratch."""
        roster = self.roster
        return None if roster.init_model is None else {"path": roster.init_model_path, "digest": roster.init_model}

    def _gather_workers(self) -> list[str]:
        deadline = time.monotonic() + self.cfg.start_timeout
        while (len(self.roster.workers) < self.cfg.workers and time.monotonic() < deadline
               and not self._interrupt.is_set()):
            self.claim.watch()  # a younger chief's claim overwrote ours: claim the run again (it refuses to start)
            try:
                _, msg = self.events.get(timeout=0.2)
            except queue.Empty:
                continue
            if msg.kind == "hello":
                self._register(msg)
        if 0 < len(self.roster.workers) < self.cfg.workers:
            log.warning("only %d of %d workers arrived within %.0f s; starting with them", len(self.roster.workers),
                        self.cfg.workers, self.cfg.start_timeout)
        self.roster.started = True
        return self.roster.workers

    def _register(self, hello: WorkerHello) -> bool:
        if (hello.edge is None) == bool(self.cfg.edges):
            self.rejects.reject(topics.worker(self.cfg.run_id, hello.worker_id, topics.HELLO), "wrong_tier",
                                f"edge {hello.edge!r}, and this chief is " + (f"the root of {self.cfg.edges} edges"
                                                                               if self.cfg.edges else "flat"))
            return False
        new = hello.worker_id not in self.roster.hosts
        refused = self.roster.offer(hello.worker_id, hello.env_id, dict(hello.actor_spec), hello.host,
                                    critic_spec=dict(hello.critic_spec), update_steps=hello.update_steps,
                                    init_model=hello.init_model, init_model_path=hello.init_model_path,
                                    algo=hello.algo)
        if refused is not None:
            self.rejects.reject(topics.worker(self.cfg.run_id, hello.worker_id, topics.HELLO), *refused)
            return False
        if new:
            log.info("worker %s joined from %s (pid %d)%s", hello.worker_id, hello.host or "?", hello.pid,
                     f" behind edge {hello.edge}" if hello.edge else "")
        if hello.edge is not None and not self.roster.started:
            self.edge_of[hello.worker_id] = hello.edge
        return True

    def _announce(self) -> None:
        """Tell every worker and edge the run (a RunStart); the root's own edge first, when it serves groups."""
        assert self.keeper is not None
        self._announced = time.monotonic()
        msg = RunStart(run_id=self.cfg.run_id, env_id=self.cfg.env, policy=self.cfg.policy, seed=self.cfg.seed,
                       algo=self.roster.algo,
                       max_episodes=self.cfg.max_episodes, tc=self.spec.tc, r_floor=self.spec.r_floor,
                       workers=sorted(self.keeper.workers), first_episode=self.keeper.next_episode,
                       session=self.session, epoch=self.epoch, rounds_per_episode=self.keeper.shape.per_episode,
                       finishers_help=self.keeper.strategy.finishers_help,
                       max_staleness=self.keeper.max_staleness, quorum=self.keeper.quorum,
                       edges={w: e for w, e in self.edge_of.items() if w in self.keeper.workers},
                       round=self.keeper.round, stand_ins=self.stand_ins, moves=self.moves)
        if failover.served_by_root(self.stand_ins):
            self._root_takes(msg)
        self._send(msg)

    def _root_takes(self, start: RunStart) -> None:
        """Hand the root's own edge (started the first time: chief/edge.py RootStandIn) the RunStart about to go
        out, so that it serves its groups before their workers read it and send their round again."""
        assert self.keeper is not None
        if self.root_edge is None:
            spec = (dict(self.keeper.actor_spec or {}), dict(self.keeper.critic_spec or {}))
            self.root_edge = RootStandIn(self.cfg, self.conn, dict.fromkeys(self.keeper.workers, spec))
            log.warning("round %d: the root serves the workers of edge %s itself (as edge %s)", self.keeper.round,
                        ", ".join(failover.served_by_root(self.stand_ins)), ROOT_EDGE)
        if not self.root_edge.take(start):
            log.warning("the root's own edge did not take its workers within %.0f s: they send their round again "
                        "after their resend interval", TAKE_TIMEOUT)

    def _send(self, msg: RunStart | RunStop | ChiefAggregate | ChiefTransfer | ChiefAck) -> Published:
        """Tag a message with the chief key and publish it on its topic, with its route's QoS."""
        topic, payload = self._outgoing(msg)
        return self.conn.publish(topic, payload, qos=qos_of(topic))

    def _outgoing(self, msg: RunStart | RunStop | ChiefAggregate | ChiefTransfer | ChiefAck) -> tuple[str, bytes]:
        """A message as it goes out (or is held back for ``_flush``): its topic and its tagged payload."""
        return chief_route(msg.kind).filter(run=self.cfg.run_id), encode(signed(msg, self.chief_key))

    def _federate(self) -> bool:
        """Run rounds until the run is over (True), or another chief's claim beats this one's (False)."""
        keeper, metrics = self.keeper, self.metrics
        assert keeper is not None and metrics is not None
        idle_since: float | None = None
        while not keeper.done:
            if self._interrupt.is_set():
                keeper.interrupt()
                break
            other = self.claim.watch()
            if other is not None:
                log.error("run %s: chief session %s on %s holds the run since before this one; stopping (the run "
                          "is that chief's)", self.cfg.run_id, other.session, other.host or "?")
                return False
            outcomes: list[RoundOutcome] = []
            try:
                topic, msg = self.events.get(timeout=0.1)
            except queue.Empty:
                pass
            else:
                try:
                    outcomes = self._handle(msg)
                except Exception as exc:  # one message never ends the run: log it, count it, go on
                    log.exception("handling %s from %s failed", msg.kind, topic)
                    self.rejects.reject(topic, "handler_error", f"{type(exc).__name__}: {exc}")
            now = time.monotonic()
            outcomes += keeper.tick(now)
            if self.cfg.edges:
                self._fail_over(now)
            if outcomes:
                self._close_rounds(outcomes)
            elif self._must_save:
                self._save()
            metrics.flush()
            self._flush()
            if keeper.any_in("active", "lagging"):
                idle_since = None
            elif idle_since is None:
                idle_since = now
            elif now - idle_since > self.cfg.idle_timeout:
                keeper.abort(f"aborted: every unfinished worker stayed offline for {self.cfg.idle_timeout:.0f} s")
            self._progress(now)
        self._progress(time.monotonic(), force=True)
        return True

    def _handle(self, msg: Any) -> list[RoundOutcome]:
        keeper = self.keeper
        assert keeper is not None
        now = time.monotonic()
        if msg.kind == "hello":
            if self._register(msg):
                # A restarted worker learns the run and the open round. At most once a second: the RunStart is the
                # same for every worker, each says hello every second until named, and at 1,024 workers (through
                # edges that pass it on to theirs) a burst of hellos must not become a burst of RunStarts.
                if now - self._announced >= ANNOUNCE_INTERVAL:
                    self._announce()
            return []
        if msg.kind == "partial":
            return self._partial(msg, now)
        if msg.kind == "edge_status":
            self._edge_status(msg, now)
            return []
        if msg.worker_id not in keeper.workers:
            self.rejects.reject(topics.worker(self.cfg.run_id, msg.worker_id, msg.kind), "unknown_worker",
                                "not part of this run")
            return []
        if msg.kind == "status":
            if msg.state == "storage" and self._storage_fault is None:
                log.error("worker %s stopped on a storage fault (%s): the run stops resumably; free space or fix the "
                          "folder, then the same command resumes it", msg.worker_id, msg.detail)
                self._storage_fault = f"{msg.worker_id}: {msg.detail}"
                self._interrupt.set()
            elif msg.state in ("offline", "error", "stopped"):
                log.warning("worker %s is %s %s", msg.worker_id, msg.state, msg.detail)
            return keeper.note_status(msg.worker_id, msg.state, now, msg.detail)
        verdict = keeper.submit(submission_of(msg), now)
        self._answer(verdict, now)
        return verdict.outcomes

    def _partial(self, msg: EdgePartial, now: float) -> list[RoundOutcome]:
        """A root takes an edge's part of a round (docs/explanation/tiered.md): its partial sum first, then its
        contributors' submissions, the last of which may close the round; then the workers the edge timed out."""
        keeper = self.keeper
        assert keeper is not None and self.metrics is not None
        subs: list[WorkerUpdate | MatureParams] = [*msg.updates, *msg.matures]
        group = msg.group or msg.edge_id  # a stand-in sums a dead edge's workers as that edge would have
        self.watch.alive_now(msg.edge_id, now)
        topic = topics.edge(self.cfg.run_id, msg.edge_id, topics.PARTIAL)
        named = sorted({*(s.worker_id for s in subs), *(c.worker_id for c in msg.contributions)})
        if msg.edge_id not in (group, self.stand_ins.get(group)) or any(self.edge_of.get(w) != group for w in named):
            self.rejects.reject(topic, "not_serving", f"edge {msg.edge_id}'s partial of round {msg.round} for edge "
                                f"{group}'s workers {named}, which it does not serve")
            return []
        if msg.contributions:
            return self._contributions(msg, group, now)
        if msg.again:  # only for the root's answer to a closed round again: no part of a sum
            for sub in subs if msg.round < keeper.round else ():
                self._answer(keeper.submit(submission_of(sub), now), now)
            return []
        if msg.round >= keeper.round:
            keeper.add_partial(msg.round, group, partial_of(msg), [s.worker_id for s in subs],
                               dict(msg.clipped), dict(msg.critic_clipped))
        outcomes: list[RoundOutcome] = []
        for sub in subs:
            verdict = keeper.submit(submission_of(sub), now)
            self._answer(verdict, now)
            outcomes += verdict.outcomes
        return outcomes + keeper.excuse(msg.round, list(msg.timed_out), now)

    def _edge_status(self, msg: EdgeStatus, now: float) -> None:
        """An edge's status: its heartbeat (a RunStart again if it holds none), or its last will. One that comes
        back (found dead, or restarted) rejoins at the open round (chief/failover.py)."""
        if msg.edge_id == ROOT_EDGE:  # the root's own (it says nothing: only another that claims its name)
            return
        online = msg.state == "online"
        back = self.watch.status(msg.edge_id, online, now, msg.started, msg.site)
        if not online:
            log.warning("edge %s: its last will came (connection lost); its workers move to another edge in %.0f s "
                        "unless it says it is back", msg.edge_id, failover.WILL_GRACE)
        elif back:
            assert self.keeper is not None
            log.warning("edge %s is back: it rejoins at round %d", msg.edge_id, self.keeper.round)
            stand_ins = failover.fail_over(sorted(self.watch.found_dead), self.edge_of, self.stand_ins, self.watch)
            if stand_ins != self.stand_ins or not msg.started:  # it takes workers: they send their round again
                self._moved(stand_ins, now)
            elif msg.edge_id in self.stand_ins:  # its own workers went elsewhere while it was away: let it know
                self._announce()
        elif not msg.started and now - self._announced >= ANNOUNCE_INTERVAL:
            self._announce()

    def _fail_over(self, now: float) -> None:
        """Move the workers of the edges found dead now to their stand-ins (chief/failover.py); only once the root
        has read what came (a root that fell behind must not take its own backlog for an edge's silence)."""
        if not self.events.empty():
            return
        dead = self.watch.newly_dead(now, self.cfg.round_timeout)
        if not dead:
            return
        assert self.keeper is not None
        stand_ins = failover.fail_over(sorted(self.watch.found_dead), self.edge_of, self.stand_ins, self.watch)
        for edge in dead:
            log.warning(failover.DEAD.format("%s") + " (its last will, or %.0f s of silence)", edge,
                        failover.silence_limit(self.cfg.round_timeout))
        for group in sorted(set(failover.served_by_root(stand_ins)) - set(failover.served_by_root(self.stand_ins))):
            log.warning("round %d: no live edge of edge %s's site is left: the root serves its workers itself",
                        self.keeper.round, group)
        if stand_ins != self.stand_ins:
            self._moved(stand_ins, now)

    def _moved(self, stand_ins: dict[str, str], now: float) -> None:
        """Take the edges' new stand-ins (saved), tell every edge and worker (a RunStart with ``moves`` + 1), and give
        the open round a full timeout from now for the moved workers to send it again."""
        assert self.keeper is not None
        self.keeper.restart_clock(now)
        for group in sorted(set(self.edge_of.values())):
            now_at = failover.serving(group, stand_ins)
            if now_at != failover.serving(group, self.stand_ins):
                log.warning("round %d: the workers of edge %s go through edge %s from now on", self.keeper.round,
                            group, now_at)
        self.stand_ins, self.moves = stand_ins, self.moves + 1
        self._save()
        self._announce()

    def _contributions(self, msg: EdgePartial, group: str, now: float) -> list[RoundOutcome]:
        """``_partial`` for a partial of Contributions: the root counts each as its edge did, and records those it
        counted in one EdgeRecord (their full records are the edge's)."""
        keeper = self.keeper
        assert keeper is not None and self.metrics is not None
        matures = {m.worker_id: m for m in msg.matures}
        if msg.round >= keeper.round:
            keeper.add_partial(msg.round, group, partial_of(msg), [c.worker_id for c in msg.contributions],
                               dict(msg.clipped), dict(msg.critic_clipped))
        outcomes: list[RoundOutcome] = []
        counted: list[Contribution] = []
        verdicts: list[Verdict] = []  # answered once their EdgeRecord is written
        for c in msg.contributions:
            mature = matures.get(c.worker_id)
            sub = submission_of(mature) if mature is not None else contributed(c)
            verdict = keeper.submit(sub, now)
            if verdict.status == "accepted":
                counted.append(c)
            verdicts.append(verdict)
            outcomes += verdict.outcomes
        if counted:
            self.metrics.edge(EdgeRecord.model_construct(
                type="edge", edge=msg.edge_id, round=msg.round, episode=msg.episode, step=msg.step,
                contributions=counted, total=msg.total, count=msg.count, uniform=msg.uniform,
                matures=sorted(w for w in matures if any(c.worker_id == w for c in counted)) or None,
                t=round(now - self.t0, 3)))
        for verdict in verdicts:
            self._answer(verdict, now, recorded=True)
        return outcomes + keeper.excuse(msg.round, list(msg.timed_out), now)

    def _answer(self, verdict: Verdict, now: float, recorded: bool = False) -> None:
        """Record what was accepted (unless its EdgeRecord did: ``recorded``), count what was not, acknowledge
        mature actors, answer again a round a worker missed."""
        sub = verdict.submission
        assert sub is not None and self.metrics is not None
        topic = topics.worker(self.cfg.run_id, sub.worker_id, topics.UPDATE)
        if verdict.status == "accepted":
            if not recorded:
                self.metrics.episode(verdict.record(now - self.t0))
        elif verdict.status == "held":  # beyond reach: counted, or refused, when its round opens (chief/rounds.py)
            log.info("%s sent round %d while round %d is open: held until it opens", sub.worker_id, verdict.round,
                     self.keeper.round if self.keeper is not None else 0)
        elif verdict.status == "duplicate":
            self.duplicates += 1  # sent again (a worker's resend, a broker's redelivery): counted once
        else:
            self.rejects.reject(topic, verdict.reason, f"{sub.kind} for episode {sub.episode}: {verdict.detail}")
            refusal = verdict.refusal(now - self.t0)
            if refusal is not None:  # what its worker played is on record (written when it tells more)
                self.metrics.refused(refusal)
        if verdict.ack is not None:
            # Sent once the state is saved (_flush): what the chief confirms is on disk first.
            self._must_save |= verdict.ack.accepted and verdict.status == "accepted"
            self._outbox.append(self._outgoing(ack_of(verdict.ack, self.session)))
        if verdict.replay is not None:
            log.info("%s sent round %d again: answering it again", sub.worker_id, verdict.replay.round)
            self._outbox.append(self._outgoing(answer_of(verdict.replay, self.session)))

    def _flush(self) -> None:
        """Send the acknowledgements and repeated answers held back until the state was saved."""
        for topic, payload in self._outbox:
            self.conn.publish(topic, payload, qos=qos_of(topic))
        self._outbox.clear()

    def _close_rounds(self, outcomes: list[RoundOutcome]) -> None:
        """Record the closed rounds, save the state, then answer the workers (in that order, so a chief that dies
        in between answers them again from its state)."""
        assert self.metrics is not None
        now = time.monotonic()
        for outcome in outcomes:
            self.metrics.round({**outcome.record(), "t": round(now - self.t0, 3)})
            for verdict in outcome.taken_up:  # held submissions the next round counted or refused
                self._answer(verdict, now)
        self._save()
        for outcome in outcomes:
            self._log_outcome(outcome)
            self._publish(outcome)

    def _publish(self, outcome: RoundOutcome) -> None:
        self._send(answer_of(outcome, self.session))

    def _log_outcome(self, outcome: RoundOutcome) -> None:
        if outcome.kind == "transfer":
            log.info("round %d: %s finished (PI %.1f); transferring %s's actor to %s", outcome.round,
                     ", ".join(outcome.finished), outcome.source_pi or 0, outcome.source_worker,
                     ", ".join(f"{w} (keep {k:.3f})" for w, k in outcome.keep_weights.items()))
        elif outcome.finished:
            log.info("round %d: %s finished (no transfer: %s)", outcome.round, ", ".join(outcome.finished),
                     "nobody left to learn" if not self.keeper or self.keeper.done else self.keeper.why_no_transfer())
        for edge in sorted({self.edge_of[w] for w in outcome.timed_out if w in self.edge_of} - set(outcome.edges)):
            behind = sorted(w for w in outcome.timed_out if self.edge_of.get(w) == edge)
            log.warning("round %d: nothing came from edge %s within %.0f s (%s timed out): its edge chief, its broker "
                        "or all of its workers are down; they are lagging until it sends again (or its workers "
                        "move to another edge)", outcome.round, edge, self.cfg.round_timeout, ", ".join(behind))

    def _progress(self, now: float, force: bool = False) -> None:
        if not force and (not self.outputs.progress or now - self._last_progress < PROGRESS_INTERVAL):
            return
        self._last_progress = now
        keeper = self.keeper
        assert keeper is not None
        cells = []
        for w, rec in keeper.workers.items():
            pi = "-" if rec.pi is None else f"{rec.pi:.1f}"
            if rec.state == "finished":
                cells.append(f"{w} solved@{rec.solved_episode} PI {pi}")
            else:
                cells.append(f"{w} ep {rec.last_episode} PI {pi}{'' if rec.state == 'active' else ' ' + rec.state}")
        line = f"round {keeper.round:4d} | " + " | ".join(cells)
        if line == self._last_line and not force and now - self._last_printed < 15.0:
            return  # nothing changed: stay quiet (but say something at least every 15 s)
        self._last_line, self._last_printed = line, now
        print(f"[{now - self.t0:7.1f}s] {line}", flush=True)

    def _finish(self) -> int:
        """Save the state, tell the workers, write the summary and the plot; the exit code (EXIT_ABORTED for an
        aborted run, EXIT_INTERRUPTED for an interrupted one, which the saved state lets a chief resume)."""
        keeper = self.keeper
        assert keeper is not None and self.metrics is not None
        cfg = self.cfg
        reason = keeper.done_reason or "stopped"
        aborted = keeper.aborted or keeper.interrupted  # ended early, not by the run's rule
        all_solved = all(r.state == "finished" for r in keeper.workers.values())
        rounds = keeper.round - 1
        self._save()
        episodes = keeper.shape.episode_of(rounds) if rounds else 0
        stop = self._send(RunStop(run_id=cfg.run_id, reason=reason, episodes=episodes, all_solved=all_solved,
                                  aborted=aborted, session=self.session))
        try:  # a stopped chief does not wait long for a broker that is gone: the workers' timeouts end them
            stop.wait_for_publish(timeout=1 if keeper.interrupted else 5)
        except (RuntimeError, ValueError) as err:  # paho: not connected
            log.warning("the RunStop could not be sent (%s): the workers end by their own timeouts", err)
        self.claim.clear()
        summary = self.summary(reason, all_solved, rounds)
        write_summary(cfg.run_dir, summary)
        if self.outputs.tensorboard and not tensorboard.live(cfg.workers):
            tensorboard.rebuild(cfg.run_dir)
        if self.outputs.plot:
            plot_learning_curves(cfg.run_dir, self.metrics.curves, self.spec.tc,
                                 f"{cfg.env}, {len(keeper.workers)} workers, policy {cfg.policy}, seed {cfg.seed}")
        log.info("run over (%s) after %d rounds; results in %s", reason, rounds, cfg.run_dir)
        if keeper.interrupted:
            log.warning("the same command with --run-id %s --run-dir %s resumes the run from round %d", cfg.run_id,
                        cfg.run_dir, keeper.round)
            return EXIT_STORAGE if self._storage_fault is not None else EXIT_INTERRUPTED
        return EXIT_ABORTED if aborted else EXIT_OK

    def summary(self, reason: str, all_solved: bool, rounds: int) -> dict[str, Any]:
        keeper = self.keeper
        assert keeper is not None
        assert self.metrics is not None
        return run_summary(keeper, reason, rigs=self.metrics.rigs(keeper.max_staleness), played=self.metrics.played,
                           run_id=self.cfg.run_id, seed=self.cfg.seed,
                           wall_s=round(time.monotonic() - self.t0, 2),
                           finished_at=dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
                           broker=str(self.broker), rejected_messages=self.rejects.as_dict(),
                           duplicates=self.duplicates, restarts=self.epoch, init_model=self._init_model(),
                           algo=self.roster.algo)
