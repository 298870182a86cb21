"""The host's fit of an identification recording (rpi_bridge/identify.py) to a rig profile, with scipy.optimize.

Multiple shooting: the recording is cut into windows of ``window_s``; each starts from the recorded angles with
non-causal velocity estimates (Savitzky-Golay, ``savgol``), all windows are simulated at once with the vectorised
equations of motion (services/qube_sim/dynamics.py, ``derivatives_array``: the simulator's own, RK4 in ``substeps``
per tick) under the recorded commands, and ``scipy.optimize.least_squares`` minimises the angle prediction error
(theta and alpha, rad) over the parameters in :data:`FITTED` (log space; the loop's delay linear; Levenberg-Marquardt,
:data:`FIRST_STAGE` first, then all of them; then the static/Coulomb arm friction ratio is scanned, which a
least-squares step cannot see, and the fit refined from the best: :func:`_scan_static`). Each command acts from its
read plus the fitted ``delay_ms`` (the previous command before). The rest comes from a base profile.

Trust: the fit is refused (:class:`FitRefused`, one line; nothing written) unless the optimiser converged, the
recording moved the arm, every value is inside its range in :data:`FITTED`, each parameter in :data:`GATED` has a
relative 1-sigma (the sandwich covariance in log space, clustered by window: :func:`_covariance`) of at most
``max_sigma``, and the RMS angle error on the held-out block (the last ``holdout`` of the recording's ``prbs``
segment, contiguous in time, never fitted) is at most ``max_heldout_deg`` and at most ``max_heldout_ratio`` times the
training RMS.

A refused fit is recorded again with the protocol's next PRBS sequence (:func:`identify_to_file`; up to
``attempts`` recordings, 2 by default): a short held-out block can be unlucky. The profile counts the rig time of
every recording.

``python -m services.qube_sim.identify RECORDING --out PROFILE.json [--base lab]``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import savgol_filter

from rpi_bridge.control import ControlConfig, ControlCore
from rpi_bridge.frame import VOLTS_PER_COUNT
from rpi_bridge.identify import IDENTIFY_ATTEMPTS, IdentifyConfig, IdentifyFailed, Recording, RecordingError, drive
from services.qube_sim.clock import VirtualClock
from services.qube_sim.dynamics import QubeParams, derivatives_array, motor_torque_array
from services.qube_sim.profile import LAB, Identified, ProfileError, RigProfile, load_profile
from services.qube_sim.spi_peer import SimulatedQube

#: Fitted quantities: name -> the range of values a fit may return (the profile's own limits, or physically
#: plausible ones; a fit outside it is refused). ``static_ratio`` is static_arm / coulomb_arm (>= 1), ``motor`` km = kt,
#: ``delay_ms`` a command's delay after its read (fitted linearly, as delay / 7 ms; everything else in log space).
FITTED: dict[str, tuple[float, float]] = {
    "Dr": (1e-7, 0.05), "Dp": (1e-8, 0.01), "coulomb_arm": (0.0, 0.05), "static_ratio": (1.0, 5.0),
    "coulomb_pendulum": (0.0, 0.01), "motor": (0.005, 0.5), "deadzone_v": (0.0, 3.0), "mr": (0.01, 1.0),
    "Lr": (0.01, 0.5), "Lp": (0.01, 0.5), "delay_ms": (0.0, 7.0), "cable_stiffness": (0.0, 0.01),
}
#: Fitted first, the others held at the base's values (see :func:`fit`).
FIRST_STAGE = ("Dr", "Dp", "coulomb_arm", "coulomb_pendulum", "motor", "mr")
#: The QubeParams fields that the fitted values set (see :func:`_params`).
_VARIED = ("Dr", "Dp", "Cr", "Sr", "Cp", "Sp", "km", "kt", "deadzone", "mr", "Lr", "Lp", "cable_stiffness")
#: Parameters whose uncertainty decides whether the fit is trusted (the ones that decide control).
GATED = ("Dr", "Dp", "coulomb_arm", "motor", "mr")
#: Viscous damping this small is negligible for the swing-up and the hold: a damping's 1-sigma is gated relative to
#: the larger of its value and this (lab's value), so that a pendulum damped 0.1x lab is known to be lightly damped
#: rather than refused because the small number is known only to +-50 % (N m s/rad). A damping the fit runs down to
#: nothing gets its 1-sigma from a step of this size (:func:`_negligible`).
NEGLIGIBLE_DAMPING = {"Dr": QubeParams.Dr, "Dp": QubeParams.Dp}


class FitRefused(RuntimeError):
    """A fit that is not to be trusted (its message is the one-line reason)."""


@dataclass(frozen=True)
class FitConfig:
    window_s: float = 0.35
    substeps: int = 2  # RK4 steps per tick (3.5 ms at 7 ms: the simulator uses 1 ms; see the docs for the effect)
    #: A fit whose held-out error exceeds ``max_heldout_deg`` is fitted again from where it ended with this many steps
    #: per tick (1 ms, as the simulator integrates) before it is judged: a sticky arm's stick-slip is what 3.5 ms
    #: steps miss most, and the finer fit (about 5x the time) finds the basin the coarse one missed.
    fine_substeps: int = 7
    savgol: int = 11  # samples in the velocity estimate's window (polynomial of order 3)
    holdout: float = 0.25  # fraction of the prbs segment, at its end, held out
    max_nfev: int = 300  # evaluations per stage; a fit still moving after them is refused
    ftol: float = 1e-4  # least_squares' tolerances: relative change of the cost, and of the parameters (log space)
    xtol: float = 1e-4
    max_sigma: float = 0.25
    max_heldout_deg: float = 2.0
    max_heldout_ratio: float = 2.5
    min_arm_travel_deg: float = 10.0  # a recording whose arm moved less than this is no identification


@dataclass
class Windows:
    """Windows of one recording: start states (n, 4), commands (n, L + 1: the one before each tick first), tick
    durations (n, L) and the measured angles after each tick (n, L, 2)."""

    x0: np.ndarray
    commands: np.ndarray
    dt: np.ndarray
    measured: np.ndarray

    def __len__(self) -> int:
        return len(self.x0)


@dataclass
class Fit:
    values: dict[str, float]
    sigma: dict[str, float]  # relative 1-sigma (delay_ms: absolute, ms)
    train_rms_deg: float
    heldout_rms_deg: float
    iterations: int
    converged: bool
    message: str
    wall_s: float
    params: QubeParams
    windows: tuple[int, int] = (0, 0)  # (training, held-out)
    extra: dict[str, float] = field(default_factory=dict)
    substeps: int = 2  # RK4 steps per tick of the fit's last stage (FitConfig.fine_substeps when it was refitted)


def cut(rec: Recording, cfg: FitConfig) -> tuple[Windows, Windows]:
    """(training, held-out) windows of ``rec``."""
    t = np.asarray(rec.t)
    theta = np.asarray(rec.theta)
    alpha = np.unwrap(np.asarray(rec.alpha))
    u = np.asarray(rec.command, dtype=float)
    n = len(t)
    length = max(2, round(cfg.window_s / rec.period_s))
    win = min(cfg.savgol, n - (1 - n % 2)) | 1
    if n < length + 1 or win < 5:
        raise FitRefused(f"the recording has {n} ticks: too short to fit")
    theta_dot = savgol_filter(theta, win, 3, deriv=1, delta=rec.period_s)
    alpha_dot = savgol_filter(alpha, win, 3, deriv=1, delta=rec.period_s)
    prbs = [(a, b) for label, a, b in rec.segments if label == "prbs"]
    hold_from = n
    if prbs:
        a, b = prbs[-1]
        hold_from = b - round(cfg.holdout * (b - a))
    starts = range(1, n - length, length)
    train = [s for s in starts if s + length <= hold_from]
    held = [s for s in starts if s >= hold_from and s + length <= (prbs[-1][1] if prbs else n)]

    def build(sel: list[int]) -> Windows:
        idx = np.asarray(sel, dtype=int)
        steps = idx[:, None] + np.arange(length)[None, :]
        return Windows(x0=np.stack([theta[idx], alpha[idx], theta_dot[idx], alpha_dot[idx]], axis=1),
                       commands=np.concatenate([u[idx - 1][:, None], u[steps]], axis=1),
                       dt=t[steps + 1] - t[steps],
                       measured=np.stack([theta[steps + 1], alpha[steps + 1]], axis=2))

    if not train or not held:
        raise FitRefused("the recording has no prbs segment long enough for both a fit and a held-out block")
    return build(train), build(held)


def simulate(p: QubeParams, w: Windows, delay_s: float | np.ndarray, substeps: int) -> np.ndarray:
    """Predicted (theta, alpha) after each tick of every window, (n, L, 2): RK4 with ``substeps`` per tick; over
    each sub-step the voltage is the time average of the previous command (until ``delay_s`` into the tick) and this
    tick's."""
    theta, alpha, theta_dot, alpha_dot = (w.x0[:, i].copy() for i in range(4))
    volts = w.commands * VOLTS_PER_COUNT
    n, length = w.dt.shape
    out = np.empty((n, length, 2))
    for k in range(length):
        dt = w.dt[:, k]
        h = dt / substeps
        before, now = volts[:, k], volts[:, k + 1]
        for i in range(substeps):
            f = np.clip((delay_s - i * h) / h, 0.0, 1.0)
            v = f * before + (1.0 - f) * now

            def rates(th: np.ndarray, al: np.ndarray, thd: np.ndarray, ald: np.ndarray,
                      v: np.ndarray = v) -> tuple[np.ndarray, ...]:
                tau = motor_torque_array(p, v, thd)
                tau = tau - p.cable_stiffness * (th - p.cable_rest)
                tdd, add = derivatives_array(p, thd, al, ald, tau)
                return thd, ald, tdd, add

            x = (theta, alpha, theta_dot, alpha_dot)
            k1 = rates(*x)
            k2 = rates(*(xi + 0.5 * h * ki for xi, ki in zip(x, k1, strict=True)))
            k3 = rates(*(xi + 0.5 * h * ki for xi, ki in zip(x, k2, strict=True)))
            k4 = rates(*(xi + h * ki for xi, ki in zip(x, k3, strict=True)))
            theta, alpha, theta_dot, alpha_dot = (
                xi + h / 6.0 * (a + 2.0 * b + 2.0 * c + d) for xi, a, b, c, d in zip(x, k1, k2, k3, k4, strict=True))
        out[:, k, 0] = theta
        out[:, k, 1] = alpha
    return out


