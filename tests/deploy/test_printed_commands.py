"""Every command the launcher prints works as printed: the footer's warm start and dashboard commands after a
qube-local run and a SAC run, and the resume line after an interrupted Acrobot run, each started with settings from
variables, carry every setting the run used (deploy.run_local.run_command), and the launcher started from them takes
the same settings. The footers come from made-up solved runs (a model saved untrained), and their commands stop at a
refused broker, right after every check: they are checked to be accepted, not to train."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from deploy import run_local
from runtime.records import RunSummary, WorkerSummary
from tests.deploy.test_interrupt import ctrl_c_as_in_a_terminal, rounds_closed, signal_all, worker_pids
from tests.federations import as_started

#: Settings the runs take from the run itself (its identity and the commands' own additions), not from the first run.
OWN = ("run_id", "run_dir", "init_model", "dashboard_linger", "dashboard_port", "broker")


@pytest.fixture
def closed_port() -> Iterator[int]:
    """A port nothing listens on: a printed command pointed at it stops after its checks, before anything starts."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        yield sock.getsockname()[1]


def solved_run(run_dir: Path, s: run_local.LocalRunSettings) -> RunSummary:
    """A run folder whose w0 solved: an untrained model of the run's task and learner, and its summary."""
    from worker.episode import build_learner_and_env
    from worker.model import provenance
    from worker.settings import WorkerSettings

    options = WorkerSettings.given(env=s.env, rig_profile=s.rig_profile, randomize=s.randomize).env_options()
    _, learner = build_learner_and_env(s.env, seed=0, device_noise=0.0, spec_only=True, algo=s.algo,
                                       env_options=options)
    (run_dir / "models").mkdir(parents=True)
    learner.save(run_dir / "models" / "w0.pt", provenance(s.env, options, 0, s.seed, 1, 1, None, "w0", "made"))
    summary = RunSummary(env=s.env, policy=s.policy, seed=s.seed, tc=1.0, r_floor=0.0, max_episodes=1, total_steps=1,
                         rounds=1, end_reason="all solved", wall_s=1.0, episodes_to_all_solved=1,
                         workers=[WorkerSummary(id="w0", index=0, solved=True, episodes=1, steps=1, final_pi=1.0,
                                                state="finished")])
    summary.write(run_dir)
    return summary


def footer(summary: RunSummary, s: run_local.LocalRunSettings, capsys: pytest.CaptureFixture[str]) -> dict[str, str]:
    """The footer's commands by what they do."""
    capsys.readouterr()
    run_local.print_next_steps(summary, s)
    lines = [line.strip().split(":  ", 1) for line in capsys.readouterr().out.splitlines() if ":  " in line]
    return {what.strip(): command.split("   (")[0].strip() for what, command in lines}


def started_from(line: str, port: int, monkeypatch: pytest.MonkeyPatch,
                 capsys: pytest.CaptureFixture[str]) -> tuple[run_local.LocalRunSettings, int, str]:
    """The settings a printed command starts the launcher with, and the launcher's exit code and output when it runs
    in this process against a broker that refuses (after every check, before anything starts)."""
    argv, env = as_started(line)
    for var in [v for v in os.environ if v.startswith("FEDRL_")]:
        monkeypatch.delenv(var)
    for var, value in env.items():
        if var.startswith("FEDRL_"):
            monkeypatch.setenv(var, value)
    monkeypatch.setenv("FEDRL_ENV_FILE", os.devnull)
    s = run_local.load(argv[3:])
    monkeypatch.setenv("FEDRL_BROKER", f"mqtt://127.0.0.1:{port}")
    capsys.readouterr()
    code = run_local.main(argv[3:])
    out = capsys.readouterr()
    return s, code, out.out + out.err


def same_settings(a: run_local.LocalRunSettings, b: run_local.LocalRunSettings) -> None:
    assert a.model_dump(exclude=set(OWN)) == b.model_dump(exclude=set(OWN))


