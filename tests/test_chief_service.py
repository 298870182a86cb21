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

from protocol import topics
from protocol.codec import decode, encode
from protocol.messages import (
    ChiefAggregate,
    ChiefTransfer,
    MatureParams,
    RunStart,
    RunStop,
    WorkerHello,
    WorkerStatus,
    WorkerUpdate,
)
from protocol.mqtt import BrokerAddress, MqttConnection
from protocol.tensors import pack_arrays, unpack_arrays

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


def update(worker: str, episode: int, pi: float, grad: list[float]) -> WorkerUpdate:
    return WorkerUpdate(worker_id=worker, episode=episode, episode_return=pi, pi=pi, steps=10,
                        gradient=pack_arrays({"w": np.array(grad, np.float32)}))


def mature(worker: str, episode: int, pi: float, params: list[float]) -> MatureParams:
    return MatureParams(worker_id=worker, episode=episode, episode_return=pi, pi=pi,
                        params=pack_arrays({"w": np.array(params, np.float32)}))


def test_chief_federates_rejects_bad_input_and_reports(any_broker: str, tmp_path: Path) -> None:
    chief = start_chief(any_broker, tmp_path / "run", workers=2)
    fake = ScriptedWorkers(any_broker)
    try:
        start = fake.join("w0", "w1")
        assert start.workers == ["w0", "w1"] and start.tc == 195.0 and start.policy == "weighted"

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
        agg = fake.expect(ChiefAggregate)
        assert agg.episode == 1 and agg.weights == pytest.approx({"w0": 0.25, "w1": 0.75})
        np.testing.assert_allclose(unpack_arrays(agg.gradient)["w"], [2.5, -1.0])

        # Round 2: w1 finishes, w0 gets its actor with w_T = 97.5 / 195 = 0.5.
        fake.send("w0", update("w0", 2, 97.5, [1.0, 1.0]))
        fake.send("w1", mature("w1", 2, 196.0, [4.0, 4.0]))
        tr = fake.expect(ChiefTransfer)
        assert tr.source_worker == "w1" and tr.keep_weights == pytest.approx({"w0": 0.5})
        np.testing.assert_array_equal(unpack_arrays(tr.params)["w"], [4.0, 4.0])

        # Round 3: w0 finishes too; the run ends.
        fake.send("w0", mature("w0", 3, 199.0, [5.0, 5.0]))
        stop = fake.expect(RunStop)
        assert stop.all_solved and stop.episodes == 3
        assert chief.wait(timeout=20) == 0
    finally:
        fake.conn.stop()
        if chief.poll() is None:
            chief.kill()
    out = chief.stdout.read() if chief.stdout else ""
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["episodes_to_all_solved"] == 3
    assert [(w["id"], w["solved"], w["episodes"]) for w in summary["workers"]] == [("w0", True, 3), ("w1", True, 2)]
    assert summary["rejected_messages"] == {"malformed": 1, "version": 1, "invalid": 1, "wrong_shape": 1,
                                            "spoofed": 1}, out
    lines = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert sum(1 for x in lines if x["type"] == "episode") == 5
    assert (tmp_path / "run" / "learning_curve.png").stat().st_size > 1000


def test_chief_goes_on_without_a_silent_worker(amqtt_broker: str, tmp_path: Path) -> None:
    chief = start_chief(amqtt_broker, tmp_path / "run", workers=3, round_timeout=1.0)
    fake = ScriptedWorkers(amqtt_broker)
    try:
        fake.join("w0", "w1", "w2")
        fake.send("w0", update("w0", 1, 10.0, [1.0, 1.0]))
        fake.send("w1", update("w1", 1, 10.0, [3.0, 3.0]))  # w2 stays silent
        agg = fake.expect(ChiefAggregate, timeout=10)
        assert agg.contributors == ["w0", "w1"]
        # w1 dies: its last will (here sent by hand) takes it out of the round at once.
        fake.send("w1", WorkerStatus(worker_id="w1", state="offline"), topics.STATUS)
        fake.send("w0", update("w0", 2, 10.0, [1.0, 1.0]))
        agg2 = fake.expect(ChiefAggregate, timeout=10)
        assert agg2.episode == 2 and agg2.contributors == ["w0"]
        # The lagging w2 and the returning w1 submit for the open round, so it waits for them again.
        fake.send("w2", mature("w2", 3, 196.0, [1.0, 1.0]))
        fake.send("w1", mature("w1", 3, 197.0, [1.0, 1.0]))
        fake.send("w0", mature("w0", 3, 198.0, [1.0, 1.0]))
        assert fake.expect(RunStop, timeout=10).all_solved
        assert chief.wait(timeout=20) == 0
    finally:
        fake.conn.stop()
        if chief.poll() is None:
            chief.kill()
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["episodes_to_all_solved"] == 3
