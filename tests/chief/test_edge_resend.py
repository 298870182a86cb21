"""An edge chief (chief/edge.py) on an in-memory hub, with a scripted root and worker: when its worker sends a
round again that the edge closed, the edge passes on the root's answer (and acknowledgement) it holds, and sends the
round's partial to the root again when what the worker waits for never came (a broker lost the partial or the
answer), at most once every RESEND_GAP seconds; never when it came."""

from __future__ import annotations

import logging
import queue
import secrets
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from chief.edge import EXIT_OK, EdgeService
from chief.settings import ChiefSettings
from protocol import topics
from protocol.auth import chief_key_of, signed, worker_key
from protocol.codec import RejectCounter, decode, encode
from protocol.memory import Hub
from protocol.messages import (
    ChiefAck,
    ChiefAggregate,
    EdgePartial,
    MatureParams,
    RunStart,
    RunStop,
    WorkerHello,
    WorkerUpdate,
)
from protocol.tasks import task
from protocol.tensors import pack_arrays

RUN, EDGE, WORKER, SESSION = "edgerun", "e0", "w0", "s1"
SPEC = {"w": (2,)}
QUIET = 0.5  # seconds in which nothing more may come


@dataclass
class Scene:
    """The edge's run: the root's and the worker's ends of the hub."""

    key: bytes | None  # the run's key, as the edge holds it
    partials: queue.Queue[bytes]  # what the edge sent the root
    relayed: queue.Queue[tuple[str, bytes]]  # what the edge passed on to its worker (leaf, payload)
    hub: Hub
    rejects: RejectCounter  # the edge's

    def root(self, leaf: str, msg: RunStart | RunStop | ChiefAggregate | ChiefAck) -> None:
        self.hub.route(topics.chief(RUN, leaf), encode(signed(msg, chief_key_of(self.key))))

    def worker(self, leaf: str, msg: WorkerHello | WorkerUpdate | MatureParams, key: bytes | None = b"") -> None:
        """The worker's message, tagged with its own key (or with ``key``: None leaves it untagged)."""
        assert self.key is not None
        own = worker_key(self.key, WORKER).encode() if key == b"" else key
        self.hub.route(topics.worker(RUN, WORKER, leaf), encode(signed(msg, own)))

    def relayed_next(self, leaf: str, timeout: float = 10.0) -> bytes:
        while True:
            got, payload = self.relayed.get(timeout=timeout)
            if got == leaf:
                return payload


@pytest.fixture
def scene(tmp_path: Path) -> Iterator[Scene]:
    hub, key = Hub(), secrets.token_hex(32)
    edge = EdgeService(ChiefSettings.given(run_id=RUN, role="edge", edge_id=EDGE, round_timeout=60.0,
                                           start_timeout=30.0, run_key=key, run_dir=tmp_path), connect=hub.connect)
    codes: list[int] = []
    thread = threading.Thread(target=lambda: codes.append(edge.run()), daemon=True)
    thread.start()
    s = Scene(edge.key, queue.Queue(), queue.Queue(), hub, edge.rejects)
    spy = hub.connect("spy", None, RejectCounter(logging.getLogger("spy")))
    spy.start()
    spy.subscribe(topics.edge(RUN, EDGE, topics.PARTIAL), lambda t, p: s.partials.put(p))
    spy.subscribe(topics.relayed(RUN, EDGE, "+"), lambda t, p: s.relayed.put((t.rsplit("/", 1)[-1], p)))
    # The worker's hello before the root's RunStart (as a worker says hello until named), then the run.
    hello = WorkerHello(worker_id=WORKER, env_id="CartPole-v0", actor_spec=SPEC, edge=EDGE)
    spec = task("CartPole-v0")
    for _ in range(100):  # until the edge, starting in its thread, has subscribed
        s.worker(topics.HELLO, hello)
        s.root(topics.START, RunStart(run_id=RUN, env_id="CartPole-v0", policy="weighted", seed=1, max_episodes=50,
                                      tc=spec.tc, r_floor=spec.r_floor, workers=(WORKER,), session=SESSION,
                                      edges={WORKER: EDGE}))
        try:
            s.relayed_next(topics.START, timeout=0.1)
            break
        except queue.Empty:
            continue
    while not s.relayed.empty():
        s.relayed.get()
    yield s
    s.root(topics.STOP, RunStop(run_id=RUN, reason="over", episodes=1, all_solved=False, session=SESSION))
    thread.join(10)
    assert codes == [EXIT_OK]


def answer(r: int) -> ChiefAggregate:
    return ChiefAggregate(round=r, episode=r, gradient=pack_arrays({"w": np.ones(2, np.float32)}),
                          weights={WORKER: 1.0}, contributors=(WORKER,), session=SESSION)


def quiet(q: queue.Queue) -> bool:
    try:
        q.get(timeout=QUIET)
    except queue.Empty:
        return True
    return False


