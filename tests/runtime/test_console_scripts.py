"""Every console script of pyproject.toml points at a ``main`` that returns an exit code, and ``--help`` is 0."""

from __future__ import annotations

import importlib
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from deploy.reference import PROCESSES
from tests.paths import ROOT

tomllib = pytest.importorskip("tomllib", reason="reading pyproject.toml needs Python 3.11")
SCRIPTS: dict[str, str] = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]


def target(name: str) -> Callable[[list[str] | None], int]:
    module, _, func = SCRIPTS[name].partition(":")
    return getattr(importlib.import_module(module), func)


def test_the_brief_s_scripts_are_declared() -> None:
    wanted = {"fedrl-run", "fedrl-chief", "fedrl-worker", "fedrl-bridge", "fedrl-sim-rig", "fedrl-dashboard",
              "fedrl-evaluate", "fedrl-audit", "fedrl-broker"}
    assert wanted <= set(SCRIPTS)
    assert {script for _, script, _ in PROCESSES} <= set(SCRIPTS), "the settings reference names undeclared scripts"


@pytest.mark.parametrize("name", sorted(SCRIPTS))
def test_help_returns_0(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    if name == "fedrl-docker":
        pytest.importorskip("docker", reason="the Docker SDK is not installed (pip install .[deploy])")
    assert target(name)(["--help"]) == 0
    assert capsys.readouterr().out.startswith("usage:")


@pytest.mark.parametrize("name", sorted(SCRIPTS))
def test_installed_script_runs(name: str) -> None:
    path = shutil.which(name) or shutil.which(name, path=str(Path(sys.executable).parent))
    if path is None:
        pytest.skip(f"{name} is not installed (pip install -e . writes the console scripts)")
    out = subprocess.run([path, "--help"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith(f"usage: {name}")
