"""The chief as a real process over a real broker, driven by scripted workers (no torch): it federates, rejects
bad input without crashing, and writes the run folder."""

from __future__ import annotations

import json
import queue
import subprocess
import sys
from pathlib import Path

import msgpack
import numpy as np
import pytest

from chief.audit import audit
from protocol import topics
from protocol.codec import decode, encode
from protocol.messages import (
    ChiefAck,
    ChiefAggregate,
    ChiefTransfer,
    MatureParams,
    Receipt,
    RunStart,
    RunStop,
    WorkerHello,
    WorkerStatus,
    WorkerUpdate,
)
from protocol.mqtt import BrokerAddress, MqttConnection
from protocol.tensors import digest, pack_arrays, unpack_arrays

RUN = "t1"
SPEC = {"w": (2,)}


def start_chief(broker: str, run_dir: Path, workers: int, policy: str = "weighted",
                round_timeout: float = 30.0) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "chief", "--broker", broker, "--run-id", RUN, "--workers", str(workers),
         "--env", "CartPole-v0", "--policy", policy, "--max-episodes", "50", "--round-timeout", str(round_timeout),
         "--run-dir", str(run_dir), "--start-timeout", "30"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


class ScriptedWorkers:
    """One MQTT connection speaking for several fake workers."""

    def __init__(self, broker: str) -> None:
        self.inbox: queue.Queue = queue.Queue()
        self.conn = MqttConnection(BrokerAddress.parse(broker), client_id="scripted-workers").start()
        self.conn.subscribe(topics.chief(RUN, "+"), lambda t, p: self.inbox.put(decode(p)))

    def send(self, worker: str, msg: object, leaf: str = topics.UPDATE) -> None:
        payload = msg if isinstance(msg, bytes) else encode(msg)  # type: ignore[arg-type]
        self.conn.publish(topics.worker(RUN, worker, leaf), payload, qos=1).wait_for_publish(5)

    def join(self, *workers: str) -> RunStart:
        """Say hello (again every 0.5 s, as real workers do) until the chief starts the run."""
        for _ in range(60):
            for w in workers:
                self.send(w, WorkerHello(worker_id=w, env_id="CartPole-v0", actor_spec=SPEC), topics.HELLO)
            try:
                return self.expect(RunStart, timeout=0.5)
            except queue.Empty:
                continue
        raise AssertionError("the chief never started the run")

    def expect(self, kind: type, timeout: float = 20.0):
        while True:
            msg = self.inbox.get(timeout=timeout)
            if isinstance(msg, kind):
                return msg


HISTORY: dict[str, list[float]] = {}


def _recent(worker: str, episode: int, ret: float) -> tuple[list[float], float]:
    """The worker's returns so far (as a real worker keeps them), its recent window and PI."""
    history = HISTORY.setdefault(worker, [])
    if episode == 1:
        history.clear()
    history.append(ret)
    recent = history[-10:]
    return recent, sum(recent) / len(recent)


def receipt(answer: ChiefAggregate | ChiefTransfer | None, worker: str) -> Receipt | None:
    """What a real worker reports having applied."""
    if answer is None:
        return None
    if isinstance(answer, ChiefTransfer):
        return Receipt(round=answer.episode, applied="transfer", digest=digest(answer.params),
                       keep=answer.keep_weights.get(worker))
    return Receipt(round=answer.episode, applied="aggregate",
                   digest=digest(answer.gradient) if answer.gradient is not None else "")


def update(worker: str, episode: int, ret: float, grad: list[float], after: object = None) -> WorkerUpdate:
    recent, pi = _recent(worker, episode, ret)
    return WorkerUpdate(worker_id=worker, episode=episode, episode_return=ret, pi=pi, recent_returns=recent,
                        steps=10, gradient=pack_arrays({"w": np.array(grad, np.float32)}),
                        receipt=receipt(after, worker))  # type: ignore[arg-type]


def mature(worker: str, episode: int, ret: float, params: list[float], after: object = None) -> MatureParams:
    recent, pi = _recent(worker, episode, ret)
    return MatureParams(worker_id=worker, episode=episode, episode_return=ret, pi=pi, recent_returns=recent,
                        steps=10, params=pack_arrays({"w": np.array(params, np.float32)}),
                        receipt=receipt(after, worker))  # type: ignore[arg-type]