def test_an_unanswered_round_sent_again_sends_its_partial_again_and_an_answered_one_its_answer(scene: Scene) -> None:
    update = WorkerUpdate(worker_id=WORKER, episode=1, episode_return=20.0, pi=20.0, recent_returns=[20.0], steps=20,
                          gradient=pack_arrays({"w": np.array([0.5, -0.5], np.float32)}))
    scene.worker(topics.UPDATE, update)
    first = scene.partials.get(timeout=10)
    assert decode(first, EdgePartial).round == 1
    scene.worker(topics.UPDATE, update)  # no answer came: the same partial again, byte for byte
    assert scene.partials.get(timeout=10) == first
    for _ in range(3):  # more copies within RESEND_GAP (a site's workers all back at once): no further partial
        scene.worker(topics.UPDATE, update)
    assert quiet(scene.partials)
    reply = answer(1)
    scene.root(topics.AGGREGATE, reply)
    assert decode(scene.relayed_next(topics.AGGREGATE), ChiefAggregate).round == 1
    scene.worker(topics.UPDATE, update)  # answered: the worker missed it, so the edge passes it on again
    assert decode(scene.relayed_next(topics.AGGREGATE), ChiefAggregate).round == 1
    assert quiet(scene.partials)


def test_a_finisher_whose_acknowledgement_was_lost_gets_it_through_the_partial_sent_again(scene: Scene) -> None:
    for episode in range(1, 10):  # a mature actor's PI is over the last 10 episodes
        scene.worker(topics.UPDATE, WorkerUpdate(
            worker_id=WORKER, episode=episode, episode_return=200.0, pi=200.0, recent_returns=[200.0] * episode,
            steps=200, gradient=pack_arrays({"w": np.array([0.5, -0.5], np.float32)})))
        assert decode(scene.partials.get(timeout=10), EdgePartial).round == episode
        scene.root(topics.AGGREGATE, answer(episode))
        scene.relayed_next(topics.AGGREGATE)
    finish = MatureParams(worker_id=WORKER, episode=10, episode_return=200.0, pi=200.0, recent_returns=[200.0] * 10,
                          steps=200, params=pack_arrays({"w": np.array([1.0, 1.0], np.float32)}))
    scene.worker(topics.UPDATE, finish)
    first = scene.partials.get(timeout=10)
    assert [m.worker_id for m in decode(first, EdgePartial).matures] == [WORKER]
    scene.root(topics.AGGREGATE, answer(10))  # the round's answer came, its acknowledgement did not
    scene.relayed_next(topics.AGGREGATE)
    scene.worker(topics.UPDATE, finish)
    assert scene.partials.get(timeout=10) == first  # the root acknowledges a repeated mature actor again
    scene.root(topics.ACK, ChiefAck(worker_id=WORKER, round=10, episode=10, accepted=True, session=SESSION))
    scene.relayed_next(topics.ACK)
    scene.worker(topics.UPDATE, finish)  # the acknowledgement came and the worker missed it: passed on again
    assert decode(scene.relayed_next(topics.ACK), ChiefAck).accepted
    assert quiet(scene.partials)


def test_an_edge_refuses_and_counts_what_is_not_its_workers_own(scene: Scene) -> None:
    """Issue 32: an edge checks each worker's tag as the root would: an update untagged, or under another worker's
    key, makes no partial and is counted; the worker's own makes one."""
    assert scene.key is not None
    update = WorkerUpdate(worker_id=WORKER, episode=1, episode_return=20.0, pi=20.0, recent_returns=[20.0], steps=20,
                          gradient=pack_arrays({"w": np.array([0.5, -0.5], np.float32)}))
    scene.worker(topics.UPDATE, update, key=None)
    scene.worker(topics.UPDATE, update, key=worker_key(scene.key, "w9").encode())
    assert quiet(scene.partials)
    assert scene.rejects.as_dict() == {"unsigned": 1, "forged": 1}
    scene.worker(topics.UPDATE, update)
    assert decode(scene.partials.get(timeout=10), EdgePartial).round == 1


def test_an_edge_holds_an_update_beyond_reach_and_refuses_it_once_its_workers_real_rounds_came(scene: Scene
                                                                                                ) -> None:
    """chief/rounds.py's rule at an edge: an update for round 3 while round 1 is open (tagged: a worker's key
    stolen, or a run without keys) makes no partial; w0's real rounds 1-3 make theirs, and the early one is refused
    as unreachable when round 3 opens."""
    def update(episode: int, ret: float, recent: list[float]) -> WorkerUpdate:
        return WorkerUpdate(worker_id=WORKER, episode=episode, episode_return=ret, pi=sum(recent) / len(recent),
                            recent_returns=recent, steps=20, gradient=pack_arrays({"w": np.ones(2, np.float32)}))

    scene.worker(topics.UPDATE, update(3, 50.0, [50.0]))
    assert quiet(scene.partials)
    for episode in (1, 2, 3):
        scene.worker(topics.UPDATE, update(episode, 20.0, [20.0] * episode))
        partial = decode(scene.partials.get(timeout=10), EdgePartial)
        assert partial.round == episode and partial.contributions[0].episode_return == 20.0
    assert scene.rejects.as_dict() == {"unreachable": 1}
