"""A simulated rig for the bridge's tests that keeps every motor command it was sent."""

from __future__ import annotations

from rpi_bridge.frame import parse_command
from services.qube_sim.spi_peer import SimulatedQube


class RecordingQube(SimulatedQube):
    """The real simulated peer, plus a log of the motor commands of its enabled frames."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.commands: list[int] = []

    def transfer(self, frame: bytes) -> bytes:
        cmd = parse_command(frame)
        if cmd.enabled:
            self.commands.append(cmd.motor)
        return super().transfer(frame)
