"""bench.unidentified's variants: an identified rig's profile with exactly one group of values set to the rig's truth
(km and kt together, the delays from the truth's profile), and no identification record."""

from __future__ import annotations

import json

import pytest

from bench.unidentified import GROUPS, variant
from services.qube_sim import families
from services.qube_sim.profile import LAB, Identified, RigProfile


def identified_rig() -> RigProfile:
    record = Identified(fitted={"Dr": 1.0}, sigma={"Dr": 0.01}, train_rms_deg=0.3, heldout_rms_deg=0.4,
                        rig_seconds=80.0, fitted_at="2026-12-06T00:00:00")
    return RigProfile.model_validate({**LAB.model_dump(), "spread": 0.0, "spread_nonideal": 0.0,
                                      "identified": record.model_dump()})


@pytest.mark.parametrize("group", list(GROUPS))
def test_a_variant_takes_one_groups_values_from_the_truth_and_keeps_the_rest(group: str) -> None:
    rig = identified_rig()
    data = json.loads(rig.to_json())
    truth_profile = families.combined()
    truth = truth_profile.rig_params(532001)
    out = RigProfile.model_validate(variant(data, truth, truth_profile, GROUPS[group]))
    assert out.identified is None
    changed = {k for k, v in out.model_dump().items() if v != getattr(rig, k) and k != "identified"}
    expected = set(GROUPS[group]) | ({"kt"} if "km" in GROUPS[group] else set())
    assert changed <= expected and changed, (group, changed)
    if group == "cable":
        assert out.cable_stiffness == truth.cable_stiffness != rig.cable_stiffness
    if group == "delays":
        assert out.action_delay_ms == truth_profile.action_delay_ms
    assert RigProfile.model_validate(variant(data, truth, truth_profile, ())).model_dump() == {
        **rig.model_dump(), "identified": None}
