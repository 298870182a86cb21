"""The tests' own launcher helper (tests/federations.py): a federation whose test fails leaves no process behind. The
launcher's children each lead a process group of their own (deploy.run_local.Fleet.start), so a SIGKILL to the
launcher alone left its embedded broker (and, until they ended, its chief and workers) running."""

from __future__ import annotations

from pathlib import Path

import psutil
import pytest

from tests.federations import federate_through


def test_a_failed_federation_leaves_no_process_of_it_behind(tmp_path: Path) -> None:
    started: list[psutil.Process] = []
    commands: list[str] = []

    def fail() -> None:
        """The fault of a test that fails mid-run: first, every process of the run (the launcher's tree)."""
        launchers = [p for p in psutil.Process().children() if "deploy.run_local" in p.cmdline()]
        assert len(launchers) == 1
        started.extend([launchers[0], *launchers[0].children(recursive=True)])
        commands.extend(" ".join(p.cmdline()) for p in started[1:])
        raise RuntimeError("the test failed")

    with pytest.raises(RuntimeError, match="the test failed"):
        federate_through(tmp_path, fail, ["--workers", "2", "--seed", "1", "--max-episodes", "600",
                                          "--dashboard-port", "off"], {}, after_rounds=1)
    assert sum("services.broker" in c for c in commands) == 1, commands  # its embedded broker among them
    assert sum(c.endswith("-m chief") for c in commands) == 1, commands
    _, alive = psutil.wait_procs(started, timeout=30)
    assert not alive, alive


def test_the_cpu_load_keeps_every_core_busy_with_one_busy_loop_at_least() -> None:
    from tests.federations import busy_loops_wanted

    assert busy_loops_wanted(cores=2, load=0.1) == 2  # a quiet machine: both cores
    assert busy_loops_wanted(cores=2, load=1.6) == 1
    assert busy_loops_wanted(cores=2, load=4.7) == 1  # make test's own processes load it already: one more
    assert busy_loops_wanted(cores=8, load=3.0) == 5
