"""Every entry point takes the settings it documents and checks them before anything starts: deploy.inprocess takes
the rig profile, the randomisation and the QUBE clock as flags and FEDRL_* variables (and records them), and refuses a
missing profile file in one line; deploy.run_local refuses it, and any child's bad variable, before its broker."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from deploy import inprocess, run_local
from runtime.settings import EntryPoint


@pytest.fixture
def env(monkeypatch: pytest.MonkeyPatch) -> pytest.MonkeyPatch:
    for var in [v for v in os.environ if v.startswith("FEDRL_")]:
        monkeypatch.delenv(var)
    monkeypatch.setenv("FEDRL_ENV_FILE", os.devnull)
    return monkeypatch


def test_an_in_process_qube_local_run_uses_the_rig_profile_of_its_variables(env: pytest.MonkeyPatch, tmp_path: Path,
                                                                            capsys: pytest.CaptureFixture[str]) -> None:
    profile = tmp_path / "mine.json"
    profile.write_text(json.dumps({"name": "mine"}))
    env.setenv("FEDRL_RIG_PROFILE", str(profile))
    env.setenv("FEDRL_RANDOMIZE", "0.1")
    code = inprocess.main(["--env", "qube-local", "--workers", "1", "--max-episodes", "1", "--qube-clock", "delayed",
                           "--run-dir", str(tmp_path / "run")])
    assert code == 0, capsys.readouterr()
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["env_options"] == {"rig_profile": str(profile), "randomize": 0.1, "qube_clock": "delayed"}


@pytest.mark.parametrize("main", [inprocess.main, run_local.main], ids=["inprocess", "run_local"])
def test_a_missing_rig_profile_is_one_line_before_anything_starts(main: EntryPoint, env: pytest.MonkeyPatch,
                                                                  tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    env.setenv("FEDRL_RIG_PROFILE", str(tmp_path / "missing.json"))
    assert main(["--env", "qube-local", "--run-dir", str(tmp_path / "run"), "--dashboard-port", "off"]
                if main is run_local.main else ["--env", "qube-local", "--run-dir", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "FEDRL_RIG_PROFILE" in err and "neither a built-in" in err, err
    assert not (tmp_path / "run").exists()  # no broker, no run folder


def test_a_setting_the_task_cannot_use_is_refused(env: pytest.MonkeyPatch, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    env.setenv("FEDRL_RANDOMIZE", "0.2")
    assert inprocess.main(["--env", "CartPole-v0", "--run-dir", str(tmp_path / "run")]) == 2
    assert "--randomize (FEDRL_RANDOMIZE) is a setting of --env qube or qube-local" in capsys.readouterr().err


def test_run_local_checks_its_children_s_own_variables_before_its_broker(env: pytest.MonkeyPatch, tmp_path: Path,
                                                                         capsys: pytest.CaptureFixture[str]) -> None:
    env.setenv("FEDRL_QUBE_DELAY_MS", "soon")  # read by the simulated rigs only
    assert run_local.main(["--env", "qube", "--run-dir", str(tmp_path / "run"), "--dashboard-port", "off"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "FEDRL_QUBE_DELAY_MS" in err, err
    assert not (tmp_path / "run").exists()
