"""Hostile topics on both brokers: a PUBLISH whose topic holds a NUL character or an MQTT wildcard
reaches no subscriber, and a SUBSCRIBE filter with a NUL is refused. The packets are written over a raw socket,
since a client library may refuse them before they leave."""

from __future__ import annotations

import queue
import socket
import struct
import time
from pathlib import Path

import paho.mqtt.client as paho
import pytest
from paho.mqtt.enums import CallbackAPIVersion

from services.broker.topic_guard import topic_fault


def _string(text: str) -> bytes:
    raw = text.encode("utf-8")
    return struct.pack("!H", len(raw)) + raw


def _packet(first: int, body: bytes) -> bytes:
    length, size = b"", len(body)
    while True:
        byte, size = size % 128, size // 128
        length += bytes([byte | (0x80 if size else 0)])
        if not size:
            return bytes([first]) + length + body


def raw_client(url: str, client_id: str) -> socket.socket:
    """An MQTT 3.1.1 connection (clean session, anonymous) that got its CONNACK."""
    host, port = url.removeprefix("mqtt://").rsplit(":", 1)
    sock = socket.create_connection((host, int(port)), timeout=5)
    sock.sendall(_packet(0x10, _string("MQTT") + bytes([4, 0x02, 0, 60]) + _string(client_id)))
    assert sock.recv(4) == bytes([0x20, 2, 0, 0])
    return sock


def publish(url: str, topic: str, payload: bytes) -> None:
    """One QoS 0 PUBLISH on its own connection, then DISCONNECT (the broker may have closed it already)."""
    sock = raw_client(url, f"raw-{time.monotonic_ns()}")
    try:
        sock.sendall(_packet(0x30, _string(topic) + payload))
        sock.sendall(_packet(0xE0, b""))
    except OSError:
        pass
    finally:
        sock.close()


def sniffer(url: str) -> tuple[paho.Client, queue.Queue[tuple[str, bytes]]]:
    """A paho client subscribed to ``#`` that queues everything it receives."""
    host, port = url.removeprefix("mqtt://").rsplit(":", 1)
    got: queue.Queue[tuple[str, bytes]] = queue.Queue()
    subscribed: queue.Queue[object] = queue.Queue()
    client = paho.Client(CallbackAPIVersion.VERSION2, client_id=f"sniffer-{time.monotonic_ns()}",
                         protocol=paho.MQTTv311)
    client.on_message = lambda c, u, m: got.put((m.topic, bytes(m.payload)))
    client.on_subscribe = lambda c, u, mid, codes, props: subscribed.put(codes)
    client.on_connect = lambda c, u, f, rc, props: c.subscribe("#", qos=1)
    client.connect(host, int(port))
    client.loop_start()
    subscribed.get(timeout=10)
    return client, got


@pytest.mark.parametrize("topic", ["fedrl/a\x00b/chief/aggregate", "fedrl/+/chief/aggregate", "fedrl/run/#"])
def test_a_hostile_publish_reaches_no_subscriber(any_broker: str, tmp_path: Path, topic: str) -> None:
    client, got = sniffer(any_broker)
    try:
        publish(any_broker, topic, b"forged")
        publish(any_broker, "fedrl/run/sentinel", b"fine")  # after the hostile one, on the same path through
        seen = [got.get(timeout=10)]
        time.sleep(0.3)
        while not got.empty():
            seen.append(got.get_nowait())
    finally:
        client.loop_stop()
        client.disconnect()
    assert seen == [("fedrl/run/sentinel", b"fine")]
    log = tmp_path / "amqtt.log"
    if log.exists():  # the embedded broker says why, in one line, and nothing else (no packets read from a payload)
        lines = log.read_text(errors="replace").splitlines()[1:]  # after "broker ready"
        assert len(lines) == 1 and ("refused" in lines[0] or "MQTT-3.3.2-2" in lines[0]), lines


def test_a_subscribe_filter_with_nul_is_refused(any_broker: str) -> None:
    sock = raw_client(any_broker, f"raw-{time.monotonic_ns()}")
    try:
        sock.sendall(_packet(0x82, struct.pack("!H", 7) + _string("fedrl/\x00/#") + bytes([0])))
        reply = sock.recv(5)
    except OSError:
        reply = b""
    finally:
        sock.close()
    # amqtt answers with a failed SUBACK; Mosquitto closes the connection.
    assert reply in (b"", bytes([0x90, 3, 0, 7, 0x80])), reply


@pytest.mark.parametrize(("topic", "publish_", "fault"), [
    ("fedrl/r/chief/aggregate", True, None), ("fedrl/r/#", False, None), ("fedrl/+/x", False, None),
    ("a\x00b", True, "NUL character in topic"), ("a\x00b", False, "NUL character in topic"),
    ("a/+", True, "wildcard in a published topic"), ("a/#", True, "wildcard in a published topic"),
    ("", True, "empty topic"),
])
def test_topic_fault(topic: str, publish_: bool, fault: str | None) -> None:
    assert topic_fault(topic, publish_) == fault


def test_a_stalled_subscriber_costs_one_warning_line_per_timeout_and_no_traceback(amqtt_broker: str,
                                                                                  tmp_path: Path) -> None:
    """A subscriber that never acknowledges a QoS 1 message: amqtt gives up after 5 s and logged a traceback for
    each (36 in one probe); now each is one warning line with the count so far."""
    stalled = raw_client(amqtt_broker, "stalled")
    try:
        stalled.sendall(_packet(0x82, struct.pack("!H", 1) + _string("stall/#") + bytes([1])))
        assert stalled.recv(5) == bytes([0x90, 3, 0, 1, 1])  # SUBACK, QoS 1
        host, port = amqtt_broker.removeprefix("mqtt://").rsplit(":", 1)
        sender = paho.Client(CallbackAPIVersion.VERSION2, client_id="sender", protocol=paho.MQTTv311)
        sender.connect(host, int(port))
        sender.loop_start()
        log = tmp_path / "amqtt.log"
        try:
            for i in range(2):
                sender.publish(f"stall/{i}", b"x", qos=1).wait_for_publish(10)
            deadline = time.monotonic() + 60  # amqtt's 5 s for each PUBACK, however loaded the machine
            while log.read_text().count("such timeouts so far") < 2 and "Traceback" not in log.read_text():
                assert time.monotonic() < deadline, log.read_text()
                sender.publish("poke", b"", qos=0)  # amqtt reports a failed delivery at its next broadcast
                time.sleep(0.5)
        finally:
            sender.loop_stop()
            sender.disconnect()
    finally:
        stalled.close()
    text = log.read_text()
    assert "Traceback" not in text and "Timeout waiting for" not in text, text
    lines = [line for line in text.splitlines() if "such timeouts" in line]
    assert [line.split(": ")[-1] for line in lines] == ["1 such timeouts so far", "2 such timeouts so far"], lines
    assert all(" WARNING a client did not acknowledge in time (PUBACK for packet ID " in line for line in lines), lines
