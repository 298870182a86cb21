"""``python -m services.qube_sim``: a simulated QUBE-Servo 2 rig behind the bridge's own control loop.

The stand-in for rig + Raspberry Pi in CI and on a laptop: the same topics and frames as ``python -m rpi_bridge``,
with the physics of services/qube_sim/dynamics.py answering the 17-byte SPI frames instead of the hardware.
"""

from __future__ import annotations

import argparse
import sys
import time

from protocol.cli import add_common, broker_from, env, parse_checked, run_service, setup_logging
from rpi_bridge.__main__ import add_loop_options, control_config
from rpi_bridge.service import BridgeService
from services.qube_sim.clock import VirtualClock
from services.qube_sim.dynamics import QubeParams
from services.qube_sim.spi_peer import SimulatedQube


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m services.qube_sim",
        description="A simulated QUBE-Servo 2 on MQTT (qube/<rig>/state, action, reset, status, telemetry). "
        "Clock 'realtime' enforces the deadline as on a real rig; 'lockstep' advances simulated time one period "
        "per answered state, for fast training. Each rig's physics differs slightly by its seed.",
    )
    add_common(parser, with_run=False)
    add_loop_options(parser)
    parser.add_argument("--clock", choices=("lockstep", "realtime"), default=env("FEDRL_QUBE_CLOCK", "lockstep"),
                        help="lockstep or realtime (env FEDRL_QUBE_CLOCK, default lockstep)")
    parser.add_argument("--seed", type=int, default=int(env("FEDRL_SEED", "1")),
                        help="draws this rig's variation (env FEDRL_SEED, default 1)")
    parser.add_argument("--variation", type=float, default=float(env("FEDRL_QUBE_VARIATION", "0.05")),
                        help="relative spread of masses, lengths, damping and motor gain between rigs "
                        "(env FEDRL_QUBE_VARIATION, default 0.05; 0 = nominal parameters)")
    return parse_checked(parser, argv)


def build_sim_service(args: argparse.Namespace) -> BridgeService:
    control = control_config(args)
    params = QubeParams.varied(args.seed, scale=args.variation) if args.variation > 0 else QubeParams()
    if args.clock == "lockstep":
        clock = VirtualClock()
        device = SimulatedQube(params, seed=args.seed, period_s=0, clock=clock)
        advance = clock.advance
    else:
        device = SimulatedQube(params, seed=args.seed, period_s=0, clock=time.perf_counter)
        advance = None
    return BridgeService(device, args.rig_id, broker_from(args), control, deadline_s=args.deadline_ms / 1e3,
                         lockstep=args.clock == "lockstep", advance=advance, client_prefix="qube-sim")


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