STATIC_RATIO_MAX = 5.0  # static / Coulomb arm friction: the lab profile has 1.33
DELAY_SCALE_MS = 7.0  # delay_ms is fitted as delay / 7 ms (linear, clipped to [0, 7] ms when used)


def _to_z(name: str, value: float) -> float:
    """The optimiser's coordinate of a value: log (static_ratio: the logit of its place in [1, STATIC_RATIO_MAX], so
    that static >= Coulomb; the delay: linear). Unbounded, so that least_squares can use Levenberg-Marquardt."""
    if name == "delay_ms":
        return value / DELAY_SCALE_MS
    if name == "static_ratio":  # 1 + (hi - 1) * sigmoid(z): bounded, so that a trial step cannot glue the arm
        f = min(1 - 1e-6, max(1e-6, (value - 1.0) / (STATIC_RATIO_MAX - 1.0)))
        return math.log(f / (1.0 - f))
    return math.log(value)


def _from_z(name: str, z: float) -> float:
    if name == "delay_ms":
        return min(DELAY_SCALE_MS, max(0.0, z * DELAY_SCALE_MS))
    if name == "static_ratio":
        return 1.0 + (STATIC_RATIO_MAX - 1.0) / (1.0 + math.exp(-max(-50.0, min(z, 50.0))))
    return math.exp(min(z, 50.0))


