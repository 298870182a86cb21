"""bench.identify compares each fitted value with the rig's truth as the simulator uses it."""

from __future__ import annotations

from dataclasses import replace

from bench.identify import true_value
from services.qube_sim.dynamics import QubeParams


def test_the_arm_s_breakaway_is_its_static_friction_or_its_coulomb_friction_when_flat() -> None:
    """A spread that draws static friction below Coulomb friction leaves the arm's friction flat at the Coulomb
    level (services/qube_sim/dynamics.py friction): that is the breakaway a fit's static_arm is compared with."""
    sticky = replace(QubeParams(), Cr=2e-3, Sr=3e-3)
    flat = replace(sticky, Sr=1.5e-3)
    assert true_value("static_arm", sticky) == 3e-3 and true_value("static_arm", flat) == 2e-3
    assert true_value("coulomb_arm", flat) == 2e-3 and true_value("Dr", flat) == flat.Dr
