"""Settings of a worker, of ``worker.evaluate`` and of ``worker.train_local`` (torch-free: launchers import them)."""

from __future__ import annotations

import ast
from collections.abc import Iterable
from pathlib import Path
from typing import Any, Self

from pydantic import ValidationInfo, field_validator, model_validator
from pydantic_settings import CliPositionalArg, CliSuppress

from protocol import learners, qube
from protocol.auth import chief_key, key_bytes, worker_key
from protocol.rigtime import Clock
from protocol.topics import check_edge, check_id
from runtime.model_file import ModelPath
from runtime.settings import (
    Assignments,
    LearnerName,
    LearnerTaskSettings,
    LogLevel,
    MqttSettings,
    QubeActions,
    RunKeySettings,
    RunMqttSettings,
    Settings,
    TaskName,
    qube_actions_setting,
    setting,
    warm_lr_setting,
    warm_start_problem,
    warm_temperature_setting,
)


class DeviceNoiseSettings(Settings):
    """The per-device action noise of the paper."""

    device_noise: float = setting(1.0, "scale of the per-device action noise N(0.002, 0.0005) of the paper; 0 turns "
                                  "it off", ge=0, allow_inf_nan=False)


class LearnerSetSettings(Settings):
    """Fields of the learner's preset replaced for this process (``--set KEY=VALUE``, repeatable): a launcher hands
    them to its workers as every other setting (``FEDRL_LEARNER_SET``: a JSON list)."""

    learner_set: CliSuppress[Assignments] = setting([], "override a field of the learner's preset for the task "
                                                  "(PPOConfig, SACConfig, DQNConfig), e.g. entropy_coef=0.03",
                                                  aliases=["--set"], metavar="KEY=VALUE")

    @model_validator(mode="after")
    def _learner_set_parses(self) -> Self:
        self.learner_overrides()
        return self

    def learner_overrides(self) -> dict[str, Any]:
        """``learner_set`` as field -> value of the learner's configuration (a ValueError for an unknown field)."""
        return parse_overrides(self.learner_set, getattr(self, "algo", learners.DEFAULT))


