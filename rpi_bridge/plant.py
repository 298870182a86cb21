"""The QUBE-Servo 2 model the bridge's reset and self-test use, and the hold's LQR design from it, as pure code.

:class:`PlantModel` is the rig as the bridge knows it: the plant values of the equations of motion (gym_brt's,
services/qube_sim/dynamics.py, with braking back-EMF), the arm's dry friction (Coulomb, static) and the motor's
deadzone. The default is the nominal rig: the manual's plant, gym_brt's damping and the friction and deadzone of the
``lab`` profile (docs/rig-profiles.md); :meth:`PlantModel.from_profile` reads an identified rig from a rig profile's
JSON fields (rpi_bridge must not import services/, so it reads the field names, not the model).

:func:`lqr_gains` designs the hold: the model linearised about upright rest (central differences of
:meth:`PlantModel.accelerations`), zero-order hold at the period, the one-tick actuation delay in the state (the
command computed from reading k reaches the motor at the transfer of tick k+1), and the discrete Riccati equation
iterated to convergence. numpy only (a Raspberry Pi has no scipy).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from rpi_bridge.frame import VOLTS_PER_COUNT

#: Profile JSON field -> PlantModel field (rig profile names, services/qube_sim/profile.py).
PROFILE_FIELDS = {"Rm": "Rm", "km": "km", "kt": "kt", "mr": "mr", "Lr": "Lr", "mp": "mp", "Lp": "Lp", "Dr": "Dr",
                  "Dp": "Dp", "g": "g", "coulomb_arm": "coulomb_arm", "static_arm": "static_arm",
                  "deadzone_v": "deadzone_v"}
#: The weights of the gains the bridge had before they were computed from a model (rpi_bridge/reset.py LQR_GAINS).
FIRST_LQR_Q = (1.0, 10.0, 0.0, 0.0)
#: The hold's design weights: Q on (theta, alpha, theta_dot, alpha_dot), R per count^2. FIRST_LQR_Q's light arm
#: weight left a slow, lightly damped arm mode: a reset handed over an arm still swinging (on `lab` rigs of the tuning
#: seeds 1.77 rad/s at ready and 35.5 deg within 3 s of holding, median), and a warm start fell on such handovers
#: after the swing-ups that it held when a balanced episode ended upright. Weighting the arm's angle and speed
#: hands over a calm arm on most rigs and swings up no worse (python -m bench.reset; chosen on tuning rig seeds 0-15
#: among 1, 20, 50 and 100 on the arm angle: docs/explanation/qube.md).
LQR_Q = (100.0, 20.0, 10.0, 0.0)
LQR_R = 5e-3


@dataclass(frozen=True)
class PlantModel:
    """A QUBE-Servo 2 (SI units, volts). Defaults: the nominal rig ([UM] Table 2.2, gym_brt damping, ``lab``'s arm
    friction and deadzone)."""

    Rm: float = 8.4
    km: float = 0.042  # back-EMF constant, V s/rad
    kt: float = 0.042  # torque constant, N m/A
    mr: float = 0.095
    Lr: float = 0.085
    mp: float = 0.024
    Lp: float = 0.129
    Dr: float = 0.00027
    Dp: float = 0.00005
    g: float = 9.81
    coulomb_arm: float = 0.0015  # N m, sliding
    static_arm: float = 0.002  # N m, breakaway (0 or >= coulomb_arm)
    deadzone_v: float = 0.05  # V: no torque below it
    volts_per_count: float = VOLTS_PER_COUNT

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"plant model: {f.name} must be finite and >= 0, got {value}")
        for name in ("Rm", "km", "kt", "mr", "Lr", "mp", "Lp", "g", "volts_per_count"):
            if not getattr(self, name) > 0:
                raise ValueError(f"plant model: {name} must be positive, got {getattr(self, name)}")

    @classmethod
    def from_profile(cls, mapping: Mapping[str, Any]) -> PlantModel:
        """The model of a rig profile's JSON (``python -m services.qube_sim --show-profile``, or an identified rig's):
        the fields of :data:`PROFILE_FIELDS`, the nominal value for those missing; other fields are ignored."""
        values = {}
        for key, name in PROFILE_FIELDS.items():
            if key in mapping:
                try:
                    values[name] = float(mapping[key])
                except (TypeError, ValueError):
                    raise ValueError(f"plant model: {key} must be a number, got {mapping[key]!r}") from None
        if "kt" not in values and "km" in values:
            values["kt"] = values["km"]
        return cls(**values)

    # -- derived values ------------------------------------------------------------------------------------------
    @property
    def swing_depth(self) -> float:
        """2*mp*g*l: the energy from hanging at rest to upright at rest (J)."""
        return self.mp * self.g * self.Lp

    @property
    def damping_ratio(self) -> float:
        """The hanging pendulum's viscous damping ratio Dp / (2 J w0): J = mp*Lp^2/3 about its pivot, w0 =
        sqrt(mp*g*(Lp/2) / J). ``lab``'s is about 0.018; Quanser's course files' Dp (5e-4) gives 0.18."""
        j_pivot = self.mp * self.Lp * self.Lp / 3.0
        return self.Dp / (2.0 * j_pivot * math.sqrt(0.5 * self.mp * self.g * self.Lp / j_pivot))

    @property
    def volts_per_newton_metre(self) -> float:
        """Motor volts per N m of arm torque at rest (Rm/kt)."""
        return self.Rm / self.kt

    def pendulum_energy(self, alpha: float, alpha_dot: float) -> float:
        """E = Jp_pivot*alpha_dot^2/2 + mp*g*(Lp/2)*(cos(alpha) - 1), Jp_pivot = mp*Lp^2/3 (rod about its
        end)."""
        j_pivot = self.mp * self.Lp * self.Lp / 3.0
        return 0.5 * j_pivot * alpha_dot * alpha_dot + 0.5 * self.mp * self.g * self.Lp * (math.cos(alpha) - 1.0)

    def _mass_and_forces(self, alpha: float, theta_dot: float, alpha_dot: float
                         ) -> tuple[float, float, float, float, float]:
        """(m11, m12, m22, r1, r2) of gym_brt's equations M @ (theta_ddot, alpha_ddot) = (tau + r1, r2), viscous
        damping in r1 and r2 (dry friction not)."""
        mp, Lp, Lr = self.mp, self.Lp, self.Lr
        s, c = math.sin(alpha), math.cos(alpha)
        s2 = 2.0 * s * c
        m11 = self.mr * Lr * Lr / 12.0 + mp * Lr * Lr + mp * Lp * Lp * s * s / 4.0
        m12 = -0.5 * mp * Lp * Lr * c
        m22 = mp * Lp * Lp / 3.0
        r1 = -(self.Dr * theta_dot + 0.25 * Lp * Lp * mp * alpha_dot * theta_dot * s2
               + 0.5 * Lp * Lr * mp * alpha_dot * alpha_dot * s)
        r2 = -self.Dp * alpha_dot + 0.125 * Lp * Lp * mp * theta_dot * theta_dot * s2 + 0.5 * Lp * self.g * mp * s
        return m11, m12, m22, r1, r2

    def accelerations(self, theta_dot: float, alpha: float, alpha_dot: float, volts: float) -> tuple[float, float]:
        """(theta_ddot, alpha_ddot) at motor voltage ``volts`` (+V drives theta negative), without dry friction."""
        m11, m12, m22, r1, r2 = self._mass_and_forces(alpha, theta_dot, alpha_dot)
        tau = -self.kt * (volts + self.km * theta_dot) / self.Rm
        det = m11 * m22 - m12 * m12
        f1, f2 = tau + r1, r2
        return (m22 * f1 - m12 * f2) / det, (m11 * f2 - m12 * f1) / det

    def command_for_arm_accel(self, theta_ddot: float, alpha: float, theta_dot: float, alpha_dot: float,
                              friction: bool = True) -> float:
        """Motor counts that give the arm acceleration ``theta_ddot`` (computed torque): the pendulum row
        eliminated, tau = -kt*(V + km*theta_dot)/Rm; with ``friction`` the arm's Coulomb friction against its motion
        (its sign smoothed over 0.05 rad/s) and the deadzone in the direction of the voltage are added."""
        m11, m12, m22, r1, r2 = self._mass_and_forces(alpha, theta_dot, alpha_dot)
        tau = (m11 - m12 * m12 / m22) * theta_ddot + m12 / m22 * r2 - r1
        if friction:
            tau += self.coulomb_arm * math.tanh(theta_dot / 0.05)
        volts = -tau * self.Rm / self.kt - self.km * theta_dot
        if friction and volts:
            volts += math.copysign(self.deadzone_v, volts)
        return volts / self.volts_per_count

    # -- linear model about upright rest ---------------------------------------------------------------------------
    def linearized(self) -> tuple[np.ndarray, np.ndarray]:
        """(A, B): x' = A x + B u about upright rest, x = (theta, alpha, theta_dot, alpha_dot), u in counts."""
        eps = 1e-6

        def f(x: np.ndarray, counts: float) -> np.ndarray:
            tdd, add = self.accelerations(float(x[2]), float(x[1]), float(x[3]), counts * self.volts_per_count)
            return np.array([x[2], x[3], tdd, add])

        zero = np.zeros(4)
        a = np.column_stack([(f(zero + eps * e, 0.0) - f(zero - eps * e, 0.0)) / (2 * eps) for e in np.eye(4)])
        b = (f(zero, eps) - f(zero, -eps)) / (2 * eps)
        return a, b.reshape(4, 1)


