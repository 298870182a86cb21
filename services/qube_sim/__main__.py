"""``python -m services.qube_sim``: a simulated QUBE-Servo 2 rig behind the bridge's own control loop.

The stand-in for rig + Raspberry Pi in CI and on a laptop: the same topics and frames as ``python -m rpi_bridge``,
with the physics of services/qube_sim/dynamics.py answering the 17-byte SPI frames instead of the hardware.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

from protocol.cli import add_common, broker_from, env, parse_checked, run_service, setup_logging
from rpi_bridge.__main__ import add_loop_options, control_config
from rpi_bridge.calibration import CalibrationStore
from rpi_bridge.runner import InjectedTiming
from rpi_bridge.service import BridgeService
from services.qube_sim.clock import VirtualClock
from services.qube_sim.dynamics import QubeParams
from services.qube_sim.spi_peer import SimulatedQube


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m services.qube_sim",
        description="A simulated QUBE-Servo 2 on MQTT (qube/<rig>/state, action, reset, status, telemetry). "
        "Clock 'realtime' enforces the deadline as on a real rig; 'lockstep' advances simulated time one period "
        "per answered state, for fast training; 'delayed' is lockstep with the real loop's timing: each action "
        "reaches the motor --delay-ms after its state's read and --miss-rate of them are lost. Each rig's physics "
        "differs slightly by its seed.",
    )
    add_common(parser, with_run=False)
    add_loop_options(parser)
    parser.add_argument("--clock", choices=("lockstep", "delayed", "realtime"),
                        default=env("FEDRL_QUBE_CLOCK", "lockstep"),
                        help="lockstep, delayed or realtime (env FEDRL_QUBE_CLOCK, default lockstep)")
    parser.add_argument("--delay-ms", default=env("FEDRL_QUBE_DELAY_MS", "0:7"),
                        help="clock 'delayed': each action reaches the motor after a delay drawn uniformly from "
                        "LO:HI ms (env FEDRL_QUBE_DELAY_MS, default 0:7)")
    parser.add_argument("--miss-rate", type=float, default=float(env("FEDRL_QUBE_MISS_RATE", "0.003")),
                        help="clock 'delayed': fraction of actions lost (the safe action instead) (env "
                        "FEDRL_QUBE_MISS_RATE, default 0.003, the real-time loop's rate in bench/results/latency.json)")
    parser.add_argument("--coulomb-arm", type=float, default=float(env("FEDRL_QUBE_COULOMB_ARM", "0")),
                        help="arm Coulomb friction torque in N m (env FEDRL_QUBE_COULOMB_ARM, default 0)")
    parser.add_argument("--coulomb-pendulum", type=float, default=float(env("FEDRL_QUBE_COULOMB_PENDULUM", "0")),
                        help="pendulum Coulomb friction torque in N m (env FEDRL_QUBE_COULOMB_PENDULUM, default 0)")
    parser.add_argument("--wiring-fault", choices=("none", "reverse-motor", "reverse-encoder0", "reverse-encoder1",
                                                   "dead-encoder1"), default=env("FEDRL_QUBE_WIRING_FAULT", "none"),
                        help="simulate a wiring fault, which the bridge's self-test must catch "
                        "(env FEDRL_QUBE_WIRING_FAULT, default none)")
    parser.add_argument("--state-dir", type=Path, default=Path(p) if (p := env("FEDRL_STATE_DIR", "")) else None,
                        help="keep the calibration in <dir>/<rig>-calibration.json (env FEDRL_STATE_DIR; default: "
                        "not kept, a simulated rig starts calibrated and at rest)")
    parser.add_argument("--seed", type=int, default=int(env("FEDRL_SEED", "1")),
                        help="draws this rig's variation (env FEDRL_SEED, default 1)")
    parser.add_argument("--variation", type=float, default=float(env("FEDRL_QUBE_VARIATION", "0.05")),
                        help="relative spread of masses, lengths, damping and motor gain between rigs "
                        "(env FEDRL_QUBE_VARIATION, default 0.05; 0 = nominal parameters)")
    return parse_checked(parser, argv)


def build_sim_service(args: argparse.Namespace) -> BridgeService:
    control = control_config(args)
    if args.coulomb_arm < 0 or args.coulomb_pendulum < 0:
        raise ValueError("Coulomb friction torques must be >= 0")
    params = QubeParams.varied(args.seed, scale=args.variation) if args.variation > 0 else QubeParams()
    params = replace(params, Cr=args.coulomb_arm, Cp=args.coulomb_pendulum)
    fault = args.wiring_fault.replace("-", "_")
    faults = {fault: True} if fault != "none" else {}
    timing = InjectedTiming.parse(args.delay_ms, args.miss_rate, seed=args.seed)  # checked whatever the clock
    if args.clock != "delayed":
        timing = None
    if args.clock in ("lockstep", "delayed"):
        clock = VirtualClock()
        device = SimulatedQube(params, seed=args.seed, period_s=0, clock=clock, **faults)
        advance, core_clock = clock.advance, clock
    else:
        device = SimulatedQube(params, seed=args.seed, period_s=0, clock=time.perf_counter, **faults)
        advance, core_clock = None, time.perf_counter
    store = CalibrationStore.for_rig(args.state_dir, args.rig_id) if args.state_dir is not None else None
    return BridgeService(device, args.rig_id, broker_from(args), control, deadline_s=args.deadline_ms / 1e3,
                         lockstep=args.clock != "realtime", advance=advance, client_prefix="qube-sim",
                         clock=core_clock, store=store, timing=timing)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    setup_logging(args.log_level, f"qube-sim[{args.rig_id}]")

    def build() -> BridgeService:
        service = build_sim_service(args)
        service.install_signal_handlers()
        return service

    return run_service("qube_sim", build)


if __name__ == "__main__":
    sys.exit(main())
