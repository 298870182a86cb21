"""An edge chief that dies mid-run, over MQTT (docs/explanation/tiered.md, "When an edge dies"): its workers go
through another edge of their site within seconds (chief/failover.py), the run ends with the per-worker episodes of
the same tiered federation without the death, and the audit passes with every root aggregate within the bound of the
flat Eq. 9. The launcher starts a dead edge again; it rejoins at the root's open round, and takes the workers of the
next edge to die."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import pytest

from chief.audit import audit
from deploy.inprocess import run_federation
from deploy.settings import InprocessSettings
from tests.federations import federate_through, per_worker, warnings_of

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("test_edge_failover")]  # the reference is made once

ENV, SEED, WORKERS, EDGES, EPISODES = "CartPole-v0", 3, 4, 2, 25  # w0 (edge e0) finishes at episode 22
#: Long enough that no round times out while a dead edge's workers move (a few seconds), on a busy machine.
ROUND_TIMEOUT = "30"


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The same tiered federation without a death, in process."""
    run_dir = tmp_path_factory.mktemp("reference")
    run_federation(InprocessSettings.given(env=ENV, policy="weighted", seed=SEED, workers=WORKERS,
                                           max_episodes=EPISODES, run_dir=run_dir, edges=EDGES),
                   plot=False, tensorboard_files=False, models=False)
    return run_dir


def edge_process(run_id: str, edge: str) -> tuple[int, dict[str, str]]:
    """The process id and environment of a run's edge chief (deploy.run_local gives each child its settings as
    FEDRL_* variables)."""
    wanted = {f"FEDRL_RUN_ID={run_id}".encode(), f"FEDRL_EDGE_ID={edge}".encode()}
    for proc in Path("/proc").iterdir():
        try:
            if proc.name.isdigit():
                environ = (proc / "environ").read_bytes().split(b"\0")
                if wanted <= set(environ) and (proc / "cmdline").read_bytes().split(b"\0")[1:3] == [b"-m", b"chief"]:
                    return int(proc.name), dict(v.decode().split("=", 1) for v in environ if b"=" in v)
        except OSError:  # gone, or not ours
            continue
    raise AssertionError(f"no edge chief {edge} of run {run_id} is running")


def wait_for(path: Path, text: str, timeout: float = 120) -> None:
    deadline = time.monotonic() + timeout
    while not (path.exists() and text in path.read_text(errors="replace")):
        assert time.monotonic() < deadline, f"{text!r} not in {path} within {timeout} s"
        time.sleep(0.05)


def check_the_same(run_dir: Path, reference: Path) -> None:
    """The run is the one without a death: each worker's episodes and steps, every round with all its workers
    (none timed out), each edge's workers summed in a partial of their own, every answer bit for bit; the audit
    passes."""
    assert per_worker(run_dir) == per_worker(reference), warnings_of(run_dir)
    rounds = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()
              if '"type":"round"' in line]
    expected = [r for r in map(json.loads, (reference / "metrics.jsonl").read_text().splitlines())
                if r["type"] == "round"]
    assert [r["edges"] for r in rounds] == [r["edges"] for r in expected]
    assert [r["digest"] for r in rounds] == [r["digest"] for r in expected]  # the same answers, bit for bit
    assert not any(r["timed_out"] for r in rounds)
    report = audit(run_dir)
    assert report.tiered == sum(1 for r in rounds if r["kind"] == "aggregate" and r["digest"]) > 0


@pytest.mark.parametrize("broker", ["amqtt", "mosquitto"])
def test_a_dead_edges_workers_move_and_the_run_is_the_same(tmp_path: Path, reference: Path, broker: str,
                                                           request: pytest.FixtureRequest) -> None:
    """Edge e0 is killed (SIGKILL) after round 8: its last will reaches the root, which finds it dead 2 s later and
    names e1 its stand-in; w0 and w2 send their unanswered round to e1, which sums them as e0 would have."""
    run = f"failover-{broker}"
    args = [] if broker == "amqtt" else ["--broker", request.getfixturevalue("mosquitto_broker")]
    run_dir = federate_through(
        tmp_path, lambda: os.kill(edge_process(run, "e0")[0], signal.SIGKILL),
        ["--workers", str(WORKERS), "--edges", str(EDGES), "--witness", "--env", ENV, "--seed", str(SEED),
         "--max-episodes", str(EPISODES), "--dashboard-port", "off", *args], {"FEDRL_ROUND_TIMEOUT": ROUND_TIMEOUT},
        after_rounds=8, name=run)
    launcher = (tmp_path / f"{run}-launcher.log").read_text()
    assert "!! edge-e0 exited with code -9" in launcher and "!! edge-e0 started again (1 of 3)" in launcher
    chief_log = (run_dir / "logs" / "chief.log").read_text()
    assert "edge e0 is dead" in chief_log and "the workers of edge e0 go through edge e1" in chief_log
    assert "edge e1: edge e0's (standing in) 2 workers (w0, w2)" in (run_dir / "logs" / "edge-e1.log").read_text()
    check_the_same(run_dir, reference)


