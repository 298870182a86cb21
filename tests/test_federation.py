"""Paper Eq. 8-11 (sign-safe) on hand-computed numbers, and the round state machine of Algorithm 1."""

from __future__ import annotations

import numpy as np
import pytest

from chief import federation as fed
from chief.rounds import RoundKeeper, Submission
from protocol.tasks import task

PENDULUM_FLOOR = task("Pendulum-v1").r_floor  # -3254.72088


# -- Eq. 8: gradient weights ---------------------------------------------------------------------------------


def test_eq8_is_the_papers_formula_when_returns_are_positive() -> None:
    # CartPole: floor 0, so w_n = PI_n / sum PI exactly: 50 / 200 and 150 / 200.
    w = fed.gradient_weights({"w0": 50.0, "w1": 150.0}, tc=195.0, r_floor=0.0, policy="weighted")
    assert w == pytest.approx({"w0": 0.25, "w1": 0.75})


def test_eq8_gives_the_better_worker_more_weight_on_negative_returns() -> None:
    # Acrobot: TC -100, floor -500. Progress: (-300+500)/400 = 0.5, (-100+500)/400 = 1, (-500+500)/400 = 0.
    # Weights 0.5/1.5, 1/1.5, 0. (The paper's raw PI/sum(PI) would give 1/3, 1/9, 5/9: the worst worker the most.)
    w = fed.gradient_weights({"w0": -300.0, "w1": -100.0, "w2": -500.0}, tc=-100.0, r_floor=-500.0,
                             policy="weighted")
    assert w == pytest.approx({"w0": 1 / 3, "w1": 2 / 3, "w2": 0.0})


def test_eq8_clips_progress_and_falls_back_to_uniform() -> None:
    # Above TC counts as 1, below the floor as 0; all at the floor -> uniform.
    w = fed.gradient_weights({"a": 500.0, "b": 97.5}, tc=195.0, r_floor=0.0, policy="weighted")
    assert w == pytest.approx({"a": 1 / 1.5, "b": 0.5 / 1.5})
    assert fed.gradient_weights({"a": -600.0, "b": -500.0}, -100.0, -500.0, "weighted") == {"a": 0.5, "b": 0.5}
    assert fed.gradient_weights({"a": 10.0, "b": 190.0}, 195.0, 0.0, "plain") == {"a": 0.5, "b": 0.5}


def test_progress_rejects_bad_scales_and_nan() -> None:
    with pytest.raises(ValueError, match="above the return floor"):
        fed.progress(1.0, tc=0.0, r_floor=0.0)
    with pytest.raises(ValueError, match="finite"):
        fed.progress(float("nan"), tc=195.0, r_floor=0.0)


# -- Eq. 9: weighted mean gradient -----------------------------------------------------------------------------


def test_eq9_weighted_mean() -> None:
    grads = {"w0": {"g": np.array([1.0, 2.0])}, "w1": {"g": np.array([3.0, -2.0])}}
    out = fed.weighted_gradient(grads, {"w0": 0.25, "w1": 0.75})
    np.testing.assert_allclose(out["g"], [0.25 * 1 + 0.75 * 3, 0.25 * 2 - 0.75 * 2])  # [2.5, -1.0]
    assert out["g"].dtype == np.float32


def test_eq9_rejects_mismatched_inputs() -> None:
    with pytest.raises(ValueError, match="shape"):
        fed.weighted_gradient({"a": {"g": np.zeros(2)}, "b": {"g": np.zeros(3)}}, {"a": 0.5, "b": 0.5})
    with pytest.raises(ValueError, match="weights given"):
        fed.weighted_gradient({"a": {"g": np.zeros(2)}}, {"b": 1.0})


# -- Eq. 10-11: soft transfer ----------------------------------------------------------------------------------


def test_eq10_transfer_weight_on_each_scale() -> None:
    assert fed.transfer_weight(97.5, 195.0, 0.0, "weighted") == pytest.approx(0.5)  # paper: PI / TC
    # Pendulum: (-1827.36044 + 3254.72088) / (-400 + 3254.72088) = 1427.36044 / 2854.72088 = 0.5
    assert fed.transfer_weight(-1827.36044, -400.0, PENDULUM_FLOOR, "weighted") == pytest.approx(0.5)
    # The paper's PI / TC would be 4.57 here and push the worker away from the mature model; ours stays in [0, 1].
    assert fed.transfer_weight(-1827.36044, -400.0, PENDULUM_FLOOR, "weighted") <= 1.0
    assert fed.transfer_weight(-3000.0, -400.0, PENDULUM_FLOOR, "weighted") == pytest.approx(254.72088 / 2854.72088)
    assert fed.transfer_weight(-200.0, -400.0, PENDULUM_FLOOR, "weighted") == 1.0
    assert fed.transfer_weight(150.0, 195.0, 0.0, "plain") == 0.0  # hard transfer


