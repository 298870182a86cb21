"""Settings of the launchers: ``deploy.run_local`` (make run), ``deploy.inprocess`` and ``deploy.docker``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    BeforeValidator,
    NonNegativeFloat,
    NonNegativeInt,
    PlainSerializer,
    PositiveInt,
    ValidationInfo,
    field_validator,
    model_validator,
)

from chief.settings import FederationSettings, quorum_problem
from deploy import sites
from protocol import learners
from protocol.mqtt import BrokerAddress
from protocol.topics import check_id
from runtime.settings import (
    Counts,
    Port,
    Settings,
    Words,
    setting,
    warm_lr_setting,
    warm_start_problem,
    warm_temperature_setting,
)
from services.qube_sim.profile import DRAWN_MODEL, check_model_source, load_profile
from services.qube_sim.settings import Clock
from worker.settings import DeviceNoiseSettings, LearnerSetSettings

OFF = ("off", "none", "no", "false")


def _off(value: Any) -> Any:
    return None if isinstance(value, str) and value.strip().lower() in OFF else value


#: A port, 0 for any free one, or ``off`` (None).
PortOrOff = Annotated[Port | None, BeforeValidator(_off), PlainSerializer(lambda v: "off" if v is None else v)]


class WarmStartSettings(Settings):
    """Where a federation's workers start (docs/how-to/warm-start.md)."""

    init_model: Path | None = setting(None, "warm start every worker from this model (a models/<id>.pt, or a run "
                                      "folder: its first worker to solve); unset: from scratch", metavar="PATH")
    warm_lr: float = warm_lr_setting()
    warm_temperature: float = warm_temperature_setting()

    @model_validator(mode="after")
    def _warm(self) -> WarmStartSettings:
        problem = warm_start_problem(self.init_model, self.warm_lr, self.warm_temperature,
                                     getattr(self, "algo", learners.DEFAULT))
        if problem is not None:
            raise ValueError(problem)
        return self


#: The tasks whose rigs are simulated (their profile, randomisation and clock are the launcher's settings).
RIG_TASKS = ("qube", "qube-local")


class SimulatedRigSettings(FederationSettings):
    """The simulated rigs of a launcher's run: --env qube (a services.qube_sim process per worker) or qube-local (the
    rig inside each worker). Refused with any other task, where nothing would use them."""

    rig_profile: str | None = setting(None, "--env qube or qube-local: the simulated rigs' profile, a built-in "
                                      "(ideal, lab), a JSON file or a folder with one per rig (docs/rig-profiles.md); "
                                      "unset: ideal", metavar="NAME|FILE|DIR")
    rig_model: str | None = setting(None, "--env qube or qube-local: the rigs' identified profiles (a file, or a "
                                    "folder with one per rig, as deploy.lab writes them), from which each rig's "
                                    "reset and self-test are computed; qube-local also takes drawn: each rig's own "
                                    "plant, and each one domain randomisation draws, as if identified exactly (a "
                                    "pretrain's); unset: the nominal rig", metavar="FILE|DIR|drawn")
    randomize: float | None = setting(None, "--env qube or qube-local: domain randomisation, draw each rig's "
                                      "parameters at each reset from +-FRACTION of the profile's values (unset: the "
                                      "profile's)", ge=0, le=0.5, metavar="FRACTION")
    qube_clock: Clock = setting("lockstep", "--env qube or qube-local: clock of the simulated rigs (python -m "
                                "services.qube_sim --help); qube-local knows lockstep and delayed (the profile's "
                                "loop timing)")

    @field_validator("rig_profile", "rig_model")
    @classmethod
    def _profile(cls, value: str | None, info: ValidationInfo) -> str | None:
        if value is None:
            return None
        if info.field_name == "rig_model":  # a missing or bad file: one line before anything starts
            check_model_source(value)
        else:
            load_profile(value)
        return value

    @model_validator(mode="after")
    def _rigs_used(self) -> SimulatedRigSettings:
        if self.env not in RIG_TASKS:
            for name in ("rig_profile", "randomize", "rig_model"):
                if getattr(self, name) is not None:
                    raise ValueError(f"--{name.replace('_', '-')} (FEDRL_{name.upper()}) is a setting of --env qube "
                                     f"or qube-local, not of {self.env}")
        if self.rig_model == DRAWN_MODEL and self.env != "qube-local":
            raise ValueError("--rig-model drawn is for the simulated rigs of --env qube-local (a rig over MQTT has its "
                             "own model: python -m rpi_bridge --rig-model, python -m services.qube_sim --rig-model)")
        return self


def default_workers(env: str) -> int:
    """The worker count of a run that does not say: 3 rigs for qube, as in the paper, else 4."""
    return 3 if env == "qube" else 4


class TieredSettings(FederationSettings):
    """A federation that may run tiered: ``edges`` edge chiefs between the workers and the root (launchers redefine
    the field for their help text; the check is this one)."""

    edges: NonNegativeInt = setting(0, "edge chiefs of a tiered run (docs/explanation/tiered.md); 0: flat")

    @model_validator(mode="after")
    def _quorum_possible(self) -> TieredSettings:
        workers = getattr(self, "workers", None) or default_workers(self.env)  # a launcher's count, or its default
        problem = quorum_problem(self.quorum, workers)  # before a launcher starts anything
        if problem is not None:
            raise ValueError(problem)
        return self


