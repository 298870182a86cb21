"""Storage faults are clear errors: on a full disk (a 64 KiB tmpfs), a read-only one (the tmpfs
remounted read-only) and a folder the process may not write, the chief's state, its run-folder files, the worker's
model and the launcher give one line naming the path and the errno, and exit code 5; the chief's last good state
stays as it was and no temporary file is left. Each case runs in a private mount namespace (root and unshare)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from runtime.storage import EXIT_STORAGE, StorageError, atomic_write
from tests.paths import ROOT
from tests.runtime.test_files_checked import UNPRIVILEGED

pytestmark = pytest.mark.skipif(os.geteuid() != 0 or shutil.which("unshare") is None,
                                reason="needs root and unshare (a tmpfs in a private mount namespace)")


def on_tmpfs(tmp_path: Path, fault: str, *cmd: str, size: str = "64k") -> subprocess.CompletedProcess[str]:
    """The shell words ``cmd`` with ``{dir}`` a fresh tmpfs holding ``prepare.py``'s output, after the fault: ``full``
    fills the disk, ``ro`` remounts it read-only, ``denied`` makes it 0555 and runs ``{py}`` (Python) without root's
    file-permission bypass."""
    disk = tmp_path / "disk"
    disk.mkdir()
    break_it = {"full": f"dd if=/dev/zero of={disk}/filler bs=4k count=100 2>/dev/null;",
                "ro": f"mount -o remount,ro {disk};", "denied": f"chmod 0555 {disk};"}[fault]
    python = " ".join([*(UNPRIVILEGED if fault == "denied" else []), sys.executable])
    run = " ".join(c.replace("{dir}", str(disk)).replace("{py}", python) for c in cmd)
    prepare = f"{sys.executable} {tmp_path / 'prepare.py'} {disk};" if (tmp_path / "prepare.py").exists() else ""
    script = f"mount -t tmpfs -o size={size},mode=0777 tmpfs {disk} && {prepare} {break_it} {run}"
    return subprocess.run(["unshare", "-m", "sh", "-c", script], cwd=ROOT, capture_output=True, text=True,
                          timeout=120, env={**os.environ, "PYTHONPATH": str(ROOT)})


CHECKPOINT = """
    import sys
    from pathlib import Path
    from chief import checkpoint
    from chief.rounds import RoundKeeper
    from protocol.tasks import task

    def keeper(n):
        return RoundKeeper([f"w{i}" for i in range(n)], "weighted", task("CartPole-v0"), 100, 30.0)

    def service(pad):
        return {"run_id": "r1", "session": "s", "epoch": 0, "duplicates": 0, "hosts": {"w0": "x" * pad},
                "update_steps": 10, "rejects": {}, "metrics_bytes": 0, "elapsed_s": 0.0}

    run_dir = Path(sys.argv[1])
    if sys.argv[2] == "first":
        checkpoint.save(run_dir, keeper(2), service(1))
    else:
        checkpoint.save(run_dir, keeper(8), service(40000))
