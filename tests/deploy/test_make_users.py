"""make-users.sh refuses prefixes that would put MQTT wildcards, levels or spaces into user names and the ACL:
one line, exit code 2, nothing written."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from tests.paths import ROOT

SCRIPT = ROOT / "deploy" / "mosquitto" / "make-users.sh"


@pytest.mark.parametrize("flag", ["--worker-prefix", "--rig-prefix"])
@pytest.mark.parametrize("prefix", ["x/+/", "w+", "w#", "a/b", "w 1", ""])
def test_a_bad_prefix_is_refused(tmp_path: Path, flag: str, prefix: str) -> None:
    done = subprocess.run([str(SCRIPT), "--acl-only", "-o", str(tmp_path / "out"), "-r", "1", flag, prefix],
                          capture_output=True, text=True)
    assert done.returncode == 2, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and "bad prefix" in done.stderr, done.stderr
    assert not (tmp_path / "out").exists()


def test_a_good_prefix_writes_the_acl(tmp_path: Path) -> None:
    done = subprocess.run([str(SCRIPT), "--acl-only", "-o", str(tmp_path), "-w", "2", "--worker-prefix", "wk-"],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert "wk-1" in (tmp_path / "acl").read_text()