def test_eq11_blend() -> None:
    out = fed.blend({"p": np.array([1.0, 1.0])}, {"p": np.array([3.0, -1.0])}, keep=0.25)
    np.testing.assert_allclose(out["p"], [0.25 * 1 + 0.75 * 3, 0.25 * 1 - 0.75 * 1])  # [2.5, -0.5]
    with pytest.raises(ValueError):
        fed.blend({"p": np.zeros(1)}, {"p": np.zeros(1)}, keep=1.5)


def test_best_mature_takes_highest_pi_then_smallest_id() -> None:
    assert fed.best_mature({"w0": 196.0, "w1": 199.0}) == "w1"
    assert fed.best_mature({"w2": 199.0, "w1": 199.0}) == "w1"


# -- Algorithm 1: rounds ---------------------------------------------------------------------------------------


def g(value: float) -> dict[str, np.ndarray]:
    return {"g": np.array([value], dtype=np.float32)}


def sub(worker: str, episode: int, pi: float, gv: float = 1.0, mature: bool = False) -> Submission:
    if mature:
        return Submission(worker, episode, pi, pi, params={"g": np.array([gv], np.float32)})
    return Submission(worker, episode, pi, pi, gradient=g(gv))


def keeper(workers: list[str], policy: str = "weighted", max_episodes: int = 100, timeout: float = 10.0):
    return RoundKeeper(workers, policy, tc=195.0, r_floor=0.0, max_episodes=max_episodes,  # type: ignore[arg-type]
                       round_timeout=timeout)


def test_round_closes_when_all_have_submitted() -> None:
    k = keeper(["w0", "w1"])
    assert k.submit(sub("w0", 1, 50.0, 1.0), now=0.0) == []
    assert k.waiting_for() == ["w1"]
    [out] = k.submit(sub("w1", 1, 150.0, 3.0), now=0.1)
    assert (out.kind, out.episode, out.contributors) == ("aggregate", 1, ["w0", "w1"])
    assert out.weights == pytest.approx({"w0": 0.25, "w1": 0.75})
    np.testing.assert_allclose(out.gradient["g"], [0.25 + 2.25])
    assert k.episode == 2 and not k.done


def test_silent_worker_times_out_and_is_not_waited_on_again() -> None:
    k = keeper(["w0", "w1", "w2"], timeout=10.0)
    k.submit(sub("w0", 1, 10.0), now=0.0)
    k.submit(sub("w1", 1, 10.0), now=1.0)
    assert k.tick(now=9.9) == []  # the timeout counts from the round's first submission
    [out] = k.tick(now=10.0)
    assert out.timed_out == ["w2"] and out.contributors == ["w0", "w1"]
    assert k.workers["w2"].state == "lagging"
    # Round 2 no longer waits for the lagging worker.
    k.submit(sub("w0", 2, 10.0), now=11.0)
    [out2] = k.submit(sub("w1", 2, 10.0), now=11.5)
    assert out2.episode == 2 and out2.timed_out == []
    # Its late answer for round 1 is stale: noted, not used.
    assert k.submit(sub("w2", 1, 30.0), now=12.0) == []
    assert k.stale == 1 and k.workers["w2"].pi == 30.0
    # Submitting for the open round brings it back: the round now waits for it again.
    k.submit(sub("w2", 3, 30.0), now=13.0)
    assert k.workers["w2"].state == "active"
    k.submit(sub("w0", 3, 10.0), now=13.1)
    assert k.waiting_for() == ["w1"]


def test_offline_worker_is_dropped_from_the_open_round() -> None:
    k = keeper(["w0", "w1"])
    k.submit(sub("w0", 1, 10.0), now=0.0)
    [out] = k.mark_offline("w1", now=0.5)
    assert out.contributors == ["w0"] and k.workers["w1"].state == "offline"


