"""The SPI link to a QUBE-Servo 2: a small protocol, and the spidev implementation for a Raspberry Pi."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from rpi_bridge.frame import FRAME_LEN


@runtime_checkable
class QubeDevice(Protocol):
    """Anything that exchanges one 17-byte frame for another: the real rig or ``services.qube_sim``."""

    def transfer(self, frame: bytes) -> bytes: ...

    def close(self) -> None: ...


class SpidevDevice:
    """QUBE-Servo 2 on a Raspberry Pi SPI bus: SPI mode 2, MSB first, 1 MHz, one ``xfer2`` of 17 bytes per
    transfer with chip select held low for the whole frame ([DS] p.1; Quanser's and KoreaTech's examples)."""

    def __init__(self, bus: int = 0, device: int = 0, mode: int = 2, speed_hz: int = 1_000_000) -> None:
        try:
            import spidev  # lazy: only the Pi needs it
        except ImportError as exc:
            raise RuntimeError(
                "the spidev module is missing: install the bridge extra with `pip install .[bridge]` "
                "(Linux with /dev/spidev*, e.g. a Raspberry Pi with SPI enabled)"
            ) from exc
        self._spi = spidev.SpiDev()
        self._spi.open(bus, device)
        self._spi.mode = mode
        self._spi.max_speed_hz = speed_hz
        self._spi.bits_per_word = 8
        self._spi.lsbfirst = False
        self.bus, self.device = bus, device

    def transfer(self, frame: bytes) -> bytes:
        if len(frame) != FRAME_LEN:
            raise ValueError(f"an SPI frame must be {FRAME_LEN} bytes, got {len(frame)}")
        reply = bytes(self._spi.xfer2(list(frame)))
        if len(reply) != FRAME_LEN:
            raise OSError(f"spidev returned {len(reply)} bytes instead of {FRAME_LEN}")
        return reply

    def close(self) -> None:
        self._spi.close()

    def __enter__(self) -> SpidevDevice:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
