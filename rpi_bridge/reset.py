"""Episode reset for the QUBE-Servo 2: swing the pendulum up from wherever it is and hold it upright, inside the
arm's travel, as pure code.

State convention (rpi_bridge/frame.py): theta = arm angle (counter-clockwise positive), alpha = pendulum angle
(0 upright, +-pi hanging), rad and rad/s. Commands are SPI motor counts; a positive command drives theta negative.
Every command is capped at ``max_command`` (at most 416 counts = 10 V, the manual's limit).

1. **swing_up**: energy pumping (Astrom & Furuta, "Swinging up a pendulum by energy control", Automatica 2000).
   The pendulum energy about its pivot, E = Jp_pivot*alpha_dot^2/2 + mp*g*l*(cos(alpha) - 1), l = Lp/2, is 0
   upright at rest and -2*mp*g*l hanging; the pendulum row of the equations of motion gives dE/dt =
   mp*l*Lr*cos(alpha)*alpha_dot*theta_ddot (plus damping), so the wanted arm acceleration is
   k*(E0 - E)*alpha_dot*cos(alpha), saturated, plus a weak PD that centres the arm. The acceleration becomes a
   command through the model (computed torque, :class:`PlantModel`), applied to the state predicted over the
   actuation delay.
2. **adaptive energy target**: damping and a rig that differs from the model make the pendulum turn back short
   of the top at E = E0. Each turnaround above horizontal but outside the catch region raises E0 by
   ``boost_gain`` times the energy it lacked, each turnaround below horizontal by ``low_boost_gain`` times it (a
   heavily damped pendulum that never gets above horizontal still raises it); each pass over the top (the catch
   did not take it) or each catch that did not hold a pendulum which came in with excess energy lowers E0 by
   ``overshoot_gain`` times the excess. E0 starts at ``initial_energy`` on every attempt.
   **pumping hard**: a pendulum whose model is damped more than ``heavy_damping_ratio`` (the course files' Dp 5e-4
   gives 0.18, ``lab``'s 0.018), or one that keeps turning back below horizontal with E0 at ``boost_max``
   (``hard_after_turns`` times: a rig damped more than its model), is pumped bang-bang at full voltage along
   alpha_dot*cos(alpha), pulled to the middle by ``hard_centre`` of the full voltage per rad of arm angle and kept
   inside ``hard_soft_limit``: the pump family that ``python -m bench.swingup`` found to reach the top at 10x
   ``lab``'s Dp. It acts on the state ``hard_prediction_ticks`` ahead (fewer than the gentle pump's: predicting
   the arm further out pulls it in and stops it early, which costs travel) and plans its braking at
   ``hard_brake_accel``, what full voltage gives with the pendulum near horizontal. In the bridge's loop it still
   falls short on a third to half of the rigs at 10x ``lab``'s Dp: the arm's travel limits the energy it puts in
   (docs/how-to/ood.md); each retry pumps with its own values of these four (6.). If even that brings the
   pendulum no nearer than ``hopeless_angle`` to upright in ``hopeless_turns`` turnarounds, the attempt fails at
   once with one line saying this pump falls short, with the model's damping (``bench.swingup`` finds no swing-up
   within 10 V at the course files' damping, but one at 10x ``lab``'s Dp).
3. **the arm's travel**: the swing-up never accelerates the arm outwards past ``arm_soft_limit``, and whenever
   the arm could no longer stop inside it with ``brake_accel`` (after ``brake_delay_ticks`` of latency) it brakes
   at full voltage. Full voltage stops the arm at 130-310 rad/s^2 in simulation (the least with the pendulum
   horizontal), so 100 rad/s^2 leaves a margin for weaker rigs.
4. **catch** / **holding**: LQR state feedback designed from the model (rpi_bridge/plant.py ``lqr_gains``: the
   one-tick actuation delay and the arm angle's integral in the state) once |alpha| < ``catch_angle``, but only if
   the arm is within ``catch_arm_limit`` and not heading for the soft limit; plus a breakaway feed-forward of the
   model's arm friction and deadzone (:meth:`ResetController.friction_feedforward`). A catch is abandoned (back to
   swing-up, braking) as soon as the arm could not stop inside the soft limit with ``catch_abandon`` of the braking
   budget. "holding" while |alpha| is inside the balance band and |theta| inside the arm band, "catch" while not.
5. **ready** after ``hold_time_s`` continuously inside the band; the hold command keeps going. **failed**
   (command 0, latched until :meth:`ResetController.reset`) when ``timeout_s`` passes without reaching ready (an
   arm still moving fast or a pendulum still swinging is first calmed, for at most ``wind_down_s``).
6. **retries**: :meth:`ResetController.reset` takes the number of attempts that failed in a row on this rig (the
   control core counts them) and picks the attempt's strategy from :data:`STRATEGIES`; a failure names it. Each
   retry pumps hard in its own way (prediction, pull to the middle, soft limit, braking): the cycle a heavily damped
   pendulum settles into short of the top depends on the rig and the pump, so the same pump would mostly repeat it.

The controller estimates alpha_dot itself from the angles (a 50s/(s+50)-type filter with a faster 100 rad/s
cutoff): the 7 ms tick plus a 20 ms filter lag cost too much phase for the catch. The gains were tuned on
``services.qube_sim`` (1 ms RK4 sub-steps behind the SPI frame, 7 ms ticks) over varied starts on nominal rigs,
rigs spread +-15 % and 5x pendulum damping; ``python -m bench.reset`` measures them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from rpi_bridge.frame import MAX_COMMAND, clamp_command
from rpi_bridge.plant import LQR_Q, PlantModel, lqr_gains
from rpi_bridge.velocity import VelocityFilter, wrap_angle

# The hold's gains before they were computed from a model: discrete LQR at T = 7 ms for x = (theta, alpha,
# theta_dot, alpha_dot), u in counts, on the nominal plant, Q = diag(1, 10, 0, 0) (rpi_bridge.plant.FIRST_LQR_Q),
# R = 5e-3 per count^2, designed without the actuation delay. rpi_bridge.plant.lqr_gains reproduces them from
# PlantModel() without the delay to 4 digits (tests/rpi_bridge/test_reset_model.py); the hold now uses the design with
# the delay and the arm angle's integral in the state, and weights the arm more (rpi_bridge.plant.LQR_Q).
LQR_GAINS = (12.7, -563.3, 13.3, -39.0)


@dataclass(frozen=True)
class ResetConfig:
    """Tunables of :class:`ResetController` (angles in rad, times in s, accelerations in rad/s^2, commands in SPI
    counts). The model gives the energy, the computed torque, the hold's gains and its friction compensation."""

    balance_band: float = math.radians(5.0)
    hold_time_s: float = 0.5
    timeout_s: float = 15.0
    max_command: int = MAX_COMMAND  # every command of the reset (10 V)
    catch_angle: float = math.radians(21.0)
    arm_band: float = math.radians(45.0)  # |theta| must also be inside it to count as holding
    catch_arm_limit: float = math.radians(57.0)  # a catch starts only with the arm inside this
    # swing-up
    swing_accel: float = 95.0  # largest arm acceleration the energy pump asks for
    energy_gain: float = 290.0  # rad/s^2 per (rad/s of alpha_dot*cos(alpha)) per unit of (E0 - E)/swing_depth
    kick_threshold: float = 0.5  # rad/s: |alpha_dot*cos(alpha)| below this while hanging gets a kick
    arm_wn: float = 4.0  # rad/s: arm centering during swing-up (critically damped acceleration PD)
    prediction_ticks: float = 1.75  # swing-up acts on the state predicted this many ticks ahead
    # adaptive energy target E0 (fractions of swing_depth)
    initial_energy: float = 0.0  # E0 at the start of an attempt
    boost_gain: float = 0.6  # E0 += boost_gain * (1 - cos(alpha))/2 at a turnaround short of the top
    boost_min_angle: float = math.radians(22.0)  # turnarounds closer to the top than this do not boost
    low_boost_gain: float = 0.1  # E0 += low_boost_gain * (the energy lacking) at a turnaround below horizontal
    boost_max: float = 0.8
    overshoot_gain: float = 0.5  # E0 -= overshoot_gain * (excess - overshoot_margin) on a pass over the top
    overshoot_margin: float = 0.1
    # a heavily damped pendulum: pump at full voltage over more of the arm's travel
    heavy_damping_ratio: float = 0.12  # a model damped more than this (PlantModel.damping_ratio) pumps hard at once
    hard_after_turns: int = 3  # ... else after this many turnarounds below horizontal with E0 at boost_max
    hard_swing_accel: float = 400.0  # arm acceleration asked for (more than 10 V gives: full voltage)
    hard_energy: float = 2.0  # E0 while pumping hard (lowered, as ever, by passes over the top)
    hard_soft_limit: float = math.radians(70.0)  # no push outwards past it
    hard_brake_accel: float = 150.0  # braking planned at this (full voltage gives 130-310: see brake_accel)
    hard_brake_delay_ticks: float = 1.3
    hard_prediction_ticks: float = 1.0  # the hard pump acts on the state predicted this many ticks ahead
    hard_centre: float = 2.5  # per rad of arm angle: the pull to the middle, a fraction of the full pump
    hopeless_turns: int = 20  # pumping hard, this many turnarounds none of which came within ``hopeless_angle``
    hopeless_angle: float = math.radians(60.0)  # of upright: the pendulum cannot be swung up (fail at once)
    # settling before the swing-up (a retry's strategy)
    settle_first: bool = False  # centre the arm and let the pendulum calm down before pumping
    settle_energy: float = -0.9  # ... until its energy is below this (fraction of swing_depth; -1 is at rest)
    settle_max_s: float = 5.0  # ... or this long at most
    max_catches: int = 12  # an attempt whose catches keep failing gives up after this many (the next one retries)
    wind_down_speed: float = 0.3  # rad/s: giving up, a faster arm (or a pendulum above settle_energy) is first held
    wind_down_s: float = 3.0  # ... in the middle for at most this long, before the attempt fails
    wind_down_wn: float = 8.0  # rad/s: the arm PD while winding down
    # the arm's travel
    arm_soft_limit: float = math.radians(80.0)  # the swing-up keeps the arm inside (the bridge faults at 110)
    brake_accel: float = 100.0  # braking assumed available at full voltage
    brake_delay_ticks: float = 1.3  # latency between a reading and the command acting
    catch_abandon: float = 0.75  # fraction of the braking budget a catch may use before it is abandoned
    # hold: LQR from the model (rpi_bridge.plant.lqr_gains) with the delay and the arm angle's integral in the state
    gains: tuple[float, ...] | None = None  # (theta, alpha, theta_dot, alpha_dot[, u_prev, integral]); None: model
    period_s: float = 0.007  # the hold's design period (the bridge's tick)
    hold_weights: tuple[float, float, float, float] = LQR_Q  # LQR Q on (theta, alpha, theta_dot, alpha_dot)
    integral_weight: float = 1.0  # LQR weight of the arm angle's integral (rad^2 s^2)
    integral_limit: float = 60.0  # counts: the integral's share of the command is bounded by this (anti-windup)
    friction_compensation: float = 0.8  # fraction of the model's arm friction and deadzone fed forward
    stick_speed: float = 0.05  # rad/s: slower than this the arm counts as stuck (breakaway feed-forward)
    theta_error_limit: float = 0.6  # rad: the hold controller sees at most this arm error
    velocity_cutoff: float | None = 100.0  # own alpha_dot filter (rad/s); None: use the alpha_dot passed in
    model: PlantModel = field(default_factory=PlantModel)

    def __post_init__(self) -> None:
        if not 0 < self.max_command <= MAX_COMMAND:
            raise ValueError(f"max_command must be in 1..{MAX_COMMAND} (+-10 V), got {self.max_command}")
        if not 0 < self.catch_angle < self.boost_min_angle < math.pi / 2:
            raise ValueError("need 0 < catch_angle < boost_min_angle < pi/2")
        if not 0 < self.arm_soft_limit < math.pi:
            raise ValueError(f"arm_soft_limit must be in (0, pi), got {self.arm_soft_limit}")
        if not 0 < self.hard_soft_limit < math.pi or self.hopeless_turns < 1:
            raise ValueError("need 0 < hard_soft_limit < pi and hopeless_turns >= 1")
        if not 0 <= self.prediction_ticks <= 5 or not 0 <= self.hard_prediction_ticks <= 5:
            raise ValueError("prediction_ticks and hard_prediction_ticks must be in [0, 5]")
        for name in ("hold_time_s", "timeout_s", "swing_accel", "brake_accel", "catch_abandon", "period_s",
                     "hard_swing_accel", "hard_brake_accel"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.gains is not None and len(self.gains) not in (4, 6):
            raise ValueError(f"gains must have 4 or 6 entries, got {len(self.gains)}")
        if len(self.hold_weights) != 4 or not all(w >= 0 for w in self.hold_weights) or not any(self.hold_weights):
            raise ValueError(f"hold_weights must be four weights >= 0, not all 0, got {self.hold_weights}")
        if not 0 <= self.friction_compensation <= 1.5 or self.integral_limit < 0 or self.integral_weight < 0:
            raise ValueError("need 0 <= friction_compensation <= 1.5, integral_limit >= 0 and integral_weight >= 0")

    def widest_soft_limit(self) -> float:
        """The largest soft arm limit any phase of an attempt may use (the bridge's fault limit must lie beyond)."""
        return max(self.arm_soft_limit, self.hard_soft_limit)

    def hold_gains(self) -> tuple[float, float, float, float, float, float]:
        """(k_theta, k_alpha, k_theta_dot, k_alpha_dot, k_u_prev, k_integral): ``gains``, or designed from the
        model."""
        k = self.gains if self.gains is not None else lqr_gains(self.model, self.period_s, tuple(self.hold_weights),
                                                               q_integral=self.integral_weight)
        return (*k, 0.0, 0.0) if len(k) == 4 else tuple(k)  # type: ignore[return-value]


#: The retry strategies: attempt n after n - 1 failures in a row on one rig uses STRATEGIES[n - 1] (the last one
#: from then on). Each is (name, changes to the ResetConfig; "timeout_factor" scales its timeout_s, "model_factors"
#: its model's values). Every retry first centres the arm and lets the pendulum calm down. "heavy" assumes an arm 3x
#: as heavy and 3x as sticky as the model (the deviations that defeat the hold of a nominal model: the sweep of
#: services/qube_sim/families.py); "wide" catches earlier and starts with energy to spare; "patient" gives a heavily
#: damped pendulum time, adapts faster and assumes an arm 2x off; "strong" pumps harder and compensates all of the
#: model's friction. Each retry also pumps hard (a heavily damped pendulum) with its own prediction, pull to the
#: middle, soft limit and braking: where the hard pump falls short, its swing settles into a cycle that depends on
#: the rig and on these, so a retry with the same pump mostly falls short again (docs/how-to/ood.md). "heavy" pulls
#: less to the middle, "wide" acts on the state now, "patient" does both over 76 deg of travel, "strong" pulls less
#: and plans its braking at 220 rad/s^2 inside 62 deg; on rigs of 10x ``lab``'s Dp each reached the top from a calm
#: start on 55-65 % of the tuning rigs (the standard pump 30-45 %), with the arm inside 93 deg.
STRATEGIES: tuple[tuple[str, dict[str, object]], ...] = (
    ("standard", {}),
    ("heavy", {"settle_first": True, "timeout_factor": 4 / 3, "hard_centre": 1.5,
               "model_factors": {"mr": 3.0, "coulomb_arm": 3.0, "static_arm": 3.0}}),
    ("wide", {"settle_first": True, "catch_angle": math.radians(26.0), "boost_min_angle": math.radians(30.0),
              "initial_energy": 0.15, "timeout_factor": 4 / 3, "hard_prediction_ticks": 0.0}),
    ("patient", {"settle_first": True, "timeout_factor": 2.0, "boost_gain": 0.9, "low_boost_gain": 0.25,
                 "boost_max": 1.2, "model_factors": {"mr": 2.0, "coulomb_arm": 2.0, "static_arm": 2.0},
                 "hard_prediction_ticks": 0.0, "hard_centre": 1.5, "hard_soft_limit": math.radians(76.0)}),
    ("strong", {"settle_first": True, "timeout_factor": 2.0, "swing_accel": 110.0, "initial_energy": 0.3,
                "boost_max": 1.2, "friction_compensation": 1.0, "hard_centre": 1.5,
                "hard_soft_limit": math.radians(62.0), "hard_brake_accel": 220.0}),
)


def strategy(config: ResetConfig, failures: int) -> tuple[str, ResetConfig]:
    """The strategy (name, config) of an attempt after ``failures`` failed attempts in a row."""
    name, changes = STRATEGIES[min(max(0, failures), len(STRATEGIES) - 1)]
    changes = dict(changes)
    factor = float(changes.pop("timeout_factor", 1.0))  # type: ignore[arg-type]
    scales: dict[str, float] = changes.pop("model_factors", {})  # type: ignore[assignment]
    model = replace(config.model, **{k: getattr(config.model, k) * v for k, v in scales.items()})
    return name, replace(config, timeout_s=config.timeout_s * factor, model=model, **changes)  # type: ignore[arg-type]


class ResetController:
    """Swing-up, catch and hold; call :meth:`step` every control tick."""

    def __init__(self, config: ResetConfig | None = None) -> None:
        self.base_config = config or ResetConfig()
        for failures in range(len(STRATEGIES)):  # every strategy's gains designed now, not in a control tick
            strategy(self.base_config, failures)[1].hold_gains()
        self.reset()

    def reset(self, failures: int = 0) -> None:
        """Start a new reset attempt (clears the timer, the energy target and a latched failure); ``failures``:
        attempts that failed in a row before this one on this rig, which choose its strategy (:data:`STRATEGIES`)."""
        self.strategy, self.config = strategy(self.base_config, failures)
        self._catch_config = self.config  # a catch is abandoned by this one's soft limit and braking, also when
        # pumping hard (whose soft limit is the pump's, not the arm's)
        self._gains = self.config.hold_gains()
        self.elapsed = 0.0
        self.in_band_time = 0.0
        self.phase = "settle" if self.config.settle_first else "swing_up"
        self.energy_target = self.config.initial_energy
        self.failure = ""
        self.catches = 0  # catches started this attempt
        self._arrival_energy = 0.0  # pendulum energy when the current catch started
        self.max_arm = 0.0  # largest |theta| seen this attempt
        self._alpha_filter: VelocityFilter | None = None
        self._last_alpha: float | None = None
        self._last_alpha_dot = 0.0
        self._integral = 0.0  # the hold's integral of the arm angle (rad s)
        self._u_prev = 0.0  # the hold's last linear command, still on its way to the motor (counts)
        self._give_up_at = math.inf  # when the attempt gave up (it then stops the arm before failing)
        self.hard = False  # pumping at full voltage (a heavily damped pendulum)
        self._low_turns = 0  # turnarounds below horizontal with the energy target at boost_max
        self._hard_turns = 0  # turnarounds while pumping hard
        self.best_turn = math.pi  # pumping hard: the highest turnaround (rad from upright)
        self.hopeless = ""  # set when pumping hard cannot swing the pendulum up: the attempt gives up with it
        if self.config.model.damping_ratio > self.config.heavy_damping_ratio:
            self._pump_hard()

    def _pump_hard(self) -> None:
        """From now on this attempt pumps at full voltage over ``hard_soft_limit`` of the arm's travel, towards an
        energy target of at least ``hard_energy``."""
        cfg = self.config
        self.hard = True
        self.config = replace(cfg, swing_accel=cfg.hard_swing_accel, arm_soft_limit=cfg.hard_soft_limit,
                              brake_accel=cfg.hard_brake_accel, brake_delay_ticks=cfg.hard_brake_delay_ticks,
                              boost_max=max(cfg.boost_max, cfg.hard_energy))
        self.energy_target = max(self.energy_target, cfg.hard_energy)

    # -- the pieces ----------------------------------------------------------------------------------------------

    def normalised_energy(self, alpha: float, alpha_dot: float) -> float:
        """Pendulum energy / swing_depth: -1 hanging at rest, 0 upright at rest."""
        model = self.config.model
        return model.pendulum_energy(alpha, alpha_dot) / model.swing_depth

    def must_brake(self, theta: float, theta_dot: float, dt: float, budget: float = 1.0,
                   config: ResetConfig | None = None) -> int:
        """+1 / -1 when the arm moving that way could not stop inside the soft limit with ``budget`` *
        ``brake_accel`` (after the actuation delay) of ``config`` (default the attempt's); 0 when it can."""
        cfg = config or self.config
        for direction in (1, -1):
            outward = direction * theta_dot
            if outward <= 0:
                continue
            room = cfg.arm_soft_limit - direction * theta - outward * cfg.brake_delay_ticks * dt
            if room <= 0 or outward * outward >= 2.0 * cfg.brake_accel * budget * room:
                return direction
        return 0

    def centre_command(self, theta: float, alpha: float, theta_dot: float, alpha_dot: float,
                       wn: float | None = None) -> int:
        """The arm centering PD alone (settling, winding down; ``wn`` default ``arm_wn``): an arm acceleration
        through the model."""
        cfg = self.config
        wn = cfg.arm_wn if wn is None else wn
        accel = -wn * wn * theta - 2.0 * wn * theta_dot
        return clamp_command(cfg.model.command_for_arm_accel(accel, alpha, theta_dot, alpha_dot), cfg.max_command)

    def swing_command(self, theta: float, alpha: float, theta_dot: float, alpha_dot: float,
                      target: float | None = None) -> int:
        """Energy pump towards ``target`` (default the energy target) plus arm centering, as an arm acceleration
        turned into counts through the model; never outwards past the soft limit."""
        cfg, model = self.config, self.config.model
        energy = self.normalised_energy(alpha, alpha_dot)
        shortfall = (self.energy_target if target is None else target) - energy
        s = alpha_dot * math.cos(alpha)
        if self.hard:  # bang-bang along s towards the target, pulled to the middle by hard_centre per rad
            direction = 1.0 if abs(s) < 1e-3 else math.copysign(1.0, s * shortfall)
            push = max(-1.0, min(1.0, direction - cfg.hard_centre * theta))
            if abs(theta) >= cfg.arm_soft_limit and push * theta > 0:
                push = 0.0
            return clamp_command(-push * cfg.max_command, cfg.max_command)  # +command drives theta negative
        if abs(s) < cfg.kick_threshold and energy < -0.9 and shortfall > 0:
            # hanging (almost) at rest: kick it to get a swing going (on the energy, not the shortfall: a raised
            # target must not turn a turnaround near horizontal into a kick the wrong way)
            pump = cfg.swing_accel
        else:
            pump = max(-cfg.swing_accel, min(cfg.swing_accel, cfg.energy_gain * shortfall * s))
        accel = pump - cfg.arm_wn**2 * theta - 2.0 * cfg.arm_wn * theta_dot
        if abs(theta) >= cfg.arm_soft_limit and accel * theta > 0:
            accel = 0.0
        return clamp_command(model.command_for_arm_accel(accel, alpha, theta_dot, alpha_dot), cfg.max_command)

    def friction_feedforward(self, theta_dot: float, command: float) -> float:
        """Counts that cancel ``friction_compensation`` of the model's arm friction and deadzone: the Coulomb level
        along a moving arm, the breakaway (static) level towards ``command`` on a stuck one, and the deadzone in
        the direction of the command."""
        cfg, model = self.config, self.config.model
        if not cfg.friction_compensation:
            return 0.0
        if abs(theta_dot) > cfg.stick_speed:  # +command drives theta negative: along the motion is -sign(theta_dot)
            torque = -math.copysign(model.coulomb_arm, theta_dot)
        else:
            torque = max(model.static_arm, model.coulomb_arm) * math.tanh(command / 4.0)
        volts = torque * model.volts_per_newton_metre + model.deadzone_v * math.tanh(command / 2.0)
        return cfg.friction_compensation * volts / model.volts_per_count

    def hold_command(self, theta: float, alpha: float, theta_dot: float, alpha_dot: float, dt: float = 0.0) -> int:
        """LQR -K.z around upright (arm error clipped to ``theta_error_limit``; the command still on its way to the
        motor and the arm angle's integral in z), plus the friction feed-forward. The integral advances by ``dt``
        and stops while the command saturates outwards; its share is bounded by ``integral_limit``."""
        cfg = self.config
        k_theta, k_alpha, k_theta_dot, k_alpha_dot, k_u, k_int = self._gains
        theta_err = max(-cfg.theta_error_limit, min(cfg.theta_error_limit, theta))
        linear = -(k_theta * theta_err + k_alpha * alpha + k_theta_dot * theta_dot + k_alpha_dot * alpha_dot
                   + k_u * self._u_prev)
        integral = 0.0
        if k_int:
            bound = cfg.integral_limit / abs(k_int)
            stepped = max(-bound, min(bound, self._integral + theta_err * dt))
            integral = -k_int * stepped
            if abs(linear + integral) < cfg.max_command or abs(stepped) < abs(self._integral):
                self._integral = stepped  # anti-windup: no integration into a saturated command
        u = linear + integral
        self._u_prev = max(-cfg.max_command, min(cfg.max_command, u))
        return clamp_command(u + self.friction_feedforward(theta_dot, u), cfg.max_command)

    def _adapt(self, alpha: float, alpha_dot: float) -> None:
        """Raise E0 after a turnaround short of the top (strongly above horizontal, weakly below), lower it after a
        pass over the top."""
        cfg = self.config
        if alpha_dot * self._last_alpha_dot < 0.0 and cfg.boost_min_angle < abs(alpha):
            lacking = (1.0 - math.cos(alpha)) / 2.0
            gain = cfg.boost_gain if abs(alpha) < math.pi / 2 else cfg.low_boost_gain
            self.energy_target = min(cfg.boost_max, self.energy_target + gain * lacking)
            self._turned(abs(alpha))
        last = self._last_alpha
        if last is not None and abs(alpha) < 0.3 and alpha * last < 0.0:
            excess = self.normalised_energy(0.0, alpha_dot) - cfg.overshoot_margin
            if excess > 0:
                self.energy_target = max(0.0, self.energy_target - cfg.overshoot_gain * excess)

    def _turned(self, height: float) -> None:
        """A turnaround ``height`` rad from upright: pump hard after ``hard_after_turns`` below horizontal with the
        target at its cap; pumping hard, ``hopeless_turns``
        none of which came within ``hopeless_angle`` of upright make the attempt hopeless."""
        cfg = self.config
        if not self.hard:
            if height > math.pi / 2 and self.energy_target >= cfg.boost_max - 1e-9:
                self._low_turns += 1
                if self._low_turns >= cfg.hard_after_turns:
                    self._pump_hard()
            return
        self.best_turn = min(self.best_turn, height)
        self._hard_turns += 1
        if self._hard_turns >= cfg.hopeless_turns and self.best_turn > cfg.hopeless_angle and not self.hopeless:
            model = cfg.model
            self.hopeless = (f"the swing-up cannot pump this pendulum to the top within "
                             f"{cfg.max_command * model.volts_per_count:.0f} V: at full voltage it turns "
                             f"back {math.degrees(self.best_turn):.0f} deg from upright at best (model Dp "
                             f"{model.Dp:.1e} N m s/rad, damping ratio {model.damping_ratio:.2f}); see "
                             f"docs/how-to/ood.md")

    # -- one tick ------------------------------------------------------------------------------------------------

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
            return self._fail("a non-finite state reached the reset controller")
        alpha = wrap_angle(alpha)
        if cfg.velocity_cutoff is not None:
            if self._alpha_filter is None:
                self._alpha_filter = VelocityFilter(dt, cfg.velocity_cutoff)
                self._alpha_filter.reset(alpha, alpha_dot)
            else:
                alpha_dot = self._alpha_filter.update(alpha, dt)

        brake = self.must_brake(theta, theta_dot, dt)
        self.max_arm = max(self.max_arm, abs(theta))
        if self.phase == "settle":
            settling = self._settle(theta, alpha, theta_dot, alpha_dot, brake)
            if settling is not None:
                return settling
        caught = self.phase in ("catch", "holding", "ready")
        catchable = (
            abs(alpha) < cfg.catch_angle
            and (caught or abs(theta) < cfg.catch_arm_limit)
            and not self.must_brake(theta, theta_dot, dt, cfg.catch_abandon, self._catch_config)
        )
        if catchable and not brake:
            if not caught:
                self.catches += 1
                self._arrival_energy = self.normalised_energy(alpha, alpha_dot)
                self._integral, self._u_prev = 0.0, 0.0
            command = self.hold_command(theta, alpha, theta_dot, alpha_dot, dt)
            inside = abs(alpha) <= cfg.balance_band and abs(theta) <= cfg.arm_band
            self.in_band_time = self.in_band_time + dt if inside else 0.0
            if self.in_band_time >= cfg.hold_time_s - 1e-9:
                self.phase = "ready"
            else:
                self.phase = "holding" if inside else "catch"
        else:
            if caught:  # a catch that did not hold: if the pendulum came in too fast, aim lower next time
                excess = self._arrival_energy - cfg.overshoot_margin
                if excess > 0:
                    self.energy_target = max(0.0, self.energy_target - cfg.overshoot_gain * excess)
            self.in_band_time = 0.0
            self.phase = "swing_up"
            self._adapt(alpha, alpha_dot)
            if brake:  # full voltage against the outward motion (+command drives theta negative)
                command = brake * cfg.max_command
            else:
                h = (cfg.hard_prediction_ticks if self.hard else cfg.prediction_ticks) * dt
                command = self.swing_command(theta + theta_dot * h, alpha + alpha_dot * h, theta_dot, alpha_dot)
        self._last_alpha, self._last_alpha_dot = alpha, alpha_dot

        if self.phase != "ready" and (self.elapsed >= cfg.timeout_s or self.catches > cfg.max_catches
                                      or self.hopeless):
            return self._give_up(theta, alpha, theta_dot, alpha_dot, brake)
        return command, self.phase

    def _settle(self, theta: float, alpha: float, theta_dot: float, alpha_dot: float,
                brake: int) -> tuple[int, str] | None:
        """The ``settle`` phase of a strategy that lets the pendulum calm down first: its tick, or None once it is
        calm (or has waited ``settle_max_s``) and the swing-up begins."""
        cfg = self.config
        calm = (self.normalised_energy(alpha, alpha_dot) < cfg.settle_energy and abs(theta) < 0.2
                and abs(theta_dot) < 0.5)
        if self.elapsed >= cfg.timeout_s:
            return self._fail(f"the pendulum did not settle within {cfg.timeout_s:.0f} s (strategy "
                              f"'{self.strategy}')")
        if calm or self.elapsed >= cfg.settle_max_s:
            self.phase = "swing_up"
            return None
        self._last_alpha, self._last_alpha_dot = alpha, alpha_dot
        return (brake * cfg.max_command if brake else self.centre_command(theta, alpha, theta_dot, alpha_dot),
                "swing_up")

    def _give_up(self, theta: float, alpha: float, theta_dot: float, alpha_dot: float,
                 brake: int) -> tuple[int, str]:
        """Out of time or catches: hold the arm in the middle while the pendulum's swing dies down (the amplifier
        goes off after a failure, and a fast arm, or a big swing dragging a free arm, would reach the stop), then
        fail with the reason."""
        cfg = self.config
        self._give_up_at = min(self._give_up_at, self.elapsed)
        calm = abs(theta_dot) < cfg.wind_down_speed and self.normalised_energy(alpha, alpha_dot) < cfg.settle_energy
        if not calm and self.elapsed < self._give_up_at + cfg.wind_down_s:
            return (brake * cfg.max_command if brake else self.centre_command(theta, alpha, theta_dot, alpha_dot,
                                                                              cfg.wind_down_wn), "swing_up")
        if self.hopeless:
            return self._fail(self.hopeless)
        if self.catches > cfg.max_catches:
            return self._fail(f"{self.catches - 1} catches did not hold the pendulum (strategy '{self.strategy}', "
                              f"arm up to {math.degrees(self.max_arm):.0f} deg, energy target "
                              f"{self.energy_target:+.2f})")
        return self._fail(f"the pendulum was not held upright within {cfg.timeout_s:.0f} s (strategy "
                          f"'{self.strategy}', {self.catches} catches started, arm up to "
                          f"{math.degrees(self.max_arm):.0f} deg, energy target {self.energy_target:+.2f})")

    def _fail(self, reason: str) -> tuple[int, str]:
        self.phase = "failed"
        self.failure = reason
        return 0, "failed"
