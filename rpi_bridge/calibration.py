"""Encoder calibration on purpose, as pure code: where the zeros of the two encoders are, when they may be set, and
the small state file that keeps them across bridge restarts.

The QUBE's counters start wherever the rig was at power-up, and the angles the bridge uses only mean something
relative to a calibration: the arm's zero (the middle of its travel, where the operator centred it) and the
pendulum hanging at rest (alpha = +-pi). The bridge never writes the encoder registers; a calibration is the pair
of raw counts that read as arm 0 and pendulum hanging, subtracted in software (:meth:`Calibration.angles`).

At start-up the bridge waits, amplifier off, until both encoders have been still over a window
(:func:`is_still`), then :func:`decide` chooses:

- no stored calibration: the pendulum hangs at rest now, so calibrate here (the arm's zero is where the arm is);
- a stored calibration that reads the resting pendulum as hanging: keep it (the arm's zero is kept too, so a
  restart after a crash mid-swing does not move the arm's zero to wherever the arm came to rest);
- a stored calibration that does not (the QUBE was power-cycled with the pendulum elsewhere, or an encoder
  slipped): refuse to run until an operator recalibrates (``--recalibrate``, after centring the arm).
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

from rpi_bridge.frame import COUNTS_PER_REV, counts_to_arm_rad, counts_to_pendulum_rad

log = logging.getLogger("rpi_bridge")

STATE_VERSION = 1


@dataclass(frozen=True)
class Calibration:
    """Raw encoder counts that read as arm angle 0 (``encoder0``) and pendulum hanging (``encoder1``)."""

    encoder0: int
    encoder1: int
    calibrated_at: str = ""  # ISO time, for the record

    def angles(self, encoder0: int, encoder1: int) -> tuple[float, float]:
        """(theta, alpha) of raw counts: theta = 0 at ``self.encoder0``, alpha = +-pi at ``self.encoder1``."""
        return counts_to_arm_rad(encoder0 - self.encoder0), counts_to_pendulum_rad(encoder1 - self.encoder1)

    def pendulum_offset_counts(self, encoder1: int) -> int:
        """How far (in counts, signed, within half a turn) ``encoder1`` is from hanging under this calibration."""
        off = (encoder1 - self.encoder1) % COUNTS_PER_REV
        return off - COUNTS_PER_REV if off > COUNTS_PER_REV // 2 else off


@dataclass(frozen=True)
class CalibrationDecision:
    action: Literal["calibrate", "keep", "refuse"]
    calibration: Calibration | None
    reason: str


def is_still(samples: Sequence[tuple[int, int]], tolerance_counts: int) -> bool:
    """Both encoders within ``tolerance_counts`` of their window minimum over all ``samples`` (raw counts)."""
    if not samples:
        return False
    enc0 = [s[0] for s in samples]
    enc1 = [s[1] for s in samples]
    return max(enc0) - min(enc0) <= tolerance_counts and max(enc1) - min(enc1) <= tolerance_counts


def decide(
    samples: Sequence[tuple[int, int]], stored: Calibration | None, hang_tolerance_counts: int = 6
) -> CalibrationDecision:
    """The calibration to use after a window of still ``samples`` (raw counts; the caller checked
    :func:`is_still`). See the module docstring for the three outcomes."""
    if not samples:
        raise ValueError("decide needs at least one sample")
    enc0 = sorted(s[0] for s in samples)[len(samples) // 2]
    enc1 = sorted(s[1] for s in samples)[len(samples) // 2]
    if stored is None:
        now = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        return CalibrationDecision("calibrate", Calibration(enc0, enc1, now),
                                   "calibrated: the pendulum hangs at rest; the arm's zero is where the arm is now")
    off = stored.pendulum_offset_counts(enc1)
    if abs(off) <= hang_tolerance_counts:
        return CalibrationDecision("keep", stored, f"stored calibration of {stored.calibrated_at or 'unknown time'} "
                                   f"kept: the resting pendulum reads {off:+d} counts from hanging")
    degrees = off * 360.0 / COUNTS_PER_REV
    return CalibrationDecision(
        "refuse", None,
        f"the stored calibration does not match the rig: the pendulum is at rest but reads {degrees:+.1f} deg from "
        "hanging (was the QUBE power-cycled, or did an encoder slip?). Centre the arm, let the pendulum hang still "
        "and restart the bridge with --recalibrate")


class CalibrationStore:
    """The calibration of one rig in a small JSON file, written atomically (temporary file + rename)."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)

    @classmethod
    def for_rig(cls, state_dir: Path, rig_id: str) -> CalibrationStore:
        return cls(Path(state_dir) / f"{rig_id}-calibration.json")

    def load(self) -> Calibration | None:
        """The stored calibration, or None (no file; an unreadable file is logged and ignored)."""
        try:
            data = json.loads(self.path.read_text())
        except FileNotFoundError:
            return None
        except (OSError, ValueError) as err:
            log.warning("ignoring the calibration file %s: %s", self.path, err)
            return None
        try:
            if data.get("version") != STATE_VERSION:
                raise ValueError(f"version {data.get('version')!r}, expected {STATE_VERSION}")
            e0, e1 = data["encoder0"], data["encoder1"]
            if not all(isinstance(v, int) and not isinstance(v, bool) for v in (e0, e1)):
                raise ValueError("encoder0 and encoder1 must be integers")
            return Calibration(e0, e1, str(data.get("calibrated_at", "")))
        except (AttributeError, KeyError, ValueError) as err:
            log.warning("ignoring the calibration file %s: %s", self.path, err)
            return None

    def save(self, calibration: Calibration) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps({"version": STATE_VERSION, **asdict(calibration)}, indent=1) + "\n")
        os.replace(tmp, self.path)

    def clear(self) -> None:
        self.path.unlink(missing_ok=True)