def zoh(a: np.ndarray, b: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Zero-order-hold discretisation: the matrix exponential of [[A, B], [0, 0]]*dt (scaling and squaring of its
    Taylor series)."""
    n, m = b.shape
    block = np.zeros((n + m, n + m))
    block[:n, :n], block[:n, n:] = a * dt, b * dt
    squarings = max(0, math.ceil(math.log2(max(1e-12, float(np.abs(block).sum(axis=1).max())))) + 1)
    scaled = block / 2.0**squarings
    result, term = np.eye(n + m), np.eye(n + m)
    for k in range(1, 20):
        term = term @ scaled / k
        result = result + term
    for _ in range(squarings):
        result = result @ result
    return result[:n, :n], result[:n, n:]


def delayed(ad: np.ndarray, bd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The one-tick actuation delay in the state: z = (x, u_prev), z' = [[Ad, Bd], [0, 0]] z + [0, 1] u."""
    n, m = bd.shape
    a = np.zeros((n + m, n + m))
    a[:n, :n], a[:n, n:] = ad, bd
    b = np.zeros((n + m, m))
    b[n:, :] = np.eye(m)
    return a, b


def dlqr(a: np.ndarray, b: np.ndarray, q: np.ndarray, r: np.ndarray, iterations: int = 20_000,
         tol: float = 1e-10) -> np.ndarray:
    """Gain K of u = -K x minimising sum x'Qx + u'Ru for x' = Ax + Bu: the discrete Riccati equation iterated from
    P = Q until it changes by less than ``tol`` (relative)."""
    p = q.copy()
    for _ in range(iterations):
        bp = b.T @ p
        k = np.linalg.solve(r + bp @ b, bp @ a)
        nxt = q + a.T @ p @ (a - b @ k)
        nxt = 0.5 * (nxt + nxt.T)
        if np.max(np.abs(nxt - p)) <= tol * max(1.0, float(np.max(np.abs(nxt)))):
            p = nxt
            break
        p = nxt
    else:
        raise ValueError("the Riccati iteration did not converge: is the model stabilisable?")
    bp = b.T @ p
    return np.asarray(np.linalg.solve(r + bp @ b, bp @ a))


@functools.lru_cache(maxsize=64)
def lqr_gains(model: PlantModel, period_s: float, q: tuple[float, ...] = LQR_Q, r: float = LQR_R,
              q_integral: float = 0.0, delay: bool = True) -> tuple[float, ...]:
    """Hold gains K of u = -K.z in counts, z = (theta, alpha, theta_dot, alpha_dot[, u_prev], integral of theta):
    the model linearised about upright, ZOH at ``period_s``, the one-tick actuation delay in the state (``delay``;
    then K has the gain on the command still waiting, u_prev), the arm angle's integral (weight ``q_integral``; 0
    gives it gain 0), Q = diag(``q``), R = ``r`` per count^2. Cached per (model, period, weights)."""
    if not period_s > 0 or len(q) != 4 or not r > 0 or q_integral < 0:
        raise ValueError("lqr_gains needs period_s > 0, four state weights, r > 0 and q_integral >= 0")
    a, b = model.linearized()
    ad, bd = zoh(a, b, period_s)
    weights = list(q)
    if delay:
        ad, bd = delayed(ad, bd)
        weights.append(0.0)
    n = ad.shape[0]
    az = np.zeros((n + 1, n + 1))  # the integral: I' = I + T*theta
    az[:n, :n], az[n, 0], az[n, n] = ad, period_s, 1.0
    bz = np.vstack([bd, np.zeros((1, 1))])
    k = dlqr(az, bz, np.diag([*weights, q_integral]), np.array([[r]]))
    return tuple(float(v) for v in k[0])
