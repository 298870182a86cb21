"""``python -m rpi_bridge``: the Raspberry Pi bridge between a QUBE-Servo 2 (SPI) and the MQTT broker."""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

from protocol.cli import add_common, broker_from, env, parse_checked, setup_logging
from rpi_bridge.control import ControlConfig
from rpi_bridge.frame import MAX_COMMAND, VOLTS_PER_COUNT


def load_env_file(path: Path) -> None:
    """KEY=VALUE lines (the systemd EnvironmentFile format) into os.environ; the real environment wins."""
    for n, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        key, sep, value = line.partition("=")
        if not sep:
            raise ValueError(f"{path}:{n}: expected KEY=VALUE, got {line!r}")
        os.environ.setdefault(key.strip(), value.strip().strip('"').strip("'"))


def add_loop_options(parser: argparse.ArgumentParser) -> None:
    """Options of the control loop, shared by the bridge and the simulated rig."""
    parser.add_argument("--rig-id", default=env("FEDRL_RIG_ID", "rig0"),
                        help="rig id, the topic prefix qube/<rig>/ (env FEDRL_RIG_ID, default rig0)")
    parser.add_argument("--period-ms", type=float, default=float(env("FEDRL_PERIOD_MS", "7")),
                        help="control period (env FEDRL_PERIOD_MS, default 7)")
    parser.add_argument("--deadline-ms", type=float, default=float(env("FEDRL_DEADLINE_MS", "7")),
                        help="an action must arrive this long after its state's read, at most the period "
                        "(env FEDRL_DEADLINE_MS, default 7)")
    parser.add_argument("--max-command", type=int, default=int(env("FEDRL_MAX_COMMAND", "400")),
                        help=f"actions are clipped to +-this many SPI counts, at most {MAX_COMMAND} "
                        f"(= {MAX_COMMAND * VOLTS_PER_COUNT:.2f} V: the manual's +-10 V) (env FEDRL_MAX_COMMAND, "
                        "default 400)")
    parser.add_argument("--arm-limit-deg", type=float, default=float(env("FEDRL_ARM_LIMIT_DEG", "110")),
                        help="arm angle that disables the amplifier (env FEDRL_ARM_LIMIT_DEG, default 110)")
    parser.add_argument("--action-timeout", type=float, default=float(env("FEDRL_ACTION_TIMEOUT", "0.5")),
                        help="watchdog: seconds without an action while running before the amplifier is disabled "
                        "(env FEDRL_ACTION_TIMEOUT, default 0.5)")


def control_config(args: argparse.Namespace) -> ControlConfig:
    if not 0 < args.deadline_ms <= args.period_ms:
        raise ValueError(f"--deadline-ms {args.deadline_ms} must be in (0, --period-ms {args.period_ms}]")
    if not 0 < args.max_command <= MAX_COMMAND:
        raise ValueError(f"--max-command must be in 1..{MAX_COMMAND} (the QUBE-Servo 2 manual's +-10 V is "
                         f"{MAX_COMMAND} counts; 999 would be about 24 V), got {args.max_command}")
    if not 0 < args.period_ms:
        raise ValueError(f"--period-ms must be positive, got {args.period_ms}")
    return ControlConfig(period_s=args.period_ms / 1e3, max_command=args.max_command,
                         arm_limit=math.radians(args.arm_limit_deg), action_timeout_s=args.action_timeout)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--config", type=Path, default=Path(p) if (p := os.environ.get("FEDRL_BRIDGE_CONFIG")) else None)
    known, _ = pre.parse_known_args(argv)
    if known.config is not None:
        load_env_file(known.config)  # before the defaults below read the environment
    parser = argparse.ArgumentParser(
        prog="python -m rpi_bridge",
        description="Bridge one QUBE-Servo 2 (SPI) to MQTT: every period it reads the rig, publishes "
        "qube/<rig>/state, applies the worker's action if it arrives before the deadline (else the safe action), "
        "runs the swing-up reset on request and disables the amplifier on a fault. Every option also reads the "
        "FEDRL_* variable named in its help; --config FILE loads such variables from a KEY=VALUE file.",
        parents=[pre],
    )
    add_common(parser, with_run=False)
    add_loop_options(parser)
    parser.add_argument("--state-dir", type=Path, default=Path(env("FEDRL_STATE_DIR", "/var/lib/fedrl")),
                        help="keeps this rig's calibration in <dir>/<rig>-calibration.json across restarts "
                        "(env FEDRL_STATE_DIR, default /var/lib/fedrl, the systemd unit's StateDirectory)")
    parser.add_argument("--recalibrate", action="store_true",
                        default=env("FEDRL_RECALIBRATE", "0").lower() in ("1", "true", "yes"),
                        help="ignore the stored calibration and calibrate again once the pendulum hangs still "
                        "(centre the arm first; env FEDRL_RECALIBRATE=1)")
    parser.add_argument("--spi-bus", type=int, default=int(env("FEDRL_SPI_BUS", "0")),
                        help="SPI bus (env FEDRL_SPI_BUS, default 0)")
    parser.add_argument("--spi-device", type=int, default=int(env("FEDRL_SPI_DEVICE", "0")),
                        help="SPI chip select (env FEDRL_SPI_DEVICE, default 0 = CE0)")
    parser.add_argument("--spi-mode", type=int, default=int(env("FEDRL_SPI_MODE", "2")),
                        help="SPI mode (env FEDRL_SPI_MODE, default 2 as the data sheet requires)")
    parser.add_argument("--spi-speed-hz", type=int, default=int(env("FEDRL_SPI_SPEED_HZ", "1000000")),
                        help="SPI clock (env FEDRL_SPI_SPEED_HZ, default 1 MHz)")
    return parse_checked(parser, argv)


def main(argv: list[str] | None = None) -> int:
    try:
        args = parse_args(argv)
        control = control_config(args)
    except (ValueError, OSError) as err:
        print(f"rpi_bridge: {err}", file=sys.stderr)
        return 2
    setup_logging(args.log_level, f"bridge[{args.rig_id}]")
    from rpi_bridge.calibration import CalibrationStore
    from rpi_bridge.device import SpidevDevice
    from rpi_bridge.service import BridgeService

    try:
        device = SpidevDevice(bus=args.spi_bus, device=args.spi_device, mode=args.spi_mode, speed_hz=args.spi_speed_hz)
    except (RuntimeError, OSError) as err:
        print(f"rpi_bridge: cannot open SPI {args.spi_bus}.{args.spi_device}: {err}", file=sys.stderr)
        return 1
    service = BridgeService(device, args.rig_id, broker_from(args), control, deadline_s=args.deadline_ms / 1e3,
                            store=CalibrationStore.for_rig(args.state_dir, args.rig_id),
                            recalibrate=args.recalibrate)
    service.install_signal_handlers()
    try:
        service.run()
    except ConnectionError as err:
        print(f"rpi_bridge: {err}", file=sys.stderr)
        return 1
    finally:
        device.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
