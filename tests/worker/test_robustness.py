"""The robustness test of ``worker.evaluate --rigs`` (worker/robustness.py): a scripted LQR balance controller
survives small torque pulses and falls to a large one, the report says which, and the command line writes it as
JSON."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest

from rpi_bridge.reset import LQR_GAINS
from services.qube_sim.profile import IDEAL, LAB
from worker.evaluate import main
from worker.qube_env import ACTIONS
from worker.robustness import AUTHORITY, Disturbances, pulse_schedule, run_rig, stall_torque


def lqr(obs: np.ndarray) -> int:
    """The bridge's hold gains (rpi_bridge/reset.py), rounded to the task's nearest action."""
    alpha, alpha_dot, theta, theta_dot = (float(v) for v in obs)
    k = LQR_GAINS
    u = -(k[0] * theta + k[1] * alpha + k[2] * theta_dot + k[3] * alpha_dot)
    return min(range(len(ACTIONS)), key=lambda i: abs(ACTIONS[i] - u))


def test_stall_torque_and_schedule() -> None:
    assert stall_torque() == pytest.approx(0.042 * 400 * 24 / 999 / 8.4)  # 48 mN m
    d = Disturbances()
    s = pulse_schedule(4, d, d.ladder, 17.15)
    assert s == pulse_schedule(4, d, d.ladder, 17.15) != pulse_schedule(5, d, d.ladder, 17.15)
    assert [abs(f) for _, f in s] == list(d.ladder[:len(s)]) and s[0][0] == d.first_s
    assert all(b[0] - a[0] >= d.pulse_ms / 1e3 + d.gap_s / 2 for a, b in itertools.pairwise(s))
    assert pulse_schedule(4, Disturbances(pulse_ms=0), d.ladder, 17.15) == []
    # the trial's pulses stay within the task's own action (+-60 of the bridge's 400 counts), the sweep's go past it
    assert AUTHORITY == pytest.approx(0.15) and max(d.ladder) == AUTHORITY and max(d.sweep) == 2 * AUTHORITY


def test_lqr_survives_small_pulses_and_falls_to_a_large_one() -> None:
    calm = run_rig(lqr, IDEAL, 0, 100, Disturbances(pulse_ms=0, sensor_noise_counts=0), max_steps=600)
    assert calm.balanced_to_end and calm.balance_s == pytest.approx(4.2) and calm.pulses == calm.sweep_pulses == []
    hit = run_rig(lqr, IDEAL, 0, 100, Disturbances(ladder=(0.02, 0.5), sweep=(), gap_s=1.0, sensor_noise_counts=0),
                  max_steps=600)
    assert not hit.balanced_to_end and hit.balance_s < 4.2
    assert [p["survived"] for p in hit.pulses] == [True, False]
    assert hit.largest_pulse_nm == pytest.approx(0.02 * stall_torque(), rel=0.2)  # the rig's own kt and Rm
    # the trial passes; the sweep, a second episode on the same rig, gives the largest pulse survived
    swept = run_rig(lqr, IDEAL, 0, 100, Disturbances(ladder=(0.02,), sweep=(0.02, 0.5), gap_s=1.0,
                                                      sensor_noise_counts=0), max_steps=600)
    assert swept.balanced_to_end and [p["survived"] for p in swept.sweep_pulses] == [True, False]
    assert swept.largest_pulse_of_stall == pytest.approx(0.02, rel=0.2)


def test_evaluate_rigs_reports_each_rig_as_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from tests.worker.test_evaluate import save_fresh

    model = save_fresh("qube-local", tmp_path / "q.pt")
    out = tmp_path / "robust.json"
    assert main([str(model), "--env", "qube-local", "--rig-profile", "lab", "--rigs", "2", "--seed", "7",
                 "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "rig   1:" in text and "rigs balanced to the end" in text
    data = json.loads(out.read_text())
    assert data["rig_profile"] == "lab" and data["summary"]["rigs"] == 2 and len(data["rigs"]) == 2
    for i, rig in enumerate(data["rigs"]):
        assert rig["seed"] == 7 + i and set(rig) >= {"balanced_to_end", "balance_s", "largest_pulse_nm", "pulses"}
    assert main([str(model), "--env", "CartPole-v0", "--rigs", "2"]) == 2
    assert "qube-local" in capsys.readouterr().err
    assert LAB.name == "lab"
