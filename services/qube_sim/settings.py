"""Settings of the simulated QUBE-Servo 2 rig."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import field_validator, model_validator

from protocol.messages import IDENTIFY_ATTEMPTS_LIMIT
from protocol.rigtime import Clock
from rpi_bridge.identify import IDENTIFY_ATTEMPTS
from rpi_bridge.runner import InjectedTiming
from rpi_bridge.settings import LoopSettings
from runtime.settings import MqttSettings, setting
from services.qube_sim.profile import RigProfile, load_profile

#: The profile of a rig that is not given one.
DEFAULT_PROFILE = "ideal"


class SimRigSettings(MqttSettings, LoopSettings):
    """A simulated QUBE-Servo 2 on MQTT, behind the bridge's own control loop."""

    qube_clock: Clock = setting("lockstep", "realtime enforces the deadline as on a real rig; lockstep advances "
                                "simulated time one period per answered state, for fast training; delayed is "
                                "lockstep with the real loop's timing (--delay-ms, --miss-rate)", aliases=["--clock"])
    qube_delay_ms: str | None = setting(None, "clock 'delayed': each action reaches the motor after a delay drawn "
                                        "uniformly from LO:HI ms (unset: the rig profile's loop_delay_ms)",
                                        aliases=["--delay-ms"], metavar="LO:HI")
    qube_miss_rate: float | None = setting(None, "clock 'delayed': fraction of actions lost (the safe action "
                                           "instead; unset: the rig profile's loop_miss_rate)",
                                           aliases=["--miss-rate"], ge=0, lt=1)
    rig_profile: str | None = setting(DEFAULT_PROFILE, "the rig's physics and non-ideal effects: a built-in profile "
                                      "(ideal, lab), a JSON file, or a folder of them, one per rig (the rig of seed "
                                      "S takes its (S mod 1000)-th file; see --show-profile and "
                                      f"docs/rig-profiles.md); unset: {DEFAULT_PROFILE}", metavar="NAME|FILE|DIR")
    randomize: float | None = setting(None, "domain randomisation: draw the rig's parameters at each reset from "
                                      "+-FRACTION of the profile's values (unset: the profile's)", ge=0, le=0.5,
                                      metavar="FRACTION")
    show_profile: str | None = setting(None, "print a rig profile (built-in name or file) as JSON and exit",
                                       env=False, metavar="NAME|FILE")
    qube_wiring_fault: Literal["none", "reverse-motor", "reverse-encoder0", "reverse-encoder1", "dead-encoder1"] = (
        setting("none", "simulate a wiring fault, which the bridge's self-test must catch",
                aliases=["--wiring-fault"]))
    state_dir: Path | None = setting(None, "keep the calibration in <dir>/<rig>-calibration.json (unset: a simulated "
                                     "rig starts calibrated and at rest)")
    seed: int = setting(1, "draws this rig's variation (the profile's spread) and its randomised episodes")
    identify: Path | None = setting(None, "identify this simulated rig and exit, without MQTT: the bridge's start-up "
                                    "checks and identification protocol on a virtual clock, then the host's fit "
                                    "over --identify-base; writes the fitted profile to OUT (only a trusted one; "
                                    "docs/how-to/identify.md)", env=False, metavar="OUT")
    identify_base: str = setting("lab", "--identify: the profile of every value the fit does not fit (its start)",
                                 env=False, metavar="NAME|FILE")
    identify_attempts: int = setting(IDENTIFY_ATTEMPTS, "--identify: recordings before giving up (a refused fit is "
                                     "recorded again with the next PRBS sequence)", env=False, ge=1,
                                     le=IDENTIFY_ATTEMPTS_LIMIT)

    @field_validator("qube_delay_ms")
    @classmethod
    def _delay(cls, value: str | None) -> str | None:
        if value is not None:
            InjectedTiming.parse(value, 0.0)
        return value

    @field_validator("show_profile", "identify_base")
    @classmethod
    def _profile(cls, value: str | None) -> str | None:
        if value is not None:
            load_profile(value)
        return value

    @model_validator(mode="after")
    def _rig_has_profile(self) -> SimRigSettings:
        self.profile()  # a folder must hold this rig's file
        return self

    def _seed(self) -> int | None:
        return self.seed

    def _loaded(self) -> None:
        if self.identify is None and self.show_profile is None:  # those two never connect
            super()._loaded()

    def profile(self) -> RigProfile:
        return load_profile(self.rig_profile or DEFAULT_PROFILE, self.seed)
