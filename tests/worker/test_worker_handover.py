"""The worker's answers from the chief over a real broker: a mature actor that is lost is sent again until the chief
acknowledges it; a refusal is reported back; another worker's acknowledgement is not taken for its own; answers are
filed by the round they carry, and one whose round is not its episode and step is rejected and counted."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from protocol import topics
from protocol.codec import decode, encode
from protocol.messages import ChiefAck, ChiefAggregate, ChiefTransfer, MatureParams, RunStart
from protocol.mqtt import BrokerAddress, MqttConnection
from protocol.routes import route_of
from protocol.tensors import pack_arrays
from worker.service import WorkerService
from worker.settings import WorkerSettings

RUN = "handover"


def mature(episode: int = 12) -> MatureParams:
    return MatureParams(worker_id="w0", episode=episode, episode_return=200.0, pi=200.0, recent_returns=[200.0] * 10,
                        steps=200, params=pack_arrays({"w": np.ones(2, np.float32)}))


class ScriptedChief:
    """Drops the first ``drop`` MatureParams it receives (as a broker restart would), then answers ``accept``."""

    def __init__(self, broker: str, drop: int, accept: bool) -> None:
        self.received: list[int] = []
        self.drop, self.accept = drop, accept
        self.lock = threading.Lock()
        self.conn = MqttConnection(BrokerAddress.parse(broker), client_id="scripted-chief").start()
        self.conn.subscribe(route_of(topics.worker(RUN, "w0", topics.UPDATE)).filter(run=RUN), self._on_update)

    def _on_update(self, topic: str, payload: bytes) -> None:
        msg = decode(payload, MatureParams)
        with self.lock:
            self.received.append(msg.episode)
            if len(self.received) <= self.drop:
                return
        # Another worker's acknowledgement first: it must not end w0's wait.
        self.conn.publish(topics.chief(RUN, topics.ACK), encode(ChiefAck(worker_id="w9", round=msg.episode,
                                                                         episode=msg.episode, accepted=True)))
        self.conn.publish(topics.chief(RUN, topics.ACK), encode(ChiefAck(
            worker_id=msg.worker_id, round=msg.episode, episode=msg.episode, accepted=self.accept,
            reason="" if self.accept else "not_mature: PI 10 over 1 episodes")))


def worker(broker: str) -> WorkerService:
    svc = WorkerService(WorkerSettings.given(broker=broker, run_id=RUN, worker_id="w0", ack_timeout=30))
    svc.conn.start()
    svc.conn.subscribe(topics.chief(RUN, "+"), svc._on_chief)
    return svc


@pytest.mark.parametrize(("drop", "accept", "received"), [
    (1, True, [12, 12]),  # the first copy was lost (as in a broker restart), the second acknowledged
    (0, False, [12]),  # refused, with the reason
])
def test_the_mature_actor_is_sent_until_the_chief_answers(amqtt_broker: str, drop: int, accept: bool,
                                                            received: list[int]) -> None:
    chief = ScriptedChief(amqtt_broker, drop=drop, accept=accept)
    svc = worker(amqtt_broker)
    try:
        ack = svc._hand_over(mature())
    finally:
        svc.conn.stop()
        chief.conn.stop()
    assert ack is not None and ack.worker_id == "w0" and ack.episode == 12 and ack.accepted == accept
    assert accept or "not_mature" in ack.reason
    assert chief.received == received


def test_answers_are_filed_by_their_round_and_a_wrong_round_is_rejected(amqtt_broker: str) -> None:
    """Under K = 3 rounds per episode, round (episode 2, step 1) is round 5: an answer saying so is filed as round 5;
    an answer whose round disagrees with its episode and step (a transfer or an acknowledgement answers step 0) is
    counted as ``wrong_round`` and never filed, so it cannot be applied as another round's answer."""
    chief = MqttConnection(BrokerAddress.parse(amqtt_broker), client_id="scripted-chief").start()
    svc = worker(amqtt_broker)
    svc.start = RunStart(run_id=RUN, env_id="CartPole-v0", policy="sync", seed=1, max_episodes=10, tc=195.0,
                         r_floor=0.0, workers=["w0"], rounds_per_episode=3)
    svc.submitted = 5  # it has submitted up to round 5 (an answer to a later round is refused: test_chief_trust.py)
    gradient = pack_arrays({"w": np.ones(2, np.float32)})
    answers = [
        ChiefAggregate(round=5, episode=2, step=1, gradient=gradient, weights={"w0": 1.0}, contributors=["w0"]),
        ChiefAggregate(round=2, episode=2, step=1, gradient=gradient, weights={"w0": 1.0}, contributors=["w0"]),
        ChiefTransfer(round=5, episode=2, source_worker="w1", source_pi=196.0, params=gradient,
                      keep_weights={"w0": 0.5}, finished=["w1"]),
        ChiefAck(worker_id="w0", round=2, episode=2, accepted=True),
        ChiefAck(worker_id="w0", round=4, episode=2, accepted=True),
    ]
    try:
        deadline = time.monotonic() + 10
        while svc.inbox.empty() and time.monotonic() < deadline:  # the worker's subscription is in place
            chief.publish(topics.chief(RUN, topics.START), encode(svc.start), qos=1)
            time.sleep(0.2)
        while not svc.inbox.empty():
            svc.inbox.get()
        for msg in answers:
            chief.publish(topics.chief(RUN, msg.kind), encode(msg), qos=1)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and len(svc.replies) + len(svc.acks) + svc.rejects.total < len(answers):
            svc._receive(timeout=0.5)
    finally:
        svc.conn.stop()
        chief.stop()
    assert sorted(svc.replies) == [5] and svc.replies[5] == answers[0] and sorted(svc.acks) == [4]
    assert svc.rejects.as_dict() == {"wrong_round": 3}


