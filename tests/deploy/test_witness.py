"""The witness of a tiered run (deploy/witness.py) records its own gaps: where its connection came back without the
broker holding its session, what was published meanwhile may never have reached it. The rule (``gaps``) on given
sequences; the witness on real brokers (the embedded amqtt and Mosquitto, free loopback ports) killed and started
again empty while messages are sent."""

from __future__ import annotations

import socket
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from deploy.witness import Link, Witness, gaps
from protocol import topics
from protocol.codec import encode
from protocol.memory import Hub
from protocol.messages import ChiefAggregate, Message, WorkerUpdate
from protocol.mqtt import BrokerAddress, MqttConnection
from protocol.tensors import pack_arrays
from protocol.transport import connector
from runtime.records import ROOT, WitnessGap, gradient_key, read_gradients
from services.broker.embedded import free_port, start_broker_process, stop_process
from tests.conftest import HOST, mosquitto_available, start_mosquitto

RUN = "wit"
FIRST, NEW, KEPT = Link(1, False), Link(2, False), Link(2, True)


# -- the rule ------------------------------------------------------------------------------------------------------


def test_a_connection_that_never_came_back_leaves_no_gap() -> None:
    seen = [((1, 0), FIRST), ((1, 0), FIRST), ((2, 0), FIRST)]
    assert gaps(seen, FIRST, FIRST) == []
    assert gaps([], FIRST, FIRST) == []


def test_a_reconnect_without_the_session_is_a_gap_between_the_messages_around_it() -> None:
    seen = [((1, 0), FIRST), ((2, 0), FIRST), ((3, 0), NEW), ((4, 0), NEW)]
    assert gaps(seen, FIRST, NEW) == [WitnessGap((2, 0), (3, 0))]
    assert gaps([((1, 1), FIRST), ((1, 2), NEW)], FIRST, NEW) == [WitnessGap((1, 1), (1, 2))]  # places, not rounds


def test_a_reconnect_that_found_its_session_is_no_gap() -> None:
    assert gaps([((1, 0), FIRST), ((2, 0), KEPT)], FIRST, KEPT) == []


def test_two_reconnects_between_messages_are_a_gap_even_if_the_last_found_its_session() -> None:
    """Only the last connect's session is known: an earlier one may have come back empty."""
    assert gaps([((1, 0), FIRST), ((2, 0), Link(3, True))], FIRST, Link(3, True)) == [WitnessGap((1, 0), (2, 0))]


def test_gaps_before_the_first_message_and_after_the_last_are_open() -> None:
    assert gaps([((3, 0), NEW)], FIRST, NEW) == [WitnessGap(None, (3, 0))]
    assert gaps([((3, 0), FIRST)], FIRST, NEW) == [WitnessGap((3, 0), None)]
    assert gaps([((3, 0), FIRST)], FIRST, None) == [WitnessGap((3, 0), None)]  # down when it stopped
    assert gaps([], FIRST, NEW) == [WitnessGap(None, None)]
    assert gaps([((1, 0), FIRST), ((2, 0), NEW), ((5, 0), Link(3, False))], FIRST, Link(4, False)) == [
        WitnessGap((1, 0), (2, 0)), WitnessGap((2, 0), (5, 0)), WitnessGap((5, 0), None)]


def test_a_connection_counted_before_it_subscribed_is_its_start() -> None:
    """A witness subscribed on its second connect (any session) has no gap for the first."""
    assert gaps([((1, 0), NEW)], NEW, NEW) == []


# -- the witness over real brokers -------------------------------------------------------------------------------


class Broker:
    """A broker on a fixed free port that can be killed (SIGKILL) and started again empty on the same port."""

    def __init__(self, folder: Path, start: Callable[[Path, int], subprocess.Popen]) -> None:
        self.folder, self._start, self.port = folder, start, free_port(HOST)
        self.proc = start(folder, self.port)

    @property
    def url(self) -> str:
        return f"mqtt://{HOST}:{self.port}"

    def restart_empty(self) -> None:
        self.proc.kill()
        self.proc.wait()
        self.proc = self._start(self.folder, self.port)


def _amqtt(folder: Path, port: int) -> subprocess.Popen:
    with (folder / "amqtt.log").open("ab") as log:
        return start_broker_process(HOST, port, stdout=log, stderr=subprocess.STDOUT)[0]


def _mosquitto(folder: Path, port: int) -> subprocess.Popen:
    if not mosquitto_available():
        pytest.skip("mosquitto is not installed (apt-get install mosquitto)")
    return start_mosquitto(folder, port)[0]  # no persistence: a restart is empty


@pytest.fixture(params=[_amqtt, _mosquitto], ids=["amqtt", "mosquitto"])
def broker(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Broker]:
    b = Broker(tmp_path, request.param)
    try:
        yield b
    finally:
        stop_process(b.proc)


def update(worker: str, episode: int) -> WorkerUpdate:
    return WorkerUpdate(worker_id=worker, episode=episode, episode_return=20.0, pi=20.0, recent_returns=(20.0,),
                        steps=20, gradient=pack_arrays({"g": np.full(2, episode, np.float32)}))


def aggregate(episode: int) -> ChiefAggregate:
    return ChiefAggregate(round=episode, episode=episode, gradient=pack_arrays({"g": np.ones(2, np.float32)}),
                          weights={"w0": 1.0}, contributors=("w0",))


