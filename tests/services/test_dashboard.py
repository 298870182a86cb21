"""The live dashboard: the pure RunView, the feed's decoding and rejects, the hub's fan-out, and the HTTP/SSE server
against a real broker (no browser; tests/services/test_dashboard_browser.py drives Chromium)."""

from __future__ import annotations

import http.client
import json
import queue
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import msgpack
import numpy as np
import pytest

from protocol import topics
from protocol.auth import chief_key_of, signed, worker_key
from protocol.codec import encode
from protocol.messages import (
    ChiefAggregate,
    ChiefTransfer,
    EdgePartial,
    MatureParams,
    QubeAction,
    QubeState,
    QubeStatus,
    QubeTelemetry,
    RunStart,
    RunStop,
    WorkerHello,
    WorkerStatus,
    WorkerUpdate,
)
from protocol.mqtt import BrokerAddress, MqttConnection
from protocol.rounds import RoundShape
from protocol.tensors import pack_arrays
from protocol.transport import connector
from services.dashboard.feed import MqttFeed, subscriptions
from services.dashboard.hub import Hub
from services.dashboard.service import DashboardConfig, DashboardService
from services.dashboard.view import NO_TELEMETRY, NO_TRANSFER, NO_TRANSFER_YET, SOLVED_WITHOUT_TRANSFER, RunView

RUN = "dash1"
BIG = {"w": np.ones((256, 256), np.float32)}  # a 256 KiB tensor: must never end up in the view


def start(workers: list[str], run_id: str = RUN) -> RunStart:
    return RunStart(run_id=run_id, env_id="CartPole-v0", policy="weighted", seed=1, max_episodes=100, tc=195.0,
                    r_floor=0.0, workers=workers)


def update(worker: str, episode: int, pi: float, ret: float | None = None) -> WorkerUpdate:
    value = pi if ret is None else ret
    return WorkerUpdate(worker_id=worker, episode=episode, episode_return=value, pi=pi, recent_returns=(value,),
                        steps=20, gradient=pack_arrays(BIG))


def mature(worker: str, episode: int, pi: float) -> MatureParams:
    return MatureParams(worker_id=worker, episode=episode, episode_return=pi, pi=pi, recent_returns=(pi,) * 10,
                        params=pack_arrays(BIG))


def aggregate(episode: int, weights: dict[str, float], step: int = 0, k: int = 1) -> ChiefAggregate:
    """The answer to step ``step`` of ``episode`` in a run of ``k`` rounds per episode."""
    return ChiefAggregate(round=RoundShape(per_episode=k).number(episode, step), episode=episode, step=step,
                          gradient=pack_arrays(BIG), weights=weights, contributors=sorted(weights))


def feed(view: RunView, *messages: Any, t: float = 100.0) -> list[dict]:
    events: list[dict] = []
    for i, msg in enumerate(messages):
        events += view.apply("t", msg, t + i)
    return events


def workers_of(view: RunView) -> dict[str, dict]:
    return {w["id"]: w for w in view.snapshot()["workers"]}


# -- RunView ---------------------------------------------------------------------------------------------------


def test_view_follows_a_run_from_hello_to_stop() -> None:
    view = RunView(RUN)
    events = feed(view, WorkerHello(worker_id="w0", env_id="CartPole-v0", actor_spec={"w": (2,)}, host="h0"))
    assert view.snapshot()["run"]["phase"] == "waiting" and view.snapshot()["run"]["env"] == "CartPole-v0"
    assert any(e["type"] == "worker" and e["id"] == "w0" and e["state"] == "waiting" for e in events)

    events = feed(view, start(["w0", "w1"]))
    run = view.snapshot()["run"]
    assert (run["phase"], run["tc"], run["policy"], run["workers"], run["round"]) == (
        "running", 195.0, "weighted", ["w0", "w1"], 1)
    assert (run["round_label"], run["no_transfer"]) == ("open round", NO_TRANSFER_YET)
    assert {w["id"]: w["state"] for w in workers_of(view).values()} == {"w0": "training", "w1": "training"}

    events = feed(view, update("w0", 1, 10.0, 12.0), update("w1", 1, 30.0))
    assert {"type": "point", "worker": "w0", "point": [1, 10.0, 12.0]} in events
    events = feed(view, aggregate(1, {"w0": 0.25, "w1": 0.75}))
    rounds = view.snapshot()["rounds"]
    assert rounds[-1]["weights"] == {"w0": 0.25, "w1": 0.75} and rounds[-1]["shared"]
    assert workers_of(view)["w1"]["weight"] == 0.75 and view.snapshot()["run"]["round"] == 2

    # Round 2 closes without w1: it is lagging until it submits for the open round.
    feed(view, update("w0", 2, 20.0), aggregate(2, {"w0": 1.0}))
    assert workers_of(view)["w1"]["state"] == "lagging" and workers_of(view)["w0"]["state"] == "training"
    feed(view, update("w1", 2, 40.0))
    assert workers_of(view)["w1"]["state"] == "training"

    # w1 finishes at round 3; w0 gets its actor with keep weight 0.1.
    feed(view, update("w0", 3, 19.5), mature("w1", 3, 196.0),
         ChiefTransfer(round=3, episode=3, source_worker="w1", source_pi=196.0, params=pack_arrays(BIG),
                       keep_weights={"w0": 0.1}, finished=["w1"]))
    snap = view.snapshot()
    assert snap["transfers"][-1]["source"] == "w1" and snap["transfers"][-1]["keep_weights"] == {"w0": 0.1}
    assert workers_of(view)["w0"]["keep"] == 0.1
    assert workers_of(view)["w1"]["state"] == "finished" and workers_of(view)["w1"]["solved_episode"] == 3
    assert snap["run"]["solved"] == [{"worker": "w1", "episode": 3}] and snap["run"]["transfers"] == 1

    feed(view, RunStop(run_id=RUN, reason="episode limit", episodes=3, all_solved=False))
    snap = view.snapshot()
    assert snap["run"]["phase"] == "stopped" and snap["run"]["stop"]["reason"] == "episode limit"
    assert (snap["run"]["round_label"], snap["run"]["rounds"]) == ("rounds", 3)  # no open round once it is over
    assert workers_of(view)["w0"]["state"] == "stopped" and workers_of(view)["w1"]["state"] == "finished"
    assert [p[0] for p in workers_of(view)["w0"]["curve"]] == [1, 2, 3]


