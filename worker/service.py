"""The worker's MQTT adapter around Algorithm 2: announce, learn episode by episode, share the actor gradient and
PI, apply the chief's answer (mean gradient through the optimizer, or the Eq. 11 blend), hand over the mature
actor when PI >= TC and wait until the chief confirms it holds it. Every submission carries a receipt of what the
worker did with the previous round's answer. On the RunStop of an interrupted run it saves its resumable state, and
takes it up when the resumed run names it again (worker/resume.py). The learning itself is the run's learner
(worker/learners.py: PPO, SAC or DQN); the environments are worker/envs.py."""

from __future__ import annotations

import io
import logging
import math
import os
import queue
import socket
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import torch

from protocol import topics
from protocol.auth import admitted, signed
from protocol.codec import RejectCounter, encode
from protocol.messages import (
    INTERRUPTED,
    ChiefAck,
    ChiefAggregate,
    ChiefTransfer,
    MatureParams,
    Message,
    RunStart,
    RunStop,
    WorkerHello,
    WorkerStatus,
    WorkerUpdate,
)
from protocol.mqtt import Stopped
from protocol.rigtime import SECONDS_LIMIT
from protocol.rounds import PER_EPISODE, RoundShape
from protocol.routes import hello_wait, qos_of
from protocol.tasks import worker_seed
from protocol.tensors import NORM_LIMIT, l2_norm
from protocol.transport import Connect, Transport
from runtime.model_file import InitModel, last_model, mature_model
from runtime.storage import StorageError, atomic_write, storage_errors
from worker import model, resume
from worker.episode import build_learner_and_env
from worker.federated import Algorithm2
from worker.qube_env import Halted
from worker.settings import WorkerSettings

log = logging.getLogger("worker")

EXIT_OK, EXIT_ERROR, EXIT_NOT_STARTED, EXIT_ABORTED = 0, 1, 3, 4
#: The exit code of a worker stopped by SIGINT or SIGTERM before it solved (it said ``stopped`` and disconnected).
EXIT_INTERRUPTED = 130
#: The exit code of a worker whose resumable state does not fit the run that resumes (worker/resume.py).
EXIT_UNFIT_STATE = 7


def auto_worker_id() -> str:
    """Hostname plus a random suffix: unique even for replicas that share a hostname (host networking)."""
    host = "".join(c if c.isalnum() or c in "-_." else "-" for c in socket.gethostname())[:40] or "worker"
    return f"{host}-{uuid.uuid4().hex[:6]}"


