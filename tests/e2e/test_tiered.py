"""Edge aggregation end to end (docs/explanation/tiered.md): a tiered federation, 2 edge chiefs x 2 workers, in
process (deploy/inprocess.py --edges). Every round's root aggregate is the flat Eq. 9 of the same submissions within
the derived bound (the audit's tiered-exact check on the wire's witness), a finisher's actor reached learners behind
both edges, and the audit passes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from chief.audit import AuditFailure, audit
from chief.records import GRADIENTS, ROOT, gradient_key
from deploy.inprocess import run_federation

pytestmark = pytest.mark.slow

ENV, SEED, WORKERS, EDGES, EPISODES = "CartPole-v0", 3, 4, 2, 25  # w0 (edge e0) finishes at episode 22


def test_a_tiered_federation_is_the_flat_one_across_levels(tmp_path: Path) -> None:
    summary = run_federation(ENV, "weighted", SEED, WORKERS, EPISODES, tmp_path, plot=False, tensorboard_files=False,
                             models=False, edges=EDGES)
    assert (tmp_path / GRADIENTS).exists()
    report = audit(tmp_path)
    rounds = [r for r in map(json.loads, (tmp_path / "metrics.jsonl").open()) if r["type"] == "round"]
    assert len(rounds) == summary["rounds"] == EPISODES
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


def test_a_tiered_federation_over_a_real_broker(tmp_path: Path) -> None:
    """The same over MQTT (deploy.run_local --edges 2: the embedded broker with the run's users and ACL, each edge
    chief its own process), the wire witnessed: every root aggregate is the flat one within the bound."""
    run_dir = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "deploy.run_local", "--workers", "4", "--edges", "2", "--witness",
                           "--env", ENV, "--seed", str(SEED), "--max-episodes", "3", "--run-dir", str(run_dir),
                           "--run-id", "tiered", "--dashboard-port", "off"], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    report = audit(run_dir)
    rounds = [r for r in map(json.loads, (run_dir / "metrics.jsonl").open()) if r["type"] == "round"]
    assert len(rounds) == 3 and all(set(r["edges"]) == {"e0", "e1"} for r in rounds)
    assert report.tiered == 3
    for e in ("e0", "e1"):
        assert "3 partials sent" in (run_dir / "logs" / f"edge-{e}.log").read_text()
