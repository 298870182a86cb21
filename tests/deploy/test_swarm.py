"""The multi-site Docker Swarm stack (deploy/swarm/stack.yml): checked as a file (services, placement, networks,
secrets against what ``python -m deploy.sites`` writes, ``docker stack config`` where the CLI has it), and run on a
live single-node swarm (marked docker; make swarm-test): two sites with one worker each, a broker per site bridged
to the core broker, the chief and the dashboard. The run ends, every worker solves and the audit passes: every
update and answer crossed a bridge, since a site's workers reach only their own broker.

The live run needs a Docker engine in swarm mode (make swarm-test starts a single-node swarm: docker swarm init).
One node carries every site there, so the copy it deploys has no placement constraints (checked here in the file).
"""

from __future__ import annotations

import json
import os
import re
import secrets
import shutil
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

from chief.audit import audit
from deploy import sites
from services.broker.embedded import free_port
from tests.deploy.test_docker_e2e import built, docker_env, run  # noqa: F401  (fixtures: the engine, the images)
from tests.deploy.test_k8s import OVERLAY, container, write_secrets
from tests.paths import ROOT

STACK = ROOT / "deploy" / "swarm" / "stack.yml"
K8S = ROOT / "deploy" / "k8s"
SITES = ("a", "b")
RUN_TIMEOUT = 1200.0


def stack() -> dict[str, Any]:
    return yaml.safe_load(STACK.read_text())


def worker_start(text: str) -> str:
    """The shell lines a worker container starts with (Compose's $$ unescaped)."""
    return text.replace("$$", "$").strip()


def test_the_stack_places_brokers_chief_dashboard_and_workers_per_site() -> None:
    services = stack()["services"]
    assert set(services) == {"core", "chief", "dashboard", *(f"{kind}-{s}" for s in SITES
                                                            for kind in ("site", "workers", "edge"))}
    for name in ("core", "chief", "dashboard"):
        assert services[name]["deploy"]["placement"]["constraints"] == ["node.labels.fedrl.role == core"]
    for s in SITES:
        for kind in ("site", "workers", "edge"):
            assert services[f"{kind}-{s}"]["deploy"]["placement"]["constraints"] == [f"node.labels.fedrl.site == {s}"]
        workers = services[f"workers-{s}"]
        assert workers["deploy"]["replicas"] == f"${{FEDRL_SITE_{s.upper()}_WORKERS:-2}}"
        assert workers["environment"]["FEDRL_BROKER"] == f"mqtt://site-{s}:1883"
        assert workers["networks"] == [f"site-{s}"]  # a site's workers see their own broker only
        assert services[f"site-{s}"]["networks"] == [f"site-{s}", "core"]
        edge = services[f"edge-{s}"]  # the site's edge chief: 0 replicas in a flat run
        assert edge["deploy"]["replicas"] == "${FEDRL_EDGE_REPLICAS:-0}" and edge["networks"] == [f"site-{s}"]
        assert "FEDRL_ROLE=edge" in edge["entrypoint"][2] and edge["environment"]["FEDRL_SITE"] == s
    assert services["chief"]["environment"]["FEDRL_BROKER"] == "mqtt://core:1883"
    assert services["workers-a"]["environment"]["FEDRL_RESEND_INTERVAL"] == f"{sites.RESEND_INTERVAL:g}"
    for name, svc in services.items():
        role = re.search(r"/(chief|worker|dashboard):", svc["image"])
        assert role or svc["image"] == "${FEDRL_MOSQUITTO_IMAGE:-eclipse-mosquitto:2}", name
        assert "ports" not in svc or name == "dashboard"  # no broker on a host port
    assert all(net["driver_opts"]["encrypted"] == "true" for net in stack()["networks"].values())


