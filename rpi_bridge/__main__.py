"""``python -m rpi_bridge``: the Raspberry Pi bridge between a QUBE-Servo 2 (SPI) and the MQTT broker."""

from __future__ import annotations

import sys

from rpi_bridge.settings import BridgeSettings
from runtime.cli import setup_logging
from runtime.settings import returns_code

DESCRIPTION = (
    "Bridge one QUBE-Servo 2 (SPI) to MQTT: every period it reads the rig, publishes qube/<rig>/state, applies the "
    "worker's action if it arrives before the deadline (else the safe action), runs the swing-up reset on request "
    "and disables the amplifier on a fault. --config FILE (FEDRL_BRIDGE_CONFIG) reads the FEDRL_* variables from a "
    "KEY=VALUE file such as /etc/fedrl/bridge.env."
)


@returns_code
def main(argv: list[str] | None = None) -> int:
    s = BridgeSettings.load(argv, prog="python -m rpi_bridge", description=DESCRIPTION)
    setup_logging(s.log_level, f"bridge[{s.rig_id}]")
    from rpi_bridge.calibration import CalibrationStore
    from rpi_bridge.device import SpidevDevice
    from rpi_bridge.service import BridgeService

    try:
        device = SpidevDevice(bus=s.spi_bus, device=s.spi_device, mode=s.spi_mode, speed_hz=s.spi_speed_hz)
    except (RuntimeError, OSError) as err:
        print(f"rpi_bridge: cannot open SPI {s.spi_bus}.{s.spi_device}: {err}", file=sys.stderr)
        return 1
    try:
        service = BridgeService(device, s.rig_id, s.address(), s.control(), deadline_s=s.deadline_ms / 1e3,
                                store=CalibrationStore.for_rig(s.state_dir, s.rig_id), recalibrate=s.recalibrate)
    except ValueError as err:  # a setting its parts refuse, e.g. a CA file it cannot read
        device.close()
        print(f"rpi_bridge: {err}", file=sys.stderr)
        return 2
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
