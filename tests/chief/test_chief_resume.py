"""A chief killed with SIGKILL mid-run (twice) is restarted by the launcher and resumes from its saved state: the run
ends with the same per-worker result as without the kills, the audit finds no round lost or counted twice, and the
waiting workers got their answers."""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bench.soak import chief_pids
from chief.audit import audit
from chief.checkpoint import FILENAME
from tests import federations as fed
from tests.federations import Runs

pytestmark = pytest.mark.slow

RUN = "resume"


def rounds_closed(metrics: Path) -> int:
    if not metrics.exists():
        return 0
    return sum(1 for line in metrics.read_text().splitlines() if '"type":"round"' in line)


def per_worker(run_dir: Path) -> list[tuple[str, int, int]]:
    return [(w["id"], w["episodes"], w["steps"]) for w in json.loads((run_dir / "summary.json").read_text())["workers"]]


#: The resumed run's cap: past the first finishers (episodes 22, 32 and 32 for this seed), so that the kills fall before
#: the first finisher and after the first transfers; the last worker (84) goes on alone after that, which the
#: uninterrupted run covers.
EPISODES = 36


@pytest.mark.xdist_group("e2e")
def test_a_killed_chief_resumes_with_the_same_result(tmp_path: Path, runs: Runs) -> None:
    """The same federation as the end-to-end tests' ``weighted`` run (tests/federations.py), with two kills, capped
    at EPISODES: up to there it is that run record by record, and worker by worker its episodes and steps."""
    run_dir = tmp_path / "run"
    launcher = subprocess.Popen(
        [sys.executable, "-m", "deploy.run_local", "--workers", str(fed.WORKERS), "--seed", str(fed.SEED),
         "--policy", "weighted", "--env", fed.ENV, "--max-episodes", str(EPISODES), "--run-dir",
         str(run_dir), "--run-id", RUN],
        stdout=(tmp_path / "launcher.log").open("wb"), stderr=subprocess.STDOUT)
    try:
        for at_round in (8, 30):  # before the first finisher, and after the first transfers
            deadline = time.monotonic() + 300
            while rounds_closed(run_dir / "metrics.jsonl") < at_round:
                assert time.monotonic() < deadline and launcher.poll() is None, (tmp_path / "launcher.log").read_text()
                time.sleep(0.02)
            [pid] = chief_pids(RUN)
            os.kill(pid, signal.SIGKILL)
        assert launcher.wait(timeout=400) == 0, (tmp_path / "launcher.log").read_text()[-3000:]
    finally:
        if launcher.poll() is None:
            launcher.kill()
    log = (tmp_path / "launcher.log").read_text()
    assert log.count("the chief died (exit code -9); restarting it") == 2
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["restarts"] == 2 and summary["rejected_messages"] == {}, fed.warnings_of(run_dir)
    assert summary["end_reason"] == f"reached the maximum of {EPISODES} episodes"
    assert (run_dir / FILENAME).exists()
    report = audit(run_dir)  # no round lost, none counted twice, every worker confirmed every answer
    assert report.rounds == EPISODES and report.transfers > 0
    if importlib.util.find_spec("tensorboardX") is not None:
        # Each restart redrew the event files from the records it kept and went on: nothing twice, nothing missing.
        from chief.tensorboard import rebuild
        from tests.tb_events import read_board

        live = read_board(run_dir)
        rebuild(run_dir)
        assert read_board(run_dir) == live and len(live) == 4
    uninterrupted = runs["weighted"]
    # Every submission and round up to the cap, answers bit for bit; worker by worker its episodes and steps.
    assert fed.records_up_to(run_dir, EPISODES) == fed.records_up_to(uninterrupted, EPISODES)
    assert per_worker(run_dir) == fed.per_worker_up_to(uninterrupted, EPISODES)
    finishers = {w["id"]: w["episodes"] for w in json.loads((uninterrupted / "summary.json").read_text())["workers"]}
    assert {w["id"]: w["episodes"] for w in summary["workers"] if w["solved"]} == {
        w: e for w, e in finishers.items() if e <= EPISODES} != {}


def root_pid(run_id: str) -> int:
    """The run's root chief (not its edge chiefs, which run ``python -m chief`` too, with FEDRL_ROLE=edge)."""
    [pid] = [p for p in chief_pids(run_id) if b"FEDRL_ROLE=edge" not in Path(f"/proc/{p}/environ").read_bytes()]
    return pid


