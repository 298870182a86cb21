"""protocol/memory.py: the in-memory hub routes as an MQTT broker does (topic filters with + and #, one delivery per
connection, in order), runs handlers on the connection's own thread with paho's error semantics, and publishes a
lost connection's last will. Both connections satisfy protocol.transport.Transport."""

from __future__ import annotations

import queue
import threading

import pytest

from protocol.memory import Hub, MemoryConnection, check_filter, matches
from protocol.mqtt import BrokerAddress, MqttConnection
from protocol.transport import Transport


@pytest.mark.parametrize(("topic_filter", "topic", "expected"), [
    ("fedrl/r/chief/+", "fedrl/r/chief/aggregate", True),
    ("fedrl/r/chief/+", "fedrl/r/chief/a/b", False),
    ("fedrl/r/chief/+", "fedrl/r/chief", False),
    ("fedrl/+/worker/+/update", "fedrl/r/worker/w0/update", True),
    ("fedrl/+/worker/+/update", "fedrl/r/worker/w0/status", False),
    ("fedrl/r/#", "fedrl/r/worker/w0/status", True),
    ("fedrl/r/#", "fedrl/r", True),  # '#' also matches the parent level
    ("fedrl/r/#", "fedrl/q/x", False),
    ("#", "anything/at/all", True),
    ("#", "$SYS/broker/load", False),  # wildcards in the first level do not match $ topics
    ("+/broker/load", "$SYS/broker/load", False),
    ("$SYS/#", "$SYS/broker/load", True),
    ("a/b", "a/b", True),
    ("a/b", "a/b/", False),
    ("a/+/c", "a//c", True),  # an empty level is a level
])
def test_topic_filters_match_as_mqtt_says(topic_filter: str, topic: str, expected: bool) -> None:
    assert matches(topic_filter, topic) is expected


@pytest.mark.parametrize("bad", ["a/#/b", "a/b#", "a+/b", ""])
def test_invalid_filters_are_refused(bad: str) -> None:
    with pytest.raises(ValueError):
        check_filter(bad)


def received(conn: MemoryConnection, topic_filter: str) -> queue.Queue[tuple[str, bytes, str]]:
    got: queue.Queue[tuple[str, bytes, str]] = queue.Queue()
    conn.subscribe(topic_filter, lambda t, p: got.put((t, p, threading.current_thread().name)))
    return got


def test_messages_arrive_once_in_order_as_bytes_on_the_delivery_thread() -> None:
    hub = Hub()
    with hub.connect("a") as a, hub.connect("b") as b:
        got = received(b, "x/+")
        b.subscribe("x/#", lambda t, p: None)  # overlapping: still one delivery, both handlers called
        mine = received(a, "x/1")  # a sender gets its own message when subscribed, as over MQTT
        payload = bytearray(b"one")
        a.publish("x/1", payload)
        payload[:] = b"two"  # the hub copied the payload
        a.publish("x/2", b"2")
        a.publish("y/1", b"not for b")
        first, second = got.get(timeout=2), got.get(timeout=2)
        assert first[:2] == ("x/1", b"one") and isinstance(first[1], bytes) and second[:2] == ("x/2", b"2")
        assert first[2] == "memory-b" != threading.current_thread().name
        assert mine.get(timeout=2)[:2] == ("x/1", b"one")
        with pytest.raises(queue.Empty):
            got.get(timeout=0.2)
        with pytest.raises(ValueError):
            a.publish("x/+", b"")


def test_a_failing_handler_is_logged_and_counted_and_delivery_goes_on(caplog: pytest.LogCaptureFixture) -> None:
    hub = Hub()
    with hub.connect("a") as a, hub.connect("b") as b:
        b.subscribe("boom", lambda t, p: 1 / 0)
        got = received(b, "ok")
        a.publish("boom", b"")
        a.publish("ok", b"still here")
        assert got.get(timeout=2)[1] == b"still here"
        assert b.handler_errors == 1 and "handler for boom failed" in caplog.text


def test_a_dropped_connection_leaves_its_will_a_stopped_one_does_not() -> None:
    hub = Hub()
    with hub.connect("watcher") as watcher:
        wills = received(watcher, "status/+")
        clean = hub.connect("clean", will=("status/clean", b"offline")).start()
        lost = hub.connect("lost", will=("status/lost", b"offline")).start()
        clean.stop()
        lost.drop()
        assert wills.get(timeout=2)[:2] == ("status/lost", b"offline")
        with pytest.raises(queue.Empty):
            wills.get(timeout=0.2)
        after = received(lost, "status/+")  # a closed connection receives and sends nothing
        lost.publish("status/x", b"")
        watcher.unsubscribe("status/+")
        hub.route("status/y", b"")
        with pytest.raises(queue.Empty):
            after.get(timeout=0.2)
        assert not lost.connected.is_set() and lost.connects == 1


def test_both_connections_are_transports() -> None:
    def takes(conn: Transport) -> Transport:  # mypy checks the structural match; this checks the members exist
        return conn

    for conn in (Hub().connect("a"), MqttConnection(BrokerAddress.parse("mqtt://127.0.0.1:9"), "a")):
        for member in ("start", "stop", "subscribe", "unsubscribe", "publish", "connected", "connects",
                       "session_present", "rejects"):
            assert hasattr(takes(conn), member)
