"""The chief's MQTT adapter: decode and validate what workers send, feed the RoundKeeper, publish its outcomes,
print live progress and write the run folder. All federation decisions live in rounds.py / federation.py."""

from __future__ import annotations

import datetime as dt
import logging
import queue
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from chief.report import MetricsLog, plot_learning_curves, write_summary
from chief.rounds import RoundKeeper, RoundOutcome, Submission
from protocol import topics
from protocol.codec import DecodeError, RejectCounter, decode, encode
from protocol.messages import (
    ChiefAggregate,
    ChiefTransfer,
    MatureParams,
    Policy,
    RunStart,
    RunStop,
    WorkerHello,
    WorkerStatus,
    WorkerUpdate,
)
from protocol.mqtt import BrokerAddress, MqttConnection
from protocol.tasks import task
from protocol.tensors import check_spec, pack_arrays, unpack_arrays

log = logging.getLogger("chief")

EXIT_OK, EXIT_NO_WORKERS = 0, 3


@dataclass
class ChiefConfig:
    broker: BrokerAddress
    run_id: str = "default"
    workers: int = 4
    env_id: str = "CartPole-v0"
    policy: Policy = "weighted"
    seed: int = 1
    max_episodes: int = 2000
    round_timeout: float = 30.0
    start_timeout: float = 300.0
    idle_timeout: float = 120.0
    run_dir: Path = Path("runs/default")
    progress_interval: float = 2.0


