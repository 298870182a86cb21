"""Deployment assets checked without a Docker engine: docker-compose.yml, deploy/Dockerfile, .env.example, the
Mosquitto ACL (statically and, where Mosquitto is installed, against a live broker), the Raspberry Pi unit."""

from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

from deploy.mosquitto_conf import placeholders, render
from deploy.settings import DockerSettings
from runtime.settings import env_name
from services.broker.embedded import free_port, stop_process
from tests.conftest import HOST, mosquitto_available
from tests.paths import ROOT

COMPOSE = ROOT / "docker-compose.yml"
HOSTNET = ROOT / "deploy" / "dev" / "compose.hostnet.yml"
DOCKERFILE = ROOT / "deploy" / "Dockerfile"
ENV_EXAMPLE = ROOT / ".env.example"
MOSQUITTO = ROOT / "deploy" / "mosquitto"
ROLES = ("chief", "worker", "qube-sim", "bridge")
LEARN_ONLY = ("torch", "gymnasium", "matplotlib")


def compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def dockerfile_stages() -> dict[str, tuple[str, list[str]]]:
    """Stage name -> (its FROM image or parent stage, its instruction lines)."""
    stages: dict[str, tuple[str, list[str]]] = {}
    current: list[str] = []
    text = re.sub(r"\\\n", " ", DOCKERFILE.read_text())
    for line in text.splitlines():
        line = line.strip()
        if match := re.match(r"FROM\s+(\S+)\s+AS\s+(\S+)", line, re.IGNORECASE):
            current = []
            stages[match.group(2)] = (match.group(1), current)
        elif line and not line.startswith("#"):
            current.append(line)
    return stages


def ancestry(stages: dict[str, tuple[str, list[str]]], name: str) -> list[str]:
    """The stage and every stage it derives from or copies from."""
    seen: list[str] = []
    todo = [name]
    while todo:
        stage = todo.pop()
        if stage in seen or stage not in stages:
            continue
        seen.append(stage)
        parent, lines = stages[stage]
        todo.append(parent)
        todo += [m.group(1) for line in lines if (m := re.match(r"COPY\s+--from=(\S+)", line))]
    return seen


# -- docker-compose.yml ------------------------------------------------------------------------------------------


def test_compose_has_broker_chief_and_scaled_workers() -> None:
    services = compose()["services"]
    assert {"mosquitto", "chief", "worker"} <= set(services)
    broker = services["mosquitto"]
    assert broker["image"] == "${FEDRL_MOSQUITTO_IMAGE:-eclipse-mosquitto:2}"
    assert "ports" not in broker, "the anonymous dev broker must not be published on the host"
    conf_mount = next(v for v in broker["volumes"] if v.endswith("/mosquitto/config/mosquitto.conf:ro"))
    assert (ROOT / conf_mount.split(":")[0]).is_file()
    assert "test" in broker["healthcheck"]

    worker, chief = services["worker"], services["chief"]
    assert worker["deploy"]["replicas"] == "${FEDRL_WORKERS:-4}"
    assert chief["environment"]["FEDRL_WORKERS"] == "${FEDRL_WORKERS:-4}"
    assert "FEDRL_WORKER_ID" not in worker["environment"], "replicas must name themselves"
    for svc in (worker, chief):
        assert svc["depends_on"]["mosquitto"]["condition"] == "service_healthy"
        assert svc["build"]["dockerfile"] == "deploy/Dockerfile"
        assert svc["build"]["target"] in ROLES
        assert svc["environment"]["FEDRL_BROKER"] == "${FEDRL_BROKER:-mqtt://mosquitto:1883}"
        assert "restart" not in svc or svc["restart"] == "no"
    assert chief["environment"]["FEDRL_RUN_DIR"].startswith("/runs/")
    assert any(v.endswith(":/runs") for v in chief["volumes"])