class WorkerSettings(RunMqttSettings, RunKeySettings, DeviceNoiseSettings, LearnerSetSettings,
                     LearnerTaskSettings):
    """A federated RL worker (paper Algorithm 2)."""

    worker_id: str = setting("auto", "worker id, unique in the run ('auto' = hostname plus a random suffix)",
                             aliases=["--id"])
    env: TaskName = setting("CartPole-v0", "task to learn; must match the chief's")
    qube_actions: QubeActions = qube_actions_setting()
    algo: LearnerName = setting(learners.DEFAULT, "learner (python -m worker.learners lists them); must match the "
                                "chief's")
    rig_id: str | None = setting(None, "QUBE-Servo 2 rig to drive when --env qube")
    slowdown: float = setting(1.0, "a straggler for measurements: after each episode wait (slowdown - 1) times the "
                              "episode's wall time, so that it plays this many times slower (1: no wait)", ge=1.0,
                              le=1000.0)
    edge: str | None = setting(None, "the edge chief this worker's rounds go through in a tiered run (its answers "
                               "come on fedrl/<run>/edge/<edge>/..., docs/explanation/tiered.md); unset: the chief's")
    qube_clock: Clock = setting("realtime", "--env qube: the clock of the rig (a real rig runs in realtime; a "
                                "services.qube_sim rig in its --clock): under realtime and delayed the rig time is "
                                "measured, under lockstep it is read from the simulated clock; --env qube-local: "
                                "delayed applies the rig profile's loop timing (any other value: lockstep), and the "
                                "rig time always comes from the simulated clock", aliases=["--clock"])
    reply_timeout: float = setting(120.0, "seconds to wait for the chief's answer to an episode before going on "
                                   "alone", gt=0)
    ack_timeout: float = setting(600.0, "after solving, seconds to keep sending the mature actor until the chief "
                                 "acknowledges it", gt=0)
    resend_interval: float = setting(30.0, "send an unanswered submission again after this many seconds (also at "
                                     "once after a reconnect or a chief restart)", gt=0)
    start_timeout: float = setting(600.0, "seconds to wait for the chief to start the run", gt=0)
    model_dir: Path | None = setting(None, "save the mature model here as <id>.pt, and a worker's last networks "
                                     "as <id>.last.pt when it plays its episodes without meeting TC (unset: not saved)")
    state_dir: Path | None = setting(None, "when the chief interrupts the run, save this worker's resumable state "
                                     "here as <run>.<id>.state.pt, and take it up when the run resumes (unset: "
                                     "--model-dir; neither: not saved, a resumed run starts this worker afresh)")
    rig_profile: str | None = setting(None, "--env qube-local: the simulated rig's profile, a built-in (ideal, lab), "
                                      "a JSON file or a folder of them, one per worker (worker i takes its i-th "
                                      "file; default ideal; a qube_sim rig has its own)", metavar="NAME|FILE|DIR")
    rig_model: str | None = setting(None, "--env qube-local: the bridge's model of the simulated rig for its resets "
                                    "(an identified profile, or a folder with one per worker; drawn: the rig's own "
                                    "plant, and each one domain randomisation draws, as if identified exactly; unset: "
                                    "the nominal rig); a rig over MQTT has its own (python -m rpi_bridge --rig-model)",
                                    metavar="FILE|DIR|drawn")
    randomize: float | None = setting(None, "--env qube-local: domain randomisation, draw the rig's parameters at "
                                      "each reset from +-FRACTION of the profile's values (unset: the profile's)",
                                      ge=0, le=0.5, metavar="FRACTION")
    init_model: ModelPath | None = setting(
        None, "warm start: begin from this model (a models/<id>.pt, or a run folder: its first worker to solve); "
        "unset: from scratch", metavar="PATH")
    warm_lr: float = warm_lr_setting()
    warm_temperature: float = warm_temperature_setting()
    worker_key: CliSuppress[str | None] = setting(None, "this worker's own key (a variable only; give "
                                                  "FEDRL_CHIEF_KEY with it): it tags everything the worker sends, "
                                                  "and no other worker holds it. The launcher derives it from the run "
                                                  "key and the worker id (protocol/auth.py worker_key); unset: "
                                                  "derived from FEDRL_RUN_KEY, if that is set")
    chief_key: CliSuppress[str | None] = setting(None, "the key the chief tags its messages with, which this worker "
                                                 "checks them with (a variable only; protocol/auth.py chief_key); "
                                                 "unset: derived from FEDRL_RUN_KEY, if that is set")

    @field_validator("worker_key", "chief_key")
    @classmethod
    def _derived_key(cls, value: str | None) -> str | None:
        if value:
            key_bytes(value)
        return value or None

    @model_validator(mode="after")
    def _keys_together(self) -> WorkerSettings:
        if (self.worker_key is None) != (self.chief_key is None):
            raise ValueError("FEDRL_WORKER_KEY and FEDRL_CHIEF_KEY go together: a worker signs with its own key "
                             "and checks the chief with the chief key")
        if self.worker_key is not None and self.worker_id == "auto":
            raise ValueError("FEDRL_WORKER_KEY is the key of one worker id: give that id (--id, FEDRL_WORKER_ID)")
        return self

    @model_validator(mode="after")
    def _warm(self) -> WorkerSettings:
        problem = warm_start_problem(self.init_model, self.warm_lr, self.warm_temperature, self.algo)
        if problem is not None:
            raise ValueError(problem)
        return self

    def own_key(self, worker_id: str) -> bytes | None:
        """The key this worker (``worker_id``, resolved) tags its messages with; None: the run has no key."""
        if self.worker_key is not None:
            return key_bytes(self.worker_key)
        run_key = self.key()
        return None if run_key is None else worker_key(run_key, worker_id).encode()

    def chief_check_key(self) -> bytes | None:
        """The key this worker checks the chief's messages with; None: it checks nothing."""
        if self.chief_key is not None:
            return key_bytes(self.chief_key)
        run_key = self.key()
        return None if run_key is None else chief_key(run_key).encode()

    @field_validator("worker_id")
    @classmethod
    def _worker_id(cls, value: str) -> str:
        return value if value == "auto" else check_id(value, "worker id")

    @field_validator("rig_id", "edge")
    @classmethod
    def _ids(cls, value: str | None, info: ValidationInfo) -> str | None:
        if value is None:
            return None
        return check_id(value, "rig id") if info.field_name == "rig_id" else check_edge(value)

    @field_validator("rig_profile", "rig_model")
    @classmethod
    def _profile(cls, value: str | None, info: ValidationInfo) -> str | None:
        if value is not None:
            from services.qube_sim.profile import check_model_source, load_profile  # pydantic only

            if info.field_name == "rig_model":
                check_model_source(value)
            else:
                load_profile(value)
        return value

    def states(self) -> Path | None:
        """The folder of this worker's resumable state (``state_dir``, else ``model_dir``); None: none is kept."""
        return self.state_dir if self.state_dir is not None else self.model_dir

    def env_options(self) -> dict[str, Any]:
        """Options for the task's factory: the rig's clock of qube, the rig profile and randomisation of qube-local."""
        actions = {"qube_actions": self.qube_actions} if self.qube_actions != qube.DEFAULT_ACTIONS else {}
        if self.env == "qube":
            return {"qube_clock": self.qube_clock, **actions}
        if self.env != "qube-local":
            return {}
        options = {k: v for k, v in (("rig_profile", self.rig_profile), ("randomize", self.randomize),
                                     ("rig_model", self.rig_model)) if v is not None}
        options.update(actions)
        return {**options, "qube_clock": "delayed"} if self.qube_clock == "delayed" else options


