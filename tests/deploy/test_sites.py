"""A multi-site deployment's brokers (deploy/sites.py): which topics cross a bridge, and the users, ACLs and
configurations ``python -m deploy.sites`` writes, checked statically and on live Mosquitto brokers (a core behind
TLS and passwords, a site bridged to it)."""

from __future__ import annotations

import os
import queue
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from deploy import sites
from deploy.sites import Bridge, Site, bridge_acl, bridge_section, bridge_topics
from protocol.mqtt import BrokerAddress, MqttConnection
from protocol.routes import ROUTES
from services.broker.embedded import free_port, stop_process, wait_for_port
from tests.conftest import HOST, mosquitto_available
from tests.paths import ROOT

MOSQUITTO = ROOT / "deploy" / "mosquitto"


def test_workers_updates_go_out_and_the_chiefs_answers_come_in() -> None:
    crossing = {(t.pattern, t.direction, t.qos) for t in bridge_topics()}
    assert ("fedrl/+/worker/+/update", "out", 1) in crossing
    assert ("fedrl/+/worker/+/status", "out", 1) in crossing  # and with it each worker's last will
    assert ("fedrl/+/chief/aggregate", "in", 1) in crossing
    assert ("qube/+/telemetry", "out", 0) in crossing  # for the dashboard at the core
    patterns = {t.pattern for t in bridge_topics()}
    # A rig's control loop stays at its site; the chief's retained claim stays at the core.
    assert not patterns & {"qube/+/state", "qube/+/action", "qube/+/reset", "fedrl/+/claim"}
    assert {t.route.topic for t in bridge_topics()} < {r.topic for r in ROUTES}
    assert all(t.qos == t.route.qos for t in bridge_topics())


def test_one_run_pins_every_topic() -> None:
    assert all(t.pattern.startswith(("fedrl/r1/", "qube/")) for t in bridge_topics("r1"))


def test_a_retained_route_may_not_cross() -> None:
    placement = {**sites.PLACEMENT, "dashboard": sites.SITE}  # a dashboard at a site would read the claim there
    with pytest.raises(ValueError, match="retained"):
        bridge_topics(placement=placement)


def test_the_bridge_keeps_its_session_under_a_fixed_id() -> None:
    text = bridge_section(Bridge("a", "core:1883"))
    assert re.search(r"^cleansession false$", text, re.M)
    assert re.search(r"^remote_clientid bridge-a$", text, re.M)
    assert "remote_username" not in text and "bridge_cafile" not in text
    secured = bridge_section(Bridge("a", "core:8883", username="bridge-a", password="pw", cafile="/c/ca.crt"))
    assert "remote_password pw" in secured and "bridge_cafile /c/ca.crt" in secured


@pytest.mark.parametrize("bad", ["a", "a=x", "a=2:3", "a/b=1", "=1", "a=1:x"])
def test_a_bad_site_is_refused(bad: str) -> None:
    with pytest.raises(ValueError):
        Site.parse(bad)


def test_a_sites_bridge_speaks_only_for_its_own_workers() -> None:
    acl = bridge_acl(Site.parse("a=2:1"), "r1")
    assert "topic write fedrl/r1/worker/a-w1/update" in acl and "topic write qube/a-rig0/telemetry" in acl
    assert "b-w0" not in acl and "topic write fedrl/r1/worker/+/" not in acl
    assert "topic read fedrl/r1/chief/aggregate" in acl


