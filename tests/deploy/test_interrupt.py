"""Ctrl-C keeps the story: a SIGINT to ``make run``'s launcher mid-run ends the run as ``interrupted`` with its
summary, its learning curve and the command that resumes it; the audit passes on that folder; and the printed
command resumes the run to the same per-worker result as a run that was never interrupted."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from chief.audit import audit
from chief.service import EXIT_INTERRUPTED
from tests.federations import as_started

pytestmark = pytest.mark.slow

ENV, POLICY, SEED, WORKERS, EPISODES = "CartPole-v0", "weighted", 101, 2, 30
RUN_KEY = "interrupt-test-run-key-0123456789"
ARGV = ["--workers", str(WORKERS), "--env", ENV, "--policy", POLICY, "--seed", str(SEED), "--max-episodes",
        str(EPISODES), "--dashboard-port", "off"]


def rounds_closed(metrics: Path) -> int:
    return metrics.read_text().count('"type":"round"') if metrics.exists() else 0


def worker_pids(log: str) -> list[int]:
    """The workers' pids, from the chief's 'worker w0 joined from <host> (pid N)' lines."""
    return [int(pid) for pid in re.findall(r"worker \S+ joined from \S+ \(pid (\d+)\)", log)]


def signal_all(pids: list[int], sig: signal.Signals) -> None:
    for pid in pids:
        try:
            os.kill(pid, sig)
        except ProcessLookupError:
            pass


def ctrl_c_as_in_a_terminal() -> None:
    """In the launcher's process before it starts Python: SIGINT as a terminal's foreground job has it. A job that a
    non-interactive shell put in the background (``make test &`` in a script) inherits SIGINT ignored, and Python then
    installs no KeyboardInterrupt handler."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def per_worker(run_dir: Path) -> list[tuple[str, int, int]]:
    return [(w["id"], w["episodes"], w["steps"]) for w in json.loads((run_dir / "summary.json").read_text())["workers"]]


def test_ctrl_c_keeps_the_story_and_the_printed_command_resumes_the_run(tmp_path: Path) -> None:
    from deploy.inprocess import run_federation
    from deploy.settings import InprocessSettings

    run_dir = tmp_path / "run"
    out = tmp_path / "launcher.log"
    launcher = subprocess.Popen([sys.executable, "-m", "deploy.run_local", *ARGV, "--run-dir", str(run_dir),
                                 "--run-id", "ctrlc"], stdout=out.open("wb"), stderr=subprocess.STDOUT,
                                preexec_fn=ctrl_c_as_in_a_terminal)
    paused: list[int] = []
    try:
        deadline = time.monotonic() + 300
        while rounds_closed(run_dir / "metrics.jsonl") < 5:
            assert time.monotonic() < deadline and launcher.poll() is None, out.read_text()
            time.sleep(0.05)
        # The workers pause, so that the run is still open when the Ctrl-C lands however loaded the machine is;
        # they go on once the launcher has taken it.
        paused = worker_pids(out.read_text())
        assert len(paused) == WORKERS, out.read_text()
        signal_all(paused, signal.SIGSTOP)
        launcher.send_signal(signal.SIGINT)  # what Ctrl-C in the terminal sends
        taken = time.monotonic() + 60
        while "interrupted: the chief saves the run" not in out.read_text():
            assert time.monotonic() < taken and launcher.poll() is None, out.read_text()[-3000:]
            time.sleep(0.05)
        signal_all(paused, signal.SIGCONT)
        assert launcher.wait(timeout=120) == EXIT_INTERRUPTED, out.read_text()[-3000:]
    finally:
        signal_all(paused, signal.SIGCONT)
        if launcher.poll() is None:  # a failed test: a second Ctrl-C stops every process the launcher started
            for _ in range(2):
                launcher.send_signal(signal.SIGINT)
                time.sleep(1)
            try:
                launcher.wait(timeout=30)
            except subprocess.TimeoutExpired:
                launcher.kill()
                signal_all(paused, signal.SIGKILL)
    log = out.read_text()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["end_reason"] == "interrupted" and summary["episodes_to_all_solved"] is None
    assert (run_dir / "learning_curve.png").stat().st_size > 1000
    audit(run_dir)  # the interrupted run's records hold every invariant
    [resume] = [line.strip() for line in log.splitlines() if "-m deploy.run_local" in line]
    assert "--run-id ctrlc" in resume and f"--run-dir {run_dir}" in resume

    argv, env = as_started(resume)  # it names this interpreter as the user would type it (relative, or plain python)
    resumed = subprocess.run(argv, capture_output=True, text=True, timeout=600, env=env)
    assert resumed.returncode == 0, resumed.stdout[-3000:] + resumed.stderr[-3000:]
    audit(run_dir)
    uninterrupted = run_federation(InprocessSettings.given(env=ENV, policy=POLICY, seed=SEED, workers=WORKERS,
                                   max_episodes=EPISODES, run_dir=tmp_path / "uninterrupted"), plot=False,
                                   tensorboard_files=False)
    assert per_worker(run_dir) == [(w.id, w.episodes, w.steps) for w in uninterrupted.workers]


