"""``python -m services.qube_sim``: a simulated QUBE-Servo 2 rig behind the bridge's own control loop.

The stand-in for rig + Raspberry Pi in CI and on a laptop: the same topics and frames as ``python -m rpi_bridge``,
with the physics of services/qube_sim/dynamics.py answering the 17-byte SPI frames instead of the hardware.
"""

from __future__ import annotations

import itertools
import sys
import time
from collections.abc import Callable
from typing import Any

from rpi_bridge.calibration import CalibrationStore
from rpi_bridge.runner import InjectedTiming
from rpi_bridge.service import BridgeService
from runtime.cli import run_service, setup_logging
from runtime.settings import returns_code
from services.qube_sim.clock import VirtualClock
from services.qube_sim.profile import ProfileError, RigProfile, load_profile
from services.qube_sim.settings import SimRigSettings
from services.qube_sim.spi_peer import SimulatedQube

DESCRIPTION = (
    "A simulated QUBE-Servo 2 on MQTT (qube/<rig>/state, action, reset, status, telemetry). Clock 'realtime' "
    "enforces the deadline as on a real rig; 'lockstep' advances simulated time one period per answered state, for "
    "fast training; 'delayed' is lockstep with the real loop's timing: each action reaches the motor --delay-ms "
    "after its state's read and --miss-rate of them are lost. The rig's physics and non-ideal effects come from its "
    "--rig-profile, each rig spread around it by its seed; --randomize draws them again at every reset."
)


def build_sim_service(s: SimRigSettings) -> BridgeService:
    """The rig service these settings describe (a ValueError for settings its parts refuse)."""
    profile = s.profile()
    params = profile.rig_params(s.seed)
    fault = s.qube_wiring_fault.replace("-", "_")
    options: dict[str, Any] = {fault: True} if fault != "none" else {}
    options.update(profile.device_options())
    timing = None
    if s.qube_clock == "delayed":
        lo, hi = profile.loop_delay_ms
        timing = InjectedTiming.parse(s.qube_delay_ms or f"{lo}:{hi}",
                                      profile.loop_miss_rate if s.qube_miss_rate is None else s.qube_miss_rate,
                                      seed=s.seed)
    core_clock: Callable[[], float]
    if s.qube_clock in ("lockstep", "delayed"):
        clock = VirtualClock()
        device = SimulatedQube(params, seed=s.seed, period_s=0, clock=clock, **options)
        advance, core_clock = clock.advance, clock
    else:
        device = SimulatedQube(params, seed=s.seed, period_s=0, clock=time.perf_counter, **options)
        advance, core_clock = None, time.perf_counter
    store = CalibrationStore.for_rig(s.state_dir, s.rig_id) if s.state_dir is not None else None
    service = BridgeService(device, s.rig_id, s.connector(), s.control(), deadline_s=s.deadline_ms / 1e3,
                            lockstep=s.qube_clock != "realtime", advance=advance, client_prefix="qube-sim",
                            clock=core_clock, store=store, timing=timing)
    randomize_episodes(service, device, profile, s.seed, s.randomize)
    return service


def randomize_episodes(service: BridgeService, device: SimulatedQube, profile: RigProfile, seed: int,
                       randomize: float | None) -> None:
    """Domain randomisation over MQTT: each reset request draws the rig's next physics (RigProfile.episode_params,
    in the order the requests arrive), applied from the next SPI transfer on."""
    if profile.episode_params(seed, 0, randomize) is None:
        return
    resets = itertools.count(1)
    on_reset = service.runner.on_reset

    def redraw_then_reset(request_id: int) -> None:
        params = profile.episode_params(seed, next(resets), randomize)
        if params is not None:
            device.set_params(params)
        on_reset(request_id)

    service.runner.on_reset = redraw_then_reset  # type: ignore[method-assign]


@returns_code
def main(argv: list[str] | None = None) -> int:
    s = SimRigSettings.load(argv, prog="python -m services.qube_sim", description=DESCRIPTION)
    if s.show_profile is not None:
        try:
            print(load_profile(s.show_profile).to_json(), end="")
        except ProfileError as err:  # validated with the settings already; a file may have changed since
            print(f"qube_sim: {err}", file=sys.stderr)
            return 2
        return 0
    if s.identify is not None:
        from services.qube_sim.identify import identify_simulated

        fault = s.qube_wiring_fault.replace("-", "_")
        return identify_simulated(s.profile(), s.seed, s.control(), load_profile(s.identify_base), s.identify,
                                  faults={fault: True} if fault != "none" else None, attempts=s.identify_attempts)
    setup_logging(s.log_level, f"qube-sim[{s.rig_id}]")

    def build() -> BridgeService:
        service = build_sim_service(s)
        service.install_signal_handlers()
        return service

    return run_service("qube_sim", build)


if __name__ == "__main__":
    sys.exit(main())
