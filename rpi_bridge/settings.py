"""Settings of the bridge and of its control loop (shared with the simulated rig)."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import Annotated, ClassVar

from pydantic import AfterValidator, ValidationInfo, field_validator

from protocol.topics import check_id
from rpi_bridge.control import ControlConfig, check_max_command
from rpi_bridge.frame import MAX_COMMAND, VOLTS_PER_COUNT
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

    def control(self) -> ControlConfig:
        """The control core's limits: these settings over the core's own defaults."""
        return replace(_CORE, period_s=self.period_ms / 1e3, max_command=self.max_command,
                       arm_limit=math.radians(self.arm_limit_deg), action_timeout_s=self.action_timeout)


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
    identify: Path | None = setting(None, "run the start-up checks and the identification protocol (about 2 minutes "
                                    "of rig time; docs/how-to/identify.md), write its recording to OUT (.json or "
                                    ".json.gz) and exit, without MQTT", env=False, metavar="OUT")
