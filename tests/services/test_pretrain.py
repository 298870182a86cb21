"""services/qube_sim/pretrain.py: a pretrain's randomisation centred on the identified rigs, with every rig inside
its ranges and tails at least +-30 % (or 3 sigma of the fit) beyond them."""

from __future__ import annotations

import pytest

from services.qube_sim import families
from services.qube_sim.pretrain import (
    AUTHORITY,
    FLOOR,
    FLOOR_CABLE,
    FLOOR_INERTIAL,
    INERTIAL,
    RANDOMISED,
    around,
    breakaway_share,
    cap_breakaway,
    for_lab,
)
from services.qube_sim.profile import LAB, Identified, RigProfile


def identified(profile: RigProfile, sigma: float = 0.02, **changes: float) -> RigProfile:
    record = Identified(fitted={k: 1.0 for k in RANDOMISED}, sigma={k: sigma for k in RANDOMISED},
                        train_rms_deg=0.3, heldout_rms_deg=0.4, rig_seconds=120.0, fitted_at="2026-12-04T00:00:00")
    return RigProfile.model_validate({**profile.model_dump(), **changes, "identified": record.model_dump(),
                                      "spread": 0.0, "spread_nonideal": 0.0})


def test_every_identified_rig_lies_inside_the_pretrains_ranges_with_wide_tails() -> None:
    rigs = [identified(families.combined()), identified(families.course(), sigma=0.3), identified(LAB)]
    profile = around(rigs)
    assert profile.randomize == 0.2 and profile.spread == 0 and profile.identified is None
    for fitted, (field, key) in RANDOMISED.items():
        lo, hi = profile.ranges[key]
        scale = profile.km if key == "motor" else 1.0
        values = [getattr(r, field) / scale for r in rigs]
        floor = FLOOR_INERTIAL if fitted in INERTIAL else FLOOR_CABLE if fitted == "cable_stiffness" else FLOOR
        assert lo <= min(values) * (1 - floor) + 1e-12 and hi >= max(values) * (1 + floor) - 1e-12, fitted
    # the course rig's fit is uncertain (30 %): its damping's range reaches 3 sigma, 90 %, beyond it
    assert profile.ranges["Dr"][1] == pytest.approx(families.course().Dr * 1.9)
    # the nominal plant is the median rig, and static friction never falls below Coulomb
    assert profile.Dp == sorted(r.Dp for r in rigs)[1]
    assert profile.static_arm >= profile.coulomb_arm and profile.static_pendulum >= profile.coulomb_pendulum
    drawn = [profile.episode_params(1, episode) for episode in range(200)]
    assert all(d is not None and profile.ranges["Dp"][0] <= d.Dp <= profile.ranges["Dp"][1] for d in drawn)


def test_only_identified_rigs_are_taken() -> None:
    with pytest.raises(ValueError, match="at least one identified rig"):
        around([])
    with pytest.raises(ValueError, match=r"not identified .*: lab"):
        around([LAB])


def test_a_lab_pretrain_never_draws_an_arm_the_actions_cannot_break_away() -> None:
    """A sticky lab rig's 1.3x tail reaches past the paper's actions' standstill torque: cut at AUTHORITY of it, for
    the nominal values and the ranges (the rest of the profile as :func:`around` made it); the stronger action set
    leaves the same rigs' ranges alone."""
    sticky = identified(LAB, static_arm=5.5e-3, coulomb_arm=4.5e-3)
    rigs = [identified(LAB), sticky]
    plain = around(rigs)
    torque = breakaway_share(plain, "paper")[1]
    assert plain.ranges["static_arm"][1] == pytest.approx(5.5e-3 * (1 + FLOOR))  # the tail: above the torque
    assert plain.ranges["static_arm"][1] > torque
    capped = for_lab(rigs, "paper", ease_in=0)
    most = AUTHORITY * torque
    assert capped.ranges["static_arm"] == (plain.ranges["static_arm"][0], pytest.approx(most))
    assert capped.ranges["coulomb_arm"] == (plain.ranges["coulomb_arm"][0],
                                            pytest.approx(min(most, plain.ranges["coulomb_arm"][1])))
    assert capped.model_dump(exclude={"ranges"}) == plain.model_dump(exclude={"ranges"})
    assert {k: v for k, v in capped.ranges.items() if not k.endswith("_arm")} == {
        k: v for k, v in plain.ranges.items() if not k.endswith("_arm")}
    drawn = [capped.episode_params(1, episode) for episode in range(200)]
    assert all(d is not None and d.Sr <= most and d.Cr <= most for d in drawn)
    assert for_lab(rigs, "levels", ease_in=0) == plain  # 150 counts: the same tail is far below the torque
    stickier = identified(LAB, static_arm=6.8e-3, coulomb_arm=4.5e-3)  # itself above 90 % of the median's torque
    kept = for_lab([identified(LAB), stickier], "paper")
    assert kept.ranges["static_arm"][1] == pytest.approx(6.8e-3)  # cut at the rig, never below it
    assert kept.ranges["static_arm"][1] > AUTHORITY * breakaway_share(kept, "paper")[1]


def test_ease_in_eases_only_the_arms_dry_friction_in_and_keeps_the_ranges() -> None:
    rigs = [identified(LAB), identified(LAB, static_arm=5.5e-3, coulomb_arm=4.5e-3)]
    plain, eased = for_lab(rigs, "paper", ease_in=0), for_lab(rigs, "paper", ease_in=150)
    assert plain.curriculum == {} and eased.curriculum == {"static_arm": 150, "coulomb_arm": 150}
    assert eased.model_dump(exclude={"curriculum"}) == plain.model_dump(exclude={"curriculum"})
    lo = plain.ranges["coulomb_arm"][0]
    first = [eased.episode_params(seed, 1) for seed in range(20)]
    assert all(p is not None and p.Cr <= lo + (plain.ranges["coulomb_arm"][1] - lo) / 150 for p in first)


def test_the_cap_holds_nominal_values_too_and_is_positive() -> None:
    profile = cap_breakaway(LAB, 1e-3)  # below lab's own friction: nominal values cut as well, ranges degenerate
    assert (profile.static_arm, profile.coulomb_arm) == (1e-3, 1e-3)
    assert profile.ranges["static_arm"] == (1e-3, 1e-3)
    with pytest.raises(ValueError, match="must be positive"):
        cap_breakaway(LAB, 0.0)
