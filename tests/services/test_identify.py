"""The host's fit (services/qube_sim/identify.py): the vectorised equations of motion equal the scalar ones; the fit
recovers Dp, Dr, the arm's Coulomb friction and the motor gain within 20 % (the issue's target) from simulated rigs
without spread on ``lab`` (from the ``course`` profile's damping, 5.6x and 10x off, as its start) and on the combined
family (over ``lab``, through ``python -m services.qube_sim.identify``); a recording of a rig that did not move is
refused and writes nothing, and a refused recording is made again; ``python -m services.qube_sim --identify`` exits
1 with one line on a rig whose start-up checks fail and 2 on a bad base profile. Recordings: one shortened protocol
per rig, made once for the module."""

from __future__ import annotations

import math
import random
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from rpi_bridge.control import ControlConfig
from rpi_bridge.identify import IdentifyConfig, Recording
from services.qube_sim import families
from services.qube_sim.dynamics import (
    QubeParams,
    derivatives,
    derivatives_array,
    friction,
    friction_array,
    motor_torque,
    motor_torque_array,
)
from services.qube_sim.identify import FitRefused, fit, fit_and_write, record_simulated
from services.qube_sim.pretrain import FLOOR_CABLE
from services.qube_sim.profile import LAB, RigProfile, load_profile
from tests.paths import ROOT

#: The bridge's protocol (about 80 s of rig time).
CONFIG = IdentifyConfig()
TARGET = {"Dp": "Dp", "Dr": "Dr", "coulomb_arm": "Cr", "motor": "km"}
#: A rig of the combined family (tuning seed 527: its spread drew the arm's static friction below its Coulomb
#: friction, 0.84x, so its friction is flat, a static/Coulomb ratio of 1 where lab's is 1.33).
FLAT_RIG = 527002
pytestmark = pytest.mark.xdist_group("test_identify")  # its module fixture is made once, in one test process


def exact(profile: RigProfile) -> RigProfile:
    return profile.model_copy(update={"spread": 0.0, "spread_nonideal": 0.0})


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("recordings")
    out = {}
    for name, truth in (("lab", exact(LAB)), ("combined", exact(families.combined()))):
        out[name] = folder / f"{name}.json.gz"
        record_simulated(truth, 11, ControlConfig(identify=CONFIG)).save(out[name])
    out["flat"] = folder / "flat.json.gz"  # a combined rig with its spread, whose arm's friction is flat
    record_simulated(families.combined(), FLAT_RIG, ControlConfig(identify=CONFIG)).save(out["flat"])
    return out


def test_the_vectorised_dynamics_equal_the_scalar_ones() -> None:
    rng = random.Random(5)
    for p in (QubeParams(), families.combined().rig_params(3), QubeParams(voltage_offset=-0.3, deadzone=0.4, Sr=0.0)):
        states = [(rng.uniform(-8, 8), rng.uniform(-4, 4), rng.uniform(-15, 15), rng.uniform(-6, 6)) for _ in range(50)]
        states += [(0.0, math.pi, 0.0, 0.0), (1e-3, 0.1, -1e-3, 0.0)]
        theta_dot, alpha, alpha_dot, volts = (np.array([s[i] for s in states]) for i in range(4))
        tau = motor_torque_array(p, volts, theta_dot)
        tdd, add = derivatives_array(p, theta_dot, alpha, alpha_dot, tau)
        fa = friction_array(p.Cr, p.Sr, theta_dot, p)
        for i, (td, a, ad, v) in enumerate(states):
            t = motor_torque(p, v, td)
            assert tau[i] == pytest.approx(t, rel=1e-12, abs=1e-15)
            assert (tdd[i], add[i]) == pytest.approx(derivatives(p, td, a, ad, t), rel=1e-10, abs=1e-10)
            assert fa[i] == pytest.approx(friction(p.Cr, p.Sr, td, p), rel=1e-12, abs=1e-15)


def errors(values: dict[str, float], truth: QubeParams) -> dict[str, float]:
    return {name: values[name] / getattr(truth, field) - 1 for name, field in TARGET.items()}


def still(moved: Recording) -> Recording:
    """``moved`` as if the rig had not moved (its fit is refused at once)."""
    return moved.model_copy(update={"theta": [0.0] * len(moved.t), "alpha": [math.pi - 1e-3] * len(moved.t)})


