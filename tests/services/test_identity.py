"""Identity and transport limits against real brokers: unguessable client ids, the embedded broker's per-run users
and ACL, its packet limit, retained leftovers ignored, and chunked messages under a 128 KB broker cap."""

from __future__ import annotations

import queue
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import msgpack
import pytest

from protocol import topics
from protocol.codec import MAX_PAYLOAD_BYTES, RejectCounter, encode
from protocol.messages import Chunk, RunStop
from protocol.mqtt import BrokerAddress, MqttConnection, split
from services.broker.embedded import MAX_PACKET_SIZE, Credentials, make_credentials, start_broker_process, stop_process
from tests.conftest import HOST, mosquitto_available, start_mosquitto

RUN = "ident"


@pytest.fixture
def secured(tmp_path: Path) -> Iterator[tuple[str, Credentials]]:
    """An embedded broker with the users and ACL `make run` gives a run of two workers."""
    creds = make_credentials(tmp_path / "broker", RUN, ["w0", "w1"])
    log = (tmp_path / "broker.log").open("wb")
    proc, port = start_broker_process(HOST, credentials=creds, stdout=log, stderr=subprocess.STDOUT)
    try:
        yield f"mqtt://{HOST}:{port}", creds
    finally:
        stop_process(proc)
        log.close()


def connect(url: str, creds: Credentials | None, user: str | None, name: str = "probe") -> MqttConnection:
    address = BrokerAddress.parse(url, username=user, password=creds.users[user] if creds and user else None)
    return MqttConnection(address, client_id=name).start(timeout=5)


def test_client_ids_have_an_unguessable_part() -> None:
    a = MqttConnection(BrokerAddress.parse("mqtt://127.0.0.1:9"), client_id="fedrl-r-chief")
    b = MqttConnection(BrokerAddress.parse("mqtt://127.0.0.1:9"), client_id="fedrl-r-chief")
    assert a.client_id.startswith("fedrl-r-chief-") and a.client_id != b.client_id
    assert len(a.client_id) - len("fedrl-r-chief-") == 12


def test_only_the_runs_users_connect(secured: tuple[str, Credentials]) -> None:
    url, creds = secured
    with pytest.raises(ConnectionError):
        connect(url, None, None)  # anonymous
    with pytest.raises(ConnectionError):
        MqttConnection(BrokerAddress.parse(url, username="chief", password="guess"), client_id="x").start(timeout=3)
    connect(url, creds, "chief").stop()
    assert (creds.password_file.stat().st_mode & 0o777) == 0o600 and "$argon2" in creds.password_file.read_text()


def test_a_worker_cannot_publish_as_the_chief(secured: tuple[str, Credentials]) -> None:
    url, creds = secured
    got: queue.Queue = queue.Queue()
    w1 = connect(url, creds, "w1", "w1")
    w1.subscribe(topics.chief(RUN, "+"), lambda t, p: got.put((t, p)))
    w0 = connect(url, creds, "w0", "w0")
    chief = connect(url, creds, "chief", "chief")
    try:
        time.sleep(0.3)
        stop = encode(RunStop(run_id=RUN, reason="fake", episodes=0, all_solved=False))
        w0.publish(topics.chief(RUN, topics.STOP), stop).wait_for_publish(5)  # denied by the ACL
        w0.publish(topics.worker(RUN, "w1", topics.UPDATE), b"x").wait_for_publish(5)  # another worker's topic
        chief.publish(topics.chief(RUN, topics.STOP), stop).wait_for_publish(5)  # the chief may
        topic, _ = got.get(timeout=5)
        assert topic == topics.chief(RUN, topics.STOP)
        with pytest.raises(queue.Empty):
            got.get(timeout=1)  # nothing else reached the worker
    finally:
        for c in (w0, w1, chief):
            c.stop()


def test_the_embedded_broker_closes_a_connection_that_sends_too_much(secured: tuple[str, Credentials]) -> None:
    url, creds = secured
    got: queue.Queue = queue.Queue()
    watcher = connect(url, creds, "chief", "watcher")
    watcher.subscribe(topics.worker(RUN, "w0", "#"), lambda t, p: got.put(len(p)))
    sender = connect(url, creds, "w0", "sender")
    try:
        time.sleep(0.3)
        sender.publish(topics.worker(RUN, "w0", topics.UPDATE), b"x" * 1000).wait_for_publish(5)
        assert got.get(timeout=5) == 1000
        sender._client.reconnect_delay_set(min_delay=30, max_delay=30)  # stay away once the broker hangs up
        sender.publish(topics.worker(RUN, "w0", topics.UPDATE), b"x" * (MAX_PACKET_SIZE + 1))
        deadline = time.monotonic() + 10
        while sender.connected.is_set() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not sender.connected.is_set()  # the broker hung up on the oversized packet
        with pytest.raises(queue.Empty):
            got.get(timeout=1)
    finally:
        sender.stop()
        watcher.stop()


