"""``python -m services.qube_sim``: a simulated QUBE-Servo 2 rig behind the bridge's own control loop.

The stand-in for rig + Raspberry Pi in CI and on a laptop: the same topics and frames as ``python -m rpi_bridge``,
with the physics of services/qube_sim/dynamics.py answering the 17-byte SPI frames instead of the hardware.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import replace

from rpi_bridge.calibration import CalibrationStore
from rpi_bridge.runner import InjectedTiming
from rpi_bridge.service import BridgeService
from runtime.cli import run_service, setup_logging
from runtime.settings import returns_code
from services.qube_sim.clock import VirtualClock
from services.qube_sim.dynamics import QubeParams
from services.qube_sim.settings import SimRigSettings
from services.qube_sim.spi_peer import SimulatedQube

DESCRIPTION = (
    "A simulated QUBE-Servo 2 on MQTT (qube/<rig>/state, action, reset, status, telemetry). Clock 'realtime' "
    "enforces the deadline as on a real rig; 'lockstep' advances simulated time one period per answered state, for "
    "fast training; 'delayed' is lockstep with the real loop's timing: each action reaches the motor --delay-ms "
    "after its state's read and --miss-rate of them are lost. Each rig's physics differs slightly by its seed."
)


def build_sim_service(s: SimRigSettings) -> BridgeService:
    """The rig service these settings describe (a ValueError for settings its parts refuse)."""
    params = QubeParams.varied(s.seed, scale=s.qube_variation) if s.qube_variation > 0 else QubeParams()
    params = replace(params, Cr=s.qube_coulomb_arm, Cp=s.qube_coulomb_pendulum)
    fault = s.qube_wiring_fault.replace("-", "_")
    faults = {fault: True} if fault != "none" else {}
    timing = InjectedTiming.parse(s.qube_delay_ms, s.qube_miss_rate, seed=s.seed) if s.qube_clock == "delayed" else None
    core_clock: Callable[[], float]
    if s.qube_clock in ("lockstep", "delayed"):
        clock = VirtualClock()
        device = SimulatedQube(params, seed=s.seed, period_s=0, clock=clock, **faults)
        advance, core_clock = clock.advance, clock
    else:
        device = SimulatedQube(params, seed=s.seed, period_s=0, clock=time.perf_counter, **faults)
        advance, core_clock = None, time.perf_counter
    store = CalibrationStore.for_rig(s.state_dir, s.rig_id) if s.state_dir is not None else None
    return BridgeService(device, s.rig_id, s.address(), s.control(), deadline_s=s.deadline_ms / 1e3,
                         lockstep=s.qube_clock != "realtime", advance=advance, client_prefix="qube-sim",
                         clock=core_clock, store=store, timing=timing)


@returns_code
def main(argv: list[str] | None = None) -> int:
    s = SimRigSettings.load(argv, prog="python -m services.qube_sim", description=DESCRIPTION)
    setup_logging(s.log_level, f"qube-sim[{s.rig_id}]")

    def build() -> BridgeService:
        service = build_sim_service(s)
        service.install_signal_handlers()
        return service

    return run_service("qube_sim", build)


if __name__ == "__main__":
    sys.exit(main())
