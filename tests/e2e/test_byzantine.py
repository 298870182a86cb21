"""One of four workers lies (it sends its gradient sign-flipped and scaled by -5, within the chief's norm bounds):
under the robust ``median`` strategy the three honest workers still learn CartPole-v0."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from chief.audit import audit

pytestmark = pytest.mark.slow


def spawn(module: str, *args: str, log: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", module, *args], stdout=log.open("wb"), stderr=subprocess.STDOUT)


def test_median_keeps_learning_with_one_liar_of_four(amqtt_broker: str, tmp_path: Path) -> None:
    common = ["--broker", amqtt_broker, "--run-id", "byzantine"]
    chief = spawn("chief", *common, "--workers", "4", "--policy", "median", "--seed", "3", "--max-episodes", "200",
                  "--run-dir", str(tmp_path / "run"), log=tmp_path / "chief.log")
    procs = [spawn("worker", *common, "--id", w, log=tmp_path / f"{w}.log") for w in ("w0", "w1", "w2")]
    procs.append(spawn("tests.adversary", *common, "--id", "w3", log=tmp_path / "w3.log"))
    try:
        assert chief.wait(timeout=900) == 0, (tmp_path / "chief.log").read_text()[-3000:]
    finally:
        for p in (chief, *procs):
            if p.poll() is None:
                p.kill()
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    honest = {w["id"]: w["episodes"] for w in summary["workers"] if w["id"] != "w3" and w["solved"]}
    assert sorted(honest) == ["w0", "w1", "w2"] and max(honest.values()) <= 120, summary["workers"]
    audit(tmp_path / "run")