class LocalRunSettings(DeviceNoiseSettings, LearnerSetSettings, WarmStartSettings, SimulatedRigSettings,
                       TieredSettings):
    """A federation on this machine: embedded MQTT broker, chief and N workers as separate processes (make run)."""

    workers: PositiveInt | None = setting(None, "number of workers (unset: 4, or 3 for qube as in the paper)")
    broker: str | None = setting(None, "use this broker (mqtt://host:port) instead of starting the embedded one")
    site_brokers: Words = setting([], "brokers per site, joined to --broker (docs/how-to/sites.md): worker i "
                                  f"connects to the (i mod n)-th of these and resends an unanswered update every "
                                  f"{sites.RESEND_INTERVAL:g} s (unless FEDRL_RESEND_INTERVAL says otherwise), the "
                                  "chief and the dashboard connect to --broker (unset: everyone to --broker)",
                                  metavar="URL,URL,...")
    run_id: str | None = setting(None, "run id, the topic prefix fedrl/<run>/ (unset: from the start time)")
    run_dir: Path | None = setting(None, "run folder (unset: runs/<time>-<env>-<policy>-s<seed>)")
    dashboard_port: PortOrOff = setting(0, "port of the live dashboard on 127.0.0.1 (0 = any free port, its URL is "
                                        "printed; off = no dashboard)")
    dashboard_linger: NonNegativeFloat = setting(0.0, "keep the dashboard up this many seconds after the run ended, "
                                                 "to look at the final state")
    edges: NonNegativeInt = setting(0, "edge chiefs of a tiered run (docs/explanation/tiered.md), each its own "
                                    "process (python -m chief --role edge), worker i behind edge e<i mod N>; 0: flat. "
                                    "A strategy that cannot be split (median, trimmed) runs flat")
    simulate_rigs: bool = setting(True, "--env qube: start a simulated rig (python -m services.qube_sim) for each "
                                  "worker; false: the rigs are real bridges on --broker (worker i drives rig<i>)")
    fork_workers: bool = setting(True, "fork the workers from one process that imported torch once (deploy/forked.py): "
                                 "about 3 s of CPU less per worker at start, and its memory shared; false: each "
                                 "worker its own python -m worker")
    witness: bool = setting(False, "with --edges: an observer keeps every worker's gradient and every root aggregate "
                            "in the run folder (gradients.npz), so that python -m chief.audit checks the root's "
                            "Eq. 9 against the flat one (docs/explanation/tiered.md)")

    @field_validator("broker")
    @classmethod
    def _broker_parses(cls, value: str | None) -> str | None:
        if value:
            BrokerAddress.parse(value)
        return value or None

    @field_validator("site_brokers")
    @classmethod
    def _sites_parse(cls, value: list[str]) -> list[str]:
        for url in value:
            BrokerAddress.parse(url)
        return value

    @model_validator(mode="after")
    def _real_rigs_need_their_broker(self) -> LocalRunSettings:
        if not self.simulate_rigs and (self.env != "qube" or not self.broker):
            raise ValueError("--no-simulate-rigs is for --env qube with --broker, the broker of the real rigs")
        return self

    @model_validator(mode="after")
    def _sites_need_a_core(self) -> LocalRunSettings:
        if self.site_brokers and not self.broker:
            raise ValueError("--site-brokers needs --broker, the core broker they are joined to (the chief's)")
        if self.site_brokers and self.edges and self.edges != len(self.site_brokers):
            raise ValueError(f"--edges {self.edges} with {len(self.site_brokers)} --site-brokers: one edge chief per "
                             "site (edge k at site k, worker i at both's i mod n)")
        return self

    @field_validator("run_id")
    @classmethod
    def _run_id(cls, value: str | None) -> str | None:
        return None if value is None else check_id(value, "run id")


class InprocessSettings(DeviceNoiseSettings, LearnerSetSettings, WarmStartSettings, SimulatedRigSettings,
                        TieredSettings):
    """A whole federation in one process, for sweeps: make run's chief and worker services on an in-memory hub."""

    workers: int = setting(4, "number of workers", ge=1)
    run_dir: Path = setting(help="the run folder to write")
    edges: NonNegativeInt = setting(0, "edge chiefs of a tiered run (docs/explanation/tiered.md), worker i behind "
                                    "edge e<i mod N>, each in its own thread; 0: flat. A strategy that cannot be split "
                                    "(median, trimmed) runs flat")

    @field_validator("env")
    @classmethod
    def _no_rigs(cls, value: str) -> str:
        if value == "qube":
            raise ValueError("the in-process mode has no MQTT for rigs: use --env qube-local")
        return value


class DockerSettings(DeviceNoiseSettings, LearnerSetSettings, FederationSettings):
    """Federations in Docker containers (Mosquitto, chief, N workers), one per worker count, through the Docker SDK."""

    workers: Counts = setting([4], "worker count(s); several make a sweep, one run each")
    sweep_dir: Path = setting(Path("runs/docker"), "folder that receives one run folder per run", aliases=["--out"])
    docker_network: Literal["bridge", "host"] = setting(
        "bridge", "bridge: a private network per run; host: the host's loopback, for engines without bridge "
        "networking", aliases=["--network"])
    mqtt_port: Port = setting(1883, "broker port with --network host")
    mosquitto_image: str = setting("eclipse-mosquitto:2", "broker image")
    base_image: str = setting("python:3.11-slim", "base of the built images")
    torch_index_url: str | None = setting(None, "wheel index holding the CPU torch")
    build_network: str = setting("default", "network of the build containers: default, or host where the engine "
                                 "has no bridge")
    image_prefix: str = setting("fedrl", "images are <prefix>/<role>:<tag>")
    image_tag: str = setting("latest", "images are <prefix>/<role>:<tag>")
    build: bool = setting(True, "build the images first (--no-build: use them as they are)")
    run_timeout: float = setting(3600.0, "seconds one run may take", aliases=["--timeout"], gt=0)