def _relative_scale(name: str, value: float) -> float:
    """d(value)/value per unit of z: 1 in log space; (r - 1)(1 - f)/r for static_ratio r, f = (r - 1)/(hi - 1)."""
    if name == "static_ratio":
        return (value - 1.0) * (1.0 - (value - 1.0) / (STATIC_RATIO_MAX - 1.0)) / value
    return 1.0


def _covariance(jac: np.ndarray, residuals: np.ndarray, windows: int) -> np.ndarray:
    """Covariance of the fitted (log) parameters, robust to the residuals of one window being correlated (they
    share its start state's error): the sandwich (J^T J)^-1 (sum over windows of J_w^T r_w r_w^T J_w) (J^T J)^-1,
    windows as independent clusters. A parameter the recording does not see (its column of J vanishes, e.g. a
    deadzone or static friction fitted to nothing) gets an infinite variance and is left out of the others'."""
    k = jac.shape[1]
    norms = np.linalg.norm(jac, axis=0)
    seen = np.flatnonzero(norms > 1e-6 * max(float(norms.max()), 1e-300))
    cov = np.full((k, k), np.inf)
    j = jac[:, seen]
    try:
        bread = np.linalg.inv(j.T @ j)
    except np.linalg.LinAlgError:
        return cov
    scores = (j * residuals[:, None]).reshape(windows, -1, len(seen)).sum(axis=1)  # (windows, seen)
    meat = scores.T @ scores * windows / max(1, windows - len(seen))
    cov[np.ix_(seen, seen)] = bread @ meat @ bread
    return np.where(np.isfinite(cov), cov, np.inf)


def _params(base: QubeParams, values: dict[str, float], static_pendulum_ratio: float) -> QubeParams:
    cr = values["coulomb_arm"]
    cp = values["coulomb_pendulum"]
    return replace(base, Dr=values["Dr"], Dp=values["Dp"], Cr=cr, Sr=cr * values["static_ratio"], Cp=cp,
                   Sp=cp * static_pendulum_ratio, km=values["motor"], kt=values["motor"], deadzone=values["deadzone_v"],
                   mr=values["mr"], Lr=values["Lr"], Lp=values["Lp"], cable_stiffness=values["cable_stiffness"])


