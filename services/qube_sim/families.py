"""Rig families outside ``lab``: how far a lab's QUBE-Servo 2 may differ from our profile, as profiles.

The published record leaves the values that decide control unknown to 10-500x (docs/rig-profiles.md): pendulum
damping from 1e-6 to 5e-4 N m s/rad, arm damping from 5e-6 to 1.5e-3, and no source for arm friction. The
out-of-distribution sweep varies one parameter at a time around ``lab`` (in RealAIGym's style: the controller keeps
what it was trained on), the combined family changes several at once, and ``course`` is the damping of Quanser's own
course files. Every benchmark and test of rigs outside ``lab`` takes its rigs from here.
"""

from __future__ import annotations

from collections.abc import Callable

from services.qube_sim.profile import LAB, RigProfile

#: The sweep: parameter -> factors on ``lab``'s value (``loop_delay``: the delay in control periods, fixed).
SWEEPS: dict[str, tuple[float, ...]] = {
    "arm_friction": (0.5, 1.0, 1.7, 2.5, 3.0),
    "Dp": (0.1, 1.0, 2.5, 5.0, 10.0),
    "Dr": (0.2, 1.0, 1.8, 3.5, 6.0),
    "arm_inertia": (1.0, 1.5, 2.0, 3.0, 4.0),
    "motor": (0.8, 0.9, 1.0, 1.1, 1.2),
    "loop_delay": (0.0, 0.25, 0.5, 0.75, 1.0),
}
PERIOD_MS = 7.0


def _arm_friction(p: RigProfile, k: float) -> dict[str, float]:
    return {"coulomb_arm": p.coulomb_arm * k, "static_arm": p.static_arm * k}


def _arm_inertia(p: RigProfile, k: float) -> dict[str, float]:
    # Jr = mr Lr^2 / 12 and mr appears nowhere else in the equations of motion: k x the arm's mass is k x its inertia
    return {"mr": p.mr * k}


def _loop_delay(p: RigProfile, k: float) -> dict[str, object]:
    return {"loop_delay_ms": (k * PERIOD_MS, k * PERIOD_MS)}


CHANGES: dict[str, Callable[[RigProfile, float], dict[str, object]]] = {
    "arm_friction": _arm_friction,  # type: ignore[dict-item]
    "Dp": lambda p, k: {"Dp": p.Dp * k},
    "Dr": lambda p, k: {"Dr": p.Dr * k},
    "arm_inertia": _arm_inertia,  # type: ignore[dict-item]
    "motor": lambda p, k: {"km": p.km * k, "kt": p.kt * k},
    "loop_delay": _loop_delay,
}


def family(parameter: str, factor: float, base: RigProfile = LAB) -> RigProfile:
    """``base`` with one parameter scaled by ``factor`` (see :data:`SWEEPS`), named e.g. ``lab-Dp-x2.5``."""
    if parameter not in CHANGES:
        raise ValueError(f"unknown sweep parameter {parameter!r}; one of {', '.join(CHANGES)}")
    changes = CHANGES[parameter](base, factor)
    unit = " periods" if parameter == "loop_delay" else "x"
    return _checked(base, {**changes, "name": f"{base.name}-{parameter}-x{factor:g}",
                                   "description": f"{base.name} with {parameter} at {factor:g}{unit}"})


def combined(base: RigProfile = LAB) -> RigProfile:
    """The combined family: ``lab`` with the pendulum's damping 2.5x, the arm's 1.8x, every dry friction 1.7x, the
    motor gain 0.9x, the cable 1.5x and the rig's delays 1.3x (the loop's delay stays within its 7 ms period)."""
    lo, hi = base.loop_delay_ms
    changes = {
        "Dp": base.Dp * 2.5, "Dr": base.Dr * 1.8,
        "coulomb_arm": base.coulomb_arm * 1.7, "static_arm": base.static_arm * 1.7,
        "coulomb_pendulum": base.coulomb_pendulum * 1.7, "static_pendulum": base.static_pendulum * 1.7,
        "km": base.km * 0.9, "kt": base.kt * 0.9, "cable_stiffness": base.cable_stiffness * 1.5,
        "sensing_latency_ms": base.sensing_latency_ms * 1.3, "action_delay_ms": base.action_delay_ms * 1.3,
        "action_jitter_ms": base.action_jitter_ms * 1.3,
        "loop_delay_ms": (min(PERIOD_MS, lo * 1.3), min(PERIOD_MS, hi * 1.3)),
    }
    return _checked(base, {**changes, "name": f"{base.name}-combined",
                                   "description": "lab with Dp 2.5x, Dr 1.8x, dry friction 1.7x, motor gain 0.9x, "
                                                  "cable 1.5x, delays 1.3x"})


def course(base: RigProfile = LAB) -> RigProfile:
    """``lab`` with the damping of Quanser's course files (Dr 1.5e-3, Dp 5e-4 N m s/rad)."""
    return _checked(base, {"Dr": 1.5e-3, "Dp": 5e-4, "name": f"{base.name}-course",
                                   "description": "lab with Quanser's course-file damping (Dr 1.5e-3, Dp 5e-4)"})


def sweep(base: RigProfile = LAB) -> list[tuple[str, float, RigProfile]]:
    """Every (parameter, factor, profile) of the sweep, in :data:`SWEEPS`'s order."""
    return [(name, k, family(name, k, base)) for name, factors in SWEEPS.items() for k in factors]


def _checked(base: RigProfile, changes: dict[str, object]) -> RigProfile:
    """``base`` with ``changes``, through the model's own validators."""
    return RigProfile.model_validate({**base.model_dump(), **changes})
