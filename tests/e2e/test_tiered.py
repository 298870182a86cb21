"""Edge aggregation end to end (docs/explanation/tiered.md): a tiered federation, 2 edge chiefs x 2 workers, in
process (deploy/inprocess.py --edges). Every round's root aggregate is the flat Eq. 9 of the same submissions within
the derived bound (the audit's tiered-exact check on the wire's witness), a finisher's actor reached learners behind
both edges, and the audit passes. The same over MQTT (an edge chief that dies: tests/e2e/test_edge_failover.py)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from chief.audit import AuditFailure, audit
from deploy.inprocess import run_federation
from deploy.settings import InprocessSettings
from runtime.records import GRADIENTS, ROOT, gradient_key

pytestmark = pytest.mark.slow

ENV, SEED, WORKERS, EDGES, EPISODES = "CartPole-v0", 3, 4, 2, 25  # w0 (edge e0) finishes at episode 22


def test_a_tiered_federation_is_the_flat_one_across_levels(tmp_path: Path) -> None:
    summary = run_federation(InprocessSettings.given(env=ENV, policy="weighted", seed=SEED, workers=WORKERS,
                             max_episodes=EPISODES, run_dir=tmp_path, edges=EDGES), plot=False, tensorboard_files=False,
                             models=False)
    assert (tmp_path / GRADIENTS).exists()
    report = audit(tmp_path)
    rounds = [r for r in map(json.loads, (tmp_path / "metrics.jsonl").open()) if r["type"] == "round"]
    assert len(rounds) == summary.rounds == EPISODES
    # every round went through both edges, worker i behind e<i mod 2>
    assert all(r["edges"] == {"e0": sorted(w for w in r["contributors"] if int(w[1:]) % 2 == 0),
                              "e1": sorted(w for w in r["contributors"] if int(w[1:]) % 2 == 1)} for r in rounds)
    aggregates = [r for r in rounds if r["kind"] == "aggregate" and r["digest"]]
    assert report.tiered == len(aggregates) >= EPISODES - 2  # each one checked against the flat Eq. 9
    transfers = [r for r in rounds if r["kind"] == "transfer"]
    assert transfers, "nobody finished: no transfer went through the edges"
    recipients = set(transfers[0]["keep_weights"])
    assert {w for w in recipients if int(w[1:]) % 2 == 0} and {w for w in recipients if int(w[1:]) % 2 == 1}
    assert report.transfer_deliveries >= len(recipients)  # ... and each confirmed it applied the actor
    # A root that summed a little wrong (one aggregate off by 1e-4 of its value) fails the audit.
    with np.load(tmp_path / GRADIENTS) as data:
        tensors = {k: data[k] for k in data.files}
    episode = aggregates[-1]["episode"]
    for key in [k for k in tensors if k.startswith(gradient_key(episode, 0, ROOT, ""))]:
        tensors[key] = tensors[key] * np.float32(1.0001)
    np.savez_compressed(tmp_path / GRADIENTS, **tensors)  # type: ignore[arg-type]
    with pytest.raises(AuditFailure) as failure:
        audit(tmp_path)
    assert failure.value.invariant == "tiered-exact"


def run_with_dashboard(tmp_path: Path, args: list[str]) -> tuple[int, dict, str]:
    """deploy.run_local with ``args``, its dashboard kept up after the end: the launcher's exit code, the dashboard's
    /api/snapshot at the end, and the launcher's output."""
    log = tmp_path / "launcher.log"
    with log.open("w") as out:
        proc = subprocess.Popen([sys.executable, "-m", "deploy.run_local", *args, "--dashboard-linger", "300"],
                                stdout=out, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 300
        while "the dashboard stays up" not in log.read_text():
            assert proc.poll() is None and time.monotonic() < deadline, log.read_text()[-3000:]
            time.sleep(0.5)
        url = re.search(r"dashboard: (http://\S+)", log.read_text())
        assert url is not None, log.read_text()[-3000:]
        with urllib.request.urlopen(url.group(1).rstrip("/") + "/api/snapshot", timeout=30) as answer:
            snapshot = json.loads(answer.read())
    finally:
        proc.terminate()  # ends the dashboard's linger (the run's exit code is kept)
        proc.wait(60)
    return proc.returncode, snapshot, log.read_text()


def test_a_tiered_federation_over_a_real_broker(tmp_path: Path) -> None:
    """The same over MQTT (deploy.run_local --edges 2: the embedded broker with the run's users and ACL, each edge
    chief its own process), the wire witnessed: every root aggregate is the flat one within the bound. Its dashboard
    lists every worker with each of its episodes from the edges' partials (2 edges x 3 rounds)."""
    run_dir = tmp_path / "run"
    code, snapshot, out = run_with_dashboard(tmp_path, [
        "--workers", "4", "--edges", "2", "--witness", "--env", ENV, "--seed", str(SEED), "--max-episodes", "3",
        "--run-dir", str(run_dir), "--run-id", "tiered"])
    assert code == 0, out[-3000:]
    report = audit(run_dir)
    rounds = [r for r in map(json.loads, (run_dir / "metrics.jsonl").open()) if r["type"] == "round"]
    assert len(rounds) == 3 and all(set(r["edges"]) == {"e0", "e1"} for r in rounds)
    assert report.tiered == 3
    for e in ("e0", "e1"):
        assert "3 partials sent" in (run_dir / "logs" / f"edge-{e}.log").read_text()
    workers = {w["id"]: w for w in snapshot["workers"]}
    assert sorted(workers) == ["w0", "w1", "w2", "w3"]
    assert all(w["episode"] == 3 and [p[0] for p in w["curve"]] == [1, 2, 3] for w in workers.values()), workers
    assert snapshot["kinds"]["partial"] == 6 and snapshot["run"]["phase"] == "stopped"
    # It stopped reading the workers' updates once the RunStart named the edges (at most those already on their way).
    assert snapshot["kinds"].get("update", 0) < 4 * 3


def test_the_audit_reads_both_levels_and_a_tampered_edge_record_fails_it(tmp_path: Path) -> None:
    """The root keeps one record per edge and round (its partial's contributors with their digests, its share total),
    each edge its workers' own records (RUN/edges/<edge>/metrics.jsonl): the audit checks every contribution against
    its edge's record and every partial's total against those records' PIs. An edge record changed afterwards, a
    contribution missing at its edge, or a partial whose total is not its records' fails it."""
    run_federation(InprocessSettings.given(env=ENV, policy="weighted", seed=SEED, workers=WORKERS, max_episodes=4,
                   run_dir=tmp_path, edges=EDGES), plot=False, tensorboard_files=False, models=False)
    root = [json.loads(line) for line in (tmp_path / "metrics.jsonl").open()]
    assert {r["type"] for r in root} == {"edge", "round"}  # no worker's own record at the root
    assert sum(len(r["contributions"]) for r in root if r["type"] == "edge") == WORKERS * 4
    report = audit(tmp_path)
    assert report.edge_records == EDGES * 4 and report.submissions == WORKERS * 4
    kept = tmp_path / "edges" / "e0" / "metrics.jsonl"
    original = kept.read_text()
    lines = original.splitlines()
    assert len(lines) == (WORKERS // EDGES) * 4
    cases = {  # what was changed -> the invariant that names it
        "a return": (kept, "\n".join([lines[0].replace('"return":', '"return":1', 1), *lines[1:]]) + "\n"),
        "a lost record": (kept, "\n".join(lines[1:]) + "\n"),
    }
    for what, (path, text) in cases.items():
        path.write_text(text)
        with pytest.raises(AuditFailure) as failure:
            audit(tmp_path)
        assert failure.value.invariant == "edge-records", what
        path.write_text(original)
    records = tmp_path / "metrics.jsonl"
    text = records.read_text()
    first = next(line for line in text.splitlines() if '"type":"edge"' in line)
    total = json.loads(first)["total"]
    records.write_text(text.replace(first, first.replace(f'"total":{total}', f'"total":{total * 1.000001}')))
    with pytest.raises(AuditFailure) as failure:
        audit(tmp_path)
    assert failure.value.invariant == "edge-records" and "total" in str(failure.value)
