"""The Raspberry Pi guide's permission steps (deploy/rpi/setup-host.sh), run for real as root into a scratch root,
then checked as the non-root user the bridge runs as: it reads the CA and the env file and writes its state folder;
other users read neither file."""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.paths import ROOT

SCRIPT = ROOT / "deploy" / "rpi" / "setup-host.sh"

pytestmark = [pytest.mark.skipif(
    os.geteuid() != 0 or shutil.which("useradd") is None or shutil.which("runuser") is None,
    reason="needs root, useradd and runuser"),
    pytest.mark.xdist_group("rpi-setup")]  # the machine's spi group: one test at a time may create and remove it


def _group_exists(name: str) -> bool:
    return subprocess.run(["getent", "group", name], capture_output=True).returncode == 0


@pytest.fixture
def host() -> Iterator[tuple[Path, str]]:
    """A scratch root every user can traverse, and a fresh user name; both removed afterwards."""
    root = Path(tempfile.mkdtemp(prefix="fedrl-pi-"))
    root.chmod(0o755)
    user = f"fedrlt{os.getpid() % 100000}"
    had_spi = _group_exists("spi")
    try:
        yield root, user
    finally:
        subprocess.run(["userdel", user], capture_output=True)
        subprocess.run(["groupdel", user], capture_output=True)
        if not had_spi:
            subprocess.run(["groupdel", "spi"], capture_output=True)
        shutil.rmtree(root, ignore_errors=True)


def _as(user: str, *cmd: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["runuser", "-u", user, "--", *cmd], capture_output=True, text=True)


def test_the_bridge_user_reads_its_files_and_nobody_else_does(host: tuple[Path, str], tmp_path: Path) -> None:
    root, user = host
    ca, env = tmp_path / "ca.crt", tmp_path / "bridge.env"
    ca.write_text("-----BEGIN CERTIFICATE-----\n")
    env.write_text("FEDRL_RIG_ID=rig0\nFEDRL_MQTT_PASSWORD=secret\n")
    for _ in range(2):  # a second run changes nothing and does not fail
        done = subprocess.run([str(SCRIPT), "--root", str(root), "--user", user, "--ca", str(ca), "--env", str(env)],
                              capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
    assert _group_exists("spi")
    groups = subprocess.run(["id", "-nG", user], capture_output=True, text=True).stdout.split()
    assert "spi" in groups and user in groups
    assert _as(user, "cat", str(root / "etc/fedrl/ca.crt")).returncode == 0
    assert "secret" in _as(user, "cat", str(root / "etc/fedrl/bridge.env")).stdout
    assert _as(user, "touch", str(root / "var/lib/fedrl/rig0-calibration.json")).returncode == 0
    assert _as("nobody", "cat", str(root / "etc/fedrl/bridge.env")).returncode != 0
    assert (root / "etc/fedrl/bridge.env").stat().st_mode & 0o777 == 0o640


def test_bad_arguments_are_one_line_and_exit_2(host: tuple[Path, str], tmp_path: Path) -> None:
    root, _ = host
    for args in (["--user", "x/+"], ["--ca", str(tmp_path / "missing.crt")], ["--bogus"]):
        done = subprocess.run([str(SCRIPT), "--root", str(root), *args], capture_output=True, text=True)
        assert done.returncode == 2
        assert len(done.stderr.strip().splitlines()) == 1, done.stderr