def marked(marker: str) -> list[int]:
    """The live processes whose environment holds ``marker`` (every process the launcher started inherits it)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and int(entry.name) != os.getpid():
            try:
                if marker.encode() in (entry / "environ").read_bytes():
                    found.append(int(entry.name))
            except OSError:  # gone, or not ours
                pass
    return found


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_sigterm_or_sighup_to_the_launcher_ends_the_run_as_ctrl_c_does_and_leaves_no_process(
        tmp_path: Path, sig: signal.Signals) -> None:
    """``kill``, ``timeout``, a closed terminal or a dropped ssh connection: the launcher passes the stop on as it
    does a Ctrl-C (the chief ends the run resumably, the summary is written and the audit passes on it, the resume
    command is printed), then stops the broker, the dashboard and the workers. It died at once and left them all
    running."""
    marker = f"TEST_RUN_MARK=launcher-{sig.name}-{os.getpid()}"
    run_dir = tmp_path / "run"
    out = tmp_path / "launcher.log"
    said = lambda: out.read_text() + ((run_dir / "logs" / "launcher.log").read_text()  # noqa: E731
                                      if (run_dir / "logs" / "launcher.log").exists() else "")
    argv = [a if a != "off" else "0" for a in ARGV]  # with the dashboard
    launcher = subprocess.Popen([sys.executable, "-m", "deploy.run_local", *argv, "--run-dir", str(run_dir),
                                 "--run-id", "killed"], stdout=out.open("wb"), stderr=subprocess.STDOUT,
                                env={**os.environ, marker.split("=")[0]: marker.split("=")[1]})
    paused: list[int] = []
    try:
        deadline = time.monotonic() + 300
        while rounds_closed(run_dir / "metrics.jsonl") < 3:
            assert time.monotonic() < deadline and launcher.poll() is None, said()
            time.sleep(0.05)
        assert len(marked(marker)) >= 5, said()  # launcher, broker, dashboard, chief, workers (and a fork server)
        paused = worker_pids(said())
        signal_all(paused, signal.SIGSTOP)  # the run is still open when the signal lands, however loaded the host
        launcher.send_signal(sig)
        taken = time.monotonic() + 60
        while "interrupted: the chief saves the run" not in said():
            assert time.monotonic() < taken and launcher.poll() is None, said()[-3000:]
            time.sleep(0.05)
        signal_all(paused, signal.SIGCONT)
        assert launcher.wait(timeout=120) == EXIT_INTERRUPTED, said()[-3000:]
        gone = time.monotonic() + 5
        while marked(marker) and time.monotonic() < gone:
            time.sleep(0.1)
        assert marked(marker) == [], said()[-3000:]
    finally:
        signal_all(paused, signal.SIGCONT)
        if launcher.poll() is None:
            launcher.kill()
            launcher.wait()
        signal_all(marked(marker), signal.SIGKILL)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["end_reason"] == "interrupted"
    audit(run_dir)
    [resume] = [line.strip() for line in said().splitlines() if "-m deploy.run_local" in line]
    assert "--run-id killed" in resume and f"--run-dir {run_dir}" in resume


def test_a_workers_storage_fault_stops_the_run_with_exit_5_and_the_same_command_resumes_it(
        amqtt_broker: str, tmp_path: Path) -> None:
    """A worker that cannot write (a full disk) says ``storage`` on its status topic and exits 5: the chief stops
    the run resumably and exits 5 as well, and so does the launcher, with the command that resumes it (it waited
    out its 120 s idle timeout, ended the run as aborted and exited 4; the same command then refused the folder).
    Here the status comes from outside, in w1's name on an open broker (tagged with w1's own key, derived from the
    run key the test gives the launcher), so that every worker saves its state and the resumed run ends with the
    result of a run that never stopped."""
    from deploy.inprocess import run_federation
    from deploy.settings import InprocessSettings
    from protocol import topics
    from protocol.auth import signed, worker_key
    from protocol.codec import encode
    from protocol.messages import WorkerStatus
    from protocol.mqtt import BrokerAddress, MqttConnection
    from runtime.storage import EXIT_STORAGE

    run_dir, run_id = tmp_path / "run", "enospc"
    out = tmp_path / "launcher.log"
    launcher = subprocess.Popen([sys.executable, "-m", "deploy.run_local", *ARGV, "--broker", amqtt_broker,
                                 "--run-dir", str(run_dir), "--run-id", run_id], stdout=out.open("wb"),
                                stderr=subprocess.STDOUT, env={**os.environ, "FEDRL_RUN_KEY": RUN_KEY})
    paused: list[int] = []
    try:
        deadline = time.monotonic() + 300
        while rounds_closed(run_dir / "metrics.jsonl") < 5:
            assert time.monotonic() < deadline and launcher.poll() is None, out.read_text()
            time.sleep(0.05)
        paused = worker_pids(out.read_text())
        signal_all(paused, signal.SIGSTOP)  # the run is still open when the status lands
        with MqttConnection(BrokerAddress.parse(amqtt_broker), client_id="full-disk") as conn:
            conn.publish(topics.worker(run_id, "w1", topics.STATUS), encode(signed(WorkerStatus(
                worker_id="w1", state="storage", detail=f"cannot write {run_dir}/workers/{run_id}.w1.state.pt: No "
                "space left on device (ENOSPC)"), worker_key(RUN_KEY.encode(), "w1").encode()))).wait_for_publish(5)
        taken = time.monotonic() + 60
        while "stopped on a storage fault" not in (run_dir / "logs" / "chief.log").read_text():
            assert time.monotonic() < taken and launcher.poll() is None, out.read_text()[-3000:]
            time.sleep(0.05)
        signal_all(paused, signal.SIGCONT)
        assert launcher.wait(timeout=120) == EXIT_STORAGE, out.read_text()[-3000:]
    finally:
        signal_all(paused, signal.SIGCONT)
        if launcher.poll() is None:
            launcher.kill()
            signal_all(paused, signal.SIGKILL)
    log = out.read_text()
    assert "the run stopped on a storage fault after" in log and "Traceback" not in log
    assert json.loads((run_dir / "summary.json").read_text())["end_reason"] == "interrupted"
    audit(run_dir)
    [resume] = [line.strip() for line in log.splitlines() if "-m deploy.run_local" in line]
    argv, env = as_started(resume)
    resumed = subprocess.run(argv, capture_output=True, text=True, timeout=600, env=env)
    assert resumed.returncode == 0, resumed.stdout[-3000:] + resumed.stderr[-3000:]
    audit(run_dir)
    uninterrupted = run_federation(InprocessSettings.given(env=ENV, policy=POLICY, seed=SEED, workers=WORKERS,
                                   max_episodes=EPISODES, run_dir=tmp_path / "uninterrupted"), plot=False,
                                   tensorboard_files=False)
    # Every worker finishes at the uninterrupted run's episode and env step. (It once did not when the resumed
    # chief's first round closed before w1 came back: the stop had left w1 excused; RoundKeeper.resume waits again.)
    assert per_worker(run_dir) == [(w.id, w.episodes, w.steps) for w in uninterrupted.workers]
