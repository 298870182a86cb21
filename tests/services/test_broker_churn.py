"""A subscriber gets every message while other clients come, subscribe and go, on both brokers.

amqtt 0.12 walks its subscriptions while it awaits the topic check of each (our topic guard makes that await real);
a client that subscribed or left meanwhile changed the dict under the walk, and the message was dropped for every
subscriber not reached yet. In a federation that was a lost submission: its round waited the full round timeout, and
the resend came as ``stale``. The embedded broker now walks a snapshot (services/broker/embedded.py)."""

from __future__ import annotations

import threading
import time

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion

from services.broker.embedded import SnapshotSubscriptions

MESSAGES = 300


def client(url: str, client_id: str) -> paho.Client:
    host, port = url.removeprefix("mqtt://").rsplit(":", 1)
    c = paho.Client(CallbackAPIVersion.VERSION2, client_id=client_id, protocol=paho.MQTTv311)
    c.connect(host, int(port))
    c.loop_start()
    return c


def churn(url: str, stop: threading.Event, count: list[int]) -> None:
    """Clients that connect, subscribe to topics of their own and leave, until ``stop``: at most about 20 a second
    each, so that on a loaded host the broker still has time for the messages (unpaced, three of these made it spend
    a second per publish on a CI host and the test ran for 8 minutes)."""
    while not stop.is_set():
        c = client(url, f"churn-{time.monotonic_ns()}")
        for t in range(3):
            c.subscribe(f"churn/{count[0]}/{t}", qos=1)
        time.sleep(0.01)
        c.disconnect()
        c.loop_stop()
        count[0] += 1
        stop.wait(0.04)


def wait_for_all(got: dict[str, set[int]], stall_s: float = 20.0) -> None:
    """Until every reader has every message, or none got a new one for ``stall_s``: a loaded broker delivers late,
    a lost message never comes."""
    seen, last = -1, time.monotonic()
    while any(len(g) < MESSAGES for g in got.values()) and time.monotonic() - last < stall_s:
        if (now := sum(len(g) for g in got.values())) != seen:
            seen, last = now, time.monotonic()
        time.sleep(0.05)


def test_every_message_arrives_while_subscriptions_change(any_broker: str) -> None:
    filters = ["load/#", "load/+", "+/x", "load/x"]  # one reader each: a walk awaits at each of them
    got: dict[str, set[int]] = {f: set() for f in filters}
    subscribed = threading.Semaphore(0)
    readers = []
    for f in filters:
        reader = client(any_broker, f"reader-{len(readers)}")
        reader.on_message = lambda c, u, m, f=f: got[f].add(int(m.payload))
        reader.on_subscribe = lambda c, u, mid, codes, props: subscribed.release()
        reader.subscribe(f, qos=1)
        assert subscribed.acquire(timeout=10)
        readers.append(reader)
    writer = client(any_broker, "writer")
    stop, churned = threading.Event(), [0]
    churners = [threading.Thread(target=churn, args=(any_broker, stop, churned), daemon=True) for _ in range(3)]
    for t in churners:
        t.start()
    try:
        for i in range(MESSAGES):
            writer.publish("load/x", str(i).encode(), qos=1).wait_for_publish(10)
            time.sleep(0.002)
        stop.set()
        wait_for_all(got)
    finally:
        stop.set()
        for t in churners:
            t.join(10)
        for c in (*readers, writer):
            c.disconnect()
            c.loop_stop()
    assert churned[0] > 20, "the churn should have come and gone many times during the publishing"
    assert {f: MESSAGES - len(g) for f, g in got.items()} == dict.fromkeys(filters, 0)  # lost messages per reader


def test_a_snapshot_walk_survives_a_change_under_it() -> None:
    subs = SnapshotSubscriptions({"a": [("s1", 1)], "b": [("s2", 1), ("s3", 0)]})
    seen = []
    for topic, subscribers in subs.items():
        subs["c"] = []  # a client subscribed meanwhile
        if topic == "a":
            subs["b"].pop(0)  # s2 left meanwhile: the walk still reaches s3
        seen += [s for s, _ in subscribers]
    for _ in subs:
        subs.pop("a", None)  # a session's subscriptions deleted during a walk
    assert seen == ["s1", "s2", "s3"] and sorted(subs) == ["b", "c"]