def test_a_refused_recording_is_made_again_and_the_fit_recovers_lab_from_a_start_far_off(
        recordings: dict[str, Path], tmp_path: Path) -> None:
    """The first recording's fit is refused: the rig is recorded again with the next PRBS sequence (attempt 1), and
    the profile counts both recordings' rig time. That fit starts from the course files' damping (Dr 5.6x, Dp 10x
    lab's) and recovers lab's. With one attempt, the refusal is final: IdentifyRefused with the rig time spent."""
    from services.qube_sim.identify import IdentifyRefused, identify_and_write

    lab = Recording.load(recordings["lab"])
    asked: list[int] = []

    def record(attempt: int) -> Recording:
        asked.append(attempt)
        return still(lab) if attempt == 0 else lab

    said: list[str] = []
    out = tmp_path / "p.json"
    result, profile, rec = identify_and_write(record, families.course(), out, "test", progress=said.append)
    assert asked == [0, 1] and rec is lab and any("recording again with PRBS sequence 1" in s for s in said)
    off = errors(result.values, LAB.params())
    assert result.converged and all(abs(e) < 0.2 for e in off.values()), off
    assert result.heldout_rms_deg < 1.0
    assert profile.identified is not None and profile.identified.attempts == 2
    assert profile.identified.rig_seconds == pytest.approx(2 * lab.rig_seconds)
    assert load_profile(out) == profile

    asked.clear()
    with pytest.raises(IdentifyRefused, match=r"the arm moved 0\.0 deg") as refused:
        identify_and_write(record, LAB, tmp_path / "q.json", "test", attempts=1)
    assert asked == [0] and refused.value.rig_seconds == lab.rig_seconds and not (tmp_path / "q.json").exists()


