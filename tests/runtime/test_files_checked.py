"""Files a process reads are checked before use: a missing or unreadable CA file or env file is
one line naming the path and the reason, and exit code 2, in the bridge and the simulated rig (no traceback from
inside paho's tls_set)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.protocol.test_clean_stop import FAKE_SPIDEV, ROOT

#: As root, which reads anything, the process runs without the capabilities that bypass file permissions.
UNPRIVILEGED = (["setpriv", "--bounding-set", "-dac_override,-dac_read_search", "--"]
                if os.geteuid() == 0 else [])


def run(module: str, tmp_path: Path, *args: str, **env: str) -> subprocess.CompletedProcess[str]:
    (tmp_path / "spidev.py").write_text(FAKE_SPIDEV)
    full = {**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{ROOT}", "FEDRL_RIG_ID": "rig0",
            "FEDRL_STATE_DIR": str(tmp_path / "state"), **env}
    return subprocess.run([*UNPRIVILEGED, sys.executable, "-m", module, *args], cwd=ROOT, env=full,
                          capture_output=True, text=True, timeout=60)


@pytest.mark.skipif(os.geteuid() == 0 and shutil.which("setpriv") is None, reason="root without setpriv")
@pytest.mark.parametrize("module", ["rpi_bridge", "services.qube_sim"])
@pytest.mark.parametrize("fault", ["missing", "unreadable"])
def test_a_bad_ca_file_is_one_line_and_exit_2(tmp_path: Path, module: str, fault: str) -> None:
    ca = tmp_path / "ca.pem"
    if fault == "unreadable":
        ca.write_text("-----BEGIN CERTIFICATE-----\n")
        ca.chmod(0)
    done = run(module, tmp_path, FEDRL_BROKER="mqtts://127.0.0.1:1", FEDRL_MQTT_CA_FILE=str(ca))
    reason = "No such file or directory" if fault == "missing" else "Permission denied"
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines() == [
        f"{'rpi_bridge' if module == 'rpi_bridge' else 'qube_sim'}: cannot read the CA file (FEDRL_MQTT_CA_FILE) "
        f"{ca}: {reason}"]


@pytest.mark.skipif(os.geteuid() == 0 and shutil.which("setpriv") is None, reason="root without setpriv")
@pytest.mark.parametrize("module,flag", [("rpi_bridge", "--config"), ("services.qube_sim", "--env-file")])
def test_an_unreadable_env_file_is_one_line_and_exit_2(tmp_path: Path, module: str, flag: str) -> None:
    env = tmp_path / "rig.env"
    env.write_text("FEDRL_RIG_ID=rig0\n")
    env.chmod(0)
    done = run(module, tmp_path, flag, str(env))
    assert done.returncode == 2, done.stderr
    [line] = done.stderr.strip().splitlines()
    assert str(env) in line and line.endswith("cannot read it: Permission denied"), line