class EvaluateSettings(MqttSettings, DeviceNoiseSettings):
    """Run a saved controller greedily and report its returns."""

    model: CliPositionalArg[Path] = setting(help="a models/<worker>.pt saved by a worker", env=False)
    env: TaskName | None = setting(None, "task to run it on (unset: the task the model records)")
    algo: LearnerName | None = setting(None, "the learner the model must have been made by (unset: the one it "
                                       "records)")
    eval_episodes: int = setting(10, "number of episodes", aliases=["--episodes"], ge=1)
    eval_seed: int = setting(0, "episode i is seeded with seed + i", aliases=["--seed"])
    eval_temperature: float | None = setting(
        None, "play the policy's sampled actions at this temperature (0 < T <= 1: what a fine-tune from "
        "--warm-temperature T plays, its sampling seeded per episode) instead of its greedy ones; PPO only",
        aliases=["--sampled"], gt=0, le=1)
    eval_json: Path | None = setting(None, "also write the results to this JSON file", aliases=["--json"])
    eval_video: Path | None = setting(None, "write an animated GIF of the first --video-episodes episodes into this "
                                      "folder (gymnasium tasks)", aliases=["--video"])
    eval_video_episodes: int = setting(1, "episodes to record with --video", aliases=["--video-episodes"], ge=1)
    rig_id: str | None = setting(None, "the rig to drive with --env qube (give --broker too)")
    rig_profile: str | None = setting(None, "--env qube-local: the simulated rigs' profile, a built-in (ideal, lab) "
                                      "or a JSON file (default ideal)", metavar="NAME|FILE")
    rig_model: str | None = setting(None, "--env qube-local: the bridge's model of the simulated rigs for their "
                                    "resets (an identified profile, or a folder with one per rig; unset: the nominal "
                                    "rig)", metavar="FILE|DIR")
    rigs: int = setting(0, "--env qube-local: a robustness test instead, two disturbed episodes (the trial and the "
                        "sweep) on each of N rigs drawn from --rig-profile (torque pulses and extra sensor noise, "
                        "docs/rig-profiles.md)",
                        ge=0, le=1000)
    pulse_ms: float = setting(50.0, "--rigs: length of each torque pulse in ms (0: no pulses)", ge=0, le=1000)
    sensor_noise: float = setting(1.0, "--rigs: extra encoder noise, standard deviation in counts", ge=0, le=20)
    log_level: LogLevel = setting("WARNING", "DEBUG, INFO, WARNING or ERROR")

    def _loaded(self) -> None:
        if self.rig_id is not None:  # only a rig over MQTT joins a broker
            super()._loaded()

    @field_validator("rig_id")
    @classmethod
    def _rig_id(cls, value: str | None) -> str | None:
        return None if value is None else check_id(value, "rig id")

    @model_validator(mode="after")
    def _task_given(self) -> EvaluateSettings:
        if self.env == "qube" and not self.rig_id:
            raise ValueError("--env qube drives a rig over MQTT: give --rig-id (and --broker)")
        if (self.rigs or self.rig_profile or self.rig_model) and self.env not in ("qube-local", None):
            raise ValueError("--rig-profile, --rig-model and --rigs are for the simulated rigs of --env qube-local")
        if self.rigs and self.eval_temperature is not None:
            raise ValueError("--rigs tests the greedy controller; --sampled plays episodes")
        from services.qube_sim.profile import load_profile  # torch-free, pydantic only

        for source in (self.rig_profile, self.rig_model):
            if source is not None:
                load_profile(source)
        return self