class ChiefService:
    """Runs one federation from the first hello to the summary."""

    def __init__(self, cfg: ChiefConfig) -> None:
        self.cfg = cfg
        self.spec = task(cfg.env_id)
        topics.check_id(cfg.run_id, "run id")
        self.rejects = RejectCounter(log)
        self.events: queue.Queue[tuple[str, Any]] = queue.Queue()
        self.hellos: dict[str, WorkerHello] = {}
        self.actor_spec: dict[str, tuple[int, ...]] | None = None
        self.keeper: RoundKeeper | None = None
        self.conn = MqttConnection(cfg.broker, client_id=f"fedrl-{cfg.run_id}-chief")
        self.metrics = MetricsLog(cfg.run_dir)
        self.t0 = time.monotonic()
        self._last_progress = 0.0
        self._last_line, self._last_printed = "", 0.0

    # -- network thread: decode, validate, enqueue -------------------------------------------------------------

    def _on_message(self, topic: str, payload: bytes) -> None:
        try:
            msg = decode(payload, WorkerHello, WorkerStatus, WorkerUpdate, MatureParams)
            sender = topics.worker_id_of(topic)
        except DecodeError as err:
            self.rejects.reject_error(topic, err)
            return
        if msg.worker_id != sender:
            self.rejects.reject(topic, "spoofed", f"payload says worker {msg.worker_id!r}, topic says {sender!r}")
            return
        self.events.put((msg.kind, msg))

    # -- main thread -------------------------------------------------------------------------------------------

    def run(self) -> int:
        cfg = self.cfg
        run = cfg.run_id
        self.conn.start()
        for leaf in (topics.HELLO, topics.STATUS, topics.UPDATE):
            self.conn.subscribe(topics.all_workers(run, leaf), self._on_message, qos=1)
        log.info("run %s: waiting for %d workers on %s (env %s, policy %s)", run, cfg.workers, cfg.broker,
                 cfg.env_id, cfg.policy)
        try:
            workers = self._gather_workers()
            if not workers:
                log.error("no worker said hello within %.0f s; giving up", cfg.start_timeout)
                return EXIT_NO_WORKERS
            self.keeper = RoundKeeper(workers, cfg.policy, self.spec.tc, self.spec.r_floor, cfg.max_episodes,
                                      cfg.round_timeout)
            self._announce()
            self._federate()
            self._finish()
            return EXIT_OK
        finally:
            self.metrics.close()
            self.conn.stop()

    def _gather_workers(self) -> list[str]:
        deadline = time.monotonic() + self.cfg.start_timeout
        while len(self.hellos) < self.cfg.workers and time.monotonic() < deadline:
            try:
                kind, msg = self.events.get(timeout=0.2)
            except queue.Empty:
                continue
            if kind == "hello":
                self._register(msg)
        if 0 < len(self.hellos) < self.cfg.workers:
            log.warning("only %d of %d workers arrived within %.0f s; starting with them", len(self.hellos),
                        self.cfg.workers, self.cfg.start_timeout)
        return sorted(self.hellos)

    def _register(self, hello: WorkerHello) -> None:
        topic = topics.worker(self.cfg.run_id, hello.worker_id, topics.HELLO)
        if hello.env_id != self.cfg.env_id:
            self.rejects.reject(topic, "wrong_env", f"worker runs {hello.env_id!r}, this run is {self.cfg.env_id!r}")
            return
        if self.actor_spec is None:
            self.actor_spec = dict(hello.actor_spec)
        elif dict(hello.actor_spec) != self.actor_spec:
            self.rejects.reject(topic, "wrong_model", "actor shape differs from the other workers'")
            return
        if hello.worker_id not in self.hellos:
            log.info("worker %s joined from %s (pid %d)", hello.worker_id, hello.host or "?", hello.pid)
        self.hellos[hello.worker_id] = hello

    def _announce(self) -> None:
        assert self.keeper is not None
        msg = RunStart(run_id=self.cfg.run_id, env_id=self.cfg.env_id, policy=self.cfg.policy, seed=self.cfg.seed,
                       max_episodes=self.cfg.max_episodes, tc=self.spec.tc, r_floor=self.spec.r_floor,
                       workers=sorted(self.keeper.workers), first_episode=self.keeper.episode)
        self.conn.publish(topics.chief(self.cfg.run_id, topics.START), encode(msg), qos=1)

    def _federate(self) -> None:
        keeper = self.keeper
        assert keeper is not None
        idle_since: float | None = None
        while not keeper.done:
            try:
                kind, msg = self.events.get(timeout=0.1)
                outcomes = self._handle(kind, msg)
            except queue.Empty:
                outcomes = []
            now = time.monotonic()
            outcomes += keeper.tick(now)
            for outcome in outcomes:
                self._publish(outcome)
            if keeper.ids_in("active", "lagging"):
                idle_since = None
            elif idle_since is None:
                idle_since = now
            elif now - idle_since > self.cfg.idle_timeout:
                keeper.abort(f"every unfinished worker stayed offline for {self.cfg.idle_timeout:.0f} s")
            self._progress(now)
        self._progress(time.monotonic(), force=True)

    def _handle(self, kind: str, msg: Any) -> list[RoundOutcome]:
        keeper = self.keeper
        assert keeper is not None
        now = time.monotonic()
        if kind == "hello":
            if msg.worker_id in keeper.workers:
                self._register(msg)
                self._announce()  # a restarted worker learns the run and the open round
            else:
                self.rejects.reject(topics.worker(self.cfg.run_id, msg.worker_id, topics.HELLO), "late_worker",
                                    "the run has started without this worker")
            return []
        if msg.worker_id not in keeper.workers:
            self.rejects.reject(topics.worker(self.cfg.run_id, msg.worker_id, kind), "unknown_worker",
                                "not part of this run")
            return []
        if kind == "status":
            if msg.state in ("offline", "error", "stopped"):
                log.warning("worker %s is %s %s", msg.worker_id, msg.state, msg.detail)
                return keeper.mark_offline(msg.worker_id, now)
            if msg.state == "finished" and keeper.workers[msg.worker_id].state != "finished":
                # Its mature actor was lost (e.g. the broker restarted as it was sent): it leaves without a transfer.
                log.warning("worker %s finished at episode %d but its mature actor never arrived", msg.worker_id,
                            msg.episode)
                return keeper.mark_finished(msg.worker_id, msg.episode, msg.pi or self.spec.tc, now)
            return []
        tensors = msg.gradient if kind == "update" else msg.params
        try:
            check_spec(tensors, self.actor_spec or {}, f"{kind} from {msg.worker_id}")
        except ValueError as err:
            self.rejects.reject(topics.worker(self.cfg.run_id, msg.worker_id, topics.UPDATE), "wrong_shape", str(err))
            return []
        arrays = unpack_arrays(tensors)
        sub = Submission(msg.worker_id, msg.episode, msg.pi, msg.episode_return,
                         gradient=arrays if kind == "update" else None, params=arrays if kind == "mature" else None)
        self.metrics.episode(msg.worker_id, msg.episode, msg.episode_return, msg.pi, msg.steps,
                             now - self.t0, kind)
        return keeper.submit(sub, now)

    def _publish(self, outcome: RoundOutcome) -> None:
        run = self.cfg.run_id
        if outcome.kind == "transfer":
            assert outcome.params is not None and outcome.source_worker is not None
            msg: ChiefAggregate | ChiefTransfer = ChiefTransfer(
                episode=outcome.episode, source_worker=outcome.source_worker, source_pi=float(outcome.source_pi or 0),
                params=pack_arrays(outcome.params), keep_weights=outcome.keep_weights, finished=outcome.finished)
            topic = topics.chief(run, topics.TRANSFER)
            log.info("round %d: %s finished (PI %.1f); transferring its actor to %s", outcome.episode,
                     ", ".join(outcome.finished), outcome.source_pi or 0, sorted(outcome.keep_weights))
        else:
            msg = ChiefAggregate(episode=outcome.episode,
                                 gradient=pack_arrays(outcome.gradient) if outcome.gradient is not None else None,
                                 weights=outcome.weights, contributors=outcome.contributors)
            topic = topics.chief(run, topics.AGGREGATE)
            if outcome.finished:
                log.info("round %d: %s finished (no transfer under %s)", outcome.episode,
                         ", ".join(outcome.finished), self.cfg.policy)
        self.conn.publish(topic, encode(msg), qos=1)
        self.metrics.round({"round": outcome.episode, "kind": outcome.kind, "contributors": outcome.contributors,
                            "weights": outcome.weights, "keep_weights": outcome.keep_weights,
                            "finished": outcome.finished, "source": outcome.source_worker,
                            "timed_out": outcome.timed_out, "t": round(time.monotonic() - self.t0, 3)})

    def _progress(self, now: float, force: bool = False) -> None:
        if not force and now - self._last_progress < self.cfg.progress_interval:
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
        line = f"round {keeper.episode:4d} | " + " | ".join(cells)
        if line == self._last_line and not force and now - self._last_printed < 15.0:
            return  # nothing changed: stay quiet (but say something at least every 15 s)
        self._last_line, self._last_printed = line, now
        print(f"[{now - self.t0:7.1f}s] {line}", flush=True)

    def _finish(self) -> None:
        keeper = self.keeper
        assert keeper is not None
        cfg = self.cfg
        reason = keeper.done_reason or "stopped"
        all_solved = all(r.state == "finished" for r in keeper.workers.values())
        rounds = keeper.episode - 1
        self.conn.publish(topics.chief(cfg.run_id, topics.STOP),
                          encode(RunStop(run_id=cfg.run_id, reason=reason, episodes=rounds, all_solved=all_solved)),
                          qos=1).wait_for_publish(timeout=5)
        summary = self.summary(reason, all_solved, rounds)
        write_summary(cfg.run_dir, summary)
        plot_learning_curves(cfg.run_dir, self.metrics.curves, self.spec.tc,
                             f"{cfg.env_id}, {len(keeper.workers)} workers, policy {cfg.policy}, seed {cfg.seed}")
        log.info("run over (%s) after %d rounds; results in %s", reason, rounds, cfg.run_dir)

    def summary(self, reason: str, all_solved: bool, rounds: int) -> dict[str, Any]:
        keeper = self.keeper
        assert keeper is not None
        workers = []
        for index, (w, rec) in enumerate(keeper.workers.items()):
            solved = rec.state == "finished"
            workers.append({"id": w, "index": index, "solved": solved,
                            "episodes": rec.solved_episode if solved else rec.last_episode,
                            "final_pi": rec.pi, "state": rec.state})
        return {
            "run_id": self.cfg.run_id,
            "env": self.cfg.env_id,
            "policy": self.cfg.policy,
            "seed": self.cfg.seed,
            "tc": self.spec.tc,
            "r_floor": self.spec.r_floor,
            "max_episodes": self.cfg.max_episodes,
            "workers": workers,
            "episodes_to_all_solved": max(w["episodes"] for w in workers) if all_solved else None,
            "rounds": rounds,
            "end_reason": reason,
            "wall_s": round(time.monotonic() - self.t0, 2),
            "finished_at": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
            "broker": str(self.cfg.broker),
            "rejected_messages": self.rejects.as_dict(),
            "stale_submissions": keeper.stale,
        }
