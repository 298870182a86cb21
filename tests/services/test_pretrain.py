"""services/qube_sim/pretrain.py: a pretrain's randomisation centred on the identified rigs, with every rig inside
its ranges and tails at least +-30 % (or 3 sigma of the fit) beyond them."""

from __future__ import annotations

import pytest

from services.qube_sim import families
from services.qube_sim.pretrain import FLOOR, FLOOR_INERTIAL, INERTIAL, RANDOMISED, around
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
        floor = FLOOR_INERTIAL if fitted in INERTIAL else FLOOR
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
