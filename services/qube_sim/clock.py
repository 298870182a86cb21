"""A clock that only moves when told to: simulated time for lockstep rigs."""

from __future__ import annotations

import threading


class VirtualClock:
    """Monotonic simulated seconds; ``advance`` is the only way forward."""

    def __init__(self, start: float = 0.0) -> None:
        self._now = start
        self._lock = threading.Lock()

    def __call__(self) -> float:
        with self._lock:
            return self._now

    def advance(self, dt: float) -> None:
        if dt < 0:
            raise ValueError(f"time cannot go back ({dt})")
        with self._lock:
            self._now += dt