def test_mosquitto_dev_config() -> None:
    from services.broker.embedded import MAX_PACKET_SIZE

    for name in ("mosquitto.conf", "mosquitto.loopback.conf", "mosquitto.prod.conf", "mosquitto.overlay.conf"):
        conf = dict(line.split(None, 1) for line in (MOSQUITTO / name).read_text().splitlines()
                    if line.strip() and not line.startswith("#") and " " in line)
        assert conf["set_tcp_nodelay"] == "true"
        assert int(conf["max_packet_size"]) == MAX_PACKET_SIZE  # the same limit as the codec and the embedded broker
        assert conf["persistence"] == "true" and conf["persistent_client_expiration"] == "1d"


def test_the_production_config_takes_its_ports_and_paths_from_variables() -> None:
    """mosquitto.prod.conf: every port and path a ${FEDRL_...:-default} placeholder, the defaults the image's layout
    and the standard ports (documented in its header), each variable rendered where set."""
    text = (MOSQUITTO / "mosquitto.prod.conf").read_text()
    defaults = {"FEDRL_MQTT_TLS_PORT": "8883", "FEDRL_MQTT_LOCAL_PORT": "1883", "FEDRL_MQTT_LOCAL_HOST": "127.0.0.1",
                "FEDRL_MOSQUITTO_CONFIG_DIR": "/mosquitto/config", "FEDRL_MOSQUITTO_CERTS_DIR": "/mosquitto/certs",
                "FEDRL_MOSQUITTO_DATA_DIR": "/mosquitto/data"}
    assert placeholders(text) == defaults
    header = [line for line in text.splitlines() if line.startswith("#")]
    for var, default in defaults.items():
        assert any(var in line and default in line for line in header), f"{var} is not documented in the header"
    plain = render(text, {})
    assert not placeholders(plain) and "listener 1883 127.0.0.1\n" in plain and "listener 8883\n" in plain
    assert "password_file /mosquitto/config/passwd" in plain and "persistence_location /mosquitto/data/" in plain
    moved = render(text, {"FEDRL_MQTT_LOCAL_PORT": "1884", "FEDRL_MQTT_TLS_PORT": "8884",
                          "FEDRL_MOSQUITTO_CONFIG_DIR": "/etc/mosquitto/fedrl"})
    assert "listener 1884 127.0.0.1\n" in moved and "listener 8884\n" in moved
    assert "acl_file /etc/mosquitto/fedrl/acl" in moved
    with pytest.raises(ValueError, match="has no default: set FEDRL_X"):
        render("port ${FEDRL_X}", {})


def compose_cli() -> list[list[str]]:
    """Every compose implementation installed here: v2 (docker compose) and v1 (docker-compose)."""
    found = []
    if shutil.which("docker") and subprocess.run(["docker", "compose", "version"], capture_output=True).returncode == 0:
        found.append(["docker", "compose"])
    if shutil.which("docker-compose"):
        found.append(["docker-compose", "--compatibility"])
    return found