def send_round(conn: MqttConnection, episode: int) -> None:
    """w0's update and the root's aggregate of round ``episode`` (episode, step 0)."""
    sent: list[tuple[str, Message]] = [(topics.worker(RUN, "w0", topics.UPDATE), update("w0", episode)),
                                       (topics.chief(RUN, topics.AGGREGATE), aggregate(episode))]
    for topic, msg in sent:
        conn.publish(topic, encode(msg)).wait_for_publish(5)


def witnessed(witness: Witness, episode: int) -> set[str]:
    """Whose tensors of round ``episode`` the witness holds (w0 and/or ROOT)."""
    with witness._lock:
        return {who for who in ("w0", ROOT) if gradient_key(episode, 0, who, "g") in witness.tensors}


def wait_for(witness: Witness, episode: int, publisher: MqttConnection | None = None, timeout: float = 20) -> None:
    """Until the witness holds both tensors of round ``episode``, sending the round again every 0.2 s when given a
    publisher (as workers and the root send again what went unanswered)."""
    deadline = time.monotonic() + timeout
    while witnessed(witness, episode) != {"w0", ROOT}:
        assert time.monotonic() < deadline, f"the witness never got round {episode}"
        if publisher is not None:
            send_round(publisher, episode)
        time.sleep(0.2)


def test_a_witness_whose_broker_came_back_empty_records_the_gap(broker: Broker, tmp_path: Path) -> None:
    """Rounds 1-3 witnessed (each sent until it was); the broker is killed and started again empty; round 4 is
    sent at once by a new publisher, before the witness is subscribed again (lost, in every run looked at); round 5
    until the witness has it. The saved GRADIENTS record one gap, from round 3 to the first round witnessed after,
    and every round the witness lacks lies in it."""
    publisher = MqttConnection(BrokerAddress.parse(broker.url), "publisher").start()
    witness = Witness(connector(broker.url), RUN, tmp_path)
    try:
        for episode in (1, 2, 3):
            wait_for(witness, episode, publisher)  # sent again until the witness's subscriptions are in place
        publisher.stop()
        broker.restart_empty()
        publisher = MqttConnection(BrokerAddress.parse(broker.url), "publisher").start()
        send_round(publisher, 4)
        deadline = time.monotonic() + 30
        while not (witness.conn.connected.is_set() and witness.conn.connects == 2):
            assert time.monotonic() < deadline, "the witness did not connect again"
            time.sleep(0.05)
        wait_for(witness, 5, publisher)
    finally:
        publisher.stop()
    tensors, saved = read_gradients(witness.save())
    first_after = (4, 0) if witnessed(witness, 4) else (5, 0)
    assert saved == [WitnessGap((3, 0), first_after)]
    missing = [(e, 0) for e in range(1, 6) if not any(k.startswith(f"e{e}s0/") for k in tensors)]
    assert all(saved[0].covers(place) for place in missing), (missing, saved)


def test_a_witness_whose_broker_stayed_up_records_no_gap(broker: Broker, tmp_path: Path) -> None:
    publisher = MqttConnection(BrokerAddress.parse(broker.url), "publisher").start()
    witness = Witness(connector(broker.url), RUN, tmp_path)
    try:
        for episode in (1, 2, 3):
            wait_for(witness, episode, publisher)
    finally:
        publisher.stop()
    tensors, saved = read_gradients(witness.save())
    assert saved == [] and len(tensors) == 6


# amqtt 0.12 keeps no messages for an anonymous client while it is away (its broker.py), and yet says it held the
# session: Mosquitto only (the launcher's embedded amqtt has every process log in).
@pytest.mark.parametrize("broker", [_mosquitto], ids=["mosquitto"], indirect=True)
def test_a_witness_whose_connection_came_back_to_its_session_records_no_gap(broker: Broker, tmp_path: Path) -> None:
    """The witness's own connection breaks, the broker stays up and keeps its session: what was sent meanwhile is
    queued for it and arrives; no gap."""
    publisher = MqttConnection(BrokerAddress.parse(broker.url), "publisher").start()
    witness = Witness(connector(broker.url), RUN, tmp_path)
    try:
        wait_for(witness, 1, publisher)
        assert isinstance(witness.conn, MqttConnection)
        sock = witness.conn._client.socket()
        assert isinstance(sock, socket.socket)
        sock.shutdown(socket.SHUT_RDWR)  # its end of the connection only
        send_round(publisher, 2)
        wait_for(witness, 2)
        send_round(publisher, 3)
        wait_for(witness, 3)
    finally:
        publisher.stop()
    assert witness.conn.connects == 2 and witness.conn.session_present
    tensors, saved = read_gradients(witness.save())
    assert saved == [] and len(tensors) == 6


def test_a_witness_in_process_records_no_gap(tmp_path: Path) -> None:
    """Over the in-memory hub (deploy.inprocess) nothing is lost and nothing reconnects."""
    hub = Hub()
    publisher = hub.connect("publisher").start()
    witness = Witness(hub.connect, RUN, tmp_path)
    publisher.publish(topics.worker(RUN, "w0", topics.UPDATE), encode(update("w0", 1)))
    publisher.publish(topics.chief(RUN, topics.AGGREGATE), encode(aggregate(1)))
    deadline = time.monotonic() + 5
    while witnessed(witness, 1) != {"w0", ROOT}:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    tensors, saved = read_gradients(witness.save())
    assert saved == [] and sorted(tensors) == [gradient_key(1, 0, ROOT, "g"), gradient_key(1, 0, "w0", "g")]