def test_a_killed_root_of_edges_resumes_with_the_same_result(tmp_path: Path) -> None:
    """A tiered run (two edge chiefs, the wire witnessed): its root is killed twice and resumed by the launcher. The
    edges' partials of the open round come again (the workers send their unanswered round again, and an edge holding
    no answer sends its partial again), the resumed root counts them once, and the run ends as the same tiered
    federation in one process does; the audit's tiered checks pass on every round."""
    from deploy.inprocess import run_federation
    from deploy.settings import InprocessSettings

    run_id, edges = "resume-tiered", 2
    episodes = 36  # past the first finishers (about 22 and 32 for this seed): kills before and after a transfer
    reference = tmp_path / "reference"
    run_federation(InprocessSettings.given(env=fed.ENV, policy="weighted", seed=fed.SEED, workers=fed.WORKERS,
                   max_episodes=episodes, run_dir=reference, edges=edges), plot=False, tensorboard_files=False,
                   models=False)
    run_dir = tmp_path / "run"
    launcher = subprocess.Popen(
        [sys.executable, "-m", "deploy.run_local", "--workers", str(fed.WORKERS), "--edges", str(edges), "--witness",
         "--seed", str(fed.SEED), "--policy", "weighted", "--env", fed.ENV, "--max-episodes", str(episodes),
         "--run-dir", str(run_dir), "--run-id", run_id, "--dashboard-port", "off"],
        stdout=(tmp_path / "launcher.log").open("wb"), stderr=subprocess.STDOUT)
    try:
        for at_round in (8, 26):
            deadline = time.monotonic() + 300
            while rounds_closed(run_dir / "metrics.jsonl") < at_round:
                assert time.monotonic() < deadline and launcher.poll() is None, (tmp_path / "launcher.log").read_text()
                time.sleep(0.02)
            os.kill(root_pid(run_id), signal.SIGKILL)
        assert launcher.wait(timeout=400) == 0, (tmp_path / "launcher.log").read_text()[-3000:]
    finally:
        if launcher.poll() is None:
            launcher.kill()
    assert (tmp_path / "launcher.log").read_text().count("the chief died (exit code -9); restarting it") == 2
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["restarts"] == 2 and summary["rejected_messages"] == {}, fed.warnings_of(run_dir)
    report = audit(run_dir)  # nothing lost or counted twice; every root aggregate the flat Eq. 9 within the bound
    rounds = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()
              if '"type":"round"' in line]
    assert report.tiered == sum(1 for r in rounds if r["kind"] == "aggregate" and r["digest"]) > 0  # sums only
    assert report.transfers > 0
    assert per_worker(run_dir) == per_worker(reference)


def chief_in(run_dir: Path, run_id: str = RUN) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "chief", "--run-dir", str(run_dir), "--run-id", run_id,
                           "--broker", "mqtt://127.0.0.1:9"], capture_output=True, text=True, timeout=60)


def test_an_unusable_state_is_refused_with_a_clear_error(tmp_path: Path) -> None:
    from chief import checkpoint
    from chief.records import ServiceState
    from chief.rounds import RoundKeeper
    from protocol.tasks import task

    garbage = tmp_path / "garbage"
    garbage.mkdir()
    (garbage / FILENAME).write_bytes(b"\x00garbage")
    out = chief_in(garbage)
    assert out.returncode == 2 and "cannot resume from" in out.stderr
    over = tmp_path / "over"
    over.mkdir()
    keeper = RoundKeeper(["w0"], "weighted", task("CartPole-v0"), 10, 30.0)
    keeper.abort("aborted: test")
    checkpoint.save(over, keeper, ServiceState(run_id=RUN, session="0" * 16, epoch=0, duplicates=0, hosts={},
                                               update_steps=0, rejects={}, metrics_bytes=0, elapsed_s=0.0))
    out = chief_in(over)
    assert out.returncode == 2 and "is over (aborted: test); choose another --run-dir" in out.stderr
    assert chief_in(over, run_id="other").stderr.strip().endswith("or another --run-dir")


def test_the_resume_command_names_the_run_and_carries_its_settings(monkeypatch: pytest.MonkeyPatch) -> None:
    from deploy.run_local import load, resume_command

    monkeypatch.setenv("FEDRL_POLICY", "sync")
    s = load(["--env", "Acrobot-v1", "--run-id=r1", "--run-dir", "runs/a b", "--workers", "2"])
    cmd = resume_command(s)
    assert cmd.startswith("FEDRL_ENV=Acrobot-v1 FEDRL_POLICY=sync FEDRL_WORKERS=2 ")
    assert cmd.endswith("-m deploy.run_local --run-id r1 --run-dir 'runs/a b'")