def test_simultaneous_finish_transfers_the_best_and_both_leave() -> None:
    k = keeper(["w0", "w1", "w2"])
    k.submit(sub("w0", 1, 196.0, 7.0, mature=True), now=0.0)
    k.submit(sub("w1", 1, 199.0, 9.0, mature=True), now=0.0)
    [out] = k.submit(sub("w2", 1, 97.5), now=0.0)
    assert out.kind == "transfer" and out.source_worker == "w1" and out.source_pi == 199.0
    np.testing.assert_array_equal(out.params["g"], [9.0])
    assert out.finished == ["w0", "w1"]
    assert out.keep_weights == pytest.approx({"w2": 0.5})  # Eq. 10: 97.5 / 195
    assert k.ids_in("active") == ["w2"]
    [last] = k.submit(sub("w2", 2, 196.0, mature=True), now=1.0)
    assert last.kind == "transfer" and last.keep_weights == {}
    assert k.done and k.done_reason == "all workers solved"
    assert {w: r.solved_episode for w, r in k.workers.items()} == {"w0": 1, "w1": 1, "w2": 2}


def test_plain_policy_is_uniform_and_hard() -> None:
    k = keeper(["w0", "w1"], policy="plain")
    k.submit(sub("w0", 1, 196.0, mature=True), now=0.0)
    [out] = k.submit(sub("w1", 1, 97.5), now=0.0)
    assert out.keep_weights == {"w1": 0.0}


def test_independent_policy_shares_nothing() -> None:
    k = keeper(["w0", "w1"], policy="independent")
    k.submit(sub("w0", 1, 20.0), now=0.0)
    [out] = k.submit(sub("w1", 1, 30.0), now=0.0)
    assert out.kind == "aggregate" and out.gradient is None and out.weights == {}
    k.submit(sub("w0", 2, 196.0, mature=True), now=1.0)
    [fin] = k.submit(sub("w1", 2, 30.0), now=1.0)
    assert fin.kind == "aggregate" and fin.finished == ["w0"] and fin.params is None


def test_run_ends_after_max_episodes() -> None:
    k = keeper(["w0"], max_episodes=2)
    k.submit(sub("w0", 1, 1.0), now=0.0)
    assert not k.done
    k.submit(sub("w0", 2, 1.0), now=1.0)
    assert k.done and "maximum" in (k.done_reason or "")
    assert k.submit(sub("w0", 3, 1.0), now=2.0) == []


def test_unknown_worker_and_bad_config_raise() -> None:
    k = keeper(["w0"])
    with pytest.raises(KeyError):
        k.submit(sub("zz", 1, 1.0), now=0.0)
    with pytest.raises(ValueError):
        keeper([])
    with pytest.raises(ValueError):
        keeper(["w0"], policy="fedavg")


def test_workers_that_went_on_without_an_answer_are_resynchronised() -> None:
    # Both submissions for round 1 were lost (say, a broker restart); the workers timed out and went on.
    k = keeper(["w0", "w1"], timeout=10.0)
    assert k.submit(sub("w0", 2, 50.0, 1.0), now=0.0) == []  # w0 is past round 1; w1 is still awaited there
    assert k.episode == 1 and k.waiting_for() == ["w1"]
    outs = k.submit(sub("w1", 2, 150.0, 3.0), now=0.1)
    # Round 1 closes empty (nobody is waiting for it), round 2 closes with both submissions.
    assert [(o.episode, o.contributors) for o in outs] == [(1, []), (2, ["w0", "w1"])]
    assert outs[1].weights == pytest.approx({"w0": 0.25, "w1": 0.75})
    assert k.episode == 3 and k.stale == 0


def test_a_worker_ahead_does_not_block_the_round_timeout() -> None:
    k = keeper(["w0", "w1", "w2"], timeout=5.0)
    k.submit(sub("w0", 1, 10.0), now=0.0)
    k.submit(sub("w1", 2, 10.0), now=0.5)  # w1 skipped round 1
    [out1, *rest] = k.tick(now=5.0)  # w2 is silent
    assert out1.episode == 1 and out1.timed_out == ["w2"] and out1.contributors == ["w0"]
    assert rest == [] and k.episode == 2 and set(k.pending) == {"w1"}


def test_finished_status_without_mature_params_ends_the_worker() -> None:
    k = keeper(["w0", "w1"])
    k.submit(sub("w0", 1, 196.0, mature=True), now=0.0)
    k.submit(sub("w1", 1, 20.0), now=0.0)
    assert k.mark_finished("w1", 5, 197.0, now=1.0) == []
    assert k.done and k.workers["w1"].solved_episode == 5