def _initial(base: RigProfile) -> dict[str, float]:
    guess = {"Dr": base.Dr or 2.7e-4, "Dp": base.Dp or 5e-5, "coulomb_arm": base.coulomb_arm or 1e-3,
             "static_ratio": base.static_arm / base.coulomb_arm if base.coulomb_arm and base.static_arm else 1.3,
             "coulomb_pendulum": base.coulomb_pendulum or 1e-4, "motor": base.km, "deadzone_v": base.deadzone_v or 0.05,
             "mr": base.mr, "Lr": base.Lr, "Lp": base.Lp, "delay_ms": 1.0,
             "cable_stiffness": base.cable_stiffness or LAB.cable_stiffness}
    return {k: min(FITTED[k][1], max(FITTED[k][0], v)) for k, v in guess.items()}  # every log value > 0 already


@dataclass
class _Problem:
    """The residuals of one fit: the base's plant, the training windows, the coordinates of :data:`FITTED`."""

    nominal: QubeParams
    static_pendulum_ratio: float
    train: Windows
    substeps: int
    names: tuple[str, ...] = tuple(FITTED)

    def values_of(self, z: np.ndarray) -> dict[str, float]:
        return {k: _from_z(k, float(zi)) for k, zi in zip(self.names, z, strict=True)}

    def params(self, values: dict[str, float]) -> QubeParams:
        return _params(self.nominal, values, self.static_pendulum_ratio)

    def residuals(self, z: np.ndarray, w: Windows) -> np.ndarray:
        v = self.values_of(z)
        with np.errstate(all="ignore"):  # a trial step may make the integration blow up: a large residual then
            pred = simulate(self.params(v), w, v["delay_ms"] / 1e3, self.substeps)
        r = (pred - w.measured).ravel()
        return np.where(np.isfinite(r), r, 10.0)

    def batch(self, z: np.ndarray, steps: np.ndarray) -> np.ndarray:
        """Residuals at z and at z + steps[j] e_j for every non-zero step, in one vectorised simulation."""
        return self.many(np.vstack([z, z + np.diag(steps)[np.flatnonzero(steps)]]))

    def many(self, zs: np.ndarray) -> np.ndarray:
        """The training residuals at each row of ``zs``, in one vectorised simulation (rows x residuals)."""
        train = self.train
        sets = [self.params(self.values_of(zi)) for zi in zs]
        n = len(train)
        arrays: dict[str, Any] = {f: np.repeat([getattr(q, f) for q in sets], n) for f in _VARIED}
        tiled = Windows(np.tile(train.x0, (len(zs), 1)), np.tile(train.commands, (len(zs), 1)),
                        np.tile(train.dt, (len(zs), 1)), train.measured)
        delays = np.repeat([self.values_of(zi)["delay_ms"] / 1e3 for zi in zs], n)
        with np.errstate(all="ignore"):
            pred = simulate(replace(self.nominal, **arrays), tiled, delays, self.substeps)
        r = (pred.reshape(len(zs), *train.measured.shape) - train.measured[None]).reshape(len(zs), -1)
        return np.where(np.isfinite(r), r, 10.0)

    def solve(self, start: np.ndarray, free: list[int], cfg: FitConfig, progress: Callable[[str], None] | None,
              evaluations: list[int]) -> Any:
        """least_squares over the coordinates ``free``, the others held at ``start``'s."""

        def full(x: np.ndarray) -> np.ndarray:
            z = start.copy()
            z[free] = x
            return z

        def counted(x: np.ndarray) -> np.ndarray:
            evaluations[0] += 1
            r = self.residuals(full(x), self.train)
            if progress is not None:
                rms = math.degrees(float(np.sqrt(np.mean(r * r))))
                progress(f"fit evaluation {evaluations[0]} ({len(free)} parameters): training RMS {rms:.3f} deg")
            return r

        def jacobian(x: np.ndarray) -> np.ndarray:
            z = full(x)
            steps = np.zeros_like(z)
            steps[free] = 1e-3 * np.maximum(1.0, np.abs(z[free]))
            r = self.batch(z, steps)
            return ((r[1:] - r[0]) / steps[free][:, None]).T

        return least_squares(counted, start[free], jac=jacobian, method="lm", x_scale="jac", max_nfev=cfg.max_nfev,
                             xtol=cfg.xtol, ftol=cfg.ftol)


def _sigmas(names: tuple[str, ...], values: dict[str, float], cov: np.ndarray) -> dict[str, float]:
    """Each fitted value's 1-sigma (relative; delay_ms in ms), and static_arm's (coulomb_arm x static_ratio)."""
    var = np.diag(cov)
    sigma = {}
    for i, name in enumerate(names):
        sd = math.sqrt(var[i]) if var[i] >= 0 else math.inf
        sigma[name] = sd * DELAY_SCALE_MS if name == "delay_ms" else sd * _relative_scale(name, values[name])
    i_c, i_r = names.index("coulomb_arm"), names.index("static_ratio")
    w = _relative_scale("static_ratio", values["static_ratio"])
    v_static = var[i_c] + w * w * var[i_r] + 2 * w * cov[i_c, i_r] if np.isfinite(var[i_r]) else var[i_c]
    sigma["static_arm"] = math.sqrt(v_static) if v_static >= 0 else math.inf
    return sigma