def test_retained_leftovers_are_never_acted_on(amqtt_broker: str) -> None:
    leftover = encode(RunStop(run_id=RUN, reason="left over", episodes=0, all_solved=False))
    old = connect(amqtt_broker, None, None, "old-run")
    old.publish(topics.chief(RUN, topics.STOP), leftover, retain=True).wait_for_publish(5)
    old.stop()
    got: queue.Queue = queue.Queue()
    rejects = RejectCounter(__import__("logging").getLogger("test"))
    fresh = MqttConnection(BrokerAddress.parse(amqtt_broker), client_id="fresh", rejects=rejects).start()
    try:
        fresh.subscribe(topics.chief(RUN, "+"), lambda t, p: got.put(p))
        with pytest.raises(queue.Empty):
            got.get(timeout=1.5)
        assert rejects.as_dict() == {"retained": 1}
    finally:
        fresh.stop()


def test_chunks_rejoin_and_bad_ones_are_counted(amqtt_broker: str) -> None:
    got: queue.Queue = queue.Queue()
    rejects = RejectCounter(__import__("logging").getLogger("test"))
    rx = MqttConnection(BrokerAddress.parse(amqtt_broker), client_id="rx", rejects=rejects).start()
    tx = MqttConnection(BrokerAddress.parse(amqtt_broker), client_id="tx", max_payload=128 * 1024).start()
    try:
        rx.subscribe("t/#", lambda t, p: got.put(p))
        time.sleep(0.2)
        big = bytes(range(256)) * 1200  # 300 KB: three chunks
        tx.publish("t/big", big).wait_for_publish(5)
        assert got.get(timeout=5) == big
        small = b"small"
        tx.publish("t/small", small).wait_for_publish(5)
        assert got.get(timeout=5) == small
        # Lies: a chunk announcing more than the codec's limit, and chunks that disagree on their count.
        raw = msgpack.unpackb(split(big, 128 * 1024)[0], raw=False)
        liar = encode(Chunk(id="00aa11bb22cc33dd", index=0, count=2, total=MAX_PAYLOAD_BYTES + 1, data=b"x"))
        tx._client.publish("t/liar", liar, qos=1).wait_for_publish(5)
        first = encode(Chunk(id="ffeeddcc", index=0, count=2, total=4, data=b"ab"))
        other = encode(Chunk(id="ffeeddcc", index=1, count=3, total=4, data=b"cd"))
        tx._client.publish("t/mixed", first, qos=1).wait_for_publish(5)
        tx._client.publish("t/mixed", other, qos=1).wait_for_publish(5)
        time.sleep(0.5)
        assert got.empty() and rejects.as_dict() == {"bad_chunk": 2} and raw["kind"] == "chunk"
    finally:
        rx.stop()
        tx.stop()


@pytest.mark.skipif(not mosquitto_available(), reason="mosquitto is not installed (apt-get install mosquitto)")
def test_a_gradient_fits_a_128_kb_broker_cap_only_in_chunks(tmp_path: Path) -> None:
    """Mosquitto with AWS IoT Core's 128 KB cap refuses the 140 KB gradient whole, and carries it in chunks."""
    import numpy as np

    from protocol.messages import WorkerUpdate
    from protocol.tensors import pack_arrays
    from worker.episode import build_learner_and_env

    _, learner = build_learner_and_env("CartPole-v0", seed=0, device_noise=0.0)
    gradient = {k: np.ones_like(v) for k, v in learner.actor_parameters().items()}
    payload = encode(WorkerUpdate(worker_id="w0", episode=1, episode_return=1.0, pi=1.0, recent_returns=(1.0,),
                                  steps=1, gradient=pack_arrays(gradient)))
    assert len(payload) > 128 * 1024
    proc, port = start_mosquitto(tmp_path, max_packet_size=128 * 1024)
    url = f"mqtt://{HOST}:{port}"
    got: queue.Queue = queue.Queue()
    try:
        rx = MqttConnection(BrokerAddress.parse(url), client_id="rx").start()
        rx.subscribe("fedrl/#", lambda t, p: got.put(p))
        whole = MqttConnection(BrokerAddress.parse(url), client_id="whole").start()
        chunked = MqttConnection(BrokerAddress.parse(url), client_id="chunked", max_payload=128 * 1024).start()
        time.sleep(0.3)
        whole.publish(topics.worker(RUN, "w0", topics.UPDATE), payload)
        with pytest.raises(queue.Empty):
            got.get(timeout=1.5)  # the broker refused it
        chunked.publish(topics.worker(RUN, "w0", topics.UPDATE), payload).wait_for_publish(5)
        assert got.get(timeout=5) == payload
        for c in (rx, whole, chunked):
            c.stop()
    finally:
        stop_process(proc)
