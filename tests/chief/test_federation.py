"""Paper Eq. 8-11 (sign-safe) on hand-computed numbers, through the strategies that use them."""

from __future__ import annotations

import numpy as np
import pytest

from chief import federation as fed
from chief import strategies
from chief.strategies import plain, weighted
from protocol.tasks import task

PENDULUM_FLOOR = task("Pendulum-v1").r_floor  # -3254.72088


def eq8(pis: dict[str, float], tc: float, r_floor: float, policy: str = "weighted") -> dict[str, float]:
    """A strategy's contribution weights for these PIs (through its aggregate, as the round state machine calls it)."""
    grads = {w: {"g": np.zeros(1, np.float32)} for w in pis}
    weights = strategies.get(policy).aggregate(grads, {w: fed.progress(p, tc, r_floor) for w, p in pis.items()}).weights
    assert weights is not None
    return weights


def eq10(pi: float, tc: float, r_floor: float, policy: str = "weighted") -> float | None:
    return strategies.get(policy).keep_weight(fed.progress(pi, tc, r_floor))


# -- Eq. 8: gradient weights ---------------------------------------------------------------------------------


def test_eq8_is_the_papers_formula_when_returns_are_positive() -> None:
    # CartPole: floor 0, so w_n = PI_n / sum PI exactly: 50 / 200 and 150 / 200.
    w = eq8({"w0": 50.0, "w1": 150.0}, tc=195.0, r_floor=0.0)
    assert w == pytest.approx({"w0": 0.25, "w1": 0.75})


def test_eq8_gives_the_better_worker_more_weight_on_negative_returns() -> None:
    # Acrobot: TC -100, floor -500. Progress: (-300+500)/400 = 0.5, (-100+500)/400 = 1, (-500+500)/400 = 0.
    # Weights 0.5/1.5, 1/1.5, 0. (The paper's raw PI/sum(PI) would give 1/3, 1/9, 5/9: the worst worker the most.)
    w = eq8({"w0": -300.0, "w1": -100.0, "w2": -500.0}, tc=-100.0, r_floor=-500.0)
    assert w == pytest.approx({"w0": 1 / 3, "w1": 2 / 3, "w2": 0.0})


def test_eq8_clips_progress_and_falls_back_to_uniform() -> None:
    # Above TC counts as 1, below the floor as 0; all at the floor -> uniform.
    w = eq8({"a": 500.0, "b": 97.5}, tc=195.0, r_floor=0.0)
    assert w == pytest.approx({"a": 1 / 1.5, "b": 0.5 / 1.5})
    assert eq8({"a": -600.0, "b": -500.0}, -100.0, -500.0) == {"a": 0.5, "b": 0.5}
    assert eq8({"a": 10.0, "b": 190.0}, 195.0, 0.0, "plain") == {"a": 0.5, "b": 0.5}
    assert weighted.contribution_weights({"a": 0.25, "b": 0.75}) == {"a": 0.25, "b": 0.75}


def test_progress_rejects_bad_scales_and_nan() -> None:
    with pytest.raises(ValueError, match="above the return floor"):
        fed.progress(1.0, tc=0.0, r_floor=0.0)
    with pytest.raises(ValueError, match="finite"):
        fed.progress(float("nan"), tc=195.0, r_floor=0.0)


# -- Eq. 9: weighted mean gradient -----------------------------------------------------------------------------


def test_eq9_weighted_mean() -> None:
    grads = {"w0": {"g": np.array([1.0, 2.0])}, "w1": {"g": np.array([3.0, -2.0])}}
    out = fed.weighted_sum(grads, {"w0": 0.25, "w1": 0.75})
    np.testing.assert_allclose(out["g"], [0.25 * 1 + 0.75 * 3, 0.25 * 2 - 0.75 * 2])  # [2.5, -1.0]
    assert out["g"].dtype == np.float32


def test_eq9_rejects_mismatched_inputs() -> None:
    with pytest.raises(ValueError, match="shape"):
        fed.weighted_sum({"a": {"g": np.zeros(2)}, "b": {"g": np.zeros(3)}}, {"a": 0.5, "b": 0.5})
    with pytest.raises(ValueError, match="weights given"):
        fed.weighted_sum({"a": {"g": np.zeros(2)}}, {"b": 1.0})


# -- Eq. 10-11: soft transfer ----------------------------------------------------------------------------------


def test_eq10_transfer_weight_on_each_scale() -> None:
    assert eq10(97.5, 195.0, 0.0) == pytest.approx(0.5)  # paper: PI / TC
    # Pendulum: (-1827.36044 + 3254.72088) / (-400 + 3254.72088) = 1427.36044 / 2854.72088 = 0.5
    assert eq10(-1827.36044, -400.0, PENDULUM_FLOOR) == pytest.approx(0.5)
    # The paper's PI / TC would be 4.57 here and push the worker away from the mature model; ours stays in [0, 1].
    assert eq10(-1827.36044, -400.0, PENDULUM_FLOOR) <= 1.0  # type: ignore[operator]
    assert eq10(-3000.0, -400.0, PENDULUM_FLOOR) == pytest.approx(254.72088 / 2854.72088)
    assert eq10(-200.0, -400.0, PENDULUM_FLOOR) == 1.0
    assert eq10(150.0, 195.0, 0.0, "plain") == 0.0  # hard transfer
    assert plain.keep_weight(0.9) == 0.0 and eq10(150.0, 195.0, 0.0, "independent") is None


def test_best_mature_takes_highest_pi_then_smallest_id() -> None:
    assert fed.best_mature({"w0": 196.0, "w1": 199.0}) == "w1"
    assert fed.best_mature({"w2": 199.0, "w1": 199.0}) == "w1"
