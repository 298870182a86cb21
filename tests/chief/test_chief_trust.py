"""Issue 19, items 1-2, on real brokers: one chief per run (a second chief exits 6; a resumed chief takes its run
back; the claim is cleared at the end), and answers workers can verify (forged, replayed, other-session and
future-round answers are refused and counted, and the run's per-worker episodes are a clean run's)."""

from __future__ import annotations

import logging
import math
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from chief.claim import RunClaim
from chief.service import EXIT_CLAIMED, EXIT_INTERRUPTED, ChiefService, Outputs
from chief.settings import ChiefSettings
from protocol import topics
from protocol.auth import signed
from protocol.codec import RejectCounter, decode, encode
from protocol.messages import ChiefAggregate, ChiefClaim, ChiefTransfer, RunStart
from protocol.mqtt import BrokerAddress, MqttConnection
from protocol.tensors import pack_arrays
from runtime.records import RunSummary
from worker.service import WorkerService
from worker.settings import WorkerSettings

KEY = "k" * 32
LOG = logging.getLogger("test")
pytestmark = pytest.mark.xdist_group("test_chief_trust")  # its module fixture is made once, in one test process
ENV, SEED, WORKERS, EPISODES = "CartPole-v0", 101, 2, 15


def connection(broker: str, name: str) -> MqttConnection:
    return MqttConnection(BrokerAddress.parse(broker), client_id=name).start()


def claim(run: str, session: str, since: float) -> ChiefClaim:
    return ChiefClaim(run_id=run, session=session, since=since, host="test", pid=1)


def test_a_run_has_one_chief_its_resumed_self_takes_it_back_and_the_claim_ends_with_it(any_broker: str) -> None:
    run = f"claim-{time.monotonic_ns()}"
    first = connection(any_broker, "first")
    try:
        holder = RunClaim(first, claim(run, "aaaa", 100.0), None, RejectCounter(LOG))
        assert holder.take() is None
        for session, since in (("bbbb", 200.0), ("0000", 150.0)):  # younger claims lose, whatever their session
            conn = connection(any_broker, session)
            try:
                second = RunClaim(conn, claim(run, session, since), None, RejectCounter(LOG))
                winner = second.take()
                assert winner is not None and winner.session == "aaaa"
                assert holder.watch() is None  # ... and the holder claimed the run again
            finally:
                conn.stop()
        resumed_conn = connection(any_broker, "resumed")  # the same session and time: the same chief, resumed
        try:
            assert RunClaim(resumed_conn, claim(run, "aaaa", 100.0), None,
                            RejectCounter(LOG)).take() is None
        finally:
            resumed_conn.stop()
        holder.clear()
        later = connection(any_broker, "later")
        try:
            assert RunClaim(later, claim(run, "cccc", 300.0), None,
                            RejectCounter(LOG)).take() is None
        finally:
            later.stop()
    finally:
        first.stop()


def test_a_chief_interrupted_before_any_worker_came_leaves_the_run_free(any_broker: str, tmp_path: Path) -> None:
    """Nothing to resume, so no claim left behind: the next chief of the run id starts (it was refused with 6)."""
    run = f"early-{time.monotonic_ns()}"

    def chief(name: str) -> ChiefService:
        return ChiefService(ChiefSettings.given(broker=any_broker, run_id=run, workers=2, env=ENV, seed=SEED,
                                                start_timeout=60, run_dir=tmp_path / name),
                            outputs=Outputs(state=False, tensorboard=False, plot=False, progress=False))

    first = chief("first")
    codes: list[int] = []
    thread = threading.Thread(target=lambda: codes.append(first.run()), daemon=True)
    thread.start()
    time.sleep(1.0)  # it has claimed the run and waits for workers
    first.interrupt()
    thread.join(timeout=30)
    assert codes == [EXIT_INTERRUPTED]
    conn = connection(any_broker, "later")
    try:
        assert RunClaim(conn, claim(run, "ffff", time.time()), None, RejectCounter(LOG)).take() is None
    finally:
        conn.stop()


def test_a_second_chief_for_a_live_run_exits_6_with_one_line(any_broker: str, tmp_path: Path) -> None:
    run = f"two-{time.monotonic_ns()}"
    conn = connection(any_broker, "holder")
    holder = RunClaim(conn, claim(run, "aaaa", time.time()), KEY.encode(), RejectCounter(LOG))  # a live chief's
    try:
        assert holder.take() is None
        out = subprocess.run([sys.executable, "-m", "chief", "--broker", any_broker, "--run-id", run, "--workers",
                              "1", "--run-dir", str(tmp_path / "b")], capture_output=True, text=True, timeout=120,
                             env={**os.environ, "FEDRL_RUN_KEY": KEY})
        assert out.returncode == EXIT_CLAIMED, out.stdout + out.stderr
        refusals = [line for line in (out.stdout + out.stderr).splitlines() if "held by another chief" in line]
        assert len(refusals) == 1 and "session aaaa" in refusals[0], out.stdout + out.stderr
        assert not (tmp_path / "b" / "metrics.jsonl").exists()
        assert holder.watch() is None  # the second chief's claim was younger: the holder claimed the run again
    finally:
        holder.clear()
        conn.stop()


