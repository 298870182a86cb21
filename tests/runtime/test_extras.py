"""A console script whose extra is not installed says which extra to install (one line, exit 1), as on a
Raspberry Pi that has only ``.[bridge]``."""

from __future__ import annotations

import subprocess
import sys

import pytest

from runtime.extras import missing


def test_missing_finds_what_cannot_be_imported_without_importing_it() -> None:
    assert missing("json", "no_such_module_here", "no_such_package.sub") == ["no_such_module_here",
                                                                             "no_such_package.sub"]


def test_the_worker_without_torch_names_the_learn_extra() -> None:
    code = "import sys; sys.modules['torch'] = None; sys.argv = ['fedrl-worker']; import worker.__main__"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 1
    assert done.stderr.strip().splitlines() == [
        "fedrl-worker needs torch: install the 'learn' extra (pip install '.[learn]' in the project's folder)"]


@pytest.mark.parametrize(("script", "module", "blocked", "extra"), [
    ("fedrl-inprocess", "deploy.inprocess", "torch", "learn"),
    ("fedrl-docker", "deploy.docker", "docker", "deploy"),
])
def test_the_launchers_without_their_extra_name_it(script: str, module: str, blocked: str, extra: str) -> None:
    code = (f"import sys; sys.modules[{blocked!r}] = None; sys.argv = [{script!r}]; "
            f"import runpy; runpy.run_module({module!r}, run_name='__main__')")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 1, done.stderr
    [line] = done.stderr.strip().splitlines()
    assert line.startswith(f"{script} needs {blocked}") and f"'{extra}' extra" in line