def test_chief_federates_rejects_bad_input_and_reports(any_broker: str, tmp_path: Path) -> None:
    chief = start_chief(any_broker, tmp_path / "run", workers=2)
    fake = ScriptedWorkers(any_broker)
    try:
        start = fake.join("w0", "w1")
        assert start.workers == ("w0", "w1") and start.tc == 195.0 and start.policy == "weighted"

        # Garbage of every kind first: the chief must log, count and carry on.
        fake.send("w0", b"\x00not msgpack")
        fake.send("w0", msgpack.packb({"schema_version": 99, "kind": "update"}))
        bad = update("w0", 1, 50.0, [1.0, 2.0]).model_dump(mode="python")
        bad["gradient"]["w"]["data"] = np.array([np.nan, 1.0], np.float32).tobytes()
        fake.send("w0", msgpack.packb(bad, use_bin_type=True))  # NaN gradient
        fake.send("w0", update("w0", 1, 50.0, [1.0, 2.0, 3.0]))  # wrong shape
        fake.send("w1", update("w0", 1, 50.0, [1.0, 2.0]))  # topic says w1, payload says w0

        # Round 1: Eq. 8-9 with PIs 50 and 150 -> weights 0.25 / 0.75.
        fake.send("w0", update("w0", 1, 50.0, [1.0, 2.0]))
        fake.send("w1", update("w1", 1, 150.0, [3.0, -2.0]))
        answer = fake.expect(ChiefAggregate)
        assert answer.episode == 1 and answer.weights == pytest.approx({"w0": 0.25, "w1": 0.75})
        np.testing.assert_allclose(unpack_arrays(answer.gradient)["w"], [2.5, -1.0])

        # Rounds 2-9: w0 ends at PI 97.5, w1 at the top; a repeated update is not counted twice.
        for e in range(2, 10):
            mine = update("w0", e, 145.0 if e == 2 else 97.5, [1.0, 1.0], after=answer)
            fake.send("w0", mine)
            if e == 2:
                fake.send("w0", mine)  # duplicate
            fake.send("w1", update("w1", e, 200.0, [1.0, 1.0], after=answer))
            answer = fake.expect(ChiefAggregate)
            assert answer.episode == e
        # A PI 10 claimed mature is refused, and acknowledged as refused.
        liar = MatureParams(worker_id="w0", episode=10, episode_return=10.0, pi=10.0, recent_returns=[10.0],
                            params=pack_arrays({"w": np.array([0.0, 0.0], np.float32)}))
        fake.send("w0", liar)
        nack = fake.expect(ChiefAck)
        assert nack.worker_id == "w0" and not nack.accepted and "not_mature" in nack.reason

        # Round 10: w1 finishes (PI 195 over 10 episodes) and says so at once: its pending actor must survive.
        finish = mature("w1", 10, 200.0, [4.0, 4.0], after=answer)
        fake.send("w1", finish)
        fake.send("w1", WorkerStatus(worker_id="w1", state="finished", episode=10, pi=195.0), topics.STATUS)
        ack = fake.expect(ChiefAck)
        assert (ack.worker_id, ack.episode, ack.accepted) == ("w1", 10, True)
        fake.send("w0", update("w0", 10, 97.5, [1.0, 1.0], after=answer))
        answer = fake.expect(ChiefTransfer)
        assert answer.episode == 10 and answer.source_worker == "w1"
        assert answer.keep_weights == pytest.approx({"w0": 0.5})  # Eq. 10: 97.5 / 195
        np.testing.assert_array_equal(unpack_arrays(answer.params)["w"], [4.0, 4.0])
        fake.send("w1", finish)  # sent again (say the ack was lost): acknowledged again, counted once
        assert fake.expect(ChiefAck).accepted

        # w0 finishes after ten episodes of 200; the run ends.
        for e in range(11, 20):
            fake.send("w0", update("w0", e, 200.0, [1.0, 1.0], after=answer))
            answer = fake.expect(ChiefAggregate)
        fake.send("w0", mature("w0", 20, 200.0, [5.0, 5.0], after=answer))
        stop = fake.expect(RunStop)
        assert stop.all_solved and stop.episodes == 20
        assert chief.wait(timeout=20) == 0
    finally:
        fake.conn.stop()
        if chief.poll() is None:
            chief.kill()
    out = chief.stdout.read() if chief.stdout else ""
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["episodes_to_all_solved"] == 20
    assert [(w["id"], w["solved"], w["episodes"]) for w in summary["workers"]] == [("w0", True, 20), ("w1", True, 10)]
    assert summary["rejected_messages"] == {"malformed": 1, "version": 1, "invalid": 1, "wrong_shape": 1,
                                            "spoofed": 1, "not_mature": 1}, out
    assert summary["duplicates"] == 2 and summary["restarts"] == 0
    lines = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert sum(1 for x in lines if x["type"] == "episode") == 30  # only what was counted
    assert (tmp_path / "run" / "learning_curve.png").stat().st_size > 1000
    report = audit(tmp_path / "run")
    assert report.transfers == 1 and report.receipts == 28


