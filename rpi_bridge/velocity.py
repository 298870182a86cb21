"""Angle-rate estimate for the pendulum (SPI has no pendulum tachometer).

The filter is the high-pass derivative H(s) = wc*s / (s + wc), wc = 50 rad/s, that Quanser's example code uses
(Quanser's QUBE-Servo 2 Arduino example ``QUBEServo2.cpp``: "50s/(s+50)", discretised there at 1 ms as
(50z - 50)/(z - 0.9512)). Here it is discretised for any period dt:

- ``"exact"`` (default): exact for an angle that moves linearly within each period (first-order hold),
  ``v[k] = a*v[k-1] + (1 - a) * (x[k] - x[k-1]) / dt`` with ``a = exp(-wc*dt)``;
- ``"bilinear"`` (Tustin): ``v[k] = a*v[k-1] + b*(x[k] - x[k-1])``, ``a = (2 - wc*dt)/(2 + wc*dt)``,
  ``b = 2*wc/(2 + wc*dt)``.

Both track a constant speed exactly in steady state. The angle difference is wrapped into [-pi, pi), so a
pendulum crossing +-pi gives no spike.
"""

from __future__ import annotations

import math

TWO_PI = 2.0 * math.pi


def wrap_angle(x: float) -> float:
    """Wrap to [-pi, pi)."""
    return (x + math.pi) % TWO_PI - math.pi


class VelocityFilter:
    """Discrete 50s/(s+50) derivative of a wrapped angle sampled every ``dt`` seconds."""

    def __init__(self, dt: float, cutoff_rad_s: float = 50.0, method: str = "exact") -> None:
        if method not in ("exact", "bilinear"):
            raise ValueError(f"method must be 'exact' or 'bilinear', got {method!r}")
        if not cutoff_rad_s > 0:
            raise ValueError(f"cutoff must be positive, got {cutoff_rad_s}")
        self.cutoff_rad_s = cutoff_rad_s
        self.method = method
        self._set_period(dt)
        self._last: float | None = None
        self.velocity = 0.0

    def _set_period(self, dt: float) -> None:
        if not dt > 0:
            raise ValueError(f"dt must be positive, got {dt}")
        wt = self.cutoff_rad_s * dt
        if self.method == "exact":
            self.a = math.exp(-wt)
            self.b = (1.0 - self.a) / dt
        else:
            self.a = (2.0 - wt) / (2.0 + wt)
            self.b = 2.0 * self.cutoff_rad_s / (2.0 + wt)
        self.dt = dt

    def reset(self, angle: float, velocity: float = 0.0) -> None:
        """Start from ``angle`` (and an optional known velocity) without a transient."""
        self._last = angle
        self.velocity = velocity

    def update(self, angle: float, dt: float | None = None) -> float:
        """Feed the next sample; returns the velocity estimate in rad/s (0 on the first sample). ``dt``
        (optional) is the actual time since the previous sample, for a loop with jitter; the coefficients
        follow it."""
        if dt is not None and dt != self.dt:
            self._set_period(dt)
        if self._last is None:
            self.reset(angle)
            return 0.0
        delta = wrap_angle(angle - self._last)
        self._last = angle
        self.velocity = self.a * self.velocity + self.b * delta
        return self.velocity