def test_the_cli_refuses_a_bad_request_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for argv in (["--site", "a=1", "--core", "nohost"], ["--site", "a=1", "--site", "a=2", "--core", "c:1"],
                 ["--site", "core=1", "--core", "c:1"]):
        assert sites.main([*argv, "-o", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and err.startswith("python -m deploy.sites: "), err
    assert not (tmp_path / "x").exists()


def lab_conf(conf: str, folder: Path, plain: int, tls: int) -> str:
    """A generated configuration adapted to this test: its files in ``folder``, its two listeners on loopback ports,
    no persistence, run as root where the test is."""
    conf = conf.replace("/mosquitto/config/", f"{folder}/").replace("/mosquitto/certs/", f"{folder}/certs/")
    conf = conf.replace("listener 1883 127.0.0.1", f"listener {plain} {HOST}")
    conf = conf.replace("listener 8883\n", f"listener {tls} {HOST}\n")
    conf = conf.replace("persistence true", "persistence false")
    return conf + ("\nuser root\n" if os.geteuid() == 0 else "")


def login(folder: Path, user: str) -> dict[str, str]:
    env = dict(line.split("=", 1) for line in (folder / "credentials" / f"{user}.env").read_text().split())
    return {"username": env["FEDRL_MQTT_USERNAME"], "password": env["FEDRL_MQTT_PASSWORD"]}


@pytest.mark.skipif(not mosquitto_available() or not shutil.which("mosquitto_passwd") or not shutil.which("openssl"),
                    reason="needs mosquitto, mosquitto_passwd and openssl (apt-get install mosquitto openssl)")
def test_generated_brokers_carry_a_run_over_tls_and_keep_sites_apart(tmp_path: Path) -> None:
    """The core with mosquitto.prod.conf and TLS; site a bridged to it over TLS with its own login. A worker's
    update reaches the chief, the chief's answer reaches the worker; what site a forwards for another site's
    worker the core refuses."""
    plain, tls, site_port, site_tls = (free_port(HOST) for _ in range(4))
    out = tmp_path / "sites"
    assert sites.main(["--site", "a=1", "--site", "b=1", "--core", f"{HOST}:{tls}", "--core-ca",
                       "/mosquitto/certs/ca.crt", "--run", "r1", "-o", str(out)]) == 0
    core, site = out / "core", out / "site-a"
    subprocess.run(["bash", str(MOSQUITTO / "make-certs.sh"), HOST, str(core / "certs")], check=True,
                   capture_output=True, timeout=120)
    shutil.copytree(core / "certs", site / "certs")  # one lab CA, one host: the same server certificate
    sites.add_user(site, "admin", "admin-pw", "user admin\ntopic readwrite #\n")  # may publish for anybody
    procs = []
    try:
        for folder, port, tls_port in ((core, plain, tls), (site, site_port, site_tls)):
            (folder / "broker.conf").write_text(lab_conf((folder / "mosquitto.conf").read_text(), folder, port,
                                                         tls_port))
            log = (folder / "broker.log").open("wb")
            procs.append(subprocess.Popen(["mosquitto", "-c", str(folder / "broker.conf")], stdout=log,
                                          stderr=subprocess.STDOUT))
            wait_for_port(HOST, port, proc=procs[-1])
        chief, at_chief = connect(f"mqtt://{HOST}:{plain}", "chief", "fedrl/r1/worker/+/update", **login(core, "chief"))
        worker, at_worker = connect(f"mqtt://{HOST}:{site_port}", "a-w0", "fedrl/r1/chief/aggregate",
                                    **login(site, "a-w0"))
        admin = MqttConnection(BrokerAddress.parse(f"mqtt://admin:admin-pw@{HOST}:{site_port}"), "admin").start()
        try:
            # Published first, so that it would reach the chief first (each side keeps the order).
            admin.publish("fedrl/r1/worker/b-w0/update", b"site a speaking for b-w0").wait_for_publish(5)
            worker.publish("fedrl/r1/worker/a-w0/update", b"update").wait_for_publish(5)
            assert at_chief.get(timeout=10) == ("fedrl/r1/worker/a-w0/update", b"update")
            chief.publish("fedrl/r1/chief/aggregate", b"answer").wait_for_publish(5)
            assert at_worker.get(timeout=10) == ("fedrl/r1/chief/aggregate", b"answer")
            assert at_chief.empty(), "the core let site a publish for another site's worker"
        finally:
            for conn in (chief, worker, admin):
                conn.stop()
    finally:
        for proc in procs:
            stop_process(proc)


def connect(url: str, name: str, topic: str, username: str, password: str
            ) -> tuple[MqttConnection, queue.Queue[tuple[str, bytes]]]:
    got: queue.Queue[tuple[str, bytes]] = queue.Queue()
    conn = MqttConnection(BrokerAddress.parse(url, username=username, password=password), name).start()
    conn.subscribe(topic, lambda t, payload: got.put((t, payload)))
    return conn, got


@pytest.mark.skipif(shutil.which("git") is None or not (ROOT / ".git").exists(), reason="not a git checkout")
def test_the_secrets_deploy_sites_writes_are_never_committed() -> None:
    paths = [f"{folder}/{place}/{name}" for folder in ("deploy/k8s/example", "deploy/swarm/secrets",
                                                        "deploy/mosquitto/secrets/sites")
             for place in ("core", "site-a") for name in sites.SECRET_FILES]
    done = subprocess.run(["git", "check-ignore", "--no-index", *paths], capture_output=True, text=True, cwd=ROOT)
    assert sorted(done.stdout.split()) == sorted(paths)


def test_each_workers_credentials_hold_its_own_key_and_the_chief_key_never_the_run_key(tmp_path: Path) -> None:
    from protocol.auth import chief_key, worker_key

    creds = tmp_path / "credentials"
    creds.mkdir()
    (creds / "chief.env").write_text("FEDRL_MQTT_USERNAME=chief\n")
    (creds / "a-w0.env").write_text("FEDRL_MQTT_USERNAME=a-w0\nFEDRL_WORKER_ID=a-w0\n")
    key = "k" * 64
    sites.with_key(tmp_path, key)
    env = {p.stem: dict(line.split("=", 1) for line in p.read_text().split()) for p in creds.glob("*.env")}
    assert env["chief"]["FEDRL_RUN_KEY"] == key
    assert env["a-w0"]["FEDRL_WORKER_KEY"] == worker_key(key.encode(), "a-w0")
    assert env["a-w0"]["FEDRL_CHIEF_KEY"] == chief_key(key.encode()) and "FEDRL_RUN_KEY" not in env["a-w0"]
