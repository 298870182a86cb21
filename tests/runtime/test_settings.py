"""The settings layer (runtime/settings.py): precedence, .env files, one-line errors, handing settings to children,
and the generated reference docs/settings.md."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from chief.settings import ChiefSettings
from deploy.reference import PROCESSES, markdown, variables_module
from deploy.run_local import Fleet
from deploy.settings import DockerSettings, LocalRunSettings
from rpi_bridge.settings import BridgeSettings
from runtime.settings import ENV_FILE_VAR, Settings, env_name, flags, to_env
from services.dashboard.settings import DashboardSettings
from services.qube_sim.settings import SimRigSettings
from tests.paths import ROOT
from worker.settings import WorkerSettings


@pytest.fixture
def clean_env(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> pytest.MonkeyPatch:
    """No FEDRL_* variable of the caller's, and the current directory a fresh one (no ./.env)."""
    for name in list(os.environ):
        if name.startswith("FEDRL_"):
            monkeypatch.delenv(name)
    monkeypatch.chdir(tmp_path)
    return monkeypatch


def test_precedence_is_flag_then_environment_then_env_file_then_default(clean_env: pytest.MonkeyPatch,
                                                                         tmp_path: Path) -> None:
    (tmp_path / ".env").write_text("FEDRL_SEED=7\nFEDRL_WORKERS=9\nFEDRL_ROUND_TIMEOUT=5\nCOMPOSE_PROJECT_NAME=x\n")
    clean_env.setenv("FEDRL_WORKERS", "2")
    clean_env.setenv("FEDRL_ROUND_TIMEOUT", "6")
    s = ChiefSettings.load(["--round-timeout", "3"], prog="chief")
    assert (s.round_timeout, s.workers, s.seed, s.max_episodes) == (3.0, 2, 7, 2000)
    assert ChiefSettings.load([], prog="chief").round_timeout == 6.0


def test_env_file_is_named_by_flag_or_variable(clean_env: pytest.MonkeyPatch, tmp_path: Path) -> None:
    (tmp_path / ".env").write_text("FEDRL_SEED=1\n")
    named = tmp_path / "lab.env"
    named.write_text("FEDRL_SEED=41\nFEDRL_RECALIBRATE=1\n")
    assert ChiefSettings.load(["--env-file", str(named)], prog="chief").seed == 41
    clean_env.setenv(ENV_FILE_VAR, str(named))
    assert ChiefSettings.load([], prog="chief").seed == 41
    clean_env.delenv(ENV_FILE_VAR)
    clean_env.setenv("FEDRL_BRIDGE_CONFIG", str(named))  # the bridge's older names for its file
    assert BridgeSettings.load([], prog="bridge").recalibrate is True
    assert BridgeSettings.load(["--config", str(named), "--no-recalibrate"], prog="bridge").recalibrate is False


def test_old_flags_are_aliases_of_the_derived_ones(clean_env: pytest.MonkeyPatch) -> None:
    s = WorkerSettings.load(["--id", "w3", "--rig-id", "rig3"], prog="worker")
    assert (s.worker_id, s.rig_id) == ("w3", "rig3")
    assert WorkerSettings.load(["--worker-id", "w4"], prog="worker").worker_id == "w4"
    d = DashboardSettings.load(["--port", "0", "--rigs", "a,b", "--dashboard-rigs", "c"], prog="dashboard")
    assert (d.dashboard_port, d.dashboard_rigs) == (0, ["a", "b", "c"])
    clean_env.setenv("FEDRL_DASHBOARD_RIGS", "r0, r1")
    assert DashboardSettings.load([], prog="dashboard").dashboard_rigs == ["r0", "r1"]