def test_view_numbers_the_rounds_of_a_per_step_strategy() -> None:
    """Under ``sync`` (K = 3 rounds per episode) a round is one mini-batch step: the page numbers the rounds as the
    chief does (1..3 in episode 1, 4..6 in episode 2), with their episode and step; the open round's episode is
    shown, and a worker is lagging only when it is behind the last round's episode without taking part in it."""
    view = RunView(RUN)
    feed(view, start(["w0", "w1"]).model_copy(update={"policy": "sync", "rounds_per_episode": 3}))
    for step in range(3):
        feed(view, update("w0", 1, 10.0), update("w1", 1, 20.0), aggregate(1, {"w0": 0.5, "w1": 0.5}, step, k=3))
    snap = view.snapshot()
    assert [(r["round"], r["episode"], r["step"]) for r in snap["rounds"]] == [(1, 1, 0), (2, 1, 1), (3, 1, 2)]
    assert (snap["run"]["round"], snap["run"]["episode"], snap["run"]["rounds"]) == (4, 2, 3)
    assert {w["state"] for w in snap["workers"]} == {"training"}  # both took part in the last round

    feed(view, update("w0", 2, 15.0), aggregate(2, {"w0": 1.0}, 0, k=3))  # round 4 closes without w1
    assert workers_of(view)["w1"]["state"] == "lagging" and workers_of(view)["w0"]["state"] == "training"
    feed(view, update("w1", 2, 25.0), aggregate(2, {"w0": 0.5, "w1": 0.5}, 1, k=3))
    snap = view.snapshot()
    assert workers_of(view)["w1"]["state"] == "training"
    assert (snap["rounds"][-1]["round"], snap["run"]["round"], snap["run"]["episode"]) == (5, 6, 2)


def test_view_keeps_no_tensors() -> None:
    view = RunView(RUN)
    feed(view, start(["w0"]), *[update("w0", e, float(e)) for e in range(1, 51)], aggregate(1, {"w0": 1.0}),
         mature("w0", 51, 200.0))
    text = json.dumps(view.snapshot(), allow_nan=False)
    assert len(text) < 10_000, "gradients or actors were kept"

    def no_bytes(obj: Any) -> None:
        assert not isinstance(obj, (bytes, np.ndarray))
        for child in obj.values() if isinstance(obj, dict) else obj if isinstance(obj, list) else []:
            no_bytes(child)

    no_bytes(view.snapshot())


def test_view_worker_states_from_status_messages() -> None:
    view = RunView(RUN)
    feed(view, start(["w0", "w1", "w2"]), WorkerStatus(worker_id="w0", state="offline", detail="connection lost"),
         WorkerStatus(worker_id="w1", state="error", detail="RuntimeError: boom"),
         WorkerStatus(worker_id="w2", state="finished", episode=7, pi=199.0))
    w = workers_of(view)
    assert (w["w0"]["state"], w["w0"]["detail"]) == ("offline", "connection lost")
    assert w["w1"]["state"] == "error" and w["w2"]["state"] == "finished" and w["w2"]["solved_episode"] == 7
    feed(view, update("w0", 3, 5.0))  # back from the dead
    assert workers_of(view)["w0"]["state"] == "training"


