"""A transport is chosen by value (protocol/transport.py): every service takes a Connect, by default its settings'
``connector()``, and nothing but ``protocol.transport.connector`` makes an MqttConnection. Choosing the in-memory
hub is passing ``Hub.connect`` instead, the rig bridge and the dashboard included, or naming it by address:
``memory://<name>``, on which a federation gives the same per-worker episodes as over ``mqtt://``."""

from __future__ import annotations

import ast
import queue
import threading
import time
import uuid
from pathlib import Path

import pytest

from protocol import topics
from protocol.codec import decode, encode
from protocol.memory import Hub, MemoryConnection
from protocol.messages import QubeStatus, WorkerStatus
from protocol.mqtt import MqttConnection
from protocol.transport import connector
from tests.federations import over_mqtt, per_worker_final
from tests.paths import ROOT
from worker.settings import WorkerSettings

PACKAGES = ("protocol", "runtime", "chief", "worker", "rpi_bridge", "services", "deploy", "bench")
FACTORY = "protocol/transport.py"
#: Seconds a message may take across the in-memory hub before the test gives up (a bound, not a measurement).
PATIENCE = 30.0


def test_only_the_factory_makes_an_mqtt_connection() -> None:
    makers = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.Call) and "MqttConnection" in (getattr(node.func, "id", None),
                                                                       getattr(node.func, "attr", None)):
                    makers.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert [m for m in makers if not m.startswith(FACTORY)] == [], "MqttConnection( outside protocol/transport.py"
    assert makers, "the factory itself was not found"


def test_a_services_connector_is_its_settings_broker_login_and_payload_cap() -> None:
    cfg = WorkerSettings.given(broker="mqtts://127.0.0.1:9", mqtt_username="w0", mqtt_password="pw",
                               max_payload=2048)
    conn = cfg.connector()("fedrl-r-worker-w0")  # made, never started: nothing connects
    assert isinstance(conn, MqttConnection)
    assert (conn.address.tls, conn.address.username, conn.address.password) == (True, "w0", "pw")
    assert conn.max_payload == 2048 and conn.client_id.startswith("fedrl-r-worker-w0-")


def _first(inbox: queue.Queue[bytes]) -> bytes:
    return inbox.get(timeout=PATIENCE)


def test_the_rig_bridge_runs_on_the_in_memory_hub() -> None:
    from rpi_bridge.service import BridgeService
    from services.qube_sim.clock import VirtualClock
    from services.qube_sim.spi_peer import SimulatedQube

    hub, said = Hub(), queue.Queue[bytes]()
    listener = hub.connect("listener").start()
    listener.subscribe(topics.rig("rig0", topics.STATUS), lambda t, p: said.put(p))
    clock = VirtualClock()
    service = BridgeService(SimulatedQube(seed=1, period_s=0, clock=clock), "rig0", hub.connect, lockstep=True,
                            advance=clock.advance, clock=clock, client_prefix="memory")
    loop = threading.Thread(target=service.run, daemon=True)
    loop.start()
    try:
        status = decode(_first(said), QubeStatus)
    finally:
        service.stop_event.set()
        loop.join(PATIENCE)
        listener.stop()
    assert (status.rig_id, status.state, status.detail) == ("rig0", "idle", "bridge up")


def test_the_dashboards_feed_runs_on_the_in_memory_hub() -> None:
    from services.dashboard.feed import MqttFeed
    from services.dashboard.hub import Hub as ViewHub
    from services.dashboard.view import RunView

    hub = Hub()
    feed = MqttFeed(hub.connect, "r", ViewHub(RunView("r")), where="the in-memory hub").start()
    sender = hub.connect("sender").start()
    try:
        sender.publish(topics.worker("r", "w0", topics.STATUS), encode(WorkerStatus(worker_id="w0", state="online")))
        deadline = time.monotonic() + PATIENCE
        while feed.received == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        sender.stop()
        feed.stop()
    assert feed.stats()["received"] == 1 and feed.stats()["rejected"] == {}


def test_a_memory_address_names_one_hub_of_this_process() -> None:
    name = f"memory://hub-{uuid.uuid4().hex[:8]}"
    cfg = WorkerSettings.given(broker=name, mqtt_username="ignored")
    a, b = cfg.connector()("a").start(), connector(name)("b").start()
    said = queue.Queue[bytes]()
    try:
        assert isinstance(a, MemoryConnection) and a.hub is b.hub and cfg.where() == name
        b.subscribe("x/#", lambda t, p: said.put(p))
        a.publish("x/y", b"hello")
        assert _first(said) == b"hello"
        assert connector(f"{name}-other")("c").hub is not a.hub  # another name, another hub
    finally:
        a.stop()
        b.stop()
    for bad in ("memory://", "memory://a/b"):
        with pytest.raises(ValueError, match="memory://<name>"):
            WorkerSettings.given(broker=bad)


def test_a_federation_over_memory_and_over_mqtt_gives_the_same_episodes(amqtt_broker: str, tmp_path: Path) -> None:
    """The same services and settings, only the broker address differs: every worker's episodes, env steps and final
    PI are the same."""
    fed = ("CartPole-v0", "weighted", 1, 2, 3)  # task, strategy, seed, workers, episodes
    over_mqtt(f"memory://fed-{uuid.uuid4().hex[:8]}", "mem", tmp_path / "memory", *fed)
    over_mqtt(amqtt_broker, "mqtt", tmp_path / "mqtt", *fed)
    assert per_worker_final(tmp_path / "memory") == per_worker_final(tmp_path / "mqtt")
    assert [w[1] for w in per_worker_final(tmp_path / "memory")] == [3, 3]