def _negligible(problem: _Problem, x: np.ndarray, residuals: np.ndarray, jac: np.ndarray, i: int, floor: float,
                train: Windows) -> tuple[float, float]:
    """A damping the fit ran down to (next to) nothing, whose log coordinate the recording cannot see (``x`` the fit,
    ``residuals`` and ``jac`` its training residuals and Jacobian): its value (at least the lowest FITTED allows) and
    its relative 1-sigma, from how the residuals change when it is raised by ``floor`` (a damping acts linearly), so
    that the gate compares its absolute uncertainty with ``floor``."""
    name = problem.names[i]
    value = max(_from_z(name, float(x[i])), FITTED[name][0])
    raised = x.copy()
    raised[i] = _to_z(name, value + floor)
    linear = jac.copy()
    linear[:, i] = problem.residuals(raised, train) - residuals  # per ``floor`` of damping
    var = _covariance(linear, residuals, len(train))[i, i]
    return value, (math.sqrt(var) * floor / value if var >= 0 else math.inf)


def fit(rec: Recording, base: RigProfile, cfg: FitConfig | None = None,
        progress: Callable[[str], None] | None = None) -> Fit:
    """Fit ``rec`` from ``base``'s values (the starting point and everything not fitted). FitRefused when the
    recording cannot be fitted at all; an untrusted fit is returned (see :func:`check`)."""
    cfg = cfg or FitConfig()
    began = time.perf_counter()
    if not rec.complete:
        raise FitRefused(f"the recording is incomplete ({rec.outcome})")
    travel = math.degrees(max(rec.theta) - min(rec.theta))
    if travel < cfg.min_arm_travel_deg:
        raise FitRefused(f"the arm moved {travel:.1f} deg over the whole recording (at least "
                         f"{cfg.min_arm_travel_deg:.0f} needed): the rig did not respond to the protocol")
    train, held = cut(rec, cfg)
    sp_ratio = base.static_pendulum / base.coulomb_pendulum if base.coulomb_pendulum and base.static_pendulum else 0.0
    problem = _Problem(base.params(), sp_ratio, train, cfg.substeps)
    names = problem.names
    start = _initial(base)
    z0 = np.array([_to_z(k, start[k]) for k in names])
    evaluations = [0]
    # first the parameters that set most of the motion (better conditioned: it finds the right basin from a base
    # 10x off), then all of them from there
    first_free = [names.index(k) for k in FIRST_STAGE]
    first = problem.solve(z0, first_free, cfg, progress, evaluations)
    z1 = z0.copy()
    z1[first_free] = first.x
    result = problem.solve(z1, list(range(len(names))), cfg, progress, evaluations)
    scanned = _scan_static(problem, result.x, float(np.sum(result.fun**2)))
    if scanned is not None:  # the step's plateau held the optimiser short of the static friction's best
        if progress is not None:
            progress(f"static/Coulomb arm friction {problem.values_of(result.x)['static_ratio']:.2f} -> "
                     f"{problem.values_of(scanned)['static_ratio']:.2f} (scan): fitting again from there")
        result = problem.solve(scanned, list(range(len(names))), cfg, progress, evaluations)
    r_held = problem.residuals(result.x, held)
    if _rms_deg(r_held) > cfg.max_heldout_deg and cfg.fine_substeps > cfg.substeps:
        if progress is not None:
            progress(f"held-out RMS {_rms_deg(r_held):.2f} deg: fitting again in {cfg.fine_substeps} steps per tick")
        problem = replace(problem, substeps=cfg.fine_substeps)
        result = problem.solve(result.x, list(range(len(names))), cfg, progress, evaluations)
        r_held = problem.residuals(result.x, held)
    values = problem.values_of(result.x)
    r_train = result.fun
    sigma = _sigmas(names, values, _covariance(np.asarray(result.jac), r_train, len(train)))
    for name, floor in NEGLIGIBLE_DAMPING.items():
        if not math.isfinite(sigma[name]):  # run down to (next to) nothing: its log coordinate is out of sight
            values[name], sigma[name] = _negligible(problem, result.x, r_train, np.asarray(result.jac),
                                                    names.index(name), floor, train)
    values["static_arm"] = values["coulomb_arm"] * values["static_ratio"]
    return Fit(values=values, sigma=sigma,
               train_rms_deg=_rms_deg(r_train), heldout_rms_deg=_rms_deg(r_held),
               iterations=evaluations[0], converged=result.status > 0, message=str(result.message),
               wall_s=time.perf_counter() - began, params=problem.params(values), windows=(len(train), len(held)),
               substeps=problem.substeps)