@pytest.mark.parametrize("variables", [
    {"FEDRL_ENV": "qube-local", "FEDRL_RIG_PROFILE": "lab", "FEDRL_RANDOMIZE": "0.2", "FEDRL_QUBE_CLOCK": "delayed",
     "FEDRL_WORKERS": "2", "FEDRL_POLICY": "sync", "FEDRL_SEED": "7"},
    {"FEDRL_ENV": "Pendulum-v1", "FEDRL_ALGO": "sac", "FEDRL_WORKERS": "2", "FEDRL_POLICY": "independent",
     "FEDRL_MAX_EPISODES": "60", "FEDRL_LOG_LEVEL": "WARNING"},
], ids=["qube-local", "sac"])
def test_the_footer_commands_start_a_run_with_the_same_settings(
        variables: dict[str, str], tmp_path: Path, closed_port: int, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    for var, value in {**variables, "FEDRL_ENV_FILE": os.devnull, "FEDRL_DASHBOARD_PORT": "off"}.items():
        monkeypatch.setenv(var, value)
    s = run_local.load(["--run-dir", str(tmp_path / "first")])
    summary = solved_run(tmp_path / "first", s)
    commands = footer(summary, s, capsys)
    for var, value in variables.items():
        assert f"{var}={value}" in commands["start a run from it"] and f"{var}={value}" in commands[
            "keep the dashboard up"]
    assert commands["start a run from it"].endswith(f"FEDRL_INIT_MODEL={tmp_path / 'first'} make run")

    again, code, out = started_from(commands["start a run from it"], closed_port, monkeypatch, capsys)
    same_settings(again, s)
    assert again.init_model == tmp_path / "first"
    assert code == 1 and "warm start: every worker from" in out and "cannot reach the MQTT broker" in out, out
    assert not again.run_dir.exists()  # a refused broker leaves no empty run folder

    lingering, code, out = started_from(commands["keep the dashboard up"], closed_port, monkeypatch, capsys)
    same_settings(lingering, s)
    assert lingering.dashboard_linger == 600 and lingering.dashboard_port == 0
    assert code == 1 and "cannot reach the MQTT broker" in out, out


@pytest.mark.slow
def test_the_resume_line_of_an_interrupted_run_started_from_variables_resumes_it(tmp_path: Path) -> None:
    """The issue's case: ``FEDRL_ENV=Acrobot-v1 FEDRL_WORKERS=2 FEDRL_POLICY=sync make run``, Ctrl-C, then the printed
    line in a shell that has none of those variables: the chief resumes the run (before, it refused with exit 130)."""
    run_dir = tmp_path / "run"
    out = tmp_path / "launcher.log"
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("FEDRL_")}, "FEDRL_ENV": "Acrobot-v1",
           "FEDRL_WORKERS": "2", "FEDRL_POLICY": "sync", "FEDRL_MAX_EPISODES": "2", "FEDRL_DASHBOARD_PORT": "off",
           "FEDRL_ENV_FILE": os.devnull}
    launcher = subprocess.Popen([sys.executable, "-m", "deploy.run_local", "--run-dir", str(run_dir), "--run-id",
                                 "acro"], stdout=out.open("wb"), stderr=subprocess.STDOUT, env=env,
                                preexec_fn=ctrl_c_as_in_a_terminal)
    paused: list[int] = []
    try:
        deadline = time.monotonic() + 120
        while rounds_closed(run_dir / "metrics.jsonl") < 1:
            assert time.monotonic() < deadline and launcher.poll() is None, out.read_text()
            time.sleep(0.05)
        paused = worker_pids(out.read_text())
        signal_all(paused, signal.SIGSTOP)  # the run is still open when the Ctrl-C lands
        launcher.send_signal(signal.SIGINT)
        taken = time.monotonic() + 60
        while "interrupted: the chief saves the run" not in out.read_text():
            assert time.monotonic() < taken and launcher.poll() is None, out.read_text()[-3000:]
            time.sleep(0.05)
        signal_all(paused, signal.SIGCONT)
        assert launcher.wait(timeout=60) == 130, out.read_text()[-3000:]
    finally:
        signal_all(paused, signal.SIGCONT)
        if launcher.poll() is None:
            for _ in range(2):
                launcher.send_signal(signal.SIGINT)
                time.sleep(1)
            launcher.wait(timeout=30)
    [resume] = [line.strip() for line in out.read_text().splitlines() if "-m deploy.run_local" in line]
    for var in ("FEDRL_ENV=Acrobot-v1", "FEDRL_WORKERS=2", "FEDRL_POLICY=sync", "--run-id acro"):
        assert var in resume, resume
    argv, env = as_started(resume)
    resumed = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
                               preexec_fn=ctrl_c_as_in_a_terminal)
    lines: list[str] = []
    try:
        assert resumed.stdout is not None
        for line in resumed.stdout:
            lines.append(line)
            if "resuming run acro" in line:
                break
        assert any("2 workers on Acrobot-v1, learner ppo, policy sync" in line for line in lines), "".join(lines)
        assert "resuming run acro" in lines[-1], "".join(lines)
    finally:
        if resumed.poll() is None:  # accepted: no need to train it to the end. One Ctrl-C: a second, on a busy
            resumed.send_signal(signal.SIGINT)  # machine while the first is still stopping the run, ends it at once
        rest = resumed.communicate(timeout=120)[0]
    assert resumed.returncode in (0, 130), "".join(lines) + rest


def test_a_warm_started_run_keeps_its_model_in_its_commands_but_a_run_from_it_names_its_own(
        monkeypatch: pytest.MonkeyPatch) -> None:
    for var in [v for v in os.environ if v.startswith("FEDRL_")]:
        monkeypatch.delenv(var)
    monkeypatch.setenv("FEDRL_ENV_FILE", os.devnull)
    s = run_local.load(["--init-model", "runs/a", "--run-id", "r1", "--run-dir", "runs/r1"])
    assert run_local.resume_command(s).startswith("FEDRL_INIT_MODEL=runs/a ")
    assert "FEDRL_INIT_MODEL=runs/a " in run_local.linger_command(s)
    again = run_local.warm_start_command(s, Path("runs/r1"))
    assert again.count("FEDRL_INIT_MODEL=") == 1 and again.endswith("FEDRL_INIT_MODEL=runs/r1 make run")
    assert "FEDRL_RUN_ID" not in again and "FEDRL_RUN_DIR" not in again


def test_a_resume_the_chief_refuses_exits_2_without_the_earlier_part_s_resume_line(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("FEDRL_ENV_FILE", os.devnull)
    s = run_local.load(["--run-id", "r1", "--run-dir", str(tmp_path)])
    (tmp_path / "summary.json").write_text(json.dumps({"end_reason": "interrupted"}))  # the first part's
    assert run_local.report(s, 2, 1.0) == 2
    out = capsys.readouterr()
    assert "the chief refused to run (exit code 2)" in out.err and "To resume it" not in out.out