"""


@pytest.mark.parametrize("fault", ["full", "ro", "denied"])
def test_the_chief_state_survives_a_failed_write(tmp_path: Path, fault: str) -> None:
    (tmp_path / "state.py").write_text(textwrap.dedent(CHECKPOINT))
    (tmp_path / "prepare.py").write_text(
        f"import subprocess, sys\nsubprocess.run([sys.executable, {str(tmp_path / 'state.py')!r}, sys.argv[1], "
        "'first'], check=True)\n")
    done = on_tmpfs(tmp_path, fault, "md5sum < {dir}/chief-state.msgpack;", "{py}",
                    str(tmp_path / "state.py"), "{dir}", "second;", "echo rc=$?; md5sum < {dir}/chief-state.msgpack;",
                    "ls -A {dir}")
    lines = done.stdout.splitlines()
    errno = {"full": "ENOSPC", "ro": "EROFS", "denied": "EACCES"}[fault]
    assert f"({errno})" in done.stderr and "chief-state" in done.stderr, done.stderr
    assert "rc=1" in lines, done.stdout  # the exception reached the script
    before, after = lines[0], lines[lines.index("rc=1") + 1]
    assert before == after  # the last good state, byte for byte
    assert "chief-state.tmp" not in lines, lines


def test_atomic_write_names_the_path_and_errno(tmp_path: Path) -> None:
    target = tmp_path / "nowhere" / "summary.json"
    with pytest.raises(FileNotFoundError) as caught:
        atomic_write(target, b"{}")
    assert not isinstance(caught.value, StorageError)  # ENOENT is not a storage fault: it passes through unchanged
    (tmp_path / "ok.json").write_bytes(b"old")
    atomic_write(tmp_path / "ok.json", b"new")
    assert (tmp_path / "ok.json").read_bytes() == b"new" and not (tmp_path / "ok.json.tmp").exists()


@pytest.mark.parametrize("fault", ["full", "ro"])
def test_the_chief_and_its_run_folder(tmp_path: Path, fault: str) -> None:
    """metrics.jsonl and summary.json on a broken disk: one line and exit code 5 from run_service."""
    (tmp_path / "prepare.py").write_text("import sys, pathlib\npathlib.Path(sys.argv[1], 'run').mkdir()\n")
    probe = (
        "from pathlib import Path; import sys\n"
        "from runtime.cli import run_service\n"
        "from chief.report import MetricsLog, write_summary\n"
        "class S:\n"
        "    def run(self):\n"
        "        log = MetricsLog(Path(sys.argv[1]) / 'run')\n"
        "        for i in range(1, 2001):\n"
        "            log.round({'round': i, 'episode': i, 'kind': 'aggregate', 'strategy': 'plain',\n"
        "                       'contributors': ['w' * 60], 'digest': 'x' * 100})\n"
        "sys.exit(run_service('chief', S))\n")
    (tmp_path / "probe.py").write_text(probe)
    done = on_tmpfs(tmp_path, fault, "{py}", str(tmp_path / "probe.py"), "{dir}")
    assert done.returncode == EXIT_STORAGE, done.stderr
    [line] = done.stderr.strip().splitlines()
    assert line.startswith("chief: cannot write ") and "/run/" in line, line
    assert line.endswith("(ENOSPC)" if fault == "full" else "(EROFS)"), line


@pytest.mark.parametrize("fault", ["full", "ro", "denied"])
def test_the_worker_model_save(tmp_path: Path, fault: str) -> None:
    probe = (
        "import sys; from pathlib import Path; from types import SimpleNamespace\n"
        "from runtime.storage import StorageError\n"
        "from worker.episode import build_learner_and_env\n"
        "from worker.service import WorkerService\n"
        "from worker.settings import WorkerSettings\n"
        "_, learner = build_learner_and_env('CartPole-v0', seed=1, device_noise=0.0)\n"
        "cfg = WorkerSettings.given(model_dir=Path(sys.argv[1]) / 'models', worker_id='w0', run_id='r1')\n"
        "me = SimpleNamespace(cfg=cfg, init_model=None)\n"
        "algo, start = SimpleNamespace(seed=1, episode=3, total_steps=100), SimpleNamespace(seed=1)\n"
        "try:\n"
        "    WorkerService._save(me, learner, algo, start)\n"
        "except StorageError as err:\n"
        "    print(err, file=sys.stderr); sys.exit(5)\n")
    (tmp_path / "probe.py").write_text(probe)
    if fault == "full":
        (tmp_path / "prepare.py").write_text("import sys, pathlib\npathlib.Path(sys.argv[1], 'models').mkdir()\n")
    done = on_tmpfs(tmp_path, fault, "{py}", str(tmp_path / "probe.py"), "{dir}", "; echo rc=$?",
                    "; ls -A {dir}/models 2>/dev/null")
    assert "rc=5" in done.stdout, done.stderr
    assert "/models" in done.stderr and "Traceback" not in done.stderr, done.stderr
    assert "w0.pt" not in done.stdout.splitlines() and "w0.pt.tmp" not in done.stdout, done.stdout


@pytest.mark.parametrize("fault", ["full", "ro", "denied"])
def test_the_launcher_never_dies_with_a_traceback(tmp_path: Path, fault: str) -> None:
    if fault == "full":
        (tmp_path / "prepare.py").write_text("import sys, pathlib\npathlib.Path(sys.argv[1], 'run').mkdir()\n")
    done = on_tmpfs(tmp_path, fault, "{py}", "-m", "deploy.run_local", "--env", "CartPole-v0",
                    "--workers", "1", "--run-dir", "{dir}/run", "--dashboard-port", "off")
    assert done.returncode == EXIT_STORAGE, done.stderr
    assert "Traceback" not in done.stderr, done.stderr
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith("python -m deploy.run_local: cannot write ") and "/run" in last, last


def test_the_chief_resumes_once_the_folder_is_writable_again(amqtt_broker: str, tmp_path: Path) -> None:
    """Issue 19, item 4: a chief whose run folder became unwritable mid-run (0555, the chief without root's
    file-permission bypass) stops with one line and exit 5, its saved state intact and no temporary left; once the
    folder is writable again the same command resumes the run from that state, and the waiting workers finish it with
    the result of an uninterrupted run."""
    from chief import checkpoint
    from chief.audit import audit
    from deploy.inprocess import run_federation
    from deploy.settings import InprocessSettings
    from protocol.tasks import task
    from tests.chief.test_chief_resume import per_worker, rounds_closed

    episodes, run_id, run_dir = 20, "storage-resume", tmp_path / "run"
    common = ["--broker", amqtt_broker, "--run-id", run_id, "--env", "CartPole-v0"]
    chief = [*UNPRIVILEGED, sys.executable, "-m", "chief", *common, "--workers", "2", "--policy", "weighted",
             "--seed", "1", "--max-episodes", str(episodes), "--run-dir", str(run_dir)]
    logs = tmp_path / "logs"
    logs.mkdir()
    workers = [subprocess.Popen([sys.executable, "-m", "worker", *common, "--worker-id", f"w{i}"], cwd=ROOT,
                                stdout=(logs / f"w{i}.log").open("wb"), stderr=subprocess.STDOUT) for i in range(2)]
    try:
        first = subprocess.Popen(chief, cwd=ROOT, stdout=(logs / "chief.log").open("wb"), stderr=subprocess.PIPE,
                                 text=True)
        deadline = time.monotonic() + 60
        while rounds_closed(run_dir / "metrics.jsonl") < 4:
            assert time.monotonic() < deadline and first.poll() is None, (logs / "chief.log").read_text()
            time.sleep(0.01)
        run_dir.chmod(0o555)
        _, err = first.communicate(timeout=60)
        assert first.returncode == EXIT_STORAGE, err
        last = err.strip().splitlines()[-1]
        assert last.startswith("chief: cannot write ") and str(run_dir) in last and last.endswith("(EACCES)"), err
        assert "Traceback" not in err, err
        saved = checkpoint.load(run_dir, task("CartPole-v0"))
        assert saved is not None and saved[0].resumable and 4 <= saved[0].round < episodes
        assert [p.name for p in run_dir.iterdir() if p.is_file() and not p.stat().st_size] == []
        # A temporary stays only where the folder turned read-only between its complete write and its rename: then
        # it cannot be removed either (that needs the folder's write permission). The next save replaces it.
        assert all(p.stat().st_size > 0 for p in run_dir.glob("*.tmp")) and not (run_dir / "summary.json").exists()

        run_dir.chmod(0o755)  # space freed, permissions fixed: the same command again
        again = subprocess.run(chief, cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
        assert f"resuming run {run_id}" in again.stdout + again.stderr
        assert [w.wait(timeout=60) for w in workers] == [0, 0]
    finally:
        if run_dir.exists():
            run_dir.chmod(0o755)
        for w in workers:
            if w.poll() is None:
                w.kill()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["restarts"] == 1 and list(run_dir.glob("*.tmp")) == []
    audit(run_dir)
    run_federation(InprocessSettings.given(env="CartPole-v0", policy="weighted", seed=1, workers=2,
                   max_episodes=episodes, run_dir=tmp_path / "uninterrupted"), plot=False)
    assert per_worker(run_dir) == per_worker(tmp_path / "uninterrupted")