def test_the_command_line_fit_recovers_the_combined_family(recordings: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "combined.json"
    done = subprocess.run([sys.executable, "-m", "services.qube_sim.identify", str(recordings["combined"]),
                           "--out", str(out), "--base", "lab"], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert done.returncode == 0, done.stderr
    profile = load_profile(out)
    assert profile.identified is not None and profile.identified.rig_seconds == pytest.approx(
        Recording.load(recordings["combined"]).rig_seconds)
    off = errors(profile.identified.fitted, families.combined().params())
    assert all(abs(e) < 0.2 for e in off.values()), off
    assert profile.Dp == profile.identified.fitted["Dp"] and profile.spread == 0
    assert "held out" in done.stdout
    # the encoder cable's pull on the arm, 1.5x the base's on this family (a pretrained controller that never saw it
    # fell on such rigs: docs/how-to/identify.md): the fit moves towards it from the base, to within the pretrain's
    # floor of its range (this recording: 0.73x, the furthest off of six recordings of this rig)
    truth = families.combined().cable_stiffness
    assert truth == pytest.approx(1.5 * LAB.cable_stiffness)
    assert abs(profile.cable_stiffness / truth - 1) < min(FLOOR_CABLE, abs(LAB.cable_stiffness / truth - 1))


def test_a_static_friction_far_from_the_bases_is_found_by_the_scan(recordings: dict[str, Path]) -> None:
    """Static friction acts only at rest: the least-squares steps stall near the base's static/Coulomb ratio (lab's
    1.33), and the scan of the ratio moves the fit to the truth's (without it, this rig's static friction came out
    1.38x the truth's; with it 1.03x)."""
    said: list[str] = []
    truth = families.combined().rig_params(FLAT_RIG)
    result = fit(Recording.load(recordings["flat"]), LAB, progress=said.append)
    assert any("(scan): fitting again from there" in line for line in said)
    assert result.values["static_arm"] / max(truth.Sr, truth.Cr) == pytest.approx(1.0, abs=0.1)
    off = errors(result.values, truth)
    assert all(abs(e) < 0.2 for e in off.values()), off


def test_a_rig_that_did_not_move_is_refused_and_nothing_is_written(recordings: dict[str, Path],
                                                                   tmp_path: Path) -> None:
    rec = still(Recording.load(recordings["lab"]))
    out = tmp_path / "p.json"
    with pytest.raises(FitRefused, match=r"the arm moved 0\.0 deg"):
        fit_and_write(rec, LAB, out, "still")
    assert not out.exists()
    path = tmp_path / "still.json"
    rec.save(path)
    done = subprocess.run([sys.executable, "-m", "services.qube_sim.identify", str(path), "--out", str(out)],
                          capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert done.returncode == 1 and done.stderr.count("\n") == 1 and "refused" in done.stderr
    assert "--identify-attempt 1" in done.stderr  # a recording of PRBS sequence 1: record sequence 2 next
    assert not out.exists()


def test_a_fit_that_does_not_converge_is_refused(recordings: dict[str, Path]) -> None:
    from services.qube_sim.identify import FitConfig, check

    result = fit(Recording.load(recordings["lab"]), LAB, FitConfig(max_nfev=1))
    with pytest.raises(FitRefused, match="did not converge"):
        check(result)


def test_a_fit_that_does_not_predict_the_held_out_block_is_fitted_again_in_finer_steps(
        recordings: dict[str, Path]) -> None:
    """A coarse fit whose held-out error exceeds the gate (here a gate of 0.1 deg) goes on from where it ended with
    ``fine_substeps`` per tick, and predicts at least as well; one within the gate is left as it is."""
    from services.qube_sim.identify import FitConfig

    rec = Recording.load(recordings["lab"])
    coarse = fit(rec, LAB, FitConfig(max_heldout_deg=90.0))
    finer = fit(rec, LAB, FitConfig(max_heldout_deg=0.1, fine_substeps=3))
    assert coarse.substeps == 2 and finer.substeps == 3
    assert finer.iterations > coarse.iterations and finer.train_rms_deg <= coarse.train_rms_deg * 1.01


def test_a_small_damping_is_gated_against_its_negligible_level(recordings: dict[str, Path]) -> None:
    """A pendulum damped 0.1x lab, known to +-56 %, is known to be lightly damped (it was refused, and the rig could
    not be identified); lab's damping known to +-56 % is still refused, and so is a damping the recording does not
    see at all (an infinite 1-sigma)."""
    from services.qube_sim.identify import NEGLIGIBLE_DAMPING, check, gated_sigma

    result = fit(Recording.load(recordings["lab"]), LAB)
    check(result)
    light = replace(result, values={**result.values, "Dp": NEGLIGIBLE_DAMPING["Dp"] / 10},
                    sigma={**result.sigma, "Dp": 0.56})
    assert gated_sigma(light, "Dp") == pytest.approx(0.056)
    check(light)
    with pytest.raises(FitRefused, match=r"Dp \+-56%"):
        check(replace(light, values=result.values))
    with pytest.raises(FitRefused, match=r"Dp \+-inf%"):
        check(replace(light, sigma={**result.sigma, "Dp": math.inf}))


def test_a_pendulum_damping_run_down_to_nothing_is_known_to_be_negligible() -> None:
    """Rig 601001 of pendulum damping 0.1x lab (bench.ood's sweep): the fit runs Dp down to nothing, where its log
    coordinate is out of sight (an infinite 1-sigma: the rig was refused, and deploy.lab stopped on it). Raised by
    lab's damping, the residuals do change: the fit keeps Dp at its least, known to a small part of lab's damping,
    and the rig is trusted. Recorded with the protocol of the time (25 s of decay, 60 s of PRBS, two breakaways per
    direction): today's shorter one happens to fit this rig's Dp at 5.9e-6 (its truth is about 5e-6)."""
    from bench.ood import _control, family_profile
    from services.qube_sim.identify import FITTED, NEGLIGIBLE_DAMPING, check, gated_sigma

    then = IdentifyConfig(decay_s=25.0, prbs_s=60.0, breakaway_repeats=2)
    result = fit(record_simulated(family_profile("Dp-x0.1"), 601001, replace(_control(None), identify=then)), LAB)
    assert result.values["Dp"] == FITTED["Dp"][0] and math.isfinite(result.sigma["Dp"])
    absolute = result.values["Dp"] * result.sigma["Dp"]
    assert absolute < 0.25 * NEGLIGIBLE_DAMPING["Dp"] and gated_sigma(result, "Dp") < 0.25
    check(result)


def test_a_low_friction_arm_shaken_by_the_swinging_pendulum_is_centred_enough() -> None:
    """Rig 601001 of arm friction 0.5x lab (bench.ood's sweep): the arm stayed within the centring tolerance but
    never still, and the identification ended with 'the arm did not settle within 5 deg of 0 deg (at -0 deg)'."""
    rec = record_simulated(families.family("arm_friction", 0.5), 601001)
    assert rec.t and max(abs(v) for v in rec.theta) > 0.1


def test_the_simulated_rig_command_exits_with_one_line(tmp_path: Path) -> None:
    out = tmp_path / "p.json"
    base = [sys.executable, "-m", "services.qube_sim", "--rig-profile", "lab", "--seed", "3", "--identify", str(out)]
    done = subprocess.run([*base, "--identify-base", "nosuch"], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert done.returncode == 2 and "nosuch" in done.stderr
    done = subprocess.run([*base, "--wiring-fault", "reverse-motor"], capture_output=True, text=True, cwd=ROOT,
                          timeout=60)
    assert done.returncode == 1 and done.stderr.count("\n") == 1, done.stderr
    assert "identification failed" in done.stderr and "self-test" in done.stderr
    assert not out.exists()