def test_a_dead_edge_is_started_again_and_rejoins_at_the_roots_round(tmp_path: Path, reference: Path) -> None:
    """Edge e0 is killed after round 6 and its workers move to e1; once the root has found it dead, the launcher
    starts it again (deploy.run_local), and it rejoins at the root's open round, serving nobody; then e1 is killed,
    and both edges' workers go through e0 from the root's round of that move on. The run is the one without a
    death."""
    run = "rejoin"
    run_dir = tmp_path / run
    chief_log, e0_log = run_dir / "logs" / "chief.log", run_dir / "logs" / "edge-e0.log"

    def faults() -> None:
        os.kill(edge_process(run, "e0")[0], signal.SIGKILL)
        wait_for(chief_log, "edge e0 is back: it rejoins at round")
        wait_for(e0_log, "the run names no worker it serves")
        os.kill(edge_process(run, "e1")[0], signal.SIGKILL)
        wait_for(chief_log, "the workers of edge e1 go through edge e0")

    federate_through(tmp_path, faults, ["--workers", str(WORKERS), "--edges", str(EDGES), "--witness", "--env", ENV,
                                        "--seed", str(SEED), "--max-episodes", str(EPISODES), "--dashboard-port",
                                        "off"],
                     {"FEDRL_ROUND_TIMEOUT": ROUND_TIMEOUT}, after_rounds=6, name=run)
    launcher = (tmp_path / f"{run}-launcher.log").read_text()
    assert "!! edge-e0 started again (1 of 3)" in launcher and "!! edge-e1 started again (1 of 3)" in launcher
    log = e0_log.read_text()
    rejoined = int(chief_log.read_text().split("edge e0 is back: it rejoins at round ")[1].split()[0])
    assert rejoined > 6
    moved = chief_log.read_text().split(": the workers of edge e1 go through edge e0")[0].rsplit("round ", 1)[1]
    took = log.split("edge e0: edge e1's (standing in) 2 workers (w1, w3) from round ")
    # e0 takes e1's workers at the root's round of the move, which is the rejoin round or later (how much later
    # depends on how fast this machine is)
    assert len(took) == 2 and int(took[1].split(",")[0]) == int(moved) >= rejoined, log[-3000:]
    check_the_same(run_dir, reference)


def test_a_lone_edges_workers_go_to_the_root(tmp_path: Path) -> None:
    """One edge (as a site with one edge chief: `--site-brokers`, Swarm, Kubernetes): killed after round 6, no edge
    of its site can stand in, so the root serves its workers itself (as edge ``root``, on its own connection); the
    launcher starts the edge again, and it rejoins serving nobody. The run is the one without a death, and the
    audit finds every contribution after the move in the root's own edge records."""
    reference = tmp_path / "reference"
    run_federation(InprocessSettings.given(env=ENV, policy="weighted", seed=SEED, workers=WORKERS,
                                           max_episodes=EPISODES, run_dir=reference, edges=1),
                   plot=False, tensorboard_files=False, models=False)
    run = "lone"
    chief_log = tmp_path / run / "logs" / "chief.log"
    run_dir = federate_through(
        tmp_path, lambda: os.kill(edge_process(run, "e0")[0], signal.SIGKILL),
        ["--workers", str(WORKERS), "--edges", "1", "--witness", "--env", ENV, "--seed", str(SEED), "--max-episodes",
         str(EPISODES), "--dashboard-port", "off"], {"FEDRL_ROUND_TIMEOUT": ROUND_TIMEOUT}, after_rounds=6, name=run)
    log = chief_log.read_text()
    assert "no live edge of edge e0's site is left: the root serves its workers itself" in log, log[-3000:]
    assert "the workers of edge e0 go through edge root" in log
    moved = int(log.split(": the workers of edge e0 go through edge root")[0].rsplit("round ", 1)[1])
    served = [json.loads(line) for line in (run_dir / "edges" / "root" / "metrics.jsonl").read_text().splitlines()]
    assert served and min(r["round"] for r in served) >= moved > 6
    assert {r["worker"] for r in served} == {f"w{i}" for i in range(WORKERS)}  # none had finished by round 7
    check_the_same(run_dir, reference)
