"""The MQTT helper against real brokers: TCP_NODELAY, last will, reconnect and resubscribe after a broker restart,
and a handler that raises does not stop delivery."""

from __future__ import annotations

import queue
import socket
import subprocess
import time
from pathlib import Path

from protocol.mqtt import BrokerAddress, MqttConnection
from services.broker.embedded import free_port, start_broker_process, stop_process
from tests.conftest import HOST


def test_nodelay_is_set_on_the_socket(any_broker: str) -> None:
    conn = MqttConnection(BrokerAddress.parse(any_broker), client_id="nodelay-probe").start()
    try:
        sock = conn._client.socket()
        assert sock is not None
        assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY) == 1
    finally:
        conn.stop()


def test_last_will_reaches_subscribers_when_a_client_dies(any_broker: str) -> None:
    got: queue.Queue = queue.Queue()
    watcher = MqttConnection(BrokerAddress.parse(any_broker), client_id="watcher").start()
    watcher.subscribe("t/+/status", lambda t, p: got.put((t, p)))
    dying = MqttConnection(BrokerAddress.parse(any_broker), client_id="dying", will=("t/dying/status", b"offline"))
    dying.start()
    watcher.publish("t/ping/status", b"ping").wait_for_publish(5)
    assert got.get(timeout=5) == ("t/ping/status", b"ping")  # the subscription is live
    dying._client.socket().close()  # an abrupt loss: no DISCONNECT packet
    dying._client.loop_stop()
    assert got.get(timeout=20) == ("t/dying/status", b"offline")
    watcher.stop()


def test_reconnects_and_resubscribes_after_a_broker_restart(tmp_path: Path) -> None:
    port = free_port(HOST)
    log = (tmp_path / "broker.log").open("wb")
    proc, _ = start_broker_process(HOST, port, stdout=log, stderr=subprocess.STDOUT)
    got: queue.Queue = queue.Queue()
    failures = []

    def handler(topic: str, payload: bytes) -> None:
        if payload == b"boom":
            failures.append(payload)
            raise RuntimeError("handler bug")
        got.put(payload)

    conn = MqttConnection(BrokerAddress(HOST, port), client_id="survivor").start()
    conn.subscribe("r/#", handler)
    try:
        conn.publish("r/x", b"boom").wait_for_publish(5)
        conn.publish("r/x", b"before").wait_for_publish(5)
        assert got.get(timeout=5) == b"before"
        assert failures == [b"boom"] and conn.handler_errors == 1

        stop_process(proc)
        for _ in range(100):  # the client notices the broker is gone
            if not conn.connected.is_set():
                break
            time.sleep(0.05)
        assert not conn.connected.is_set()
        proc, _ = start_broker_process(HOST, port, stdout=log, stderr=subprocess.STDOUT)
        assert conn.connected.wait(20), "did not reconnect"
        # Published after the reconnect: arrives only if the subscription was renewed.
        for _ in range(50):
            conn.publish("r/y", b"after").wait_for_publish(5)
            try:
                assert got.get(timeout=0.2) == b"after"
                break
            except queue.Empty:
                continue
        else:
            raise AssertionError("no message after the broker restart")
    finally:
        conn.stop()
        stop_process(proc)
        log.close()


def test_a_stopped_client_leaves_no_session_that_queues_messages(any_broker: str) -> None:
    """Sessions are persistent (clean session off) so that a reconnect loses nothing; but a client id is never used
    again once its process stops, so a stopped connection must not leave the broker queueing every later QoS 1
    message for it (a soak saw Mosquitto grow 22 MiB a minute with finished workers' sessions). Reconnecting under
    the stopped id shows what the broker kept for it: nothing."""
    import paho.mqtt.client as paho
    from paho.mqtt.enums import CallbackAPIVersion

    address = BrokerAddress.parse(any_broker)
    gone = MqttConnection(address, client_id="finished").start()
    gone.subscribe("t/broadcast", lambda t, p: None)
    time.sleep(0.5)  # the SUBSCRIBE is through
    gone.stop()
    sender = MqttConnection(address, client_id="sender").start()
    for i in range(5):
        sender.publish("t/broadcast", f"m{i}".encode()).wait_for_publish(5)
    got: queue.Queue = queue.Queue()
    probe = paho.Client(CallbackAPIVersion.VERSION2, client_id=gone.client_id, protocol=paho.MQTTv311,
                        clean_session=False)
    probe.on_message = lambda c, u, m: got.put(m.payload)
    probe.connect(address.host, address.port)
    probe.loop_start()
    try:
        time.sleep(2.0)
        assert got.empty(), f"the broker kept {got.qsize()} messages for a stopped client"
    finally:
        probe.disconnect()
        probe.loop_stop()
        sender.stop()
