"""Client-id takeover under the production Mosquitto config: an authenticated user who connects
with another client's id does not disconnect it (``use_username_as_clientid``), and our own connections still
publish and receive."""

from __future__ import annotations

import os
import queue
import re
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import paho.mqtt.client as paho
import pytest
from paho.mqtt.enums import CallbackAPIVersion

from deploy.mosquitto_conf import render
from protocol.mqtt import BrokerAddress, MqttConnection
from services.broker.embedded import free_port, stop_process
from tests.conftest import HOST, mosquitto_available
from tests.deploy.test_deploy_static import MOSQUITTO, make_users, wait_for_listener

R = "r1"


@pytest.fixture
def prod_broker(tmp_path: Path) -> Iterator[tuple[int, dict[str, str]]]:
    """mosquitto.prod.conf on a free loopback port (plain listener only), users from make-users.sh (run r1)."""
    if not mosquitto_available() or not shutil.which("mosquitto_passwd"):
        pytest.skip("mosquitto and mosquitto_passwd are not installed (apt-get install mosquitto)")
    secrets = make_users(tmp_path, "--run", R)
    pw = {path.stem: dict(ln.split("=", 1) for ln in path.read_text().split())["FEDRL_MQTT_PASSWORD"]
          for path in (secrets / "credentials").iterdir()}
    port = free_port(HOST)
    conf = render((MOSQUITTO / "mosquitto.prod.conf").read_text(), {
        "FEDRL_MOSQUITTO_CONFIG_DIR": str(secrets), "FEDRL_MQTT_LOCAL_PORT": str(port), "FEDRL_MQTT_LOCAL_HOST": HOST})
    conf = re.sub(r"listener 8883\n(cafile|certfile|keyfile|tls_version).*?(?=\n\S*listener)", "", conf, flags=re.S)
    conf = conf.replace("persistence true", "persistence false")
    if os.geteuid() == 0:
        conf += "\nuser root\n"  # else Mosquitto drops to its own user, who cannot read tmp_path
    (tmp_path / "broker.conf").write_text(conf)
    log = (tmp_path / "broker.log").open("wb")
    proc = subprocess.Popen(["mosquitto", "-c", str(tmp_path / "broker.conf")], stdout=log, stderr=subprocess.STDOUT)
    try:
        wait_for_listener(port, proc)
        yield port, pw
    finally:
        stop_process(proc)
        log.close()


class Probe:
    """A raw paho client logged in as ``user`` under ``client_id``, counting its disconnects and queueing messages."""

    def __init__(self, port: int, user: str, password: str, client_id: str, subscribe: str | None = None) -> None:
        self.got: queue.Queue[tuple[str, bytes]] = queue.Queue()
        self.disconnects = 0
        self.ready: queue.Queue[object] = queue.Queue()
        self.client = paho.Client(CallbackAPIVersion.VERSION2, client_id=client_id, protocol=paho.MQTTv311,
                                  clean_session=False, reconnect_on_failure=False)
        self.client.username_pw_set(user, password)
        self.client.on_message = lambda c, u, m: self.got.put((m.topic, bytes(m.payload)))
        self.client.on_disconnect = lambda *a: setattr(self, "disconnects", self.disconnects + 1)
        self.client.on_subscribe = lambda *a: self.ready.put(True)
        self.client.on_connect = lambda c, u, f, rc, p: (c.subscribe(subscribe, qos=1) if subscribe
                                                          else self.ready.put(rc))
        self.client.connect(HOST, port)
        self.client.loop_start()
        self.ready.get(timeout=10)

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


@pytest.mark.parametrize(("victim", "thief"), [("chief", "rig0"), ("w0", "w1")])
def test_another_users_client_id_takes_nothing_over(prod_broker: tuple[int, dict[str, str]], victim: str,
                                                   thief: str) -> None:
    port, pw = prod_broker
    victim_id = f"fedrl-{R}-{victim}-0123456789ab"
    listen = f"fedrl/{R}/worker/#" if victim == "chief" else f"fedrl/{R}/chief/#"
    sender, topic = ("w2", f"fedrl/{R}/worker/w2/hello") if victim == "chief" else ("chief", f"fedrl/{R}/chief/start")
    b = Probe(port, victim, pw[victim], victim_id, subscribe=listen)
    a = Probe(port, thief, pw[thief], victim_id)  # the guessed id
    s = Probe(port, sender, pw[sender], f"sender-{time.monotonic_ns()}")
    try:
        time.sleep(0.5)
        s.client.publish(topic, b"after the takeover", qos=1).wait_for_publish(5)
        assert b.got.get(timeout=5) == (topic, b"after the takeover")
        assert b.disconnects == 0 and b.client.is_connected()
    finally:
        for p in (a, b, s):
            p.close()


def test_our_connections_still_publish_and_receive(prod_broker: tuple[int, dict[str, str]]) -> None:
    port, pw = prod_broker

    def connect(user: str) -> MqttConnection:
        address = BrokerAddress.parse(f"mqtt://{HOST}:{port}", username=user, password=pw[user])
        return MqttConnection(address, client_id=f"fedrl-{R}-{user}").start(timeout=5)

    chief, worker = connect("chief"), connect("w0")
    to_chief: queue.Queue[bytes] = queue.Queue()
    to_worker: queue.Queue[bytes] = queue.Queue()
    try:
        chief.subscribe(f"fedrl/{R}/worker/#", lambda t, p: to_chief.put(p))
        worker.subscribe(f"fedrl/{R}/chief/#", lambda t, p: to_worker.put(p))
        time.sleep(0.5)
        worker.publish(f"fedrl/{R}/worker/w0/hello", b"hello")
        chief.publish(f"fedrl/{R}/chief/start", b"start")
        assert to_chief.get(timeout=5) == b"hello" and to_worker.get(timeout=5) == b"start"
        assert chief.connects == 1 and worker.connects == 1  # nobody was kicked and reconnected
    finally:
        worker.stop()
        chief.stop()