@pytest.mark.parametrize(
    ("argv", "env", "env_file", "needle"),
    [
        (["--help"], {"FEDRL_SEED": "abc"}, None,
         "python -m chief: bad setting FEDRL_SEED='abc' (environment): input should be a valid integer"),
        (["--workers", "0"], {}, None,
         "python -m chief: bad setting --workers '0' (command line): input should be greater than or equal to 1"),
        ([], {}, "FEDRL_MAX_EPISODES=many\n",
         "python -m chief: bad setting FEDRL_MAX_EPISODES='many' (.env file .env): input should be a valid integer"),
        ([], {"FEDRL_ENV_FILE": "missing.env"}, None,
         "python -m chief: bad setting FEDRL_ENV_FILE=missing.env: no such file"),
        (["--wokers", "2"], {}, None, "python -m chief: unrecognized arguments: --wokers 2"),
        (["--env-file"], {}, None, "python -m chief: argument --env-file: expected one argument"),
    ],
)
def test_a_bad_setting_is_one_line_and_exit_2(argv: list[str], env: dict[str, str], env_file: str | None,
                                              needle: str, tmp_path: Path) -> None:
    if env_file is not None:
        (tmp_path / ".env").write_text(env_file)
    clean = {k: v for k, v in os.environ.items() if not k.startswith("FEDRL_")}
    out = subprocess.run([sys.executable, "-m", "chief", *argv], capture_output=True, text=True, timeout=60,
                         cwd=tmp_path, env={**clean, "PYTHONPATH": str(ROOT), **env})
    assert out.returncode == 2, out.stderr
    assert out.stderr.startswith(needle) and len(out.stderr.strip().splitlines()) == 1, out.stderr
    assert "Traceback" not in out.stderr and out.stdout == ""


ID_FIELDS = ("run_id", "worker_id", "rig_id", "edge", "edge_id")


@pytest.mark.parametrize(("command", "cls", "name"),
                         [(c, cls, n) for c, _, cls in PROCESSES for n in ID_FIELDS if n in cls.model_fields],
                         ids=lambda v: v if isinstance(v, str) else getattr(v, "__name__", ""))