def test_answers_sent_again_are_ignored_counted_and_logged_once_per_round(caplog: pytest.LogCaptureFixture) -> None:
    """A chief answers every resent submission of a round it closed, and a broker may redeliver: the worker applies
    a round's answer once, counts each copy it ignores, logs the first copy of each round with its reason (not one
    line per copy), and its last word reports the counts."""
    from protocol.memory import Hub

    svc = WorkerService(WorkerSettings.given(run_id=RUN, worker_id="w0"), connect=Hub().connect)
    svc.start = RunStart(run_id=RUN, env_id="CartPole-v0", policy="weighted", seed=1, max_episodes=10, tc=195.0,
                         r_floor=0.0, workers=["w0"])
    svc.submitted = 2
    gradient = pack_arrays({"w": np.ones(2, np.float32)})
    answer = {n: ChiefAggregate(round=n, episode=n, gradient=gradient, weights={"w0": 1.0}, contributors=["w0"])
              for n in (1, 2)}
    topic = topics.chief(RUN, topics.AGGREGATE)
    caplog.set_level("INFO", logger="worker")
    for n in (1, 1, 1):  # filed, then twice ignored before it was applied
        svc.inbox.put((topic, answer[n]))
        svc._receive(timeout=0.1)
    svc.answered.add(1)
    svc.replies.pop(1)
    for n in (1, 1, 2, 2, 2):  # applied: ignored; round 2: filed, then ignored
        svc.inbox.put((topic, answer[n]))
        svc._receive(timeout=0.1)
    assert sorted(svc.replies) == [2] and svc.duplicates == 2 + 2 + 2 and svc.rejects.total == 0
    lines = [r.getMessage() for r in caplog.records if "sent again" in r.getMessage()]
    assert len(lines) == 2 and "round 1's aggregate" in lines[0] and "already received" in lines[0]
    assert "round 2's aggregate" in lines[1] and "[ignored so far: 5]" in lines[1]
    svc._report_counts()
    assert "6 repeated answers ignored" in caplog.records[-1].getMessage()