def test_the_stacks_secrets_are_what_deploy_sites_writes(tmp_path: Path) -> None:
    write_secrets(tmp_path / "secrets", "core:1883")
    files = {name: s["file"] for name, s in stack()["secrets"].items()}
    missing = [f for f in files.values() if not (tmp_path / f).is_file()]
    assert not missing, f"the stack names files deploy.sites does not write: {missing}"
    used = {ref["source"] for svc in stack()["services"].values() for ref in svc.get("secrets", [])}
    assert used == set(files)
    conf = (tmp_path / "secrets" / "site-a" / "mosquitto.conf").read_text()
    assert "address core:1883" in conf and "remote_username bridge-a" in conf


@pytest.mark.skipif(shutil.which("docker") is None, reason="no docker CLI")
def test_docker_stack_config_renders_the_stack(tmp_path: Path) -> None:
    docker = str(shutil.which("docker"))
    if "config" not in subprocess.run([docker, "stack", "--help"], capture_output=True, text=True).stdout:
        pytest.skip("this docker CLI has no `docker stack config` (Docker 25 and later have)")
    shutil.copy(STACK, tmp_path / "stack.yml")
    write_secrets(tmp_path / "secrets", "core:1883")
    env = {k: v for k, v in os.environ.items() if not k.startswith("FEDRL_")}
    done = subprocess.run([docker, "stack", "config", "-c", str(tmp_path / "stack.yml")], capture_output=True,
                          text=True, env={**env, "FEDRL_SITE_A_WORKERS": "3"})
    assert done.returncode == 0, done.stderr
    rendered = yaml.safe_load(done.stdout)["services"]
    assert rendered["workers-a"]["deploy"]["replicas"] == 3 and rendered["workers-b"]["deploy"]["replicas"] == 2
    assert rendered["workers-a"]["environment"]["FEDRL_SLOT"] == "{{.Task.Slot}}"


def test_swarm_and_kubernetes_start_a_worker_alike() -> None:
    services = stack()["services"]
    swarm = worker_start(services["workers-a"]["entrypoint"][2])
    job = yaml.safe_load((K8S / "base" / "site" / "workers.yaml").read_text())
    assert swarm == worker_start(container(job)["command"][2])
    edge = yaml.safe_load((K8S / "base" / "site" / "edge.yaml").read_text())
    assert worker_start(services["edge-a"]["entrypoint"][2]) == worker_start(container(edge)["command"][2])


# -- live, on a single-node swarm -----------------------------------------------------------------------------------



@pytest.fixture(scope="module")
def swarm(built: dict[str, str]) -> dict[str, str]:  # noqa: F811
    """The engine is a swarm manager (else skipped, or failed under make swarm-test)."""
    state = run("docker", "info", "--format", "{{.Swarm.LocalNodeState}} {{.Swarm.ControlAvailable}}").stdout.split()
    if state != ["active", "true"]:
        reason = "the Docker engine is not a swarm manager (docker swarm init --advertise-addr 127.0.0.1)"
        if os.environ.get("FEDRL_REQUIRE_DOCKER"):
            pytest.fail(reason)
        pytest.skip(reason)
    return built


def single_node(text: str) -> str:
    """The stack without placement constraints: one node is the core and every site."""
    stack = yaml.safe_load(text)
    for svc in stack["services"].values():
        svc["deploy"].pop("placement", None)
    return yaml.safe_dump(stack, sort_keys=False)


def task_container(name: str, service: str) -> str:
    """The id of the running container of a service of stack ``name``, once there is one."""
    deadline = time.monotonic() + RUN_TIMEOUT
    while time.monotonic() < deadline:
        ids = run("docker", "ps", "-q", "--filter", f"label=com.docker.swarm.service.name={name}_{service}").stdout
        if ids.split():
            return ids.split()[0]
        time.sleep(2)
    raise AssertionError(f"{name}_{service} never ran")


def wait_for_rounds(name: str, rounds: int) -> None:
    """Until the chief has closed ``rounds`` rounds (its metrics.jsonl, read in its container)."""
    chief = task_container(name, "chief")
    deadline = time.monotonic() + RUN_TIMEOUT
    while time.monotonic() < deadline:
        done = run("docker", "exec", chief, "sh", "-c", f"grep -c '\"type\":\"round\"' /runs/{name}/metrics.jsonl")
        if done.stdout.strip().isdigit() and int(done.stdout) >= rounds:
            return
        time.sleep(1)
    raise AssertionError(f"the chief did not close {rounds} rounds within {RUN_TIMEOUT:.0f} s")