def test_chief_goes_on_without_a_silent_worker(amqtt_broker: str, tmp_path: Path) -> None:
    chief = start_chief(amqtt_broker, tmp_path / "run", workers=3, round_timeout=1.0)
    fake = ScriptedWorkers(amqtt_broker)
    try:
        fake.join("w0", "w1", "w2")
        fake.send("w0", update("w0", 1, 10.0, [1.0, 1.0]))
        fake.send("w1", update("w1", 1, 10.0, [3.0, 3.0]))  # w2 stays silent
        agg = fake.expect(ChiefAggregate, timeout=10)
        assert agg.contributors == ("w0", "w1")
        # w1 dies: its last will (here sent by hand) takes it out of the round at once.
        fake.send("w1", WorkerStatus(worker_id="w1", state="offline"), topics.STATUS)
        for e in range(2, 11):
            fake.send("w0", update("w0", e, 200.0, [1.0, 1.0]))
            agg = fake.expect(ChiefAggregate, timeout=10)
            assert agg.episode == e and agg.contributors == ("w0",)
        # The lagging w2 and the returning w1 submit for the open round, so it waits for them again. (Their
        # episodes 2-10 never reached the chief; their mature PIs cover episodes 2-11.)
        HISTORY["w1"], HISTORY["w2"] = [10.0] + [200.0] * 9, [200.0] * 9
        fake.send("w2", mature("w2", 11, 200.0, [1.0, 1.0]))
        fake.send("w1", mature("w1", 11, 200.0, [1.0, 1.0]))
        fake.send("w0", mature("w0", 11, 200.0, [1.0, 1.0]))
        assert fake.expect(RunStop, timeout=10).all_solved
        assert chief.wait(timeout=20) == 0
    finally:
        fake.conn.stop()
        if chief.poll() is None:
            chief.kill()
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["episodes_to_all_solved"] == 11


def test_one_message_that_breaks_the_chief_is_counted_and_the_run_goes_on(tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """Whatever goes wrong while handling one message (here: the round state machine raises), the main loop logs
    and counts it and carries on with the next message."""
    from chief.report import MetricsLog
    from chief.rounds import RoundKeeper
    from chief.service import ChiefService
    from chief.settings import ChiefSettings
    from protocol.tasks import task

    svc = ChiefService(ChiefSettings.given(broker="mqtt://127.0.0.1:9", run_id=RUN, workers=1,
                                           run_dir=tmp_path / "run", max_episodes=2))
    sent: list[str] = []
    monkeypatch.setattr(svc.conn, "publish", lambda topic, payload, qos=1: sent.append(topic))
    svc.keeper = RoundKeeper(["w0"], "weighted", task("CartPole-v0"), 2, 30.0, actor_spec={"w": (2,)})
    svc.metrics = MetricsLog(tmp_path / "run")
    real_submit, calls = svc.keeper.submit, []

    def flaky(sub, now):  # type: ignore[no-untyped-def]
        calls.append(sub.episode)
        if len(calls) == 1:
            raise RuntimeError("a bug triggered by one message")
        return real_submit(sub, now)

    monkeypatch.setattr(svc.keeper, "submit", flaky)
    HISTORY.clear()
    topic = topics.worker(RUN, "w0", topics.UPDATE)
    first = update("w0", 1, 10.0, [1.0, 1.0])
    for msg in (first, first, update("w0", 2, 10.0, [1.0, 1.0])):
        svc.events.put((topic, msg))
    svc._federate()
    assert svc.keeper.done and calls == [1, 1, 2]
    assert svc.rejects.as_dict() == {"handler_error": 1}
    assert sent.count(topics.chief(RUN, topics.AGGREGATE)) == 2