#: The static/Coulomb arm friction ratios :func:`_scan_static` tries: 1 to 3 in steps of 0.05, then to the most a fit
#: may return in steps of 0.25.
STATIC_SCAN = (*np.round(np.arange(1.0, 3.0, 0.05), 2), *np.arange(3.0, STATIC_RATIO_MAX + 1e-9, 0.25))


def _scan_static(problem: _Problem, x: np.ndarray, cost: float) -> np.ndarray | None:
    """The fit ``x`` (training cost ``cost``) with its static/Coulomb arm friction ratio moved to the best of
    :data:`STATIC_SCAN`, the rest held (None: no ratio there fits better). Static friction acts only while the arm is
    at rest, so the training cost is a staircase in it at the scale of a finite-difference step: Levenberg-Marquardt
    stops on a tread near where it started (the base's ratio), and a rig's ratio far from the base's came out shrunk
    towards it (static friction 0.74x the truth's on a rig of ratio 2.0, 1.38x on one whose friction is flat: tuning
    rigs 528000 and 527002 of the combined family). One vectorised simulation of every ratio finds the basin; the
    optimiser then refines from it."""
    i = problem.names.index("static_ratio")
    zs = np.tile(x, (len(STATIC_SCAN), 1))
    zs[:, i] = [_to_z("static_ratio", r) for r in STATIC_SCAN]
    costs = np.sum(problem.many(zs) ** 2, axis=1)
    best = int(np.argmin(costs))
    return zs[best] if costs[best] < cost * (1 - 1e-3) else None


def _rms_deg(residuals: np.ndarray) -> float:
    """The RMS of angle residuals (rad), in degrees."""
    return math.degrees(float(np.sqrt(np.mean(residuals**2))))


def gated_sigma(result: Fit, name: str) -> float:
    """The 1-sigma the trust gate compares: relative, and for a damping relative to at least its negligible level
    (:data:`NEGLIGIBLE_DAMPING`)."""
    floor = NEGLIGIBLE_DAMPING.get(name)
    if floor is None or not math.isfinite(result.sigma[name]):
        return result.sigma[name]
    value = result.values[name]
    return result.sigma[name] * value / max(value, floor)


def check(result: Fit, cfg: FitConfig | None = None) -> None:
    """FitRefused (one line) unless the fit is to be trusted (see the module docstring)."""
    cfg = cfg or FitConfig()
    if not result.converged:
        raise FitRefused(f"the fit did not converge ({result.iterations} evaluations in all: {result.message})")
    loose = [f"{k} +-{result.sigma[k]:.0%}" for k in GATED if not gated_sigma(result, k) <= cfg.max_sigma]
    if loose:
        raise FitRefused(f"the fit is too uncertain: {', '.join(loose)} (at most +-{cfg.max_sigma:.0%} trusted): "
                         "the recording does not determine them")
    for k, (lo, hi) in FITTED.items():
        if not lo <= result.values[k] <= hi:
            raise FitRefused(f"the fit put {k} at {result.values[k]:.3g}, outside [{lo:g}, {hi:g}]: no rig this model "
                             "describes")
    if not result.values["static_arm"] <= FITTED["coulomb_arm"][1]:
        raise FitRefused(f"the fit put static_arm at {result.values['static_arm']:.3g}: no rig this model describes")
    if not result.heldout_rms_deg <= cfg.max_heldout_deg:
        raise FitRefused(f"held-out RMS angle error {result.heldout_rms_deg:.2f} deg exceeds "
                         f"{cfg.max_heldout_deg:.1f} deg: the fitted model does not predict the rig")
    if not result.heldout_rms_deg <= cfg.max_heldout_ratio * result.train_rms_deg:
        raise FitRefused(f"held-out RMS angle error {result.heldout_rms_deg:.2f} deg is more than "
                         f"{cfg.max_heldout_ratio:g}x the training error ({result.train_rms_deg:.2f} deg): overfitted")


