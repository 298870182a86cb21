"""deploy.forked: a forked ``python -m module`` gets its environment, its log, its own process group and its exit
code, and answers the launcher's Popen calls; the launcher's workers are such forks."""

from __future__ import annotations

import signal
import subprocess
from pathlib import Path

import pytest

from deploy.forked import ForkedProcess


def test_a_fork_runs_the_module_with_its_environment_log_and_exit_code(tmp_path: Path) -> None:
    log = tmp_path / "probe.log"
    log.write_text("earlier part\n")  # appended to, as a resumed run's log
    proc = ForkedProcess("tests.forked_probe", {"FEDRL_PROBE": "hello", "FEDRL_PROBE_CODE": "7"}, log)  # all of it
    assert proc.wait(60) == 7 and proc.poll() == 7 and proc.returncode == 7
    lines = log.read_text().splitlines()
    assert lines[0] == "earlier part"
    # its own process group (a terminal's Ctrl-C reaches the launcher only), and torch came with the fork
    assert "probe=hello own_group=True torch=True" in lines and "to stderr" in lines


def test_wait_times_out_and_a_signal_ends_it_as_popen_reports(tmp_path: Path) -> None:
    proc = ForkedProcess("tests.forked_probe", {"FEDRL_PROBE_SLEEP": "60"}, tmp_path / "probe.log")
    assert proc.poll() is None
    with pytest.raises(subprocess.TimeoutExpired):
        proc.wait(0.5)
    proc.terminate()
    assert proc.wait(30) == -signal.SIGTERM
    proc.kill()  # after its end: nothing happens, as with Popen


def test_the_launcher_forks_its_workers_unless_told_not_to(amqtt_broker: str, tmp_path: Path) -> None:
    """Both ways give the same run (the e2e tests compare forked runs record by record with stored ones); here: a
    forked worker connects and exits as a process of its own would (no run starts: exit code 3), and
    --no-fork-workers starts ``python -m worker``."""
    from deploy.run_local import Fleet
    from worker.settings import WorkerSettings

    settings = WorkerSettings.given(broker=amqtt_broker, run_id="forked", worker_id="w0", start_timeout=1.0)
    for fork in (True, False):
        fleet = Fleet(tmp_path, fork_workers=fork)
        try:
            proc = fleet.start("worker-w0", "worker", settings)
            assert isinstance(proc, ForkedProcess) is fork
            assert proc.wait(120) == 3
        finally:
            fleet.stop()
    log = (tmp_path / "worker-w0.log").read_text()
    assert log.count("connected to " + amqtt_broker) == 2, log
