"""Every process has --help, and a bad value from an environment variable is a clear error, not a traceback."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

MODULES = ["services.broker", "chief", "worker", "rpi_bridge", "services.qube_sim", "deploy.run_local",
           "deploy.docker", "deploy.inprocess", "bench.paper", "bench.latency", "bench.reset", "bench.loop_cost",
           "bench.soak", "chief.audit", "chief.strategies"]


@pytest.mark.parametrize("module", MODULES)
def test_help(module: str) -> None:
    out = subprocess.run([sys.executable, "-m", module, "--help"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("usage:")


@pytest.mark.parametrize(
    ("module", "var", "value", "message"),
    [
        ("chief", "FEDRL_POLICY", "fedavg", "FEDRL_POLICY='fedavg' (environment): invalid choice 'fedavg'"),
        ("worker", "FEDRL_ENV", "Breakout", "invalid choice 'Breakout'"),
        ("deploy.run_local", "FEDRL_ENV", "Breakout", "invalid choice 'Breakout'"),
        ("services.qube_sim", "FEDRL_QUBE_CLOCK", "sundial", "FEDRL_QUBE_CLOCK='sundial' (environment): input should "
         "be 'lockstep', 'delayed' or 'realtime'"),
        ("chief", "FEDRL_WORKERS", "0", "FEDRL_WORKERS='0' (environment): input should be greater than or equal to 1"),
        ("rpi_bridge", "FEDRL_DEADLINE_MS", "9", "must be in (0, --period-ms"),
        ("rpi_bridge", "FEDRL_MAX_COMMAND", "999", "FEDRL_MAX_COMMAND='999' (environment): max_command must be "
         "in 1..416"),
        ("services.qube_sim", "FEDRL_QUBE_MISS_RATE", "1.5", "FEDRL_QUBE_MISS_RATE='1.5' (environment): input should "
         "be less than 1"),
        ("deploy.docker", "FEDRL_WORKERS", "2,x", "FEDRL_WORKERS='2,x' (environment): input should be a valid integer"),
    ],
)
def test_bad_settings_are_clear_errors(module: str, var: str, value: str, message: str) -> None:
    out = subprocess.run([sys.executable, "-m", module], capture_output=True, text=True, timeout=60,
                         env={**os.environ, var: value})
    assert out.returncode == 2
    assert message in out.stderr and "Traceback" not in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1, out.stderr