@pytest.mark.parametrize("value", ["", " ", "\t"], ids=["empty", "space", "tab"])
def test_an_empty_or_blank_id_flag_is_one_line_and_exit_2(command: str, cls: type[Settings], name: str, value: str,
                                                          clean_env: pytest.MonkeyPatch,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """pydantic-settings drops an empty flag as it drops an empty variable, so `--run-id "$RUN"` with RUN unset
    joined the run `default`: every command refuses it instead (an empty variable still means unset)."""
    flag = flags(name, cls.model_fields[name])[0]
    with pytest.raises(SystemExit) as exit_:
        cls.load([*example(cls), flag, value], prog=command)
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err == f"{command}: bad setting {flag} {value!r} (command line): empty; leave " \
        "the flag out for its default\n", err
    clean_env.setenv(env_name(name, cls.model_fields[name]) or "", "")
    assert cls.load(example(cls), prog=command) is not None  # an empty variable: unset


@pytest.mark.parametrize("argv", [["worker", "--id", ""], ["worker", "--run-id", ""], ["worker", "--run-id="],
                                  ["services.qube_sim", "--rig-id", ""], ["chief", "--role", "edge", "--edge-id", " "],
                                  ["deploy.sites", "--site", "a=1", "--core", "h:1883", "--run", ""]])
def test_the_commands_refuse_an_empty_id(argv: list[str], tmp_path: Path) -> None:
    clean = {k: v for k, v in os.environ.items() if not k.startswith("FEDRL_")}
    out = subprocess.run([sys.executable, "-m", *argv, "--broker" if argv[0] != "deploy.sites" else "-o",
                          "mqtt://127.0.0.1:9" if argv[0] != "deploy.sites" else str(tmp_path / "out")],
                         capture_output=True, text=True, timeout=60, cwd=tmp_path,
                         env={**clean, "PYTHONPATH": str(ROOT)})
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1, out.stderr
    assert "id" in out.stderr and "Traceback" not in out.stderr and not (tmp_path / "out").exists()


def example(cls: type) -> list[str]:
    """Command-line values of a model's required settings."""
    return {"worker.settings:EvaluateSettings": ["m.pt", "--env", "CartPole-v0"],
            "deploy.settings:InprocessSettings": ["--run-dir", "runs/x"]}.get(f"{cls.__module__}:{cls.__name__}", [])


@pytest.mark.parametrize("cls", [cls for _, _, cls in PROCESSES], ids=lambda cls: cls.__name__)
def test_to_env_reads_back_into_the_same_settings(cls: type[Settings], clean_env: pytest.MonkeyPatch) -> None:
    given = cls.load(example(cls), prog="launcher")
    for name, value in to_env(given).items():
        clean_env.setenv(name, value)
    assert cls.load(example(cls), prog="child").model_dump() == given.model_dump()


def test_non_default_values_survive_the_trip(clean_env: pytest.MonkeyPatch) -> None:
    launcher = LocalRunSettings.load(["--dashboard-port", "off", "--workers", "3", "--qube-clock", "delayed"],
                                     prog="run")
    docker = DockerSettings.load(["--workers", "2,4", "--no-build"], prog="docker")
    for settings in (launcher, docker):
        for name, value in to_env(settings).items():
            clean_env.setenv(name, value)
        assert type(settings).load([], prog="child").model_dump() == settings.model_dump()
        for name in to_env(settings):
            clean_env.delenv(name)


def test_a_child_process_sees_what_the_launcher_was_given(clean_env: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """run_local's own path: LocalRunSettings -> child settings -> Fleet.start -> the child's environment."""
    clean_env.setenv("FEDRL_LOG_LEVEL", "DEBUG")  # not a launcher setting: the children read it as before
    (tmp_path / ".env").write_text("FEDRL_START_TIMEOUT=77\n")
    launcher = LocalRunSettings.load(["--seed", "5", "--policy", "plain", "--round-timeout", "4", "--env",
                                      "qube", "--qube-clock", "delayed", "--device-noise", "0.5", "--set",
                                      "hidden_sizes=(64, 64)", "--set", "entropy_coef=0.03"], prog="run")
    wanted = {
        "chief": launcher.child(ChiefSettings, workers=3, broker="mqtt://127.0.0.1:1", run_id="r1",
                                mqtt_username="chief", mqtt_password="s3cret", run_dir=tmp_path / "run"),
        "worker": launcher.child(WorkerSettings, broker="mqtt://127.0.0.1:1", run_id="r1", worker_id="w1",
                                 rig_id="rig1"),
        "rig": launcher.child(SimRigSettings, broker="mqtt://127.0.0.1:1", rig_id="rig1", seed=5001),
    }
    fleet = Fleet(tmp_path)
    clean_env.setenv("FEDRL_SEED", "999")  # the launcher's settings win over the environment the child inherits
    clean_env.setenv("PYTHONPATH", str(ROOT))
    try:
        for name, settings in wanted.items():
            clean_env.setenv("PROBE_MODEL", f"{type(settings).__module__}:{type(settings).__name__}")
            clean_env.setenv("PROBE_OUT", str(tmp_path / f"{name}.json"))
            assert fleet.start(name, "tests.settings_probe", settings).wait(60) == 0
    finally:
        fleet.stop()
    seen = {name: json.loads((tmp_path / f"{name}.json").read_text()) for name in wanted}
    assert seen["chief"] == json.loads(wanted["chief"].model_dump_json())
    assert (seen["chief"]["seed"], seen["chief"]["policy"], seen["chief"]["round_timeout"]) == (5, "plain", 4.0)
    assert (seen["chief"]["start_timeout"], seen["chief"]["log_level"]) == (77.0, "DEBUG")
    assert (seen["chief"]["mqtt_username"], seen["chief"]["mqtt_password"]) == ("chief", "s3cret")
    assert (seen["worker"]["env"], seen["worker"]["device_noise"], seen["worker"]["rig_id"]) == ("qube", 0.5, "rig1")
    assert seen["worker"]["learner_set"] == ["hidden_sizes=(64, 64)", "entropy_coef=0.03"]
    assert (seen["rig"]["qube_clock"], seen["rig"]["seed"]) == ("delayed", 5001)


@pytest.mark.parametrize(("text", "items"), [
    ("entropy_coef=0.03", ["entropy_coef=0.03"]),
    ("hidden_sizes=(64, 64),entropy_coef=0.03", ["hidden_sizes=(64, 64)", "entropy_coef=0.03"]),
    ("actor_lr=1e-4, obs_scale=(1.0,2.0)", ["actor_lr=1e-4", "obs_scale=(1.0,2.0)"]),
    ("", [])])
def test_a_variables_learner_set_splits_where_another_key_starts(text: str, items: list[str],
                                                                 clean_env: pytest.MonkeyPatch) -> None:
    clean_env.setenv("FEDRL_LEARNER_SET", text)
    assert WorkerSettings.load([], prog="worker").learner_set == items


def test_an_unknown_learner_field_is_refused_in_one_line(clean_env: pytest.MonkeyPatch,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        LocalRunSettings.load(["--set", "entropy=0.1"], prog="run")
    assert "expected KEY=VALUE with KEY one of" in capsys.readouterr().err


def test_a_container_child_reads_nothing_of_the_host(clean_env: pytest.MonkeyPatch) -> None:
    clean_env.setenv("FEDRL_LOG_LEVEL", "DEBUG")
    launcher = DockerSettings.load(["--seed", "3"], prog="docker")
    inherited = launcher.child(WorkerSettings, worker_id="w0")
    container = launcher.child(WorkerSettings, inherit=False, worker_id="w0")
    assert (inherited.log_level, container.log_level) == ("DEBUG", "INFO")
    assert to_env(container)["FEDRL_WORKER_ID"] == "w0"


def test_the_reference_is_up_to_date() -> None:
    assert (ROOT / "docs" / "settings.md").read_text() == markdown(), (
        "docs/settings.md is stale: python -m deploy.reference --markdown > docs/settings.md")


def test_the_known_variables_are_up_to_date() -> None:
    assert (ROOT / "runtime" / "variables.py").read_text() == variables_module(), (
        "runtime/variables.py is stale: python -m deploy.reference --variables > runtime/variables.py")


@pytest.mark.parametrize("cls", [WorkerSettings, LocalRunSettings, ChiefSettings, BridgeSettings])
def test_a_misspelt_variable_is_a_warning_naming_the_closest_setting(cls: type[Settings], clean_env: pytest.MonkeyPatch,
                                                                     tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    clean_env.setenv("FEDRL_WROKERS", "3")
    clean_env.setenv("FEDRL_BROKER", "mqtt://127.0.0.1:1")
    clean_env.setenv("FEDRL_ROUND_TIMEOUT", "5")  # the chief's: known to every process (a shared .env holds it)
    (tmp_path / ".env").write_text("FEDRL_SEEED=4\nFEDRL_SITE=a\n")  # FEDRL_SITE: a stack file's
    cls.load([], prog="p")
    assert capsys.readouterr().err.splitlines() == [
        "p: warning: FEDRL_WROKERS (environment) is no setting of any process, ignored (did you mean FEDRL_WORKERS?)",
        "p: warning: FEDRL_SEEED (.env file) is no setting of any process, ignored (did you mean FEDRL_SEED?)"]


@pytest.mark.parametrize("cls", [WorkerSettings, ChiefSettings, DashboardSettings, SimRigSettings])
def test_a_process_with_no_broker_configured_says_which_it_joins_first(cls: type[Settings],
                                                                       clean_env: pytest.MonkeyPatch,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    cls.load([], prog="p")
    assert capsys.readouterr().err.splitlines()[0] == (
        "p: no broker configured (--broker, FEDRL_BROKER): joining mqtt://127.0.0.1:1883")
    cls.load(["--broker", "mqtt://127.0.0.1:1"], prog="p")
    assert capsys.readouterr().err == ""


def test_settings_import_no_torch() -> None:
    code = ("import sys, runtime.settings, deploy.reference, chief.settings, rpi_bridge.settings, "
            "services.qube_sim.settings, services.dashboard.settings, services.broker.settings, "
            "worker.settings, deploy.settings; "
            "bad = [m for m in ('torch', 'gymnasium', 'docker') if m in sys.modules]; print(bad); sys.exit(bool(bad))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.returncode == 0, out.stdout + out.stderr


def _commands() -> list[type[Settings]]:
    from deploy.lab import LabSettings
    from worker.identify import IdentifySettings

    return [cls for _, _, cls in PROCESSES] + [LabSettings, IdentifySettings]


@pytest.mark.parametrize("cls", _commands(), ids=lambda cls: cls.__name__)
def test_help_names_a_variable_only_for_a_setting_that_reads_one(cls: type[Settings]) -> None:
    """``--help`` says ``[env: FEDRL_X]`` exactly for the settings a variable sets (a flag-only one, such as
    ``python -m rpi_bridge --identify OUT``, used to advertise a variable that was ignored with a warning), and shows
    a setting's own metavar (``OUT``, ``NAME|FILE``)."""
    parser, _ = cls.parser("x")
    shown = {a.dest: a for a in parser._actions}
    for name, field in cls.model_fields.items():
        action = shown.get(name)
        if action is None or action.help is None:
            continue
        extra = field.json_schema_extra if isinstance(field.json_schema_extra, dict) else {}
        assert ("[env: " in action.help) == bool(extra.get("env", True)), (name, action.help)
        if extra.get("metavar"):
            assert action.metavar == extra["metavar"], name