class WorkerService:
    """One worker process: Algorithm 2 over MQTT (or over whatever ``connect`` makes: protocol.transport.Connect,
    e.g. protocol/memory.py's hub for a federation in one process)."""

    def __init__(self, cfg: WorkerSettings, connect: Connect | None = None) -> None:
        """``cfg``: the worker's settings, already checked; its worker id is this worker's (not ``auto``)."""
        if cfg.worker_id == "auto":
            raise ValueError("resolve worker_id 'auto' before starting the worker (auto_worker_id())")
        self.cfg = cfg
        self.rejects = RejectCounter(log)
        self.inbox: queue.Queue[Any] = queue.Queue()
        self.replies: dict[int, ChiefAggregate | ChiefTransfer] = {}
        self.acks: dict[int, ChiefAck] = {}  # by the round of the MatureParams they answer
        self.answered: set[int] = set()  # rounds whose answer was applied (a repeated answer is not applied again)
        self.stop: RunStop | None = None
        self._interrupt = threading.Event()  # set by ``interrupt`` (a signal handler)
        self.start: RunStart | None = None
        self.restarted = False  # a RunStart of a new epoch arrived (the chief restarted), or its edge changed
        self.why = "the chief restarted"  # ... which of the two (for the log)
        self.epoch = 0
        self.duplicates = 0  # answers sent again and ignored (each round's first copy logged): see _ignore
        self.ignored: set[int] = set()  # rounds whose repeated answer was logged already
        self.missed_replies = 0
        self.measured = False  # whether this worker's rig time is measured (a rig on a realtime or delayed clock)
        self.idle_s = 0.0  # measured: wall seconds spent waiting for the chief since the last submission
        # A warm start's model, checked against the task before anything connects (a ValueError: one line, exit 2).
        self.init_model: InitModel | None = None
        self.init_state: dict[str, Any] | None = None
        if cfg.init_model is not None:
            self.init_model, self.init_state = model.open_init_model(cfg.init_model, cfg.env, cfg.rig_id, cfg.algo,
                                                                          cfg.qube_actions)
        # Every chief message must carry its HMAC under the chief key; everything this worker sends carries its HMAC
        # under the worker's own key (protocol/auth.py).
        self.key = cfg.chief_check_key()
        self.own_key = cfg.own_key(cfg.worker_id)
        self.submitted = 0  # the last round this worker submitted to: no answer to a later one is taken
        self.via = cfg.edge  # the edge its rounds go through now (its own, or a dead one's stand-in)
        self.moves = 0  # the RunStart ``moves`` its edge last passed on
        self.outbox: dict[int, tuple[bytes, float]] = {}  # staleness: owed rounds' payloads and when first sent
        will = self._signed(WorkerStatus(worker_id=cfg.worker_id, state="offline", detail="connection lost"))
        self.conn: Transport = (connect or cfg.connector())(f"fedrl-{cfg.run_id}-worker-{cfg.worker_id}",
                                                       (self._topic(topics.STATUS), will), self.rejects)

    def interrupt(self) -> None:
        """Stop at the next wait (SIGINT, SIGTERM): say ``stopped`` and disconnect cleanly, so no last will is
        published. Safe from a signal handler."""
        self._interrupt.set()

    @property
    def halted(self) -> bool:
        """Whether to stop: the chief's RunStop came, or the worker was interrupted."""
        return self.stop is not None or self._interrupt.is_set()

    def _signed(self, msg: Message) -> bytes:
        """A message of this worker as it goes out: tagged with its own key (protocol/auth.py), encoded."""
        return encode(signed(msg, self.own_key))

    def _topic(self, leaf: str) -> str:
        return topics.worker(self.cfg.run_id, self.cfg.worker_id, leaf)

    def _send(self, leaf: str, payload: bytes) -> None:
        """Publish on one of this worker's topics, with its route's QoS."""
        topic = self._topic(leaf)
        self.conn.publish(topic, payload, qos=qos_of(topic))

    def _on_chief(self, topic: str, payload: bytes) -> None:
        msg = admitted(payload, RunStart, RunStop, ChiefAggregate, ChiefTransfer, ChiefAck, topic=topic, key=self.key,
                       rejects=self.rejects)
        if msg is None:
            return
        if isinstance(msg, ChiefAck) and msg.worker_id != self.cfg.worker_id:
            return  # another worker's acknowledgement
        if isinstance(msg, (ChiefAggregate, ChiefTransfer)):
            tensors = msg.params if isinstance(msg, ChiefTransfer) else msg.gradient
            norm = l2_norm(tensors) if tensors is not None else 0.0
            if not norm <= NORM_LIMIT:
                self.rejects.reject(topic, "absurd_norm", f"round {msg.round}'s {msg.kind} has an L2 norm of "
                                    f"{norm:.3g} (limit {NORM_LIMIT:g})")
                return
        self.inbox.put((topic, msg))

    def _status(self, state: str, episode: int = 0, pi: float | None = None, detail: str = "") -> None:
        msg = WorkerStatus(worker_id=self.cfg.worker_id, state=state, episode=episode, pi=pi, detail=detail)
        self._send(topics.STATUS, self._signed(msg))

    # -- main ------------------------------------------------------------------------------------------------

    def run(self) -> int:
        cfg = self.cfg
        torch.set_num_threads(1)
        try:
            self.conn.start(stop=self._interrupt)
        except Stopped:
            return EXIT_INTERRUPTED  # not connected: nobody to tell
        for topic_filter in sorted(self._answer_filters(cfg.edge)):
            self.conn.subscribe(topic_filter, self._on_chief, qos=qos_of(topic_filter))
        try:
            start = self._join()
            if start is None and self._interrupt.is_set():
                self._status("stopped", detail="interrupted before the run started")
                return EXIT_INTERRUPTED
            if start is None:
                log.error("no RunStart naming %s within %.0f s", cfg.worker_id, cfg.start_timeout)
                return EXIT_NOT_STARTED
            return self._learn(start)
        except resume.UnfitState as exc:
            log.error("refusing to start: %s (remove it to start this worker afresh, its learning lost)", exc)
            self._status("error", detail=str(exc)[:2000])
            return EXIT_UNFIT_STATE
        except StorageError as exc:  # main prints it as one line: exit 5; the chief stops the run resumably
            self._status("storage", detail=str(exc))
            raise
        except Halted as exc:  # a signal while the env waited for its rig (a reset, a state): at once, not after it
            log.info("%s: the episode in play is dropped", exc)
            self._status("stopped", detail="interrupted during an episode")
            return EXIT_INTERRUPTED
        except Exception as exc:
            log.exception("worker %s failed", cfg.worker_id)
            self._status("error", detail=f"{type(exc).__name__}: {exc}")
            return EXIT_ERROR
        finally:
            self._report_counts()
            time.sleep(0.2)  # let the last status go out
            self.conn.stop()

    def _play(self, algo: Algorithm2) -> WorkerUpdate | MatureParams:
        """The next episode, played ``slowdown`` times slower than this machine plays it (a straggler)."""
        began = time.monotonic()
        submission = algo.play()
        if self.cfg.slowdown > 1.0:
            self._interrupt.wait((self.cfg.slowdown - 1.0) * (time.monotonic() - began))
        return submission

    def _join(self) -> RunStart | None:
        """Say hello until the chief's RunStart names this worker (protocol.routes.hello_wait apart)."""
        cfg = self.cfg
        _, probe = build_learner_and_env(cfg.env, seed=0, device_noise=0.0, rig_id=cfg.rig_id, conn=self.conn,
                                         spec_only=True, algo=cfg.algo, env_options=cfg.env_options(),
                                         overrides=cfg.learner_overrides())
        hello = WorkerHello(worker_id=cfg.worker_id, env_id=cfg.env, actor_spec=probe.actor_spec(),
                            critic_spec=probe.critic_spec(), update_steps=probe.config.update_epochs, algo=cfg.algo,
                            host=socket.gethostname(), pid=os.getpid(),
                            init_model=self.init_model.digest if self.init_model else None,
                            init_model_path=self.init_model.given[:1000] if self.init_model else "",
                            edge=cfg.edge)
        self.actor_spec = probe.actor_spec()
        deadline = time.monotonic() + cfg.start_timeout
        next_hello, sent = 0.0, 0
        while time.monotonic() < deadline and not self._interrupt.is_set():
            if time.monotonic() >= next_hello:
                self._send(topics.HELLO, self._signed(hello))
                sent += 1
                next_hello = time.monotonic() + hello_wait(sent)
            try:
                topic, msg = self.inbox.get(timeout=0.2)
            except queue.Empty:
                continue
            if isinstance(msg, RunStart) and cfg.worker_id in msg.workers:
                if msg.env_id != cfg.env:
                    raise ValueError(f"the chief runs {msg.env_id!r} but this worker was started for {cfg.env!r}")
                if msg.algo != cfg.algo:
                    raise ValueError(f"the chief runs learner {msg.algo!r} but this worker was started with "
                                     f"{cfg.algo!r}")
                self.start, self.epoch = msg, msg.epoch
                self._route(topic, msg)
                return msg
            reason = "not_in_run" if isinstance(msg, RunStart) else "before_start"
            self.rejects.reject(topic, reason, f"a {msg.kind} before a RunStart naming {cfg.worker_id}")
        return None

    def _learn(self, start: RunStart) -> int:
        cfg = self.cfg
        index = start.workers.index(cfg.worker_id)
        seed = worker_seed(start.seed, index)
        env, learner = build_learner_and_env(cfg.env, seed=seed, device_noise=cfg.device_noise,
                                             init_seed=start.seed, rig_id=cfg.rig_id, conn=self.conn,
                                             env_options={**cfg.env_options(), "halt": self._interrupt}, algo=cfg.algo,
                                             overrides=cfg.learner_overrides())
        if cfg.learner_set:
            log.info("learner preset overridden: %s", ", ".join(cfg.learner_set))
        if self.init_model is not None and self.init_state is not None:  # the model replaces the shared init seed
            model.warm_start(learner, self.init_state, cfg.env, self.init_model.file, cfg.algo,
                             cfg.qube_actions, cfg.warm_temperature)
            log.info("warm start from %s (networks %s%s)", self.init_model.file, self.init_model.digest[:12],
                     f", temperature {cfg.warm_temperature:g}" if cfg.warm_temperature != 1.0 else "")
        self.measured = bool(getattr(env, "measured", False))
        algo = Algorithm2(cfg.worker_id, env, learner, start.tc, seed, first_episode=start.first_episode,
                          shape=start.shape, max_staleness=start.max_staleness,
                          warm_lr=cfg.warm_lr if self.init_model is not None else 1.0)
        try:
            pending = self._take_up(algo, start)  # a submission the chief has not answered yet, sent first
            log.info("worker %s (index %d, seed %d) learning %s under policy %s from episode %d", cfg.worker_id,
                     index, seed, cfg.env, start.policy, algo.next_episode if pending is None else algo.episode)
            self._status("training", episode=algo.next_episode - 1)
            while pending is not None or (algo.next_episode <= start.max_episodes and not self.halted):
                submission: WorkerUpdate | MatureParams | None = pending if pending is not None else self._play(algo)
                pending = None
                if isinstance(submission, MatureParams):  # Algorithm 2: learning finished -> hand it over, stop
                    self._save(learner, algo, start)
                    ack = self._hand_over(submission)
                    if ack is not None and ack.accepted:
                        self._status("finished", episode=submission.episode, pi=submission.pi)
                        log.info("solved at episode %d with PI %.1f; the chief holds the mature actor",
                                 submission.episode, submission.pi)
                        algo.accepted(ack)
                        if not start.finishers_help:
                            return EXIT_OK
                        log.info("going on playing and sharing until every worker has finished")
                        if algo.per_step:
                            self._catch_up(algo)
                        continue
                    if ack is None:
                        if self.halted:
                            pending = submission  # not acknowledged: the state keeps it
                            break
                        raise TimeoutError(f"the chief did not acknowledge the mature actor of episode "
                                           f"{submission.episode} within {cfg.ack_timeout:.0f} s")
                    log.error("the chief refused the mature actor of episode %d (%s); learning on",
                              submission.episode, ack.reason)
                    submission = algo.refused(submission)
                if algo.max_staleness and submission is not None:  # submit; play on unless more than S rounds owed
                    self._post(submission, algo.round)
                    self._settle(algo, algo.max_staleness)
                    continue
                pending = self._rounds(algo, submission)
                if pending is not None:
                    break
            if algo.owed and not algo.finished and pending is None:
                self._settle(algo, 0)  # the last answers, as a worker without staleness waits for its last
            self._keep(algo, start, pending)
            if not algo.finished and pending is None and algo.next_episode > start.max_episodes:
                self._save(learner, algo, start, last=True)  # its episodes played without meeting TC
            return self._ended(algo)
        finally:
            algo.close()

    def _ended(self, algo: Algorithm2) -> int:
        """Say how this worker stopped; its exit code."""
        if not algo.finished:
            self._status("stopped", episode=algo.next_episode - 1, pi=algo.pi,
                         detail=self.stop.reason if self.stop else "interrupted" if self.halted else "episode limit")
        interrupted = self.halted if self.stop is None else self.stop.reason == INTERRUPTED
        if interrupted and not algo.finished:  # Ctrl-C or SIGTERM here, or the chief's (_keep saved the state)
            return EXIT_INTERRUPTED
        if self.stop is not None and self.stop.aborted and not algo.finished:
            log.error("the run was aborted (%s) before this worker solved", self.stop.reason)
            return EXIT_ABORTED
        return EXIT_OK

    def _rounds(self, algo: Algorithm2, submission: WorkerUpdate | None) -> WorkerUpdate | None:
        """Exchange an episode's submissions for the chief's answers (one round, or K under a per-step strategy) and
        apply them; the submission left unanswered when the run stopped (not applied: the state keeps it), else None."""
        while submission is not None:
            reply = self._exchange(submission, algo.round)
            if reply is None and self.halted:
                return submission
            submission = algo.apply(reply)
            if algo.refused_answer is not None and reply is not None:
                self.rejects.reject(topics.chief(self.cfg.run_id, reply.kind), "wrong_shape", algo.refused_answer)
        return None

    # -- resumable state (worker/resume.py) ------------------------------------------------------------------

    def _state_file(self) -> Path | None:
        folder = self.cfg.states()
        return None if folder is None else resume.state_file(folder, self.cfg.run_id, self.cfg.worker_id)

    def _identity(self, algo: Algorithm2) -> resume.Identity:
        return resume.Identity(self.cfg.run_id, self.cfg.worker_id, self.cfg.env, algo.actor_spec,
                               algo.learner.critic_spec())

    def _take_up(self, algo: Algorithm2, start: RunStart) -> WorkerUpdate | MatureParams | None:
        """Go on from this worker's saved state when there is one (UnfitState when it does not fit this run); the
        submission it left unanswered. Without one, a worker joining a run at a later episode says its learning
        before was lost (its first receipt says ``restarted``)."""
        path = self._state_file()
        if path is None or not path.exists():
            if start.first_episode > 1:
                log.warning("no resumable state of %s in run %s (%s): it starts at episode %d with new networks, "
                            "its learning before is lost", self.cfg.worker_id, self.cfg.run_id,
                            path or "no --state-dir", start.first_episode)
            return None
        resumed = resume.load(path, self._identity(algo), start)
        try:
            algo.restore(resumed.algorithm)
        except (ValueError, KeyError, RuntimeError) as exc:  # networks or env of another shape, a damaged state
            raise resume.UnfitState(f"{path} does not fit this worker ({type(exc).__name__}: {exc})") from exc
        self.answered |= resumed.answered
        resume.discard(path)
        log.warning("resumed from %s at episode %d, PI %s, %s", path, algo.episode,
                    "-" if algo.pi is None else f"{algo.pi:.1f}",
                    f"sending round {algo.round} again" if resumed.pending is not None else "its last answer applied")
        return resumed.pending

    def _keep(self, algo: Algorithm2, start: RunStart, pending: WorkerUpdate | MatureParams | None) -> None:
        """On the RunStop of an interrupted run, save the resumable state (with the unanswered submission)."""
        if self.stop is None or self.stop.reason != INTERRUPTED:
            return
        path = self._state_file()
        if path is None:
            log.warning("the run was interrupted and %s keeps no state (no --state-dir or --model-dir): the resumed "
                        "run starts it with new networks", self.cfg.worker_id)
            return
        resume.save(path, self._identity(algo), start, self.epoch, algo.state(), pending, self.answered)
        log.info("the run was interrupted: saved this worker's state at episode %d to %s", algo.episode, path)

    def _catch_up(self, algo: Algorithm2) -> None:
        """A finisher that goes on helping under a per-step strategy: wait for the answers of its finishing
        episode's rounds (published to every worker) and apply them, as the others did, before it plays on."""
        rounds = algo.skipped_rounds
        deadline = time.monotonic() + self.cfg.reply_timeout
        while not self.halted and time.monotonic() < deadline and any(r not in self.replies for r in rounds):
            self._receive(timeout=0.5)
        applied = algo.catch_up({r: m for r in rounds if isinstance(m := self.replies.get(r), ChiefAggregate)})
        for r in rounds:
            if self.replies.pop(r, None) is not None:
                self.answered.add(r)
        if len(applied) < len(rounds) and not self.halted:
            missing = [r for r in rounds if r not in applied]
            log.warning("applied the answers of rounds %s of the finishing episode, not %s (%s): this worker's "
                        "networks now differ from the others'", applied, missing,
                        algo.refused_answer or "no answer in time")

    def _hand_over(self, mature: MatureParams) -> ChiefAck | None:
        """Send the mature actor until the chief acknowledges it (accepted or refused); None on RunStop or when no
        answer came within ``ack_timeout``. Resending is safe: the chief counts a worker's episode once."""
        began = time.monotonic()
        payload = self._signed(self._stamp(mature))
        round_ = self.shape.number(mature.episode)
        # A finisher that goes on helping takes the answers to the other rounds of its finishing episode (_catch_up).
        self.submitted = max(self.submitted, self.shape.rounds_of(mature.episode)[-1])
        deadline = time.monotonic() + self.cfg.ack_timeout
        interval = 2.0
        while not self.halted and time.monotonic() < deadline:
            self._send(topics.UPDATE, payload)
            self.restarted = False
            resend_at = min(deadline, time.monotonic() + interval)
            while (not self.halted and round_ not in self.acks and time.monotonic() < resend_at
                   and not self.restarted):
                self._receive(timeout=min(0.5, max(0.0, resend_at - time.monotonic())))
            if round_ in self.acks:
                self.idle_s += time.monotonic() - began
                return self.acks.pop(round_)
            if self.restarted:  # its edge changed, or the chief restarted: at once
                continue
            interval = min(2 * interval, 30.0)
            log.warning("no acknowledgement of the mature actor of episode %d yet; sending it again", mature.episode)
        self.idle_s += time.monotonic() - began
        return None

    def _stamp(self, submission: WorkerUpdate | MatureParams) -> WorkerUpdate | MatureParams:
        """A rig's episode submission (step 0) with the idle seconds measured since the last one (only when this
        worker measures its rig time: under a simulated clock the chief models them, protocol/rigtime.py)."""
        if not self.measured or submission.balance_steps is None:
            return submission
        idle, self.idle_s = min(self.idle_s, SECONDS_LIMIT), 0.0
        return submission.model_copy(update={"idle_s": round(idle, 6)})

    def _receive(self, timeout: float) -> None:
        """Take one message from the chief (if any within ``timeout``) and file it; count what is dropped."""
        try:
            topic, msg = self.inbox.get(timeout=timeout)
        except queue.Empty:
            return
        start = self.start
        if isinstance(msg, RunStop):
            if start is not None and msg.session != start.session:
                self.rejects.reject(topic, "wrong_session", f"a RunStop of session {msg.session!r}, this run's is "
                                    f"{start.session!r}")
            else:
                self.stop = msg
        elif isinstance(msg, RunStart):
            if start is not None and msg.session != start.session:
                self.rejects.reject(topic, "wrong_session", f"a RunStart of session {msg.session!r}, this run's is "
                                    f"{start.session!r}")
            elif start is not None and msg.epoch > self.epoch:
                self.epoch, self.restarted = msg.epoch, True  # the chief restarted: it may have lost our submission
                self.why = "the chief restarted"
            if start is not None and msg.session == start.session:
                self._route(topic, msg)
        elif self._answer_fits(topic, msg) and self._round_agrees(topic, msg):  # filed by the round it answers
            if isinstance(msg, ChiefAck):
                self.acks[msg.round] = msg
            elif msg.round in self.replies or msg.round in self.answered:
                self._ignore(topic, msg)
            else:
                self.replies[msg.round] = msg

    def _answer_filters(self, via: str | None) -> set[str]:
        """What a worker reads the root's answers on while its rounds go through edge ``via`` (None: a flat run's
        chief; topics.ROOT_EDGE: the root itself): the root's own topics; else that edge's, and the root's
        RunStart, which names a stand-in while a dead edge says nothing."""
        run = self.cfg.run_id
        if via is None or via == topics.ROOT_EDGE:
            return {topics.chief(run, "+")}
        return {topics.answers(run, via, "+"), topics.chief(run, topics.START)}

    def _route(self, topic: str, start: RunStart) -> None:
        """A tiered run's RunStart: listen to the edge that serves this worker now (a dead edge's stand-in,
        chief/failover.py), and send the unanswered round again when it changed, and when the serving edge passes on
        a RunStart with more ``moves`` (it has taken this worker: a stand-in, or its own edge restarted)."""
        if self.via is None:
            return
        run, home = self.cfg.run_id, self.cfg.edge
        assert home is not None
        via = start.stand_ins.get(home, home)
        if via != self.via:
            old, new = self._answer_filters(self.via), self._answer_filters(via)
            for topic_filter in sorted(new - old):  # first: nothing is missed in between
                self.conn.subscribe(topic_filter, self._on_chief, qos=qos_of(topic_filter))
            for topic_filter in old - new:
                self.conn.unsubscribe(topic_filter)
            who = "the root" if via == topics.ROOT_EDGE else f"edge {via}"
            log.warning("%s stands in for edge %s: this worker's rounds go through it", who, home)
            self.via, self.restarted, self.why = via, True, f"{who} stands in for edge {home}"
        if start.moves > self.moves and topic == topics.answers(run, self.via, topics.START):
            self.moves, self.restarted, self.why = start.moves, True, f"edge {self.via} took this worker"

    def _ignore(self, topic: str, answer: ChiefAggregate | ChiefTransfer) -> None:
        """An answer sent again (the chief answers a resent submission, a broker redelivers): applied once, the
        copies counted in ``duplicates`` and logged once per round with the reason."""
        self.duplicates += 1
        if answer.round in self.ignored:
            return
        self.ignored.add(answer.round)
        why = "already applied" if answer.round in self.answered else "already received"
        log.info("ignored round %d's %s sent again on %s (%s); its further copies are only counted [ignored so far: "
                 "%d]", answer.round, answer.kind, topic, why, self.duplicates)

    def _report_counts(self) -> None:
        """The worker's last word on what it refused: messages rejected by reason, and answers ignored as sent
        again."""
        log.info("worker %s: %d messages rejected %s, %d repeated answers ignored, %d answers missed",
                 self.cfg.worker_id, self.rejects.total, self.rejects.as_dict(), self.duplicates, self.missed_replies)

    @property
    def shape(self) -> RoundShape:
        """How the run numbers its rounds (from its RunStart)."""
        return self.start.shape if self.start is not None else PER_EPISODE

    def _answer_fits(self, topic: str, answer: ChiefAggregate | ChiefTransfer | ChiefAck) -> bool:
        """Whether an answer comes from the chief of this worker's RunStart (its session) and answers a round this
        worker has submitted to; one that does not is rejected and counted, and never filed (another chief's answer,
        or a forged one that would make this worker run ahead)."""
        session = self.start.session if self.start is not None else ""
        if answer.session != session:
            self.rejects.reject(topic, "wrong_session", f"a {answer.kind} for round {answer.round} of session "
                                f"{answer.session!r}, this run's is {session!r}")
            return False
        if answer.round > self.submitted:
            self.rejects.reject(topic, "not_submitted", f"a {answer.kind} for round {answer.round}, and this worker "
                                f"has submitted up to round {self.submitted}")
            return False
        return True

    def _round_agrees(self, topic: str, answer: ChiefAggregate | ChiefTransfer | ChiefAck) -> bool:
        """Whether an answer's round is the round of its episode and step (a transfer or an acknowledgement answers
        step 0); one that is not is rejected and counted, and never filed."""
        step = answer.step if isinstance(answer, ChiefAggregate) else 0
        if self.shape.agrees(answer.round, answer.episode, step):
            return True
        self.rejects.reject(topic, "wrong_round", f"a {answer.kind} for round {answer.round} says episode "
                            f"{answer.episode} step {step}, not that round with {self.shape.per_episode} rounds per "
                            f"episode")
        return False

    def _exchange(self, submission: WorkerUpdate, round_: int) -> ChiefAggregate | ChiefTransfer | None:
        """Submit one round and wait for the chief's answer to it (Algorithm 2, 'wait for a message m_c').

        The submission goes out again when the connection came back, when the chief announced itself again (it may
        have restarted) and every ``resend_interval`` seconds: the chief counts it once, and answers a round it
        already closed again, so a lost message costs seconds, not ``reply_timeout``.
        """
        payload = self._signed(self._stamp(submission))
        began = time.monotonic()
        deadline = began + self.cfg.reply_timeout
        self.submitted = max(self.submitted, round_)
        sent_at, connects = -math.inf, -1
        self.restarted = False
        while round_ not in self.replies and not self.halted:
            now = time.monotonic()
            if now >= deadline:
                self.missed_replies += 1
                log.warning("no answer from the chief for round %d within %.0f s; going on alone (missed %d)",
                            round_, self.cfg.reply_timeout, self.missed_replies)
                self.idle_s += now - began
                return None
            if self.conn.connects != connects or self.restarted or now - sent_at >= self.cfg.resend_interval:
                if connects != -1:
                    log.info("sending round %d again (%s)", round_, "reconnected" if self.conn.connects != connects
                             else self.why if self.restarted else "no answer yet")
                self._send(topics.UPDATE, payload)
                sent_at, connects, self.restarted = now, self.conn.connects, False
            self._receive(timeout=min(deadline - now, 0.5))
        for old in [r for r in self.replies if r < round_]:
            self.rejects.reject(topics.chief(self.cfg.run_id, self.replies[old].kind), "stale",
                                f"round {old}'s answer came after this worker had moved on")
            del self.replies[old]
        self.idle_s += time.monotonic() - began
        reply = self.replies.pop(round_, None)
        if reply is not None:
            self.answered.add(round_)
        return reply

    def _post(self, submission: WorkerUpdate, round_: int) -> None:
        """Bounded staleness: send one round's submission and keep it for resending until its answer is applied."""
        payload = self._signed(self._stamp(submission))
        self.submitted = max(self.submitted, round_)
        self.outbox[round_] = (payload, time.monotonic())
        self._send(topics.UPDATE, payload)

    def _settle(self, algo: Algorithm2, allowed: int) -> None:
        """Bounded staleness: apply the answers that came, in round order, and wait (resending what is owed, as
        ``_exchange`` does) while more than ``allowed`` rounds are owed. The oldest owed answer is given up as
        missed ``reply_timeout`` s after its submission went out. The wait counts as idle time."""
        began = time.monotonic()
        sent_at, connects = began, self.conn.connects
        self.restarted = False
        while True:
            self._take(algo)
            if len(algo.owed) <= allowed or self.halted:
                break
            now = time.monotonic()
            oldest = algo.owed[0]
            if now - self.outbox[oldest][1] >= self.cfg.reply_timeout:
                self.missed_replies += 1
                log.warning("no answer from the chief for round %d within %.0f s; going on without it (missed %d)",
                            oldest, self.cfg.reply_timeout, self.missed_replies)
                algo.give_up()
                continue
            if self.conn.connects != connects or self.restarted or now - sent_at >= self.cfg.resend_interval:
                log.info("sending rounds %s again (%s)", algo.owed, "reconnected" if self.conn.connects != connects
                         else self.why if self.restarted else "no answer yet")
                for r in algo.owed:
                    self._send(topics.UPDATE, self.outbox[r][0])
                sent_at, connects, self.restarted = now, self.conn.connects, False
            self._receive(timeout=0.5)
        self.idle_s += time.monotonic() - began
        for r in [r for r in self.outbox if r not in algo.owed]:
            del self.outbox[r]

    def _take(self, algo: Algorithm2) -> None:
        """Apply the filed answers to the rounds ``algo`` owes, oldest first; drop those to rounds it no longer owes
        (given up: counted as stale)."""
        while algo.owed and algo.owed[0] in self.replies:
            round_ = algo.owed[0]
            reply = self.replies.pop(round_)
            algo.take({round_: reply})
            self.answered.add(round_)
            if algo.refused_answer is not None:
                self.rejects.reject(topics.chief(self.cfg.run_id, reply.kind), "wrong_shape", algo.refused_answer)
        for old in [r for r in self.replies if r not in algo.owed]:
            self.rejects.reject(topics.chief(self.cfg.run_id, self.replies[old].kind), "stale",
                                f"round {old}'s answer came after this worker had given it up")
            del self.replies[old]

    def _save(self, learner: Any, algo: Algorithm2, start: RunStart, last: bool = False) -> None:
        """Save the mature model with its provenance (worker/model.py) as <model_dir>/<id>.pt; ``last``: the networks
        of a worker that played its episodes without meeting TC, as <model_dir>/<id>.last.pt."""
        if self.cfg.model_dir is None:
            return
        cfg = self.cfg
        prov = model.provenance(cfg.env, cfg.env_options(), algo.seed, start.seed, algo.episode, algo.total_steps,
                                self.init_model, worker_id=cfg.worker_id, run_id=cfg.run_id)
        path = (last_model if last else mature_model)(self.cfg.model_dir, self.cfg.worker_id)
        with storage_errors(path):  # a full or read-only disk: one line and exit 5, not a traceback
            self.cfg.model_dir.mkdir(parents=True, exist_ok=True)
        data = io.BytesIO()  # torch.save reports a full disk as a RuntimeError: serialise first, then write
        torch.save({**learner.state_dict(), "provenance": prov}, data)
        atomic_write(path, data.getvalue())  # the same bytes as learner.save(path, prov)
        log.info("saved the %s model to %s", "last (TC not met)" if last else "mature", path)