def test_view_a_refused_finish_goes_back_to_training() -> None:
    view = RunView(RUN)
    feed(view, start(["w0", "w1"]), mature("w0", 12, 196.0))
    assert workers_of(view)["w0"]["state"] == "finished"
    # The chief's refusal (a newer message kind; duck-typed here) or a later update both mean it goes on learning.
    feed(view, SimpleNamespace(kind="ack", worker_id="w0", episode=12, accepted=False, reason="PI does not match"))
    assert workers_of(view)["w0"]["state"] == "training" and workers_of(view)["w0"]["solved_episode"] is None
    feed(view, mature("w1", 12, 196.0), update("w1", 13, 150.0))
    assert workers_of(view)["w1"]["state"] == "training"


def test_view_resent_points_replace_and_long_curves_are_thinned() -> None:
    view = RunView(RUN, max_points=8)
    feed(view, start(["w0"]), update("w0", 1, 1.0), mature("w0", 2, 2.0), mature("w0", 2, 2.0))
    assert [p[0] for p in workers_of(view)["w0"]["curve"]] == [1, 2]
    view = RunView(RUN, max_points=8)
    feed(view, start(["w0"]), *[update("w0", e, float(e)) for e in range(1, 10)])
    curve = [p[0] for p in workers_of(view)["w0"]["curve"]]
    assert len(curve) <= 8 and curve[-1] == 9 and curve == sorted(curve)
    assert curve[0] <= 2, "thinning keeps the start of the curve"


def partial(edge: str, episode: int, *submissions: WorkerUpdate | MatureParams) -> EdgePartial:
    """Edge ``edge``'s part of round ``episode``: its workers' submissions as the root gets them, without tensors."""
    return EdgePartial(edge_id=edge, round=episode, episode=episode,
                       updates=[u.model_copy(update={"gradient": {}}) for u in submissions
                                if isinstance(u, WorkerUpdate)],
                       matures=[m for m in submissions if isinstance(m, MatureParams)], count=len(submissions))


def test_view_shows_the_workers_of_a_tiered_run_from_their_edges_partials() -> None:
    """A dashboard that sees only the root's side of a tiered run (the edges' partials and the chief's answers)
    shows every worker's episodes, PI and finish; one that sees the workers' own updates as well shows one point
    per episode, and a partial seen after the worker's newer update neither regresses its PI nor its curve's order."""
    edge = lambda e: topics.edge(RUN, e, topics.PARTIAL)  # noqa: E731
    view = RunView(RUN)
    feed(view, start(["w0", "w1", "w2"]))
    for episode in (1, 2):
        events = view.apply(edge("e0"), partial("e0", episode, update("w0", episode, 10.0 * episode),
                                                update("w2", episode, 5.0 * episode)), 10.0 + episode)
        assert {"type": "point", "worker": "w2", "point": [episode, 5.0 * episode, 5.0 * episode]} in events
        view.apply(edge("e1"), partial("e1", episode, update("w1", episode, 1.0)), 10.5 + episode)
        feed(view, aggregate(episode, {"w0": 0.5, "w1": 0.25, "w2": 0.25}))
    view.apply(edge("e1"), partial("e1", 3, mature("w1", 3, 196.0)), 14.0)
    workers = workers_of(view)
    assert {w: (v["episode"], v["pi"], [p[0] for p in v["curve"]]) for w, v in workers.items()} == {
        "w0": (2, 20.0, [1, 2]), "w2": (2, 10.0, [1, 2]), "w1": (3, 196.0, [1, 2, 3])}
    assert workers["w1"]["state"] == "finished" and workers["w1"]["solved_episode"] == 3
    assert view.snapshot()["kinds"]["partial"] == 5
    # An edge's copy of the chief's answer is not shown again: the chief's own is.
    assert view.apply(topics.relayed(RUN, "e0", topics.AGGREGATE), aggregate(2, {"w0": 1.0}), 15.0) == []
    assert view.snapshot()["run"]["rounds"] == 2 and view.snapshot()["ignored"] == {"aggregate": 1}

    both = RunView(RUN)  # the workers' own updates and the partials
    feed(both, start(["w0"]), update("w0", 1, 10.0), update("w0", 2, 20.0))  # w0 ahead of its edge's round 1
    events = both.apply(edge("e0"), partial("e0", 1, update("w0", 1, 10.0)), 5.0)
    assert events and all(e["type"] != "point" for e in events)  # the page's curve takes no older point
    w0 = workers_of(both)["w0"]
    assert ([p[0] for p in w0["curve"]], w0["episode"], w0["pi"]) == ([1, 2], 2, 20.0)


def test_view_refuses_an_edge_partial_without_the_run_key() -> None:
    view = RunView(RUN, key=KEY)
    view.apply(topics.chief(RUN, topics.START), signed(start(["w0"]), chief_key_of(KEY)), 1.0)
    topic = topics.edge(RUN, "e0", topics.PARTIAL)
    assert view.apply(topic, partial("e0", 1, update("w0", 1, 10.0)), 2.0) == []
    assert view.snapshot()["refused"] == {"unsigned partial": 1} and workers_of(view)["w0"]["episode"] == 0
    assert view.apply(topic, signed(partial("e0", 1, update("w0", 1, 10.0)), KEY), 3.0) != []
    assert workers_of(view)["w0"]["episode"] == 1


