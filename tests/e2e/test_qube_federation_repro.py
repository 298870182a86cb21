"""A whole QUBE-Servo 2 federation is reproducible: the chief, 3 workers and 3 simulated lockstep rigs over MQTT
(``deploy.run_local --env qube``), once on the embedded amqtt broker and once on Mosquitto under extra CPU load,
give the same episodes and returns rig by rig, the same rounds and the same aggregates bit for bit (tensor
digests). The runs are capped (not solved): the point is that the wall clock decides nothing."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from chief.audit import audit
from runtime.records import EpisodeRecord, RoundRecord, RunSummary, read_metrics
from tests.federations import cpu_load

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("e2e")]  # one federation at a time with the others

SEED = 3
WORKERS = 3
#: Rounds of the capped run: a few seconds of simulated rig time each, ~20 s a run on 2 cores (most of it start-up),
#: enough for every worker to fall, reset and take aggregates many times.
MAX_EPISODES = 8
CAPPED = f"reached the maximum of {MAX_EPISODES} episodes"


def federate_qube(tmp_path: Path, name: str, broker: str | None = None) -> Path:
    """One capped QUBE federation through the launcher; its run folder (asserted: exit 0, ended by the cap)."""
    run_dir = tmp_path / name
    argv = [sys.executable, "-m", "deploy.run_local", "--env", "qube", "--workers", str(WORKERS),
            "--qube-clock", "lockstep", "--seed", str(SEED), "--max-episodes", str(MAX_EPISODES),
            "--dashboard-port", "off", "--run-dir", str(run_dir), "--run-id", name]
    if broker:
        argv += ["--broker", broker]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert f"not all solved ({CAPPED})" in proc.stdout, proc.stdout[-3000:]
    return run_dir


def episodes(run_dir: Path) -> dict[str, list[tuple[int, float, int, int | None, float | None, str]]]:
    """Per worker (its rig), in order: (episode, return, env steps, balance steps, reset s on the simulated clock,
    the digest of the answer it applied before it)."""
    out: dict[str, list[tuple[int, float, int, int | None, float | None, str]]] = {}
    for r in read_metrics(run_dir):
        if isinstance(r, EpisodeRecord):
            out.setdefault(r.worker, []).append((r.episode, r.return_, r.steps, r.balance_steps, r.reset_s,
                                                 r.receipt.digest if r.receipt else ""))
    return out


def rounds(run_dir: Path) -> list[tuple[int, int, str, list[str], dict[str, float], dict[str, float], str]]:
    """The chief's rounds: (round, episode, kind, contributors, PIs, weights, digest of the answer's tensors)."""
    return [(r.round, r.episode, r.kind, sorted(r.contributors), r.pis, r.weights, r.digest)
            for r in read_metrics(run_dir) if isinstance(r, RoundRecord)]


def test_same_seed_same_qube_federation_on_both_brokers_under_cpu_load(mosquitto_broker: str, tmp_path: Path
                                                                         ) -> None:
    quiet = federate_qube(tmp_path, "qube-amqtt")
    with cpu_load():
        loaded = federate_qube(tmp_path, "qube-mosquitto", broker=mosquitto_broker)
    a, b = RunSummary.read(quiet), RunSummary.read(loaded)
    assert b.broker == mosquitto_broker and a.broker != mosquitto_broker
    assert a.end_reason == b.end_reason == CAPPED and a.rounds == b.rounds == MAX_EPISODES
    # The federation did something: every round aggregated all 3 workers' updates into a new network, and each
    # worker applied the answers (receipts naming their digests) and played its rig to falls and resets.
    ra = rounds(quiet)
    assert len(ra) == MAX_EPISODES and all(r[2] == "aggregate" and r[6] and len(r[3]) == WORKERS for r in ra)
    ea = episodes(quiet)
    assert sorted(ea) == [f"w{i}" for i in range(WORKERS)]
    assert all([e[0] for e in eps] == list(range(1, MAX_EPISODES + 1)) for eps in ea.values())
    assert all(sum(bool(e[5]) for e in eps) == MAX_EPISODES - 1 for eps in ea.values())  # all but the first
    # Reproducible: rig by rig the same episodes, returns and steps, the chief the same rounds bit for bit.
    assert episodes(loaded) == ea
    assert rounds(loaded) == ra
    assert [(w.id, w.episodes, w.steps, w.final_pi, w.rig) for w in b.workers] == \
        [(w.id, w.episodes, w.steps, w.final_pi, w.rig) for w in a.workers]
    assert a.total_steps == b.total_steps and a.last_rig == b.last_rig
    ra_audit, rb_audit = audit(quiet), audit(loaded)
    assert ra_audit.rounds == rb_audit.rounds == MAX_EPISODES
    assert ra_audit.receipts == rb_audit.receipts == WORKERS * (MAX_EPISODES - 1)
    assert json.loads((quiet / "summary.json").read_text())["env"] == "qube"
