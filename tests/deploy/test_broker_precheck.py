"""Broker problems in one line, before anything starts: the launcher's start-up check completes an MQTT CONNECT with
the run's login and TLS settings (protocol.mqtt.connect_problem) and names the cause of a refused login, a listener
that is not MQTT, a certificate that does not verify and one made for another host name; over Mosquitto (a password
file and a TLS listener from make-certs.sh) and the embedded amqtt (the run's own users)."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from deploy import run_local
from protocol.mqtt import BrokerAddress, MqttConnection, connect_problem
from services.broker.embedded import free_port, make_credentials, start_broker_process, stop_process
from tests.conftest import HOST, mosquitto_available
from tests.paths import ROOT

MOSQUITTO = ROOT / "deploy" / "mosquitto"
REFUSED = "the broker refused the login of user 'alice'"
NOT_MQTT = "without an MQTT answer (is it an MQTT broker's port?"


class Lab:
    """A Mosquitto with a password file (user alice) on a plain and a TLS listener, its CA file beside it."""

    def __init__(self, plain: int, tls: int, ca: Path) -> None:
        self.plain, self.tls, self.ca = plain, tls, str(ca)


def listening(port: int, proc: subprocess.Popen, timeout: float = 60.0) -> None:
    """Until the port takes TCP connections (an MQTT check would need a login)."""
    deadline = time.monotonic() + timeout
    while True:
        assert proc.poll() is None, f"mosquitto exited with code {proc.returncode}"
        try:
            socket.create_connection((HOST, port), timeout=1).close()
            return
        except OSError:
            assert time.monotonic() < deadline, f"mosquitto does not listen on {port}"
            time.sleep(0.05)


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Lab]:
    if not mosquitto_available() or not shutil.which("mosquitto_passwd") or not shutil.which("openssl"):
        pytest.skip("needs mosquitto, mosquitto_passwd and openssl (apt-get install mosquitto openssl)")
    folder = tmp_path_factory.mktemp("lab")
    subprocess.run(["bash", str(MOSQUITTO / "make-certs.sh"), HOST, str(folder / "certs")], check=True,
                   capture_output=True, timeout=120)
    subprocess.run(["mosquitto_passwd", "-c", "-b", str(folder / "passwd"), "alice", "secret"], check=True,
                   capture_output=True, timeout=60)
    plain, tls = free_port(HOST), free_port(HOST)
    (folder / "mosquitto.conf").write_text(
        f"per_listener_settings false\nallow_anonymous false\npassword_file {folder}/passwd\n"
        f"listener {plain} {HOST}\nlistener {tls} {HOST}\ncafile {folder}/certs/ca.crt\n"
        f"certfile {folder}/certs/server.crt\nkeyfile {folder}/certs/server.key\n"
        + ("user root\n" if os.geteuid() == 0 else ""))
    with (folder / "broker.log").open("wb") as log:
        proc = subprocess.Popen(["mosquitto", "-c", str(folder / "mosquitto.conf")], stdout=log,
                                stderr=subprocess.STDOUT)
    try:
        for port in (plain, tls):
            listening(port, proc)
        yield Lab(plain, tls, folder / "certs" / "ca.crt")
    finally:
        stop_process(proc)


@pytest.fixture
def not_mqtt() -> Iterator[int]:
    """A listener that answers like a web server and hangs up: what a wrong port often is."""
    server = socket.create_server((HOST, 0))
    stop = threading.Event()

    def serve() -> None:
        while not stop.is_set():
            try:
                conn, _ = server.accept()
            except OSError:
                return
            with conn:
                conn.recv(256)
                conn.sendall(b"HTTP/1.1 400 Bad Request\r\n\r\n")

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield server.getsockname()[1]
    finally:
        stop.set()
        server.close()


def at(url: str, password: str = "secret", ca: str | None = None) -> BrokerAddress:
    return BrokerAddress.parse(url, username="alice", password=password, ca_file=ca)


def test_a_process_that_cannot_start_says_why(lab: Lab) -> None:
    """A refused login at once (whatever the timeout), any other cause once the timeout has passed."""
    with pytest.raises(ConnectionError, match=f"at mqtt://{HOST}:{lab.plain}: {REFUSED}"):
        MqttConnection(at(f"mqtt://{HOST}:{lab.plain}", "wrong"), "c").start(timeout=60)
    with pytest.raises(ConnectionError, match="within 1 s: TLS: the broker's certificate does not verify"):
        MqttConnection(at(f"mqtts://{HOST}:{lab.tls}"), "c").start(timeout=1)


def test_each_cause_has_its_own_line_over_mosquitto(lab: Lab, not_mqtt: int) -> None:
    assert connect_problem(at(f"mqtt://{HOST}:{lab.plain}")) is None
    assert connect_problem(at(f"mqtts://{HOST}:{lab.tls}", ca=lab.ca)) is None
    assert REFUSED in (connect_problem(at(f"mqtt://{HOST}:{lab.plain}", "wrong")) or "")
    assert "certificate does not verify" in (connect_problem(at(f"mqtts://{HOST}:{lab.tls}")) or "")
    assert "is not for host 'localhost'" in (connect_problem(at(f"mqtts://localhost:{lab.tls}", ca=lab.ca)) or "")
    assert "TLS handshake failed" in (connect_problem(at(f"mqtts://{HOST}:{lab.plain}", ca=lab.ca)) or "")
    assert NOT_MQTT in (connect_problem(at(f"mqtt://{HOST}:{lab.tls}")) or "")
    assert NOT_MQTT in (connect_problem(at(f"mqtt://{HOST}:{not_mqtt}")) or "")


def test_a_refused_login_over_the_embedded_broker(tmp_path: Path) -> None:
    creds = make_credentials(tmp_path / "broker", "r1", ["w0"])
    with (tmp_path / "broker.log").open("wb") as log:
        proc, port = start_broker_process(HOST, credentials=creds, stdout=log, stderr=subprocess.STDOUT)
    try:
        url = f"mqtt://{HOST}:{port}"
        assert connect_problem(BrokerAddress.parse(url, username="chief", password=creds.users["chief"])) is None
        problem = connect_problem(BrokerAddress.parse(url, username="chief", password="guess")) or ""
        assert "the broker refused the login of user 'chief'" in problem, problem
        with pytest.raises(ConnectionError) as err:  # a process that cannot start says why too, at the refusal
            MqttConnection(BrokerAddress.parse(url, username="chief", password="guess"), "c").start(timeout=60)
        assert str(err.value) == f"could not connect to the MQTT broker at {url}: {problem}"
    finally:
        stop_process(proc)


@pytest.fixture
def env(monkeypatch: pytest.MonkeyPatch) -> pytest.MonkeyPatch:
    for var in [v for v in os.environ if v.startswith("FEDRL_")]:
        monkeypatch.delenv(var)
    monkeypatch.setenv("FEDRL_ENV_FILE", os.devnull)
    return monkeypatch


@pytest.mark.parametrize("case", ["password", "no CA", "host name", "not MQTT"])
def test_the_launcher_refuses_in_one_line_before_anything_starts(case: str, lab: Lab, not_mqtt: int,
                                                                 env: pytest.MonkeyPatch, tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    env.setenv("FEDRL_MQTT_USERNAME", "alice")
    env.setenv("FEDRL_MQTT_PASSWORD", "wrong" if case == "password" else "secret")
    if case == "host name":
        env.setenv("FEDRL_MQTT_CA_FILE", lab.ca)
    broker = {"password": f"mqtt://{HOST}:{lab.plain}", "no CA": f"mqtts://{HOST}:{lab.tls}",
              "host name": f"mqtts://localhost:{lab.tls}", "not MQTT": f"mqtt://{HOST}:{not_mqtt}"}[case]
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGHUP)}
    code = run_local.main(["--broker", broker, "--run-dir", str(tmp_path / "run"), "--dashboard-port", "off"])
    # the launcher ignores a repeated kill while it stops, then gives the handlers back: a SIGTERM ignored for good
    # in this process would be inherited by whatever it starts later (a fork server's workers ignored theirs)
    assert {sig: signal.getsignal(sig) for sig in handlers} == handlers
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1 and err[0].startswith("cannot reach the MQTT broker at "), err
    assert {"password": REFUSED, "no CA": "does not verify", "host name": "not for host 'localhost'",
            "not MQTT": NOT_MQTT}[case] in err[0]
    assert not (tmp_path / "run").exists()  # nothing started, nothing left behind