def test_view_end_state_says_the_run_is_over() -> None:
    """After the run: the number of rounds (no open round), and nobody "has finished yet" but nobody finished."""
    view = RunView(RUN)
    feed(view, start(["w0"]), update("w0", 1, 10.0), aggregate(1, {"w0": 1.0}), update("w0", 2, 12.0),
         aggregate(2, {"w0": 1.0}))
    assert view.snapshot()["run"]["round"] == 3 and view.snapshot()["run"]["no_transfer"] == NO_TRANSFER_YET
    feed(view, RunStop(run_id=RUN, reason="interrupted", episodes=2, all_solved=False, aborted=True))
    run = view.snapshot()["run"]
    assert (run["round_label"], run["rounds"], run["no_transfer"]) == ("rounds", 2, NO_TRANSFER)


def test_view_of_workers_that_solved_without_a_transfer_says_so() -> None:
    """A sync or independent run, or a warm start solved in one round: nobody "finished" is not what happened."""
    view = RunView(RUN)
    feed(view, start(["w0"]), update("w0", 1, 199.0), WorkerStatus(worker_id="w0", state="finished", episode=1,
                                                                   pi=199.0))
    assert view.snapshot()["run"]["no_transfer"] == SOLVED_WITHOUT_TRANSFER
    feed(view, RunStop(run_id=RUN, reason="all solved", episodes=1, all_solved=True, aborted=False))
    assert view.snapshot()["run"]["no_transfer"] == SOLVED_WITHOUT_TRANSFER


def test_view_rig_without_telemetry_says_why() -> None:
    """A lockstep rig publishes no loop telemetry: its row says so instead of showing 0 ticks and no timing."""
    view = RunView(RUN)
    feed(view, QubeStatus(rig_id="rig0", state="running", episode=1))
    rig = view.snapshot()["rigs"][0]
    assert (rig["telemetry"], rig["note"], rig["ticks"]) == (False, NO_TELEMETRY, 0)
    assert "lockstep" in rig["note"] and "answers" in rig["note"]
    feed(view, QubeTelemetry(rig_id="rig0", ticks=50, deadline_misses=0, late_actions=0, faults=0,
                             jitter_ms={"p99": 0.1}, latency_ms={"p50": 1.0, "p99": 2.0, "max": 3.0}))
    rig = view.snapshot()["rigs"][0]
    assert (rig["telemetry"], rig["note"], rig["ticks"]) == (True, "", 50)


def test_view_rigs_other_runs_and_unshown_kinds() -> None:
    view = RunView(RUN)
    feed(view, QubeStatus(rig_id="rig0", state="running", episode=4),
         QubeTelemetry(rig_id="rig0", ticks=1430, deadline_misses=2, late_actions=1, faults=0,
                       jitter_ms={"p50": 0.01, "p99": 0.2, "max": 1.0}, latency_ms={"p50": 1.1, "p99": 2.5, "max": 6}))
    rig = view.snapshot()["rigs"][0]
    assert (rig["id"], rig["phase"], rig["episode"], rig["deadline_misses"], rig["latency_ms"]["p99"]) == (
        "rig0", "running", 4, 2, 2.5)
    assert feed(view, start(["x"], run_id="other"), RunStop(run_id="other", reason="x", episodes=1,
                                                           all_solved=True)) == []
    assert view.snapshot()["run"]["phase"] == "waiting"
    assert feed(view, QubeState(rig_id="rig0", seq=1, t=0.0, theta=0, alpha=0, theta_dot=0, alpha_dot=0),
                QubeAction(rig_id="rig0", seq=1, command=0)) == []
    assert view.snapshot()["ignored"] == {"qube_state": 1, "qube_action": 1}


def test_view_same_run_id_again_starts_afresh() -> None:
    view = RunView(RUN)
    feed(view, start(["w0"]), update("w0", 1, 1.0), RunStop(run_id=RUN, reason="done", episodes=1, all_solved=False))
    events = feed(view, start(["w5"]))
    assert events[0] == {"type": "reset"}
    assert list(workers_of(view)) == ["w5"] and view.snapshot()["run"]["phase"] == "running"


# -- feed and hub ----------------------------------------------------------------------------------------------


def test_subscriptions_leave_out_the_143_hz_state_topic() -> None:
    subs = dict(subscriptions(RUN, None))
    run = {f: q for f, q in subs.items() if f.startswith(f"fedrl/{RUN}/")}
    assert {f: q for f, q in subs.items() if f not in run} == {"qube/+/status": 1, "qube/+/telemetry": 0}
    assert {f"fedrl/{RUN}/worker/+/update", f"fedrl/{RUN}/edge/+/partial", f"fedrl/{RUN}/chief/aggregate"} <= set(run)
    assert dict(subscriptions(RUN, ["rigA"])) == {**run, "qube/rigA/status": 1, "qube/rigA/telemetry": 0}
    with pytest.raises(ValueError):
        subscriptions(RUN, ["bad/rig"])


