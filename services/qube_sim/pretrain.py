"""A pretrain's rigs centred on a lab's identified rigs, with ranges from what the fit could not pin down.

A controller pretrained in simulation holds on the real rigs only if their physics lies inside what it was
randomised over. Randomising ±20 % around ``lab`` does not cover a lab whose rigs differ from ``lab`` by 2-10x. So
the pretrain randomises around the rigs as identified (services/qube_sim/identify.py): its nominal plant is the
median of the identified rigs, and each fitted parameter is drawn at every reset from a range that spans every rig
and reaches ``sigmas`` standard deviations of its fit beyond it, never less than ``floor`` (±30 % for damping, friction
and deadzone: wider tails than the ±20 % of before; ±10 % for masses, lengths and motor gain), because a fit is made
from a few minutes of one rig's motion and a rig drifts (warm-up, wear).
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Sequence

from protocol.qube import action_set
from rpi_bridge.frame import VOLTS_PER_COUNT
from services.qube_sim.profile import RigProfile

#: Identified name (Identified.fitted) -> the profile field of its value and the ``ranges`` key it is drawn under.
RANDOMISED: dict[str, tuple[str, str]] = {
    "Dr": ("Dr", "Dr"), "Dp": ("Dp", "Dp"), "mr": ("mr", "mr"), "Lr": ("Lr", "Lr"), "Lp": ("Lp", "Lp"),
    "coulomb_arm": ("coulomb_arm", "coulomb_arm"), "static_arm": ("static_arm", "static_arm"),
    "coulomb_pendulum": ("coulomb_pendulum", "coulomb_pendulum"), "deadzone_v": ("deadzone_v", "deadzone_v"),
    "motor": ("km", "motor"), "cable_stiffness": ("cable_stiffness", "cable_stiffness"),
}
#: The least half-width of a range, relative to the value (a fit that claims more precision is not believed): wide for
#: what dissipates energy (damping, dry friction, deadzone), which a few minutes of one rig pin down least and which
#: drifts with temperature and wear; narrower for the masses, lengths and motor gain, which the fit pins down to a few
#: per cent and which the reset's model must match for the pretrain's rigs to swing up.
FLOOR = 0.3
FLOOR_INERTIAL = 0.1
INERTIAL = frozenset({"mr", "Lr", "Lp", "motor"})
#: ... and for the encoder cable's stiffness, whose pull on the arm (a few tenths of a mN m over the arm's travel) a
#: recording pins down least: 0.87-1.13x the truth's on eleven tuning rigs (bench/results/identify-cable-tune.json),
#: 0.73x on the combined rig of tests/services/test_identify.py, each fit claiming a 1-sigma of 0.4-10 %.
FLOOR_CABLE = 0.5
#: A range reaches this many of the fit's standard deviations beyond the rigs' values.
SIGMAS = 3.0
#: The ranges of the arm's dry friction (what decides whether the actions move the arm at all).
ARM_FRICTION = ("static_arm", "coulomb_arm")
#: Episodes over which a lab's pretrain eases the arm's dry friction in (for_lab's ``ease_in``). Drawn from the whole
#: range from the first episode, a sticky draw teaches nothing (the arm hardly moves), and a lab whose draws hold
#: many of them can stall every worker before one learns to balance: bench.pretrain_tune's tuning labs 705 (no TC in
#: 600 episodes) and 532 (its first attempt, none in 600 in the lab of 2026-12-06) met TC by their 214th and 205th
#: episode eased in over 150 (docs/how-to/lab.md, "When a pretrain misses TC").
EASE_IN = 150
#: Every randomisable parameter not identified is drawn from ± this fraction of the nominal value.
REST = 0.2
#: The largest share of the actions' standstill torque (on the median identified rig) that a pretrain rig's arm
#: breakaway may take. Above it the arm barely moves under the actions, no controller balances the rig, and such draws
#: among the others keep the mean of the last 10 returns below TC: the pretrain never meets it. A tail that reaches
#: past it (a sticky lab rig's 1.3x) is cut there.
AUTHORITY = 0.9


def around(rigs: Sequence[RigProfile], floor: float = FLOOR, sigmas: float = SIGMAS, rest: float = REST,
           name: str = "identified-rigs") -> RigProfile:
    """The pretrain profile of ``rigs`` (identified profiles, ``RigProfile.identified`` set): the median rig, each
    identified parameter drawn per episode from [min_i v_i (1 - w_i), max_i v_i (1 + w_i)] with w_i = max(floor,
    sigmas * sigma_i) (sigma_i: the fit's relative 1-sigma of rig i's value; the floor of the masses, lengths and motor
    gain is ``FLOOR_INERTIAL``), the rest from ± ``rest``. A
    ValueError for no rigs, or for a profile that was not identified."""
    if not rigs:
        raise ValueError("a pretrain around identified rigs needs at least one identified rig profile")
    missing = [r.name for r in rigs if r.identified is None]
    if missing:
        raise ValueError(f"not identified (no 'identified' record): {', '.join(missing)}")
    if not 0 < floor < 1 or sigmas < 0 or not 0 <= rest <= 0.5:
        raise ValueError("need 0 < floor < 1, sigmas >= 0 and 0 <= rest <= 0.5")
    fields = sorted({field for field, _ in RANDOMISED.values()} | {"kt", "static_pendulum", "action_delay_ms"})
    nominal = {f: statistics.median(getattr(r, f) for r in rigs) for f in fields}
    for static, coulomb in (("static_arm", "coulomb_arm"), ("static_pendulum", "coulomb_pendulum")):
        nominal[static] = max(nominal[static], nominal[coulomb])  # medians of each need not keep the order
    ranges: dict[str, tuple[float, float]] = {}
    for fitted, (field, key) in RANDOMISED.items():
        lo, hi = [], []
        for rig in rigs:
            assert rig.identified is not None
            value = getattr(rig, field)
            least = min(floor, FLOOR_INERTIAL) if fitted in INERTIAL else floor
            if fitted == "cable_stiffness":
                least = max(least, FLOOR_CABLE)
            width = max(least, sigmas * rig.identified.sigma.get(fitted, 0.0))
            lo.append(max(0.0, value * (1 - width)))
            hi.append(value * (1 + width))
        scale = nominal["km"] if key == "motor" else 1.0  # 'motor' is a factor on the nominal km and kt
        ranges[key] = (min(lo) / scale, max(hi) / scale)
    names = ", ".join(r.name for r in rigs)
    data = {**rigs[0].model_dump(), **nominal, "name": name[:64], "identified": None,
            "description": f"randomised around {len(rigs)} identified rigs ({names})"[:2000],
            "spread": 0.0, "spread_nonideal": 0.0, "randomize": rest, "ranges": ranges}
    return RigProfile.model_validate(data)


def breakaway_share(profile: RigProfile, actions: str | None) -> tuple[float, float]:
    """The arm's breakaway torque (its static dry friction) as a share of the largest torque the action set
    ``actions`` gives at standstill on ``profile``'s nominal rig (deadzone and offset included), and that torque
    (N m). What is left over the share is the balancing controller's authority: the paper's three actions have little
    of it on a sticky arm."""
    from services.qube_sim.dynamics import motor_torque

    p = profile.params()
    torque = abs(motor_torque(p, action_set(actions).limit * VOLTS_PER_COUNT, 0.0))
    return (p.Sr / torque if torque > 0 else math.inf), torque


def for_lab(rigs: Sequence[RigProfile], actions: str | None, name: str = "identified-rigs",
            authority: float = AUTHORITY, ease_in: int = EASE_IN) -> RigProfile:
    """The pretrain profile of a lab's identified ``rigs`` under the action set ``actions``: :func:`around` them, its
    arm friction capped at ``authority`` x the actions' standstill torque on the median rig (:func:`cap_breakaway`),
    but never below an identified rig's own: the pretrain keeps every rig the controller must hold. With ``ease_in``
    N > 0 the arm's dry friction is eased in over each worker's first N episodes (RigProfile.curriculum): drawn from
    the bottom of its range at first, from all of it from episode N on."""
    profile = around(rigs, name=name)
    own = max(max(r.static_arm, r.coulomb_arm) for r in rigs)
    profile = cap_breakaway(profile, max(authority * breakaway_share(profile, actions)[1], own))
    if ease_in <= 0:
        return profile
    return RigProfile.model_validate({**profile.model_dump(), "curriculum": {key: ease_in for key in ARM_FRICTION}})


def cap_breakaway(profile: RigProfile, most: float) -> RigProfile:
    """``profile`` with the arm's dry friction (static and Coulomb) drawn no higher than ``most`` (N m), nor its
    nominal values: a pretrain rig whose arm the actions cannot break away teaches nothing (no controller balances
    it) and, drawn at random among the others, keeps the mean of the last 10 returns below TC. A ValueError for a cap
    that is not positive."""
    if not most > 0:
        raise ValueError(f"the arm's breakaway cap must be positive, not {most}")
    ranges = dict(profile.ranges)
    for key in ARM_FRICTION:
        lo, hi = ranges.get(key, (getattr(profile, key) * (1 - profile.randomize),
                                  getattr(profile, key) * (1 + profile.randomize)))
        ranges[key] = (min(lo, most), min(hi, most))
    return RigProfile.model_validate({**profile.model_dump(), "ranges": ranges,
                                      "static_arm": min(profile.static_arm, most),
                                      "coulomb_arm": min(profile.coulomb_arm, most)})