class Rogue:
    """A client of an anonymous broker without the run's key: it reads the run, forges answers for rounds ahead
    (tagged with a key of its own, or untagged), and replays the chief's genuine answers of earlier rounds."""

    def __init__(self, broker: str, run: str) -> None:
        self.run = run
        self.conn = connection(broker, "rogue")
        self.session = ""
        self.genuine: list[tuple[str, bytes]] = []
        self.own: set[bytes] = set()
        self.sent = 0
        self.conn.subscribe(topics.chief(run, "+"), self._on)

    def _on(self, topic: str, payload: bytes) -> None:
        if payload in self.own:  # its own forgeries come back on the same topics: answering them would flood
            return
        msg = decode(payload)
        if isinstance(msg, RunStart):
            self.session = msg.session
        elif isinstance(msg, ChiefAggregate):
            self.genuine.append((topic, payload))
            ahead = msg.round + 1
            zeros = {"w": np.zeros(1, np.float32)}
            for forged in (
                ChiefAggregate(round=ahead, episode=ahead, gradient=None, weights={}, contributors=(),
                               session=self.session),
                signed(ChiefAggregate(round=ahead, episode=ahead, gradient=None, weights={}, contributors=(),
                                      session=self.session), b"not the run's key!"),
                signed(ChiefTransfer(round=msg.round, episode=msg.episode, source_worker="w0", source_pi=200.0,
                                     params=pack_arrays(zeros), keep_weights={"w0": 0.0, "w1": 0.0},
                                     finished=("w0",), session=self.session), b"not the run's key!"),
            ):
                self.own.add(encode(forged))
                self.conn.publish(topics.chief(self.run, forged.kind), encode(forged))
                self.sent += 1
            if len(self.genuine) > 2:  # an answer of two rounds ago, tag and all
                self.own.add(self.genuine[-3][1])
                self.conn.publish(*self.genuine[-3])
                self.sent += 1


def federation(broker: str, run: str, run_dir: Path) -> tuple[ChiefService, list[WorkerService]]:
    chief = ChiefService(ChiefSettings.given(broker=broker, run_id=run, workers=WORKERS, env=ENV, policy="weighted",
                                             seed=SEED, max_episodes=EPISODES, round_timeout=math.inf,
                                             start_timeout=60, idle_timeout=120, run_dir=run_dir, run_key=KEY),
                         outputs=Outputs(state=False, tensorboard=False, plot=False, progress=False))
    workers = [WorkerService(WorkerSettings.given(broker=broker, run_id=run, worker_id=f"w{i}", env=ENV,
                                                  reply_timeout=120, start_timeout=60, ack_timeout=120,
                                                  resend_interval=60, run_key=KEY)) for i in range(WORKERS)]
    return chief, workers


@pytest.fixture(scope="module")
def clean(tmp_path_factory: pytest.TempPathFactory) -> RunSummary:
    """The same federation without a rogue, in process: what the attacked runs must equal."""
    from deploy.inprocess import run_federation
    from deploy.settings import InprocessSettings

    return run_federation(InprocessSettings.given(env=ENV, policy="weighted", seed=SEED, workers=WORKERS,
                          max_episodes=EPISODES, run_dir=tmp_path_factory.mktemp("clean")), plot=False,
                          tensorboard_files=False)


@pytest.mark.slow
def test_forged_and_replayed_answers_are_refused_and_change_nothing(any_broker: str, tmp_path: Path,
                                                                    clean: RunSummary) -> None:
    run = f"forged-{time.monotonic_ns()}"
    rogue = Rogue(any_broker, run)
    chief, workers = federation(any_broker, run, tmp_path / "run")
    threads = [threading.Thread(target=w.run, daemon=True) for w in workers]
    for t in threads:
        t.start()
    try:
        assert chief.run() == 0
    finally:
        for t in threads:
            t.join(timeout=60)
        rogue.conn.stop()
    summary = chief.summary("", True, 0)
    # every env step of every episode is the same: no forged answer was applied (steps follow each update)
    assert [(w["id"], w["episodes"], w["steps"]) for w in summary["workers"]] == [
        (w.id, w.episodes, w.steps) for w in clean.workers]
    assert rogue.sent > 0
    for w in workers:
        refused = w.rejects.as_dict()
        assert refused.get("forged", 0) > 0 and refused.get("unsigned", 0) > 0, refused
        assert w.duplicates + refused.get("stale", 0) > 0, refused  # the replays: filed once, applied once


def test_without_a_key_an_aggregate_for_a_round_not_submitted_to_is_refused(tmp_path: Path) -> None:
    """No key (anonymous broker, trusting any publisher): still, an answer for a round ahead of the worker's
    submissions, or of another chief session, is refused and counted, never filed."""
    worker = WorkerService(WorkerSettings.given(worker_id="w0"), connect=lambda *a: _NoConnection())
    worker.start = RunStart(run_id="default", env_id=ENV, policy="weighted", seed=1, max_episodes=5, tc=195.0,
                            r_floor=0.0, workers=("w0",), session="good")
    worker.submitted = 3
    ahead = ChiefAggregate(round=4, episode=4, gradient=None, weights={}, contributors=(), session="good")
    other = ChiefAggregate(round=3, episode=3, gradient=None, weights={}, contributors=(), session="evil")
    fine = ChiefAggregate(round=3, episode=3, gradient=None, weights={}, contributors=(), session="good")
    topic = topics.chief("default", topics.AGGREGATE)
    for msg in (ahead, other, fine):
        worker._on_chief(topic, encode(msg))
        worker._receive(timeout=0.1)
    assert worker.rejects.as_dict() == {"not_submitted": 1, "wrong_session": 1}
    assert list(worker.replies) == [3]


class _NoConnection:
    connected = threading.Event()
    connects = 0

    def __getattr__(self, name: str) -> object:
        return lambda *a, **k: None