class Subscriber:
    """What a feed asked its connection to subscribe to and unsubscribe from."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, str]] = []

    def subscribe(self, topic_filter: str, handler: Any, qos: int = 1) -> None:
        self.calls.append(("subscribe", topic_filter))

    def unsubscribe(self, topic_filter: str) -> None:
        self.calls.append(("unsubscribe", topic_filter))


def test_feed_reads_no_worker_updates_in_a_tiered_run() -> None:
    """Once the run's RunStart names edges, the feed stops reading the workers' updates (their edges' partials carry
    them, without gradients); a flat run under the same id reads them again."""
    hub = Hub(RunView(RUN))
    fd = MqttFeed(connector(BrokerAddress.parse("mqtt://127.0.0.1:9")), RUN, hub)  # never started
    fd.conn = Subscriber()  # type: ignore[assignment]
    fd.follow_tier(hub.view.tiered)
    hub.apply([("t", start(["w0"]), 1.0)])
    fd.follow_tier(hub.view.tiered)
    assert fd.conn.calls == []  # type: ignore[attr-defined]  # a flat run: its updates are read
    hub.apply([("t", RunStop(run_id=RUN, reason="done", episodes=1, all_solved=False), 2.0),
               ("t", start(["w0", "w1"]).model_copy(update={"edges": {"w0": "e0", "w1": "e1"}}), 3.0)])
    fd.follow_tier(hub.view.tiered)
    fd.follow_tier(hub.view.tiered)
    assert fd.conn.calls == [("unsubscribe", f"fedrl/{RUN}/worker/+/update")]  # type: ignore[attr-defined]
    hub.apply([("t", RunStop(run_id=RUN, reason="done", episodes=1, all_solved=False), 4.0), ("t", start(["w0"]), 5.0)])
    fd.follow_tier(hub.view.tiered)
    assert fd.conn.calls[-1] == ("subscribe", f"fedrl/{RUN}/worker/+/update")  # type: ignore[attr-defined]


def test_feed_rejects_counts_and_survives_bad_payloads() -> None:
    hub = Hub(RunView(RUN))
    # never started: on_message is called directly
    fd = MqttFeed(connector(BrokerAddress.parse("mqtt://127.0.0.1:9")), RUN, hub)
    topic = topics.worker(RUN, "w0", topics.UPDATE)
    fd.on_message(topic, b"\x00junk")
    fd.on_message(topic, msgpack.packb({"schema_version": 1, "kind": "future_thing", "x": 1}))
    fd.on_message(topic, msgpack.packb({"schema_version": 7, "kind": "update"}))
    fd.on_message(topic, encode(update("w1", 1, 5.0)))  # spoofed: topic says w0
    fd.on_message("qube/rig1/telemetry", encode(QubeTelemetry(rig_id="rig2", ticks=1, deadline_misses=0,
                                                              late_actions=0, faults=0, jitter_ms={}, latency_ms={})))
    fd.on_message(topic, encode(update("w0", 1, 5.0)))
    stats = fd.stats()
    assert stats["received"] == 6 and stats["unknown"] == {"'future_thing'": 1}
    assert stats["rejected"] == {"malformed": 1, "version": 1, "spoofed": 2}
    assert fd.inbox.qsize() == 1
    hub.apply([fd.inbox.get_nowait()])
    assert workers_of(hub.view)["w0"]["points"] == 1


def test_feed_never_blocks_the_network_thread() -> None:
    fd = MqttFeed(connector(BrokerAddress.parse("mqtt://127.0.0.1:9")), RUN, Hub(RunView(RUN)), max_queue=2)
    for e in range(1, 5):
        fd.on_message(topics.worker(RUN, "w0", topics.UPDATE), encode(update("w0", e, 1.0)))
    assert fd.inbox.qsize() == 2 and fd.stats()["dropped"] == 2


def test_hub_cuts_off_a_page_that_falls_behind() -> None:
    hub = Hub(RunView(RUN), client_batches=2)
    snapshot, slow = hub.connect()
    _, fast = hub.connect()
    assert snapshot["run"]["phase"] == "waiting" and hub.clients == 2
    for e in range(1, 4):
        hub.apply([("t", update("w0", e, 1.0), 0.0)])
        if e < 3:
            assert fast.next_batch(0.1)
    assert slow.overflowed.is_set() and hub.dropped_clients == 1 and hub.clients == 1
    assert [ev["point"][0] for ev in fast.next_batch(0.1) if ev["type"] == "point"] == [3]


# -- the HTTP server and its event stream, against a real broker ---------------------------------------------


class SseReader:
    """Reads ``event:``/``data:`` pairs from /events in a thread."""

    def __init__(self, host: str, port: int) -> None:
        self.conn = http.client.HTTPConnection(host, port, timeout=30)
        self.conn.request("GET", "/events")
        self.response = self.conn.getresponse()
        self.events: queue.Queue[tuple[str, Any]] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        name = None
        try:
            for raw in self.response:
                line = raw.decode().rstrip("\n")
                if line.startswith("event: "):
                    name = line[7:]
                elif line.startswith("data: ") and name:
                    self.events.put((name, json.loads(line[6:])))
        except Exception:  # the server went away
            pass

    def until(self, predicate: Any, timeout: float = 20.0) -> tuple[str, Any]:
        deadline = time.monotonic() + timeout
        seen: list[str] = []
        while time.monotonic() < deadline:
            try:
                name, data = self.events.get(timeout=0.2)
            except queue.Empty:
                continue
            if predicate(name, data):
                return name, data
            seen.append(f"{name}: {json.dumps(data)[:300]}")
        raise AssertionError("the expected event never came; got:\n" + "\n".join(seen[-8:]))


@pytest.fixture
def dashboard(amqtt_broker: str) -> Iterator[DashboardService]:
    service = DashboardService(DashboardConfig(broker=BrokerAddress.parse(amqtt_broker), run_id=RUN, port=0)).start()
    try:
        yield service
    finally:
        service.stop()


def send_until(send: Callable[[str, Any], None], sse: SseReader, topic: str, payload: Any,
               seen: Callable[[str, Any], bool], tries: int = 10, timeout: float = 3.0) -> tuple[str, Any]:
    """Send until the page shows it: ``tries`` times, each waiting up to ``timeout`` s for an event ``seen`` accepts
    (once, in a make test at load 3, the page never showed an update; a resent submission replaces its point)."""
    for _ in range(tries):
        send(topic, payload)
        try:
            return sse.until(seen, timeout=timeout)
        except AssertionError:
            continue
    raise AssertionError(f"the page never showed what was sent on {topic}")


def test_event_stream_and_page_over_a_real_broker(dashboard: DashboardService, amqtt_broker: str) -> None:
    host, port = dashboard.server.server_address[:2]
    assert host == "127.0.0.1" and port not in (0, 1883)
    http_conn = http.client.HTTPConnection(host, port, timeout=10)
    http_conn.request("GET", "/")
    page = http_conn.getresponse()
    body = page.read().decode()
    assert page.status == 200 and "<canvas id=\"curves\"" in body and "/app.js" in body
    assert "default-src 'none'" in page.getheader("Content-Security-Policy")
    assert "http://" not in body and "https://" not in body, "the page must load nothing from elsewhere"
    http_conn.request("GET", "/nope")
    missing = http_conn.getresponse()
    assert missing.status == 404 and missing.read()
    http_conn.request("GET", "/api/snapshot", headers={"Host": f"rebound.example:{port}"})  # DNS rebinding
    refused = http_conn.getresponse()
    assert refused.status == 403 and b"run" not in refused.read()
    http_conn.request("GET", "/healthz", headers={"Host": f"localhost:{port}"})
    assert http_conn.getresponse().read() == b"ok\n"

    sse = SseReader(host, port)
    assert sse.response.getheader("Content-Type").startswith("text/event-stream")
    _, snap = sse.until(lambda n, d: n == "snapshot")
    assert snap["run"]["phase"] == "waiting" and snap["workers"] == []

    pub = MqttConnection(BrokerAddress.parse(amqtt_broker), client_id="dash-test-pub").start()
    try:
        def send(topic: str, payload: Any) -> None:
            pub.publish(topic, payload if isinstance(payload, bytes) else encode(payload), qos=1).wait_for_publish(5)

        # The dashboard subscribes without waiting for the broker's SUBACKs (and amqtt may handle them in any
        # order): repeat a rig status and a message on a topic that does not carry its kind (refused as
        # wrong_topic) until both have been seen.
        send_until(send, sse, "qube/rigS/status", QubeStatus(rig_id="rigS", state="idle"),
                   lambda n, d: n == "delta" and any(e["type"] == "rig" for e in d), tries=100, timeout=0.3)
        send_until(send, sse, topics.worker(RUN, "w9", topics.STATUS), QubeAction(rig_id="rigS", seq=0, command=0),
                   lambda n, d: n == "stats" and d["rejected"].get("wrong_topic"), tries=30, timeout=1.5)
        send(topics.chief(RUN, topics.START), start(["w0", "w1"]))
        send(topics.worker(RUN, "w0", topics.UPDATE), b"\x00garbage")  # must not stop anything
        send(topics.chief("someone-else", topics.START), start(["x"], run_id="someone-else"))
        send("qube/rigS/state", QubeState(rig_id="rigS", seq=1, t=0, theta=0, alpha=0, theta_dot=0, alpha_dot=0))

        def has_point(name: str, data: Any) -> bool:
            return name == "delta" and any(e["type"] == "point" and e["worker"] == "w0" for e in data)

        _, delta = send_until(send, sse, topics.worker(RUN, "w0", topics.UPDATE), update("w0", 1, 12.0), has_point)
        assert {"type": "point", "worker": "w0", "point": [1, 12.0, 12.0]} in delta
        send_until(send, sse, "qube/rigS/status", QubeStatus(rig_id="rigS", state="ready"),
                   lambda n, d: n == "delta" and any(e["type"] == "rig" and e["phase"] == "ready" for e in d))
        _, stats = sse.until(lambda n, d: n == "stats" and d["rejected"].get("malformed") == 1)
        assert stats["connected"] and stats["pages"] == 1

        # A second page connecting now gets everything so far in its snapshot.
        late = SseReader(host, port)
        _, snap = late.until(lambda n, d: n == "snapshot")
        assert snap["run"]["workers"] == ["w0", "w1"] and snap["workers"][0]["curve"] == [[1, 12.0, 12.0]]
        assert [r["id"] for r in snap["rigs"]] == ["rigS"], "qube/<rig>/state must not be subscribed"
        send(topics.worker(RUN, "w1", topics.UPDATE), update("w1", 1, 30.0))
        for reader in (sse, late):
            reader.until(lambda n, d: n == "delta" and any(e.get("worker") == "w1" for e in d))
    finally:
        pub.stop()


KEY = b"dashboard-test-run-key-0123456789"
CHIEF_KEY = chief_key_of(KEY)


def test_view_shows_only_messages_tagged_with_their_senders_keys() -> None:
    """An unsigned or wrongly tagged RunStart/RunStop/aggregate, or a worker's update not tagged with that worker's
    own key, changes nothing shown and is counted as refused; the chief's (chief key) and the workers' own are shown."""
    view = RunView(RUN, key=KEY)
    chief = lambda leaf: topics.chief(RUN, leaf)  # noqa: E731
    assert view.apply(chief(topics.START), start(["w0"]), 1.0) == []  # unsigned
    assert view.apply(chief(topics.START), signed(start(["w0"]), KEY), 1.5) == []  # the run key is not the chief key
    assert view.snapshot()["run"]["phase"] == "waiting"
    assert view.apply(chief(topics.START), signed(start(["w0"]), CHIEF_KEY), 2.0) != []
    stop = RunStop(run_id=RUN, reason="forged by an outsider", episodes=1, all_solved=False)
    assert view.apply(chief(topics.STOP), stop, 3.0) == []
    assert view.apply(chief(topics.STOP), signed(stop, b"another-key-of-somebody-else"), 4.0) == []
    assert view.apply(chief(topics.AGGREGATE), aggregate(1, {"w0": 1.0}), 5.0) == []
    w0 = topics.worker(RUN, "w0", topics.UPDATE)
    assert view.apply(w0, update("w0", 1, 10.0), 5.5) == []  # unsigned
    assert view.apply(w0, signed(update("w0", 1, 10.0), worker_key(KEY, "w1").encode()), 5.6) == []  # w1's key
    snap = view.snapshot()
    assert snap["run"]["phase"] == "running" and snap["rounds"] == []
    assert snap["refused"] == {"unsigned run_start": 1, "forged run_start": 1, "unsigned run_stop": 1,
                               "forged run_stop": 1, "unsigned aggregate": 1, "unsigned update": 1,
                               "forged update": 1}
    assert view.apply(w0, signed(update("w0", 1, 10.0), worker_key(KEY, "w0").encode()), 6.0) != []
    view.apply(chief(topics.STOP), signed(stop.model_copy(update={"reason": "episode limit"}), CHIEF_KEY), 7.0)
    assert view.snapshot()["run"]["phase"] == "stopped"
    assert RunView(RUN).apply(chief(topics.STOP), stop, 1.0) != []  # without a key: trusted, as before


def test_a_forged_run_stop_never_reaches_the_snapshot_over_a_real_broker(amqtt_broker: str) -> None:
    service = DashboardService(DashboardConfig(broker=BrokerAddress.parse(amqtt_broker), run_id=RUN, port=0,
                                               key=KEY)).start()
    pub = MqttConnection(BrokerAddress.parse(amqtt_broker), client_id="dash-forger").start()
    try:
        host, port = service.server.server_address[:2]
        sse = SseReader(host, port)
        sse.until(lambda n, d: n == "snapshot")

        def send(topic: str, payload: Any) -> None:
            pub.publish(topic, encode(payload), qos=1).wait_for_publish(5)

        send_until(send, sse, topics.chief(RUN, topics.START), signed(start(["w0", "w1"]), CHIEF_KEY),
                   lambda n, d: n == "delta" and any(e["type"] == "run" and e["phase"] == "running" for e in d),
                   tries=100, timeout=0.3)
        forged = RunStop(run_id=RUN, reason="forged by an outsider", episodes=3, all_solved=False)
        send(topics.chief(RUN, topics.STOP), forged)
        sse.until(lambda n, d: n == "stats" and d.get("refused", {}).get("unsigned run_stop") == 1)
        http_conn = http.client.HTTPConnection(host, port, timeout=10)
        http_conn.request("GET", "/api/snapshot")
        snap = json.loads(http_conn.getresponse().read())
        assert snap["run"]["phase"] == "running" and snap["run"].get("stop") is None, snap["run"]
        assert snap["refused"] == {"unsigned run_stop": 1} and snap["stats"]["refused"] == {"unsigned run_stop": 1}
    finally:
        pub.stop()
        service.stop()


def test_command_line_errors_are_one_line(tmp_path: Path) -> None:
    import subprocess

    for argv, needle in ((["--port", "70000"], "--port '70000' (command line): input should be less than or equal to "
                          "65535"), (["--run-id", "a/b"], "--run-id 'a/b' (command line): run id")):
        out = subprocess.run([sys.executable, "-m", "services.dashboard", "--broker", "mqtt://127.0.0.1:9", *argv],
                             capture_output=True, text=True, timeout=60)
        assert out.returncode == 2, out.stderr
        assert needle in out.stderr and "Traceback" not in out.stderr and len(out.stderr.splitlines()) == 1


# -- deployment ------------------------------------------------------------------------------------------------


def test_compose_and_dockerfile_run_the_dashboard() -> None:
    import re

    from tests.deploy.test_deploy_static import ROOT, ancestry, compose, dockerfile_stages

    services = compose()["services"]
    dash, chief = services["dashboard"], services["chief"]
    assert dash["build"]["dockerfile"] == "deploy/Dockerfile" and dash["build"]["target"] == "dashboard"
    assert dash["ports"] == ["${FEDRL_DASHBOARD_BIND:-127.0.0.1}:${FEDRL_DASHBOARD_PORT:-8050}:8050"]
    assert dash["depends_on"]["mosquitto"]["condition"] == "service_healthy"
    for var in ("FEDRL_BROKER", "FEDRL_RUN_ID"):
        assert dash["environment"][var] == chief["environment"][var]
    stages = dockerfile_stages()
    lines = stages["dashboard"][1]
    assert 'ENTRYPOINT ["python", "-m", "services.dashboard"]' in lines
    assert 'CMD ["--host", "0.0.0.0", "--port", "8050"]' in lines and "EXPOSE 8050" in lines
    chain = ancestry(stages, "dashboard")
    assert "runtime" in chain
    installs = re.findall(r"pip-install ([^&;\n]*)", " ".join(line for s in chain for line in stages[s][1]))
    assert installs and not [i for i in installs if "[learn]" in i or re.search(r"\b(torch|gymnasium)\b", i)], installs
    assert '"services.dashboard" = ["static/*"]' in (ROOT / "pyproject.toml").read_text(), "the page must be packaged"


def test_dashboard_imports_no_torch() -> None:
    import subprocess

    code = ("import sys, services.dashboard.__main__, services.dashboard.screenshot; "
            "bad = [m for m in ('torch', 'gymnasium') if m in sys.modules]; print(bad); sys.exit(bool(bad))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr


def test_view_shows_each_rigs_time_and_the_last_rig() -> None:
    """QUBE-Servo 2: each worker's rig time (balance + reset, summed once per episode), its idle seconds modelled
    round by round (a round closes when its slowest rig is ready, protocol/rigtime.py) and the run's last rig."""
    view = RunView(RUN)
    feed(view, start(["w0", "w1"]))

    def timed(worker: str, episode: int, steps: int, reset: float) -> WorkerUpdate:
        return update(worker, episode, 1.0).model_copy(update={
            "balance_steps": steps, "balance_s": steps * 0.007, "reset_s": reset})

    # Round 1: w0 3.7 s, w1 1.0 + 0.7 = 1.7 s (sent twice: summed once) -> w1 waits 2 s.
    feed(view, timed("w0", 1, 100, 3.0), timed("w1", 1, 100, 1.0), timed("w1", 1, 100, 1.0),
         aggregate(1, {"w0": 0.5, "w1": 0.5}))
    rows = {w: r["rig"] for w, r in workers_of(view).items()}
    assert rows["w0"] == {"balance_steps": 100, "balance_s": 0.7, "reset_s": 3.0, "idle_s": 0.0, "rig_s": 3.7,
                          "idle": "modelled"}
    assert rows["w1"]["rig_s"] == 1.7 and rows["w1"]["idle_s"] == 2.0
    last = view.snapshot()["run"]["last_rig"]
    assert last["id"] in ("w0", "w1") and last["rig_s"] + last["idle_s"] == pytest.approx(3.7)
    # A gymnasium run shows no rig time.
    plain = RunView(RUN)
    feed(plain, start(["w0"]), update("w0", 1, 1.0), aggregate(1, {"w0": 1.0}))
    assert workers_of(plain)["w0"]["rig"] is None and plain.snapshot()["run"]["last_rig"] is None