def to_profile(result: Fit, base: RigProfile, rec: Recording, source: str, name: str | None = None,
               refused: tuple[float, ...] = ()) -> RigProfile:
    """``base`` with the fitted values, no spread (it is one rig), and what it was fitted from; ``refused``: the rig
    seconds of recordings made before ``rec`` whose fits were refused (counted in the rig time)."""
    v = result.values
    delay = max(0.0, min(7.0 - base.action_jitter_ms,
                         v["delay_ms"] - base.sensing_latency_ms - base.action_jitter_ms / 2))
    identified = Identified(
        fitted={k: v[k] for k in (*FITTED, "static_arm") if k != "static_ratio"},
        sigma={k: result.sigma[k] for k in (*FITTED, "static_arm") if k != "static_ratio"},
        train_rms_deg=result.train_rms_deg, heldout_rms_deg=result.heldout_rms_deg,
        rig_seconds=rec.rig_seconds + sum(refused), attempts=1 + len(refused),
        fitted_at=datetime.now(UTC).isoformat(timespec="seconds"), source=source, base=base.name,
        rig=rec.rig, fit_wall_s=result.wall_s)
    data = {**base.model_dump(), "name": name or f"{rec.rig or base.name}-identified",
            "description": f"identified from {source} ({rec.rig_seconds:.0f} s of rig time) over {base.name}",
            "Dr": v["Dr"], "Dp": v["Dp"], "coulomb_arm": v["coulomb_arm"], "static_arm": v["static_arm"],
            "coulomb_pendulum": v["coulomb_pendulum"], "static_pendulum": result.params.Sp,
            "km": v["motor"], "kt": v["motor"], "deadzone_v": v["deadzone_v"],
            "mr": v["mr"], "Lr": v["Lr"], "Lp": v["Lp"], "cable_stiffness": v["cable_stiffness"],
            "action_delay_ms": delay, "spread": 0.0,
            "spread_nonideal": 0.0, "randomize": 0.0, "ranges": {}, "identified": identified.model_dump()}
    return RigProfile.model_validate(data)


def summary(result: Fit) -> str:
    """One line per fitted value with its 1-sigma, then the errors."""
    lines = []
    for k, v in result.values.items():
        if k == "static_ratio":
            continue
        sd = f"+-{result.sigma[k]:.2f} ms" if k == "delay_ms" else f"+-{result.sigma[k]:.1%}"
        lines.append(f"  {k:17s} {v:.4g} {sd}")
    lines.append(f"  RMS angle error: training {result.train_rms_deg:.3f} deg ({result.windows[0]} windows), "
                 f"held out {result.heldout_rms_deg:.3f} deg ({result.windows[1]} windows); {result.iterations} "
                 f"evaluations, {result.wall_s:.1f} s, RK4 in {result.substeps} steps per tick")
    return "\n".join(lines)


def fit_and_write(rec: Recording, base: RigProfile, out: Path, source: str, cfg: FitConfig | None = None,
                  progress: Callable[[str], None] | None = None) -> tuple[Fit, RigProfile]:
    """Fit, check and write the profile (only a trusted one); FitRefused otherwise."""
    result, profile, _ = identify_and_write(lambda _: rec, base, out, source, 1, cfg, progress)
    return result, profile


class IdentifyRefused(FitRefused):
    """Every recording's fit was refused: the last refusal, and the rig seconds of all the recordings."""

    def __init__(self, reason: str, rig_seconds: float) -> None:
        super().__init__(reason)
        self.rig_seconds = rig_seconds


def identify_and_write(record: Callable[[int], Recording], base: RigProfile, out: Path, source: str,
                       attempts: int = IDENTIFY_ATTEMPTS, cfg: FitConfig | None = None,
                       progress: Callable[[str], None] | None = None) -> tuple[Fit, RigProfile, Recording]:
    """Record (``record(attempt)``, IdentifyFailed when the protocol does not finish), fit, and write the profile
    only if trusted; a refused fit is recorded again with the next PRBS sequence, up to ``attempts`` recordings.
    The trusted fit, its profile (with every recording's rig time) and its recording; IdentifyRefused otherwise."""
    refused: list[float] = []
    last = FitRefused("no recording")
    for rec, result, refusal in fit_attempts(record, base, attempts, cfg, progress):
        if refusal is None and result is not None:
            profile = to_profile(result, base, rec, source, refused=tuple(refused))
            out.write_text(profile.to_json())
            return result, profile, rec
        last = refusal or last
        refused.append(rec.rig_seconds)
        if len(refused) < attempts and progress is not None:
            progress(f"refused: {last}; recording again with PRBS sequence {len(refused)} "
                     f"(attempt {len(refused) + 1} of {attempts})")
    tried = f" ({len(refused)} recordings, each refused)" if len(refused) > 1 else ""
    raise IdentifyRefused(f"{last}{tried}", sum(refused))


def fit_attempts(record: Callable[[int], Recording], base: RigProfile, attempts: int, cfg: FitConfig | None = None,
                 progress: Callable[[str], None] | None = None,
                 ) -> Iterator[tuple[Recording, Fit | None, FitRefused | None]]:
    """The retry policy of every identification: record (``record(attempt)``) and fit until a fit is trusted or
    ``attempts`` recordings are made; each recording with its fit (None: none could be made) and its refusal (None:
    trusted, the last one yielded)."""
    for attempt in range(attempts):
        rec = record(attempt)
        try:
            result = fit(rec, base, cfg, progress)
        except FitRefused as err:
            yield rec, None, err
            continue
        if progress is not None:
            progress(summary(result))
        try:
            check(result, cfg)
        except FitRefused as err:
            yield rec, result, err
            continue
        yield rec, result, None
        return


