"""A clean stop publishes no last will: every queued packet and a DISCONNECT reach the broker
before the network loop ends, for the connections of a worker, the chief and the bridge, on both brokers, and for a
real ``python -m rpi_bridge`` (on a simulated SPI peer), ``python -m services.qube_sim``, ``python -m worker`` and
``python -m chief`` stopped by SIGTERM."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from protocol import topics
from protocol.codec import decode, encode
from protocol.messages import QubeStatus, WorkerStatus
from protocol.mqtt import BrokerAddress, MqttConnection
from protocol.routes import CHIEF, qos_of, received_by
from tests.paths import ROOT

RUN = "stoprun"

#: A spidev module answering with the simulated rig: ``python -m rpi_bridge`` runs unchanged on it.
FAKE_SPIDEV = '''
from services.qube_sim.spi_peer import SimulatedQube


class SpiDev:
    def open(self, bus, device):
        self._rig = SimulatedQube(seed=1)

    def xfer2(self, data):
        return list(self._rig.transfer(bytes(data)))

    def close(self):
        pass
'''


class Watcher:
    """A subscriber that keeps what arrives on one topic."""

    def __init__(self, url: str, topic: str, client_id: str = "watcher") -> None:
        self.got: list[bytes] = []
        self.event = threading.Event()
        self.conn = MqttConnection(BrokerAddress.parse(url), client_id=client_id).start()
        self.conn.subscribe(topic, self._on, qos=1)
        time.sleep(0.3)  # the SUBACK

    def _on(self, topic: str, payload: bytes) -> None:
        self.got.append(payload)
        self.event.set()

    def details(self) -> list[str]:
        return [decode(p).detail for p in self.got]  # type: ignore[attr-defined]


ROLES = {
    # the worker's connection: a will on its status topic, the chief's topics subscribed
    "worker": (topics.worker(RUN, "w0", topics.STATUS),
               encode(WorkerStatus(worker_id="w0", state="offline", detail="connection lost")),
               [topics.chief(RUN, "#")]),
    # the bridge's: a will on the rig's status, action (QoS 0) and reset (QoS 1) subscribed
    "bridge": (topics.rig("rig9", topics.STATUS),
               encode(QubeStatus(rig_id="rig9", state="offline", detail="connection lost")),
               [topics.rig("rig9", topics.ACTION), topics.rig("rig9", topics.RESET)]),
    # the chief has no will; its many subscriptions and its last QoS 1 message must still go out
    "chief": (None, b"", [route.filter(run=RUN) for route in received_by(CHIEF)]),
}


@pytest.mark.parametrize("role", sorted(ROLES))
def test_a_stopped_connection_leaves_no_will_and_sends_its_last_message(any_broker: str, role: str) -> None:
    will_topic, will, filters = ROLES[role]
    last = topics.chief(RUN, "last") if will_topic is None else will_topic
    watcher = Watcher(any_broker, last)
    try:
        for attempt in range(5):  # the lost DISCONNECT was a race: it happened 6 times out of 6 with the bridge
            conn = MqttConnection(BrokerAddress.parse(any_broker), client_id=f"stop-{role}",
                                  will=(will_topic, will) if will_topic else None).start()
            for topic_filter in filters:
                conn.subscribe(topic_filter, lambda t, p: None, qos=qos_of(topic_filter) if "#" not in topic_filter
                               and "+" not in topic_filter else 1)
            time.sleep(0.2)
            goodbye = (encode(WorkerStatus(worker_id="w0", state="offline", detail=f"stopped {attempt}"))
                       if role != "bridge" else
                       encode(QubeStatus(rig_id="rig9", state="offline", detail=f"stopped {attempt}")))
            conn.publish(last, goodbye, qos=1)
            conn.stop()
        time.sleep(1.5)  # a will would be published at once (both brokers), a late one within the keep-alive
        assert watcher.details() == [f"stopped {i}" for i in range(5)]  # every goodbye, in order, and no will
    finally:
        watcher.conn.stop()


@pytest.mark.parametrize("module", ["rpi_bridge", "services.qube_sim"])
def test_sigterm_stops_the_bridge_without_a_will(any_broker: str, tmp_path: Path, module: str) -> None:
    (tmp_path / "spidev.py").write_text(FAKE_SPIDEV)
    env = {**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{ROOT}", "FEDRL_BROKER": any_broker,
           "FEDRL_RIG_ID": "rig5", "FEDRL_STATE_DIR": str(tmp_path / "state"), "FEDRL_LOG_LEVEL": "INFO"}
    watcher = Watcher(any_broker, topics.rig("rig5", topics.STATUS))
    log = (tmp_path / "bridge.log").open("wb")
    proc = subprocess.Popen([sys.executable, "-m", module], cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        assert watcher.event.wait(15), (tmp_path / "bridge.log").read_text()  # "bridge up"
        time.sleep(0.5)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(15) == 0, (tmp_path / "bridge.log").read_text()
        time.sleep(1.5)
        details = watcher.details()
        assert details[0] == "bridge up" and details[-1] == "bridge loop stopped", details
        assert "connection lost" not in details, details
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        log.close()
        watcher.conn.stop()


def test_sigterm_stops_a_worker_and_the_chief_without_a_will(any_broker: str, tmp_path: Path) -> None:
    """A real ``python -m worker`` and ``python -m chief`` mid-run, each stopped by SIGTERM: the worker says
    ``stopped`` and its status topic never shows its last will; the chief (which has no will) ends the run resumably
    and its last messages (the RunStop, then the cleared claim) still reach the broker before it disconnects."""
    run, run_dir = "sigterm", tmp_path / "run"
    common = ["--broker", any_broker, "--run-id", run, "--env", "CartPole-v0"]
    status = Watcher(any_broker, topics.worker(run, "w0", topics.STATUS), "watch-status")
    chief_said = Watcher(any_broker, topics.chief(run, "#"), "watch-chief")
    logs = {name: (tmp_path / f"{name}.log").open("wb") for name in ("chief", "worker")}
    chief = subprocess.Popen([sys.executable, "-m", "chief", *common, "--workers", "1", "--max-episodes", "2000",
                              "--run-dir", str(run_dir)], cwd=ROOT, stdout=logs["chief"], stderr=subprocess.STDOUT)
    worker = subprocess.Popen([sys.executable, "-m", "worker", *common, "--worker-id", "w0"], cwd=ROOT,
                              stdout=logs["worker"], stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while not any(decode(p).state == "training" for p in status.got):  # type: ignore[attr-defined]
            assert time.monotonic() < deadline and worker.poll() is None, (tmp_path / "worker.log").read_text()
            time.sleep(0.1)
        time.sleep(1.0)  # a few rounds
        worker.send_signal(signal.SIGTERM)
        assert worker.wait(15) == 130, (tmp_path / "worker.log").read_text()
        chief.send_signal(signal.SIGTERM)
        assert chief.wait(15) == 130, (tmp_path / "chief.log").read_text()
        time.sleep(1.5)  # a will would be published at once (both brokers), a late one within the keep-alive
        details = status.details()
        assert details[-1] == "interrupted" and "connection lost" not in details, details
        stops = [m for m in map(decode, chief_said.got) if m.kind == "run_stop"]  # type: ignore[attr-defined]
        assert [s.reason for s in stops] == ["interrupted"], stops  # type: ignore[attr-defined]
        claim = Watcher(any_broker, topics.claim(run), "watch-claim")
        claim.conn.stop()
        assert claim.got == [], claim.got  # the claim was cleared: no retained claim is left
    finally:
        for proc in (worker, chief):
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        for log in logs.values():
            log.close()
        status.conn.stop()
        chief_said.conn.stop()


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_a_signal_stops_an_edge_chief_cleanly(amqtt_broker: str, tmp_path: Path, sig: signal.Signals) -> None:
    """An edge chief had no handler: SIGTERM or SIGHUP killed it with the signal's code. Now it says so in one line
    and exits 130, as the root chief does."""
    log = tmp_path / "edge.log"
    with log.open("wb") as out:
        edge = subprocess.Popen([sys.executable, "-m", "chief", "--role", "edge", "--edge-id", "e0", "--broker",
                                 amqtt_broker, "--run-id", "edgestop"], cwd=ROOT, stdout=out, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + 60
            while "waiting for the root's RunStart" not in log.read_text():
                assert time.monotonic() < deadline and edge.poll() is None, log.read_text()
                time.sleep(0.1)
            edge.send_signal(sig)
            assert edge.wait(15) == 130, log.read_text()
        finally:
            if edge.poll() is None:
                edge.kill()
                edge.wait()
    said = log.read_text()
    assert "edge e0: interrupted" in said and "Traceback" not in said, said


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_a_qube_worker_waiting_on_a_rig_reset_stops_at_once(amqtt_broker: str, tmp_path: Path,
                                                           sig: signal.Signals) -> None:
    """A worker of env qube whose rig never answers its reset (none is running) waits in the reset up to 60 s: a
    signal ends that wait at once, with the worker's code 130, `stopped` on its status topic and no traceback (it
    said "stopping cleanly", then failed with a TimeoutError 59 s later). The bound (2 s) is left to a generous
    timeout here: the suite must not depend on the machine's speed."""
    run = "resetstop"
    common = ["--broker", amqtt_broker, "--run-id", run, "--env", "qube"]
    status = Watcher(amqtt_broker, topics.worker(run, "w0", topics.STATUS), "watch-status")
    logs = {name: (tmp_path / f"{name}.log").open("wb") for name in ("chief", "worker")}
    chief = subprocess.Popen([sys.executable, "-m", "chief", *common, "--workers", "1", "--run-dir",
                              str(tmp_path / "run")], cwd=ROOT, stdout=logs["chief"], stderr=subprocess.STDOUT)
    worker = subprocess.Popen([sys.executable, "-m", "worker", *common, "--worker-id", "w0", "--rig-id", "nobody"],
                              cwd=ROOT, stdout=logs["worker"], stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while not any(decode(p).state == "training" for p in status.got):  # type: ignore[attr-defined]
            assert time.monotonic() < deadline and worker.poll() is None, (tmp_path / "worker.log").read_text()
            time.sleep(0.1)
        time.sleep(0.5)  # in the reset's wait (it publishes its request every second)
        worker.send_signal(sig)
        assert worker.wait(10) == 130, (tmp_path / "worker.log").read_text()
        log = (tmp_path / "worker.log").read_text()
        assert "Traceback" not in log and "failed" not in log, log
        assert decode(status.got[-1]).state == "stopped"  # type: ignore[attr-defined]
        chief.send_signal(sig)
        assert chief.wait(10) == 130, (tmp_path / "chief.log").read_text()
        assert "Traceback" not in (tmp_path / "chief.log").read_text()
    finally:
        for proc in (worker, chief):
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        for log_file in logs.values():
            log_file.close()
        status.conn.stop()


def handles(pid: int, sig: signal.Signals) -> bool:
    """Whether process ``pid`` has a handler of its own for ``sig`` installed (its SigCgt mask)."""
    status = Path(f"/proc/{pid}/status").read_text()
    caught = int(next(line.split()[1] for line in status.splitlines() if line.startswith("SigCgt:")), 16)
    return bool(caught >> (sig - 1) & 1)


@pytest.mark.parametrize(("module", "code"), [("worker", 130), ("chief", 130), ("services.qube_sim", 0),
                                              ("services.dashboard", 0)])
def test_a_signal_while_the_broker_cannot_be_reached_stops_at_once(tmp_path: Path, module: str, code: int) -> None:
    """Each waited out its connect timeout (10 s, the rig's 60 s), then exited 1; now a signal ends the wait with
    the process's stopped code. The handler is in place (the process's signal mask says so) before it is sent."""
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-m", module, "--broker", f"mqtt://127.0.0.1:{port}", "--run-dir",
                             str(tmp_path / "run")] if module == "chief" else
                            [sys.executable, "-m", module, "--broker", f"mqtt://127.0.0.1:{port}"],
                            cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT), "FEDRL_DASHBOARD_PORT": "0"},
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 30
        while not handles(proc.pid, signal.SIGHUP):
            assert time.monotonic() < deadline and proc.poll() is None, proc.communicate()[0]
            time.sleep(0.05)
        time.sleep(0.2)
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=8)  # under the 10 s of the connect timeout that ended it before
        assert proc.returncode == code and "Traceback" not in out, out
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
