"""Settings of the bridge and of its control loop (shared with the simulated rig)."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Annotated, ClassVar

from pydantic import AfterValidator, ValidationInfo, field_validator, model_validator

from protocol.messages import IDENTIFY_ATTEMPTS_LIMIT
from protocol.topics import check_id
from rpi_bridge.control import ControlConfig, check_max_command, with_model
from rpi_bridge.frame import MAX_COMMAND, VOLTS_PER_COUNT
from rpi_bridge.plant import PlantModel
from runtime.rigfiles import rig_file
from runtime.settings import ENV_FILE_VAR, MqttSettings, Settings, setting

#: The core's defaults, which the settings below start from (each stated once, in rpi_bridge/control.py).
_CORE = ControlConfig()


class LoopSettings(Settings):
    """The control loop of one rig."""

    rig_id: str = setting("rig0", "rig id, the topic prefix qube/<rig>/")
    period_ms: float = setting(_CORE.period_s * 1e3, "control period", gt=0)
    deadline_ms: float = setting(_CORE.period_s * 1e3, "an action must arrive this long after its state's read, at "
                                 "most the period")
    max_command: Annotated[int, AfterValidator(check_max_command)] = setting(
        _CORE.max_command, f"actions are clipped to +-this many SPI counts, at most {MAX_COMMAND} "
        f"(= {MAX_COMMAND * VOLTS_PER_COUNT:.2f} V: the manual's +-10 V)")
    arm_limit_deg: float = setting(math.degrees(_CORE.arm_limit), "arm angle that disables the amplifier", gt=0,
                                   lt=180)
    action_timeout: float = setting(_CORE.action_timeout_s, "watchdog: seconds without an action while running "
                                    "before the amplifier is disabled", gt=0)
    rig_model: Path | None = setting(None, "the rig's identified profile (JSON: python -m worker.identify, "
                                     "services.qube_sim.identify or deploy.lab write it), or a folder of them, one "
                                     "per rig: the reset's swing-up and hold and the self-test are computed from it "
                                     "(unset: the nominal QUBE-Servo 2)", metavar="FILE|DIR")


    @field_validator("rig_id")
    @classmethod
    def _rig_id(cls, value: str) -> str:
        return check_id(value, "rig id")

    @field_validator("deadline_ms")
    @classmethod
    def _deadline(cls, value: float, info: ValidationInfo) -> float:
        period = info.data.get("period_ms")
        if period is not None and not 0 < value <= period:
            raise ValueError(f"must be in (0, --period-ms {period:g}]")
        return value

    @model_validator(mode="after")
    def _model_reads(self) -> LoopSettings:
        self.plant_model()
        return self

    def plant_model(self) -> PlantModel | None:
        """The model of ``--rig-model`` (None: unset); a ValueError with one line for a file it cannot read."""
        if self.rig_model is None:
            return None
        try:
            path = rig_file(self.rig_model, self._seed(), "rig model")
            data = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            raise ValueError(f"rig model {self.rig_model}: not readable JSON ({err})") from None
        if not isinstance(data, dict):
            raise ValueError(f"rig model {path}: expected a JSON object (a rig profile)")
        return PlantModel.from_profile(data)

    def _seed(self) -> int | None:
        """The seed that picks this rig's file from a --rig-model folder (a simulated rig's; a bridge: None)."""
        return None

    def control(self) -> ControlConfig:
        """The control core's limits: these settings over the core's own defaults, and the rig's model if given."""
        config = replace(_CORE, period_s=self.period_ms / 1e3, max_command=self.max_command,
                         arm_limit=math.radians(self.arm_limit_deg), action_timeout_s=self.action_timeout)
        model = self.plant_model()
        return config if model is None else with_model(config, model)


class BridgeSettings(MqttSettings, LoopSettings):
    """The Raspberry Pi bridge between one QUBE-Servo 2 (SPI) and the broker."""

    env_file_flags: ClassVar[tuple[str, ...]] = ("--env-file", "--config")
    env_file_vars: ClassVar[tuple[str, ...]] = (ENV_FILE_VAR, "FEDRL_BRIDGE_CONFIG")

    state_dir: Path = setting(Path("/var/lib/fedrl"), "keeps this rig's calibration in <dir>/<rig>-calibration.json "
                              "across restarts (the systemd unit's StateDirectory)")
    recalibrate: bool = setting(False, "ignore the stored calibration and calibrate again once the pendulum hangs "
                                "still (centre the arm first)")
    spi_bus: int = setting(0, "SPI bus", ge=0)
    spi_device: int = setting(0, "SPI chip select (0 = CE0)", ge=0)
    spi_mode: int = setting(2, "SPI mode (the data sheet requires 2)", ge=0, le=3)
    spi_speed_hz: int = setting(1_000_000, "SPI clock", gt=0)
    identify: Path | None = setting(None, "run the start-up checks and the identification protocol (about 80 s "
                                    "of rig time; docs/how-to/identify.md), write its recording to OUT (.json or "
                                    ".json.gz) and exit, without MQTT", env=False, metavar="OUT")
    identify_attempt: int = setting(0, "with --identify: 0 the protocol's own PRBS sequence; n another one (record "
                                    "again so when the fit of a recording was refused)", env=False, ge=0,
                                    lt=IDENTIFY_ATTEMPTS_LIMIT)

    def _loaded(self) -> None:
        if self.identify is None:  # --identify never connects
            super()._loaded()
