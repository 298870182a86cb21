"""The Kubernetes manifests of the multi-site federation (deploy/k8s/), checked without a cluster (make k8s-check):
rendered offline by ``kubectl kustomize`` with the secrets ``python -m deploy.sites`` writes (into a copy under the
test's folder), every object validated against the Kubernetes 1.32 schemas (kubernetes-validate, strict), and the
federation they describe checked: one run, a broker and workers per site in the site's namespace and nodes."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
import yaml

from deploy import sites
from tests.paths import ROOT

K8S = ROOT / "deploy" / "k8s"
OVERLAY = str(ROOT / "deploy" / "mosquitto" / "mosquitto.overlay.conf")
SITES = ("a", "b")


def write_secrets(out: Path, core: str) -> None:
    """What ``python -m deploy.sites`` writes for the examples' two sites of two workers each."""
    if shutil.which("mosquitto_passwd") is None:
        pytest.skip("mosquitto_passwd is not installed (apt-get install mosquitto): deploy.sites hashes with it")
    args = [a for s in SITES for a in ("--site", f"{s}=2")]
    assert sites.main([*args, "--core", core, "--base", OVERLAY, "-o", str(out), "--force"]) == 0


def container(job: dict[str, Any]) -> dict[str, Any]:
    spec = job["spec"]["template"]["spec"]
    assert len(spec["containers"]) == 1
    return spec["containers"][0]


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> list[dict[str, Any]]:
    """``kubectl kustomize`` of the example overlay, with its secrets written into a copy of deploy/k8s."""
    if shutil.which("kubectl") is None:
        pytest.skip("kubectl is not installed (it renders the kustomization offline)")
    copy = tmp_path_factory.mktemp("k8s") / "k8s"
    shutil.copytree(K8S, copy, ignore=shutil.ignore_patterns(*sites.SECRET_FILES))
    write_secrets(copy / "example", "broker.fedrl:1883")
    done = subprocess.run(["kubectl", "kustomize", str(copy / "example")], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    return [doc for doc in yaml.safe_load_all(done.stdout) if doc]


def test_the_manifests_are_valid_kubernetes_1_32(rendered: list[dict[str, Any]]) -> None:
    import kubernetes_validate

    for doc in rendered:
        kubernetes_validate.validate(doc, "1.32.0", strict=True)


def objects(rendered: list[dict[str, Any]], kind: str, name: str) -> dict[str, dict[str, Any]]:
    """Objects of a kind and name (the generated ones by their name before the hash), by namespace."""
    return {d["metadata"].get("namespace", ""): d for d in rendered
            if d["kind"] == kind and re.fullmatch(rf"{name}(-[a-z0-9]{{10}})?", d["metadata"]["name"])}


def test_each_site_has_its_broker_and_workers_in_its_namespace(rendered: list[dict[str, Any]]) -> None:
    namespaces = {f"fedrl-site-{s}": s for s in SITES}
    workers = objects(rendered, "Job", "workers")
    assert set(workers) == set(namespaces)
    assert set(objects(rendered, "Deployment", "broker")) == {"fedrl", *namespaces}
    total = 0
    for ns, site in namespaces.items():
        job = workers[ns]
        env = {e["name"]: e["value"] for e in container(job)["env"]}
        assert env == {"FEDRL_SITE": site, "FEDRL_BROKER": "mqtt://broker:1883"}  # its own namespace's broker
        assert job["spec"]["template"]["spec"]["nodeSelector"] == {"fedrl.site": site}
        assert job["spec"]["completionMode"] == "Indexed"
        assert job["spec"]["completions"] == job["spec"]["parallelism"]
        total += job["spec"]["completions"]
        assert objects(rendered, "Job", "edge")[ns]["spec"]["suspend"] is True  # the edge role's slot, disabled
        bridge = objects(rendered, "Secret", "broker")[ns]
        assert bridge["metadata"]["name"] in str(objects(rendered, "Deployment", "broker")[ns])
    run = {ns: cm["data"] for ns, cm in objects(rendered, "ConfigMap", "run").items()}
    assert set(run) == {"fedrl", *namespaces} and all(r == run["fedrl"] for r in run.values())  # one run
    assert int(run["fedrl"]["FEDRL_WORKERS"]) == total  # the chief waits for every site's workers
    assert float(run["fedrl"]["FEDRL_RESEND_INTERVAL"]) == sites.RESEND_INTERVAL
    chief = container(objects(rendered, "Job", "chief")["fedrl"])
    assert chief["image"].startswith("fedrl/chief:") and {"name": "FEDRL_BROKER", "value": "mqtt://broker:1883"} \
        in chief["env"]
