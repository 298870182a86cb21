"""Episode reset for the QUBE-Servo 2: swing the pendulum up from hanging and hold it upright, as pure code.

State convention (rpi_bridge.frame): theta = arm angle (counter-clockwise positive), alpha = pendulum angle
(0 upright, +-pi hanging), rad and rad/s. Commands are SPI motor counts; a positive command drives theta
negative.

1. **swing_up**: energy pumping (Astrom & Furuta, "Swinging up a pendulum by energy control", Automatica
   2000). The pendulum energy about its pivot, E = Jp_pivot*alpha_dot^2/2 + mp*g*l*(cos(alpha) - 1) with l =
   Lp/2, is 0 upright at rest and -2*mp*g*l hanging. From the equations of motion (reference/qube-servo2.md)
   the pendulum row gives dE/dt = mp*l*Lr*cos(alpha)*alpha_dot*theta_ddot, so the wanted arm acceleration is
   k*(E0 - E)*alpha_dot*cos(alpha) (saturated), plus a PD term that keeps the arm near 0. That acceleration is
   turned into a command through the model (computed torque, :class:`PlantModel`), applied to the state
   predicted over the actuation delay (the command computed from one SPI reply acts from the next transfer
   on). The energy estimate depends on the pendulum's inertia; where the rig differs from the model the
   pendulum turns back short of the top, so each turnaround above horizontal raises the target E0 a little
   ("boost").
2. **catch** / **holding**: once |alpha| < catch angle, linear state feedback command = -K.x; "holding" while
   |alpha| is inside the balance band (and |theta| inside the arm band), "catch" while not yet.
3. **ready** after ``hold_time_s`` continuously inside the band; the hold command keeps going. Leaving the
   catch region goes back to swing_up. **failed** (command 0, latched until :meth:`ResetController.reset`)
   when ``timeout_s`` passes without reaching ready.

The controller estimates alpha_dot itself from the angles (a 50s/(s+50)-type filter with a faster 100 rad/s
cutoff): the 7 ms tick plus a 20 ms filter lag cost too much phase for the catch. Gains and defaults were
tuned on ``services.qube_sim`` (lockstep SPI peer at 7 ms, 1 ms RK4 sub-steps, +-5 % rig variation).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from rpi_bridge.frame import clamp_command
from rpi_bridge.velocity import VelocityFilter, wrap_angle

# Discrete LQR at T = 7 ms for x = (theta, alpha, theta_dot, alpha_dot), u in SPI counts (1 count = 24/999 V),
# on the linearised gym_brt plant with braking back-EMF (services.qube_sim.dynamics.linearize, nominal
# parameters), Q = diag(1, 10, 0, 0), R = 5e-3 per count^2. Chosen among LQR designs for the largest catch
# region with the one-tick actuation delay and the alpha_dot filter in the loop: spectral radius of that
# closed loop 0.985 with the 100 rad/s filter (<= 0.988 over +-5 % rigs); more aggressive designs (R <= 1e-3)
# go unstable with 50 rad/s.
LQR_GAINS = (12.7, -563.3, 13.3, -39.0)


@dataclass(frozen=True)
class PlantModel:
    """Nominal QUBE-Servo 2 ([UM] Table 2.2, gym_brt damping) for the energy and the computed-torque command.
    Kept here because rpi_bridge must not import services/."""

    Rm: float = 8.4
    km: float = 0.042
    mr: float = 0.095
    Lr: float = 0.085
    mp: float = 0.024
    Lp: float = 0.129
    Dr: float = 0.00027
    Dp: float = 0.00005
    g: float = 9.81
    volts_per_count: float = 24.0 / 999.0

    @property
    def swing_depth(self) -> float:
        """2*mp*g*l: the energy from hanging at rest to upright at rest (J)."""
        return self.mp * self.g * self.Lp

    def pendulum_energy(self, alpha: float, alpha_dot: float) -> float:
        """E = Jp_pivot*alpha_dot^2/2 + mp*g*(Lp/2)*(cos(alpha) - 1), Jp_pivot = mp*Lp^2/3 (rod about its
        end)."""
        j_pivot = self.mp * self.Lp * self.Lp / 3.0
        return 0.5 * j_pivot * alpha_dot * alpha_dot + 0.5 * self.mp * self.g * self.Lp * (
            math.cos(alpha) - 1.0
        )

    def command_for_arm_accel(
        self, theta_ddot: float, alpha: float, theta_dot: float, alpha_dot: float
    ) -> float:
        """Motor counts that give the arm acceleration ``theta_ddot``: the equations of motion of
        reference/qube-servo2.md as M @ (theta_ddot, alpha_ddot) = (tau + r1, r2), the pendulum row
        eliminated, with tau = -km*(V + km*theta_dot)/Rm."""
        mp, Lp, Lr = self.mp, self.Lp, self.Lr
        s, c = math.sin(alpha), math.cos(alpha)
        s2 = 2.0 * s * c
        m11 = self.mr * Lr * Lr / 12.0 + mp * Lr * Lr + mp * Lp * Lp * s * s / 4.0
        m12 = -0.5 * mp * Lp * Lr * c
        m22 = mp * Lp * Lp / 3.0
        r1 = -(
            self.Dr * theta_dot
            + 0.25 * Lp * Lp * mp * alpha_dot * theta_dot * s2
            + 0.5 * Lp * Lr * mp * alpha_dot * alpha_dot * s
        )
        r2 = (
            -self.Dp * alpha_dot
            + 0.125 * Lp * Lp * mp * theta_dot * theta_dot * s2
            + 0.5 * Lp * self.g * mp * s
        )
        tau = (m11 - m12 * m12 / m22) * theta_ddot + m12 / m22 * r2 - r1
        volts = -tau * self.Rm / self.km - self.km * theta_dot
        return volts / self.volts_per_count


@dataclass(frozen=True)
class ResetConfig:
    """Tunables of :class:`ResetController` (angles in rad, times in s, commands in SPI counts)."""

    balance_band: float = math.radians(5.0)
    hold_time_s: float = 0.5
    timeout_s: float = 15.0
    max_command_swing: int = 400  # about 9.6 V
    max_command_hold: int = 500  # about 12 V
    catch_angle: float = math.radians(20.0)
    arm_band: float = math.radians(45.0)  # |theta| must also be inside it to count as holding
    # swing-up
    swing_accel: float = 100.0  # rad/s^2: largest arm acceleration the energy pump asks for
    energy_gain: float = 80.0  # rad/s^2 per (rad/s of alpha_dot*cos(alpha)) per unit of (E0 - E)/swing_depth
    energy_target: float = 0.0  # E0 as a fraction of swing_depth (0: just enough to reach upright)
    boost_gain: float = 0.3  # E0 += boost_gain * (1 - cos(alpha))/2 at each turnaround above horizontal
    boost_max: float = 0.3
    boost_min_angle: float = math.radians(30.0)  # turnarounds closer to the top than this do not boost
    kick_threshold: float = 0.5  # rad/s: |alpha_dot*cos(alpha)| below this while hanging gets a kick
    arm_wn: float = 6.0  # rad/s: arm centering during swing-up (acceleration PD)
    arm_zeta: float = 1.0
    arm_soft_limit: float = 1.2  # rad: past it no pumping outwards, and a spring back
    arm_barrier: float = 300.0  # rad/s^2 per rad past the soft limit
    prediction_ticks: float = 2.5  # swing-up acts on the state predicted this many ticks ahead
    # hold
    gains: tuple[float, float, float, float] = LQR_GAINS
    theta_error_limit: float = 0.6  # rad: the hold controller sees at most this arm error
    velocity_cutoff: float | None = 100.0  # own alpha_dot filter (rad/s); None: use the alpha_dot passed in
    model: PlantModel = field(default_factory=PlantModel)


class ResetController:
    """Swing-up, catch and hold; call :meth:`step` every control tick."""

    def __init__(self, config: ResetConfig | None = None) -> None:
        self.config = config or ResetConfig()
        self.reset()

    def reset(self) -> None:
        """Start a new reset attempt (clears the timer, the energy boost and a latched failure)."""
        self.elapsed = 0.0
        self.in_band_time = 0.0
        self.phase = "swing_up"
        self.boost = 0.0
        self._alpha_filter: VelocityFilter | None = None
        self._last_alpha_dot = 0.0

    def swing_command(self, theta: float, alpha: float, theta_dot: float, alpha_dot: float) -> int:
        """Energy pump plus arm centering, as an arm acceleration turned into counts through the model."""
        cfg, model = self.config, self.config.model
        shortfall = (
            cfg.energy_target + self.boost - model.pendulum_energy(alpha, alpha_dot) / model.swing_depth
        )
        s = alpha_dot * math.cos(alpha)
        if abs(s) < cfg.kick_threshold and shortfall > 0.9:
            pump = cfg.swing_accel  # hanging (almost) at rest: kick it to get a swing going
        else:
            pump = max(-cfg.swing_accel, min(cfg.swing_accel, cfg.energy_gain * shortfall * s))
        accel = pump - cfg.arm_wn**2 * theta - 2.0 * cfg.arm_zeta * cfg.arm_wn * theta_dot
        excess = abs(theta) - cfg.arm_soft_limit
        if excess > 0.0:  # past the soft limit: no pumping outwards, and a stiff spring back
            if pump * theta > 0.0:
                accel -= pump
            accel -= math.copysign(cfg.arm_barrier * excess, theta)
        return clamp_command(model.command_for_arm_accel(accel, alpha, theta_dot, alpha_dot), cfg.max_command_swing)

    def hold_command(self, theta: float, alpha: float, theta_dot: float, alpha_dot: float) -> int:
        """Linear state feedback -K.x around upright (arm error clipped to ``theta_error_limit``)."""
        cfg = self.config
        k_theta, k_alpha, k_theta_dot, k_alpha_dot = cfg.gains
        theta_err = max(-cfg.theta_error_limit, min(cfg.theta_error_limit, theta))
        u = -(k_theta * theta_err + k_alpha * alpha + k_theta_dot * theta_dot + k_alpha_dot * alpha_dot)
        return clamp_command(u, cfg.max_command_hold)

    def step(self, state: tuple[float, float, float, float], dt: float) -> tuple[int, str]:
        """One tick: ``state`` = (theta, alpha, theta_dot, alpha_dot), ``dt`` = time since the last tick (>
        0). Returns (command in counts, phase)."""
        if not dt > 0:
            raise ValueError(f"dt must be positive, got {dt}")
        cfg = self.config
        theta, alpha, theta_dot, alpha_dot = state
        self.elapsed += dt
        if self.phase == "failed":
            return 0, "failed"
        if not all(math.isfinite(v) for v in (theta, alpha, theta_dot, alpha_dot)):
            self.phase = "failed"
            return 0, "failed"
        alpha = wrap_angle(alpha)
        if cfg.velocity_cutoff is not None:
            if self._alpha_filter is None:
                self._alpha_filter = VelocityFilter(dt, cfg.velocity_cutoff)
                self._alpha_filter.reset(alpha, alpha_dot)
            else:
                alpha_dot = self._alpha_filter.update(alpha, dt)

        if abs(alpha) < cfg.catch_angle:
            command = self.hold_command(theta, alpha, theta_dot, alpha_dot)
            inside = abs(alpha) <= cfg.balance_band and abs(theta) <= cfg.arm_band
            self.in_band_time = self.in_band_time + dt if inside else 0.0
            if self.in_band_time >= cfg.hold_time_s - 1e-9:
                self.phase = "ready"
            else:
                self.phase = "holding" if inside else "catch"
        else:
            self.in_band_time = 0.0
            self.phase = "swing_up"
            turned = alpha_dot * self._last_alpha_dot < 0.0
            if (
                turned and cfg.boost_min_angle < abs(alpha) < math.pi / 2
            ):  # turned back clearly short of the top
                self.boost = min(cfg.boost_max, self.boost + cfg.boost_gain * (1.0 - math.cos(alpha)) / 2.0)
            h = cfg.prediction_ticks * dt
            command = self.swing_command(theta + theta_dot * h, alpha + alpha_dot * h, theta_dot, alpha_dot)
        self._last_alpha_dot = alpha_dot

        if self.phase != "ready" and self.elapsed >= cfg.timeout_s:
            self.phase = "failed"
            return 0, "failed"
        return command, self.phase