class TrainLocalSettings(DeviceNoiseSettings, LearnerSetSettings, LearnerTaskSettings):
    """One worker, no federation: Algorithm 2 without the chief, for experiments and tuning."""

    env: TaskName = setting("CartPole-v0", "task to learn")
    qube_actions: QubeActions = qube_actions_setting()
    algo: LearnerName = setting(learners.DEFAULT, "learner (python -m worker.learners lists them)")
    seed: int = setting(1, "seed of the networks, the sampling and the env")
    max_episodes: int = setting(2000, "the most episodes (the paper's M)", aliases=["--episodes"], ge=1)
    print_every: int = setting(10, "print every N episodes", aliases=["--every"], ge=1)


def parse_override(text: str, algo: str = learners.DEFAULT) -> tuple[str, Any]:
    """``KEY=VALUE`` of a field of learner ``algo``'s configuration; the value as a Python literal where it is one."""
    from worker.learners import get  # torch: only where overrides are given

    key, sep, raw = text.partition("=")
    names = set(get(algo).config_fields())
    if not sep or key not in names:
        raise ValueError(f"expected KEY=VALUE with KEY one of {sorted(names)}, got {text!r}")
    lowered = raw.strip().lower()
    if lowered in ("true", "false", "none"):
        return key, {"true": True, "false": False, "none": None}[lowered]
    try:
        return key, ast.literal_eval(raw)
    except (ValueError, SyntaxError):
        return key, raw


def parse_overrides(texts: Iterable[str], algo: str = learners.DEFAULT) -> dict[str, Any]:
    """Every ``KEY=VALUE`` of ``texts`` (parse_override), later ones winning: field -> value of ``algo``'s config."""
    return dict(parse_override(text, algo) for text in texts)


def handed_keys(run_key: str, worker_id: str) -> dict[str, Any]:
    """The key settings a launcher hands worker ``worker_id`` of a run with ``run_key`` (protocol/auth.py): its own
    key and the chief key, never the run key (with it, a worker could derive every other worker's key)."""
    raw = key_bytes(run_key)
    return {"worker_key": worker_key(raw, worker_id), "chief_key": chief_key(raw), "run_key": None}