def record_simulated(truth: RigProfile, seed: int, control: ControlConfig | None = None,
                     progress: Callable[[str], None] | None = None, rig: str = "",
                     faults: dict[str, bool] | None = None, attempt: int = 0) -> Recording:
    """The identification recording of simulated rig ``seed`` of ``truth``: the bridge's ControlCore (start-up checks
    and the protocol; ``attempt``: its PRBS sequence) over a SimulatedQube on a virtual clock, lockstep. ``faults``:
    SimulatedQube's wiring faults. IdentifyFailed when it does not finish."""
    clock = VirtualClock()
    options: dict[str, Any] = {**truth.device_options(), **(faults or {})}
    device = SimulatedQube(truth.rig_params(seed), seed=seed, period_s=0, clock=clock, **options)
    core = ControlCore(device, control or ControlConfig(), clock=clock)
    recording = drive(core, lambda: clock.advance(core.cfg.period_s), progress=progress, attempt=attempt)
    return recording.model_copy(update={"rig": rig or f"{truth.name}-seed{seed}"})


def identify_to_file(record: Callable[[int], Recording], base: RigProfile, out: Path, source: str, prog: str,
                     attempts: int = IDENTIFY_ATTEMPTS, hint: str = "") -> int:
    """The host's end of every identification command: :func:`identify_and_write` with progress; 0 with the line
    that says what was written, or 1 with one line naming ``prog`` (the protocol failed, every fit refused: then
    ``hint``, the file unwritable)."""
    try:
        result, profile, _ = identify_and_write(record, base, out, source, attempts,
                                                progress=lambda line: print(line, flush=True))
    except IdentifyFailed as err:
        print(f"{prog}: identification failed: {err}", file=sys.stderr)
        return 1
    except FitRefused as err:
        print(f"{prog}: refused: {err}{hint}", file=sys.stderr)
        return 1
    except OSError as err:
        print(f"{prog}: cannot write {out}: {err}", file=sys.stderr)
        return 1
    ident = profile.identified
    assert ident is not None
    tried = f" in {ident.attempts} recordings" if ident.attempts > 1 else ""
    print(f"identify: wrote {out}: profile {profile.name!r} from {ident.rig_seconds:.1f} s of rig time{tried}, "
          f"fit {result.wall_s:.1f} s")
    return 0


def identify_simulated(truth: RigProfile, seed: int, control: ControlConfig, base: RigProfile, out: Path,
                       faults: dict[str, bool] | None = None, attempts: int = IDENTIFY_ATTEMPTS) -> int:
    """``python -m services.qube_sim --identify OUT``: record simulated rig ``seed`` of ``truth`` (its truth only
    simulates), fit over ``base``, write a trusted profile to ``out`` (recorded again on a refusal, up to
    ``attempts`` recordings). 0, or 1 with one line."""

    def record(attempt: int) -> Recording:
        began = time.perf_counter()
        rec = record_simulated(truth, seed, control, progress=lambda seg: print(f"identify: segment {seg}", flush=True),
                               faults=faults, attempt=attempt)
        print(f"identify: recorded {rec.rig_seconds:.1f} s of rig time ({len(rec.t)} ticks) in "
              f"{time.perf_counter() - began:.1f} s; fitting over {base.name}", flush=True)
        return rec

    return identify_to_file(record, base, out, f"simulated rig {truth.name}-seed{seed}", "qube_sim", attempts)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.qube_sim.identify",
                                     description="Fit a rig profile to a bridge's identification recording "
                                                 "(python -m rpi_bridge --identify OUT); writes it only if trusted.")
    parser.add_argument("recording", type=Path)
    parser.add_argument("--out", type=Path, required=True, help="the profile JSON to write")
    parser.add_argument("--base", default="lab", help="profile of everything not fitted (built-in name or file)")
    args = parser.parse_args(argv)
    try:
        base = load_profile(args.base)
        rec = Recording.load(args.recording)
    except (ProfileError, RecordingError) as err:
        print(f"identify: {err}", file=sys.stderr)
        return 2
    following = int(rec.config.get("seed", IdentifyConfig.seed))  # attempt n records PRBS sequence seed + n
    hint = (f"; record the rig again with another PRBS sequence (python -m rpi_bridge --identify OUT "
            f"--identify-attempt {following}) and fit that")
    return identify_to_file(lambda _: rec, base, args.out, str(args.recording), "identify", 1, hint)


if __name__ == "__main__":
    sys.exit(main())
