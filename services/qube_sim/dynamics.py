"""Rotary inverted pendulum physics of the QUBE-Servo 2 (pure Python, RK4).

Equations of motion: gym_brt's ``gym_brt/quanser/qube_simulator.py`` (BlueRiverTech/quanser-openai-driver, "From
Rotary Pendulum Workbook"), parameters from the QUBE-Servo 2 User Manual v1.0 Table 2.2, with one correction: the
motor torque is the physically consistent

    tau = -km * (V + km * theta_dot) / Rm

so the back-EMF brakes the arm (gym_brt's ``-km*(V - km*theta_dot)/Rm`` adds energy). A positive voltage (and
a positive SPI motor command) drives theta negative, matching the SPI convention (theta = -encoder0 *
2*pi/2048).

State: theta (arm, rad), alpha (pendulum, rad, 0 = upright, +-pi hanging), theta_dot, alpha_dot. The
integrator keeps alpha continuous (unwrapped) so encoder counts stay continuous; :attr:`QubeDynamics.state`
wraps it.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, fields, replace

import numpy as np

from rpi_bridge.velocity import wrap_angle


@dataclass(frozen=True)
class QubeParams:
    """Physical parameters, QUBE-Servo 2 User Manual Table 2.2; damping from gym_brt (not in the manual)."""

    Rm: float = 8.4  # terminal resistance, ohm
    km: float = 0.042  # back-EMF constant, V/(rad/s)
    kt: float = 0.042  # torque constant, N m/A (= km in SI units)
    mr: float = 0.095  # arm mass, kg
    Lr: float = 0.085  # arm length, pivot to rod end, m
    mp: float = 0.024  # pendulum mass, kg
    Lp: float = 0.129  # pendulum length, m
    Dr: float = 0.00027  # arm viscous damping, N m s/rad
    Dp: float = 0.00005  # pendulum viscous damping, N m s/rad
    g: float = 9.81
    Cr: float = 0.0  # arm Coulomb friction torque, N m (0: none; real rigs have some, the manual gives no value)
    Cp: float = 0.0  # pendulum Coulomb friction torque, N m
    coulomb_speed: float = 0.02  # rad/s: friction = -C*tanh(speed/coulomb_speed), a smooth sign for the integrator
    Sr: float = 0.0  # arm static (breakaway) friction torque, N m; 0 or >= Cr (Stribeck: C + (S - C)*exp(-(v/vs)^2))
    Sp: float = 0.0  # pendulum static friction torque, N m
    stribeck_speed: float = 0.1  # rad/s: below it the friction rises from Coulomb towards static
    deadzone: float = 0.0  # V: the motor makes no torque below this |V|; above, V - sgn(V)*deadzone
    voltage_offset: float = 0.0  # V: amplifier offset added to every commanded voltage while it is enabled
    cable_stiffness: float = 0.0  # N m/rad: the encoder cable pulls the arm back towards cable_rest
    cable_rest: float = 0.0  # rad: arm angle where the cable exerts no torque
    full_scale_voltage: float = 24.0  # 999 SPI counts = 100 % duty, about 24 V ([DS] p.2)
    max_voltage: float = 15.0  # amplifier maximum, +-15 V ([UM] Table 2.2)

    @property
    def Jr(self) -> float:
        """Arm moment of inertia, mr*Lr^2/12 as in gym_brt."""
        return self.mr * self.Lr**2 / 12.0

    @property
    def Jp(self) -> float:
        """Pendulum moment of inertia about its centre, mp*Lp^2/12."""
        return self.mp * self.Lp**2 / 12.0

    @classmethod
    def varied(cls, seed: int, scale: float = 0.05, base: QubeParams | None = None) -> QubeParams:
        """Per-rig variation, like devices from one factory: masses, lengths, damping and the motor constant
        (km and kt together) each scaled by 1 + N(0, scale), clipped to 1 +- 3*scale. Deterministic in
        ``seed``."""
        base = base or cls()
        rng = random.Random(seed)

        def factor() -> float:
            return min(1.0 + 3.0 * scale, max(1.0 - 3.0 * scale, 1.0 + rng.gauss(0.0, scale)))

        changes = {name: getattr(base, name) * factor() for name in ("mr", "Lr", "mp", "Lp", "Dr", "Dp")}
        motor = factor()
        changes.update(km=base.km * motor, kt=base.kt * motor)
        return replace(base, **changes)

    @classmethod
    def spread(cls, seed: int, fraction: float = 0.15, base: QubeParams | None = None) -> QubeParams:
        """A rig at the edge of a +-``fraction`` spread: masses, lengths, damping and the motor constant (km and kt
        together) each scaled by a factor drawn uniformly from [1 - fraction, 1 + fraction]. Deterministic in
        ``seed``; friction and voltages are kept."""
        if not 0 <= fraction < 1:
            raise ValueError(f"fraction must be in [0, 1), got {fraction}")
        base = base or cls()
        rng = random.Random(seed)
        changes = {name: getattr(base, name) * rng.uniform(1 - fraction, 1 + fraction)
                   for name in ("mr", "Lr", "mp", "Lp", "Dr", "Dp")}
        motor = rng.uniform(1 - fraction, 1 + fraction)
        changes.update(km=base.km * motor, kt=base.kt * motor)
        return replace(base, **changes)

    def as_dict(self) -> dict[str, float]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


def command_to_voltage(command: float, params: QubeParams | None = None) -> float:
    """SPI motor counts to amplifier volts: V = cmd/999 * 24, clamped to +-15 V."""
    p = params or QubeParams()
    v = command / 999.0 * p.full_scale_voltage
    return max(-p.max_voltage, min(p.max_voltage, v))


def motor_torque(p: QubeParams, voltage: float, theta_dot: float) -> float:
    """tau = -kt*(V' + km*theta_dot)/Rm: +V drives theta negative, back-EMF brakes. V' is the voltage at the motor:
    the command plus the amplifier's ``voltage_offset``, less the ``deadzone`` (none below it)."""
    if p.voltage_offset or p.deadzone:
        voltage += p.voltage_offset
        voltage = math.copysign(max(0.0, abs(voltage) - p.deadzone), voltage)
    return -p.kt * (voltage + p.km * theta_dot) / p.Rm


def friction(coulomb: float, static: float, speed: float, p: QubeParams) -> float:
    """Dry friction torque opposing ``speed``: Coulomb ``coulomb`` rising to ``static`` at rest (Stribeck curve),
    its sign smoothed by tanh(speed/coulomb_speed) so the integrator sees a continuous force."""
    level = coulomb
    if static > coulomb:
        level += (static - coulomb) * math.exp(-((speed / p.stribeck_speed) ** 2))
    return level * math.tanh(speed / p.coulomb_speed)


def derivatives(
    p: QubeParams, theta_dot: float, alpha: float, alpha_dot: float, tau: float
) -> tuple[float, float]:
    """(theta_ddot, alpha_ddot): gym_brt equations of motion (``qube_simulator.py``), plus dry
    friction next to the viscous terms: the arm's generalised force is tau - Dr*theta_dot - F(Cr, Sr, theta_dot),
    the pendulum's -Dp*alpha_dot - F(Cp, Sp, alpha_dot) (:func:`friction`). ``tau`` includes any external torque
    on the arm (the cable's: see :meth:`QubeDynamics._rates`)."""
    mp, Lp, Lr = p.mp, p.Lp, p.Lr
    if p.Cr or p.Sr:
        tau -= friction(p.Cr, p.Sr, theta_dot, p)
    friction_p = friction(p.Cp, p.Sp, alpha_dot, p) if p.Cp or p.Sp else 0.0
    s, c = math.sin(alpha), math.cos(alpha)
    s2 = 2.0 * s * c  # sin(2 alpha)
    P = 4.0 * p.Jp + Lp * Lp * mp
    Q = 4.0 * p.Jr + Lp * Lp * mp * s * s + 4.0 * Lr * Lr * mp
    D = 4.0 * Lp * Lp * Lr * Lr * mp * mp * c * c - P * Q
    A = -8.0 * (p.Dp * alpha_dot + friction_p) + Lp * Lp * mp * theta_dot * theta_dot * s2 + 4.0 * Lp * p.g * mp * s
    B = (
        4.0 * p.Dr * theta_dot
        + Lp * Lp * mp * alpha_dot * theta_dot * s2
        + 2.0 * Lp * Lr * mp * alpha_dot * alpha_dot * s
        - 4.0 * tau
    )
    theta_ddot = (-Lp * Lr * mp * A * c + P * B) / D
    alpha_ddot = (2.0 * Lp * Lr * mp * B * c - 0.5 * Q * A) / D
    return theta_ddot, alpha_ddot


# -- the same equations of motion on numpy arrays (many states at once: the identification fit's windows) ---------
# Kept beside the scalar functions above, term for term; tests/services/test_identify.py checks they agree. The scalar
# path stays pure Python (numpy on one state is several times slower). Any field of ``p`` may itself be an array
# broadcasting with the states (one parameter set per state: the fit's Jacobian in one batch), so the terms that the
# scalar code skips when a parameter is 0 are always computed here (they are then exactly 0).


def motor_torque_array(p: QubeParams, voltage: np.ndarray, theta_dot: np.ndarray) -> np.ndarray:
    """:func:`motor_torque` on arrays."""
    voltage = voltage + p.voltage_offset
    voltage = np.sign(voltage) * np.maximum(0.0, np.abs(voltage) - p.deadzone)
    return -p.kt * (voltage + p.km * theta_dot) / p.Rm


def friction_array(coulomb: float, static: float, speed: np.ndarray, p: QubeParams) -> np.ndarray:
    """:func:`friction` on arrays."""
    level = coulomb + np.maximum(0.0, static - coulomb) * np.exp(-((speed / p.stribeck_speed) ** 2))
    return level * np.tanh(speed / p.coulomb_speed)


def derivatives_array(
    p: QubeParams, theta_dot: np.ndarray, alpha: np.ndarray, alpha_dot: np.ndarray, tau: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`derivatives` on arrays of states (same parameters for all)."""
    mp, Lp, Lr = p.mp, p.Lp, p.Lr
    tau = tau - friction_array(p.Cr, p.Sr, theta_dot, p)
    friction_p = friction_array(p.Cp, p.Sp, alpha_dot, p)
    s, c = np.sin(alpha), np.cos(alpha)
    s2 = 2.0 * s * c
    P = 4.0 * p.Jp + Lp * Lp * mp
    Q = 4.0 * p.Jr + Lp * Lp * mp * s * s + 4.0 * Lr * Lr * mp
    D = 4.0 * Lp * Lp * Lr * Lr * mp * mp * c * c - P * Q
    A = -8.0 * (p.Dp * alpha_dot + friction_p) + Lp * Lp * mp * theta_dot * theta_dot * s2 + 4.0 * Lp * p.g * mp * s
    B = (
        4.0 * p.Dr * theta_dot
        + Lp * Lp * mp * alpha_dot * theta_dot * s2
        + 2.0 * Lp * Lr * mp * alpha_dot * alpha_dot * s
        - 4.0 * tau
    )
    theta_ddot = (-Lp * Lr * mp * A * c + P * B) / D
    alpha_ddot = (2.0 * Lp * Lr * mp * B * c - 0.5 * Q * A) / D
    return theta_ddot, alpha_ddot


class QubeDynamics:
    """The plant: integrate with :meth:`step`; optional hard end stops at +-``arm_limit`` rad."""

    def __init__(self, params: QubeParams | None = None, arm_limit: float | None = None) -> None:
        self.params = params or QubeParams()
        self.arm_limit = arm_limit
        self.theta = 0.0
        self.alpha = math.pi
        self.theta_dot = 0.0
        self.alpha_dot = 0.0
        self.time = 0.0
        self.at_limit = 0  # -1 / +1 while the arm rests against an end stop, else 0
        self.external_torque = 0.0  # N m on the arm (a disturbance), in the direction of increasing theta

    # -- state -----------------------------------------------------------------------------------------
    def set_state(self, theta: float, alpha: float, theta_dot: float = 0.0, alpha_dot: float = 0.0) -> None:
        self.theta, self.alpha, self.theta_dot, self.alpha_dot = theta, alpha, theta_dot, alpha_dot
        self.at_limit = 0

    @property
    def state(self) -> tuple[float, float, float, float]:
        """(theta, alpha wrapped to [-pi, pi), theta_dot, alpha_dot)."""
        return self.theta, wrap_angle(self.alpha), self.theta_dot, self.alpha_dot

    def energy(self) -> float:
        """Mechanical energy of arm + pendulum (J), zero hanging at rest.

        Mass matrix of the equations of motion: M11 = Jr + mp*Lr^2 + mp*Lp^2*sin^2(alpha)/4,
        M12 = -mp*Lp*Lr*cos(alpha)/2, M22 = Jp + mp*Lp^2/4; potential mp*g*(Lp/2)*(1 + cos alpha).
        """
        p = self.params
        s, c = math.sin(self.alpha), math.cos(self.alpha)
        m11 = p.Jr + p.mp * p.Lr**2 + p.mp * p.Lp**2 * s * s / 4.0
        m12 = -p.mp * p.Lp * p.Lr * c / 2.0
        m22 = p.Jp + p.mp * p.Lp**2 / 4.0
        td, ad = self.theta_dot, self.alpha_dot
        kinetic = 0.5 * m11 * td * td + m12 * td * ad + 0.5 * m22 * ad * ad
        return kinetic + p.mp * p.g * p.Lp / 2.0 * (1.0 + c)

    # -- integration -----------------------------------------------------------------------------------
    def _rates(self, x: tuple[float, ...], voltage: float, motor: bool) -> tuple[float, ...]:
        theta, alpha, theta_dot, alpha_dot = x
        p = self.params
        tau = motor_torque(p, voltage, theta_dot) if motor else 0.0
        if p.cable_stiffness:
            tau -= p.cable_stiffness * (theta - p.cable_rest)
        if self.external_torque:
            tau += self.external_torque
        theta_ddot, alpha_ddot = derivatives(self.params, theta_dot, alpha, alpha_dot, tau)
        return theta_dot, alpha_dot, theta_ddot, alpha_ddot

    def step(self, voltage: float, dt: float, substeps: int | None = None, amplifier_on: bool = True) -> None:
        """Advance ``dt`` seconds holding ``voltage`` (clamped to +-max_voltage), RK4 in ``substeps`` equal
        steps (default: steps of at most 1 ms). ``amplifier_on=False`` leaves the motor open-circuit (no
        torque at all, no back-EMF braking), as when the amplifier is disabled."""
        if dt <= 0:
            return
        p = self.params
        voltage = max(-p.max_voltage, min(p.max_voltage, voltage))
        n = substeps if substeps is not None else max(1, math.ceil(dt / 1e-3 - 1e-9))
        h = dt / n
        x: tuple[float, ...] = (self.theta, self.alpha, self.theta_dot, self.alpha_dot)
        for _ in range(n):
            k1 = self._rates(x, voltage, amplifier_on)
            k2 = self._rates(
                tuple(xi + 0.5 * h * ki for xi, ki in zip(x, k1, strict=True)), voltage, amplifier_on
            )
            k3 = self._rates(
                tuple(xi + 0.5 * h * ki for xi, ki in zip(x, k2, strict=True)), voltage, amplifier_on
            )
            k4 = self._rates(tuple(xi + h * ki for xi, ki in zip(x, k3, strict=True)), voltage, amplifier_on)
            x = tuple(
                xi + h / 6.0 * (a + 2.0 * b + 2.0 * c + d)
                for xi, a, b, c, d in zip(x, k1, k2, k3, k4, strict=True)
            )
            x = self._end_stop(x)
        self.theta, self.alpha, self.theta_dot, self.alpha_dot = x
        self.time += dt

    def _end_stop(self, x: tuple[float, ...]) -> tuple[float, ...]:
        """Hard stop at +-arm_limit: the arm stops dead (inelastic), the pendulum keeps its motion."""
        limit = self.arm_limit
        theta, alpha, theta_dot, alpha_dot = x
        self.at_limit = 0
        if limit is None:
            return x
        if theta >= limit and theta_dot >= 0.0:
            self.at_limit = 1
            return limit, alpha, 0.0, alpha_dot
        if theta <= -limit and theta_dot <= 0.0:
            self.at_limit = -1
            return -limit, alpha, 0.0, alpha_dot
        if abs(theta) >= limit:  # at the stop but moving away
            self.at_limit = 1 if theta > 0 else -1
        return x

    def pressing_limit(self, voltage: float) -> bool:
        """True while the arm rests on an end stop and ``voltage`` pushes it further into it (+V drives theta
        negative)."""
        return (self.at_limit > 0 and voltage < 0.0) or (self.at_limit < 0 and voltage > 0.0)


def linearize(params: QubeParams | None = None, eps: float = 1e-6) -> tuple[list[list[float]], list[float]]:
    """Continuous-time linearisation about upright rest: x' = A x + B V with x = (theta, alpha, theta_dot,
    alpha_dot) and V in volts (central differences of :func:`derivatives`)."""
    p = params or QubeParams()

    def f(x: list[float], v: float) -> list[float]:
        tau = motor_torque(p, v, x[2])
        tdd, add = derivatives(p, x[2], x[1], x[3], tau)
        return [x[2], x[3], tdd, add]

    zero = [0.0, 0.0, 0.0, 0.0]
    cols = []
    for j in range(4):
        xp, xm = list(zero), list(zero)
        xp[j], xm[j] = eps, -eps
        fp, fm = f(xp, 0.0), f(xm, 0.0)
        cols.append([(a - b) / (2 * eps) for a, b in zip(fp, fm, strict=True)])
    a_mat = [[cols[j][i] for j in range(4)] for i in range(4)]
    fp, fm = f(zero, eps), f(zero, -eps)
    b_vec = [(a - b) / (2 * eps) for a, b in zip(fp, fm, strict=True)]
    return a_mat, b_vec