@pytest.mark.parametrize("files", [[COMPOSE], [COMPOSE, HOSTNET]], ids=["bridge", "hostnet"])
def test_compose_config_cli(files: list[Path]) -> None:
    """`docker compose config` accepts the file and the worker count follows FEDRL_WORKERS alone."""
    clis = compose_cli()
    if not clis:
        pytest.skip("neither `docker compose` (v2) nor docker-compose (v1) is installed; the YAML checks above ran")
    env = {k: v for k, v in os.environ.items() if not k.startswith(("FEDRL_", "COMPOSE_"))}
    env |= {"FEDRL_WORKERS": "8", "FEDRL_ENV": "Acrobot-v1"}
    for cli in clis:
        args = [a for f in files for a in ("-f", str(f))]
        out = subprocess.run([*cli, *args, "config"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, f"{' '.join(cli)} config failed:\n{out.stderr}"
        services = yaml.safe_load(out.stdout)["services"]
        assert int(services["worker"]["deploy"]["replicas"]) == 8, cli
        assert str(services["chief"]["environment"]["FEDRL_WORKERS"]) == "8"
        assert services["worker"]["environment"]["FEDRL_ENV"] == "Acrobot-v1"


# -- Dockerfile --------------------------------------------------------------------------------------------------


def test_dockerfile_targets() -> None:
    text = DOCKERFILE.read_text()
    stages = dockerfile_stages()
    assert set(ROLES) <= set(stages)
    assert re.search(r"^ARG BASE_IMAGE=python:3\.11-slim$", text, re.MULTILINE)
    assert re.search(r"^ARG TORCH_INDEX_URL=", text, re.MULTILINE)
    assert "syntax=" not in text, "a syntax line makes BuildKit pull a frontend image"
    for role in ROLES:
        chain = ancestry(stages, role)
        assert "runtime" in chain, role
        role_lines = stages[role][1]
        assert any(line.startswith("ENTRYPOINT") for line in role_lines), role
    runtime = stages["runtime"][1]
    assert "USER fedrl" in runtime
    assert any(line.startswith("HEALTHCHECK") for line in runtime)


def test_bridge_and_chief_images_have_no_torch() -> None:
    """The bridge (and the chief, and qube-sim) install neither torch nor gymnasium; the worker does."""
    tomllib = pytest.importorskip("tomllib")
    stages = dockerfile_stages()
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    bridge_reqs = meta["dependencies"] + meta["optional-dependencies"]["bridge"]
    assert not [r for r in bridge_reqs if r.lower().startswith(LEARN_ONLY)], bridge_reqs
    for role in ("bridge", "qube-sim", "chief"):
        lines = " ".join(line for s in ancestry(stages, role) for line in stages[s][1])
        installs = re.findall(r"pip-install ([^&;\n]*)", lines)
        assert installs, role
        bad = [i for i in installs if "[learn]" in i or re.search(r"\b(torch|gymnasium)\b", i)]
        assert not bad, f"{role} image would install learning libraries: {bad}"
    worker = " ".join(line for s in ancestry(stages, "worker") for line in stages[s][1])
    assert "[learn]" in worker and "TORCH_INDEX_URL" in worker


def test_dockerignore_is_an_allowlist() -> None:
    lines = [ln.strip() for ln in (ROOT / ".dockerignore").read_text().splitlines()
             if ln.strip() and not ln.startswith("#")]
    assert lines[0] == "*", "start from nothing, then allow what the images need"
    allowed = {ln[1:].rstrip("/") for ln in lines if ln.startswith("!")}
    assert {"pyproject.toml", "constraints.txt", "protocol", "runtime", "chief", "worker", "rpi_bridge", "services",
            "deploy/wheels"} <= allowed
    assert "COPY constraints.txt deploy/wheel[s] /wheels/" in DOCKERFILE.read_text(), "the wheelhouse is optional"


# -- .env.example ------------------------------------------------------------------------------------------------


def test_every_variable_is_documented() -> None:
    documented = set(re.findall(r"^#?([A-Z][A-Z0-9_]*)=", ENV_EXAMPLE.read_text(), re.MULTILINE))
    used: set[str] = set()
    for path in (COMPOSE, HOSTNET):
        text = re.sub(r"^\s*#.*$", "", path.read_text(), flags=re.MULTILINE)
        used |= set(re.findall(r"\$\{([A-Z][A-Z0-9_]*)", text))
        used |= set(re.findall(r"\b(FEDRL_[A-Z0-9_]+)\b", text))
    used |= set(re.findall(r"\b(FEDRL_[A-Z0-9_]+)\b", DOCKERFILE.read_text()))
    used |= {var for name, field in DockerSettings.model_fields.items() if (var := env_name(name, field))}
    # Set inside the containers by compose/Dockerfile, not by the user:
    internal = {"FEDRL_RUN_DIR", "FEDRL_RIG_ID"}
    missing = sorted(used - internal - documented)
    assert not missing, f"not documented in .env.example: {missing}"


# -- Mosquitto ACL -----------------------------------------------------------------------------------------------


def make_users(tmp: Path, *extra: str) -> Path:
    out = tmp / "secrets"
    subprocess.run(["bash", str(MOSQUITTO / "make-users.sh"), "-w", "3", "-r", "2", "-o", str(out), *extra],
                   check=True, capture_output=True, text=True, timeout=60)
    return out


def topic_matches(acl: str, topic: str) -> bool:
    a, t = acl.split("/"), topic.split("/")
    for i, level in enumerate(a):
        if level == "#":
            return True
        if i >= len(t) or (level != "+" and level != t[i]):
            return False
    return len(a) == len(t)


class Acl:
    """Mosquitto 2.0 ACL semantics: a user's deny rules first, then its topic rules, then %u patterns."""

    def __init__(self, text: str) -> None:
        self.users: dict[str, list[tuple[str, str]]] = {}
        self.patterns: list[tuple[str, str]] = []
        user = None
        for line in text.splitlines():
            parts = line.split()
            if not parts or parts[0].startswith("#"):
                continue
            if parts[0] == "user":
                user = parts[1]
                self.users[user] = []
            elif parts[0] in ("topic", "pattern"):
                rule = (parts[1], parts[2]) if len(parts) == 3 else ("readwrite", parts[1])
                (self.patterns if parts[0] == "pattern" else self.users[user]).append(rule)

    def allows(self, user: str, access: str, topic: str) -> bool:
        rules = self.users.get(user, [])
        if any(a == "deny" and topic_matches(t, topic) for a, t in rules):
            return False
        candidates = rules + [(a, t.replace("%u", user)) for a, t in self.patterns]
        return any(a in (access, "readwrite") and topic_matches(t, topic) for a, t in candidates)


def wait_for_listener(port: int, proc: subprocess.Popen, timeout: float = 15.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert proc.poll() is None, f"mosquitto exited with code {proc.returncode}"
        try:
            socket.create_connection((HOST, port), timeout=1).close()
            return
        except OSError:
            time.sleep(0.05)
    raise TimeoutError(f"mosquitto is not listening on {HOST}:{port}")


R = "r1"
ACL_CASES = [  # (user, access, topic, allowed)
    ("chief", "write", f"fedrl/{R}/chief/aggregate", True),
    ("chief", "write", f"fedrl/{R}/chief/transfer", True),
    ("chief", "read", f"fedrl/{R}/worker/w0/update", True),
    ("chief", "write", f"fedrl/{R}/worker/w0/update", False),
    ("chief", "write", "qube/rig0/action", False),
    ("chief", "write", f"fedrl/{R}/edge/root/partial", True),  # standing in for a dead edge (chief/failover.py)
    ("chief", "write", f"fedrl/{R}/edge/e0/partial", False),
    ("w0", "write", f"fedrl/{R}/worker/w0/update", True),
    ("w0", "write", f"fedrl/{R}/worker/w0/status", True),
    ("w0", "read", f"fedrl/{R}/chief/aggregate", True),
    ("w0", "write", f"fedrl/{R}/worker/w1/update", False),
    ("w0", "write", f"fedrl/{R}/chief/aggregate", False),
    ("w0", "write", f"fedrl/{R}/chief/transfer", False),
    ("w0", "write", "qube/rig0/action", True),
    ("w0", "write", "qube/rig0/reset", True),
    ("w0", "read", "qube/rig0/state", True),
    ("w0", "write", "qube/rig0/state", False),
    ("w0", "write", "qube/rig1/action", False),
    ("w0", "read", "qube/rig1/state", False),
    ("w2", "write", "qube/rig0/action", False),
    ("w2", "read", f"fedrl/{R}/chief/stop", True),
    ("rig0", "write", "qube/rig0/state", True),
    ("rig0", "write", "qube/rig0/telemetry", True),
    ("rig0", "write", "qube/rig0/status", True),
    ("rig0", "read", "qube/rig0/action", True),
    ("rig0", "read", "qube/rig0/reset", True),
    ("rig0", "write", "qube/rig0/action", False),
    ("rig0", "write", "qube/rig1/state", False),
    ("rig0", "write", f"fedrl/{R}/worker/rig0/update", False),
    ("rig0", "read", f"fedrl/{R}/chief/aggregate", False),
]


def test_acl_gives_each_role_only_its_topics(tmp_path: Path) -> None:
    acl = Acl((make_users(tmp_path, "--acl-only") / "acl").read_text())
    wrong = [case for case in ACL_CASES if acl.allows(*case[:3]) != case[3]]
    assert not wrong, f"(user, access, topic, expected) the ACL gets wrong: {wrong}"


def test_acl_can_pin_one_run(tmp_path: Path) -> None:
    acl = Acl((make_users(tmp_path, "--acl-only", "--run", R) / "acl").read_text())
    assert acl.allows("w0", "write", f"fedrl/{R}/worker/w0/update")
    assert not acl.allows("w0", "write", "fedrl/other/worker/w0/update")
    assert not acl.allows("chief", "write", "fedrl/other/chief/aggregate")


@pytest.mark.skipif(not mosquitto_available() or not shutil.which("mosquitto_passwd"),
                    reason="mosquitto and mosquitto_passwd are not installed (apt-get install mosquitto)")
def test_acl_on_a_live_mosquitto(tmp_path: Path) -> None:
    """The production config with generated users: what each user may publish and receive, plus TLS."""
    paho = pytest.importorskip("paho.mqtt.client")
    secrets = make_users(tmp_path)
    (secrets / "acl").write_text((secrets / "acl").read_text() + "\nuser admin\ntopic readwrite #\n")
    subprocess.run(["mosquitto_passwd", "-b", str(secrets / "passwd"), "admin", "admin-pw"], check=True)
    pw = {"admin": "admin-pw"}
    for path in (secrets / "credentials").iterdir():
        pw[path.stem] = dict(ln.split("=", 1) for ln in path.read_text().split())["FEDRL_MQTT_PASSWORD"]
    tls = shutil.which("openssl") is not None
    if tls:
        subprocess.run(["bash", str(MOSQUITTO / "make-certs.sh"), HOST, str(secrets / "certs")], check=True,
                       capture_output=True, timeout=120)
    plain_port, tls_port = free_port(HOST), free_port(HOST)
    conf = render((MOSQUITTO / "mosquitto.prod.conf").read_text(), {
        "FEDRL_MOSQUITTO_CONFIG_DIR": str(secrets), "FEDRL_MOSQUITTO_CERTS_DIR": str(secrets / "certs"),
        "FEDRL_MQTT_TLS_PORT": f"{tls_port} {HOST}", "FEDRL_MQTT_LOCAL_PORT": str(plain_port),
        "FEDRL_MQTT_LOCAL_HOST": HOST})
    conf = conf.replace("persistence true", "persistence false")
    if not tls:
        conf = re.sub(r"listener \d+ \S+\n(cafile|certfile|keyfile|tls_version).*?(?=\n\S*listener)", "", conf,
                      flags=re.S)
    if os.geteuid() == 0:
        conf += "\nuser root\n"  # else Mosquitto drops to its own user, who cannot read tmp_path
    (tmp_path / "broker.conf").write_text(conf)
    log = (tmp_path / "broker.log").open("wb")
    proc = subprocess.Popen(["mosquitto", "-c", str(tmp_path / "broker.conf")], stdout=log, stderr=subprocess.STDOUT)
    clients = []
    try:
        wait_for_listener(plain_port, proc)

        def connect(user: str, port: int = plain_port, ca: Path | None = None) -> tuple[Any, list[tuple[str, bytes]]]:
            got: list[tuple[str, bytes]] = []
            c = paho.Client(paho.CallbackAPIVersion.VERSION2, protocol=paho.MQTTv311)
            c.username_pw_set(user, pw[user])
            if ca:
                c.tls_set(ca_certs=str(ca))
            c.on_message = lambda _c, _u, m: got.append((m.topic, m.payload))
            c.connect(HOST, port)
            c.loop_start()
            clients.append(c)
            return c, got

        admin, seen = connect("admin")
        admin.subscribe("#", qos=1)
        readers: dict[str, tuple[Any, list[tuple[str, bytes]]]] = {}  # one connection per user (client id = user)
        for user, access, topic, _ in ACL_CASES:
            if access == "read":
                if user not in readers:
                    readers[user] = connect(user)
                readers[user][0].subscribe(topic, qos=1)
        time.sleep(0.5)
        for user, access, topic, _ in ACL_CASES:
            if access == "write":
                if user not in readers:
                    readers[user] = connect(user)
                readers[user][0].publish(topic, user.encode(), qos=1).wait_for_publish(5)
            else:
                admin.publish(topic, b"admin", qos=1).wait_for_publish(5)
        if tls:
            tc, _ = connect("w1", tls_port, secrets / "certs" / "ca.crt")
            tc.publish(f"fedrl/{R}/worker/w1/hello", b"tls", qos=1).wait_for_publish(5)
        time.sleep(1.0)
        wrong = []
        for user, access, topic, allowed in ACL_CASES:
            got = (topic, user.encode()) in seen if access == "write" else (topic, b"admin") in readers[user][1]
            if got != allowed:
                wrong.append((user, access, topic, allowed))
        assert not wrong, f"(user, access, topic, expected) the live broker gets wrong: {wrong}"
        if tls:
            assert (f"fedrl/{R}/worker/w1/hello", b"tls") in seen, "nothing arrived over the TLS listener"
    finally:
        for c in clients:
            c.disconnect()
        for c in clients:
            c.loop_stop()
        stop_process(proc)
        log.close()


# -- Raspberry Pi and the launcher -----------------------------------------------------------------------------------


def test_rpi_unit_runs_the_bridge_in_real_time() -> None:
    unit = (ROOT / "deploy" / "rpi" / "fedrl-bridge.service").read_text()
    assert re.search(r"^ExecStart=.*-m rpi_bridge", unit, re.MULTILINE)
    assert re.search(r"^CPUSchedulingPolicy=fifo$", unit, re.MULTILINE)
    assert 1 <= int(re.search(r"^CPUSchedulingPriority=(\d+)$", unit, re.MULTILINE).group(1)) <= 99
    assert re.search(r"^Restart=always$", unit, re.MULTILINE)
    assert re.search(r"^EnvironmentFile=", unit, re.MULTILINE)
    template = (ROOT / "deploy" / "rpi" / "bridge.env.example").read_text()
    for name in ("FEDRL_RIG_ID", "FEDRL_BROKER", "FEDRL_MQTT_USERNAME", "FEDRL_MQTT_PASSWORD"):
        assert re.search(rf"^{name}=", template, re.MULTILINE), name


def test_docker_launcher_help() -> None:
    pytest.importorskip("docker", reason="the Docker SDK is not installed (pip install .[deploy])")
    out = subprocess.run([sys.executable, "-m", "deploy.docker", "--help"], cwd=ROOT, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "--workers" in out.stdout


def test_the_dashboards_acl_is_what_it_reads(tmp_path: Path) -> None:
    """make-users.sh --dashboard: the dashboard may read every topic it subscribes to (services/dashboard/feed.py),
    among them a tiered run's edge partials it shows the workers' progress from, and nothing it does not read (a
    rig's 143 Hz state, its commands); it may write nothing."""
    from services.dashboard.feed import subscriptions

    acl = Acl((make_users(tmp_path, "--acl-only", "--dashboard", "--edge", "e0", "--run", "r1") / "acl").read_text())
    for topic_filter, _ in subscriptions("r1", None):
        example = topic_filter.replace("#", "worker/w0/update").replace("+", "rig0")
        assert acl.allows("dashboard", "read", example), topic_filter
    for topic in ("fedrl/r1/edge/e0/partial", "fedrl/r1/chief/aggregate", "fedrl/r1/worker/w1/status",
                  "qube/rig1/telemetry", "qube/rig1/status"):
        assert acl.allows("dashboard", "read", topic), topic
    for topic in ("qube/rig0/state", "qube/rig0/action", "fedrl/r2/worker/w0/update"):
        assert not acl.allows("dashboard", "read", topic), topic
    assert not any(acl.allows("dashboard", "write", t) for t in ("fedrl/r1/chief/stop", "qube/rig0/action"))
