"""``python -m rpi_bridge``: the Raspberry Pi bridge between a QUBE-Servo 2 (SPI) and the MQTT broker."""

from __future__ import annotations

import sys
import time

from rpi_bridge.device import QubeDevice
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
    if s.identify is not None:
        try:
            return identify(device, s)
        finally:
            device.close()
    try:
        service = BridgeService(device, s.rig_id, s.connector(), s.control(), deadline_s=s.deadline_ms / 1e3,
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


def identify(device: QubeDevice, s: BridgeSettings) -> int:
    """``--identify OUT``: start-up checks and the protocol in real time on this rig, the recording to OUT."""
    assert s.identify is not None
    from rpi_bridge.calibration import CalibrationStore
    from rpi_bridge.control import ControlCore
    from rpi_bridge.identify import IdentifyFailed, drive

    core = ControlCore(device, s.control(), store=CalibrationStore.for_rig(s.state_dir, s.rig_id),
                       recalibrate=s.recalibrate)
    period = core.cfg.period_s
    next_tick = time.perf_counter()

    def wait() -> None:
        nonlocal next_tick
        next_tick += period
        pause = next_tick - time.perf_counter()
        if pause > 0:
            time.sleep(pause)
        else:
            next_tick = time.perf_counter()  # late: no burst of ticks to catch up

    try:
        recording = drive(core, wait, progress=lambda seg: print(f"identify: {seg}", flush=True),
                          attempt=s.identify_attempt)
    except IdentifyFailed as err:
        print(f"rpi_bridge: identification failed: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("rpi_bridge: identification interrupted", file=sys.stderr)
        return 1
    finally:
        core.disable("identification over")
    recording = recording.model_copy(update={"rig": s.rig_id})
    try:
        recording.save(s.identify)
    except OSError as err:
        print(f"rpi_bridge: cannot write the recording {s.identify}: {err}", file=sys.stderr)
        return 1
    print(f"identify: wrote {s.identify} ({recording.rig_seconds:.0f} s of rig time, {len(recording.t)} ticks)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