def wait_for_chief(name: str) -> str:
    """The chief task's final state (Complete, Failed, ...), once it has one."""
    deadline = time.monotonic() + RUN_TIMEOUT
    while time.monotonic() < deadline:
        states = run("docker", "service", "ps", f"{name}_chief", "--format", "{{.CurrentState}}").stdout.split("\n")
        if states and states[0].startswith(("Complete", "Failed", "Rejected", "Shutdown")):
            return states[0]
        time.sleep(5)
    raise AssertionError(f"the chief did not finish within {RUN_TIMEOUT:.0f} s")


@pytest.mark.docker
def test_a_two_site_federation_runs_on_a_single_node_swarm(tmp_path: Path, swarm: dict[str, str]) -> None:
    name = f"fedrl-test-{secrets.token_hex(3)}"
    (tmp_path / "stack.yml").write_text(single_node(STACK.read_text()))
    assert sites.main(["--site", "a=1", "--site", "b=1", "--core", "core:1883", "--base", OVERLAY, "-o",
                       str(tmp_path / "secrets")]) == 0
    env = {**swarm, "FEDRL_SITE_A_WORKERS": "1", "FEDRL_SITE_B_WORKERS": "1", "FEDRL_WORKERS": "2",
           "FEDRL_RUN_ID": name, "FEDRL_SEED": "3", "FEDRL_MAX_EPISODES": "600",
           "FEDRL_DASHBOARD_PORT": str(free_port())}
    t0 = time.monotonic()
    deployed = run("docker", "stack", "deploy", "-c", str(tmp_path / "stack.yml"), name, env=env, cwd=tmp_path)
    try:
        assert deployed.returncode == 0, deployed.stderr
        wait_for_rounds(name, 10)
        killed = run("docker", "kill", "--signal", "KILL", task_container(name, "site-a"))
        assert killed.returncode == 0, killed.stderr  # Swarm starts it again, on the same volume
        state = wait_for_chief(name)
        print(f"\nswarm run {name}: chief {state} after {time.monotonic() - t0:.0f} s")
        assert state.startswith("Complete"), run("docker", "service", "logs", "--raw", f"{name}_chief").stdout[-3000:]
        logs = run("docker", "service", "logs", "--raw", f"{name}_workers-a")
        worker_log = logs.stdout + logs.stderr
        copied = run("docker", "run", "--rm", "--user", "0", "--network", "none", "--entrypoint", "cp", "-v",
                     f"{name}_runs:/runs:ro", "-v", f"{tmp_path}:/out", f"{env.get('FEDRL_IMAGE_PREFIX', 'fedrl')}"
                     "/chief:latest", "-r", f"/runs/{name}", "/out/run")
        assert copied.returncode == 0, copied.stderr
    finally:
        run("docker", "stack", "rm", name)
        remove_volumes(name)
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert sorted(w["id"] for w in summary["workers"]) == ["a-w0", "b-w0"]
    assert all(w["solved"] for w in summary["workers"]), summary["workers"]
    audit(tmp_path / "run")
    # The workers reach only their site's broker and the chief only the core's (the stack's networks, checked
    # above): every update and answer crossed a bridge, site a's also its broker's death.
    assert "lost the broker" in worker_log and "going on alone" not in worker_log


def remove_volumes(name: str) -> None:
    """The stack's volumes, once its containers are gone (docker stack rm leaves volumes)."""
    deadline = time.monotonic() + 60
    while run("docker", "ps", "-aq", "--filter", f"label=com.docker.stack.namespace={name}").stdout.strip():
        if time.monotonic() > deadline:
            return
        time.sleep(1)
    volumes = run("docker", "volume", "ls", "-q", "--filter", f"label=com.docker.stack.namespace={name}").stdout
    if volumes.split():
        run("docker", "volume", "rm", *volumes.split())
