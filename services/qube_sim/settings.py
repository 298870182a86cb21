"""Settings of the simulated QUBE-Servo 2 rig."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import field_validator

from rpi_bridge.runner import InjectedTiming
from rpi_bridge.settings import LoopSettings
from runtime.settings import MqttSettings, setting

Clock = Literal["lockstep", "delayed", "realtime"]


class SimRigSettings(MqttSettings, LoopSettings):
    """A simulated QUBE-Servo 2 on MQTT, behind the bridge's own control loop."""

    qube_clock: Clock = setting("lockstep", "realtime enforces the deadline as on a real rig; lockstep advances "
                                "simulated time one period per answered state, for fast training; delayed is "
                                "lockstep with the real loop's timing (--delay-ms, --miss-rate)", aliases=["--clock"])
    qube_delay_ms: str = setting("0:7", "clock 'delayed': each action reaches the motor after a delay drawn "
                                 "uniformly from LO:HI ms", aliases=["--delay-ms"])
    qube_miss_rate: float = setting(0.003, "clock 'delayed': fraction of actions lost (the safe action instead); "
                                    "the default is the real-time loop's rate in bench/results/latency.json",
                                    aliases=["--miss-rate"], ge=0, lt=1)
    qube_coulomb_arm: float = setting(0.0, "arm Coulomb friction torque in N m", aliases=["--coulomb-arm"], ge=0)
    qube_coulomb_pendulum: float = setting(0.0, "pendulum Coulomb friction torque in N m",
                                           aliases=["--coulomb-pendulum"], ge=0)
    qube_wiring_fault: Literal["none", "reverse-motor", "reverse-encoder0", "reverse-encoder1", "dead-encoder1"] = (
        setting("none", "simulate a wiring fault, which the bridge's self-test must catch",
                aliases=["--wiring-fault"]))
    state_dir: Path | None = setting(None, "keep the calibration in <dir>/<rig>-calibration.json (unset: a simulated "
                                     "rig starts calibrated and at rest)")
    seed: int = setting(1, "draws this rig's variation")
    qube_variation: float = setting(0.05, "relative spread of masses, lengths, damping and motor gain between rigs "
                                    "(0 = nominal parameters)", aliases=["--variation"], ge=0)

    @field_validator("qube_delay_ms")
    @classmethod
    def _delay(cls, value: str) -> str:
        InjectedTiming.parse(value, 0.0)
        return value
