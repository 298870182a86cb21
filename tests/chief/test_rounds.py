"""Algorithm 1's round state machine: rounds, the finish path, and what a worker's word is (not) taken for."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from chief.rounds import AHEAD_WINDOW, RoundKeeper, Submission, Verdict
from protocol.rounds import RoundShape
from protocol.tasks import PI_WINDOW, performance_index, task
from runtime.records import RoundRecord

CARTPOLE = task("CartPole-v0")
SPEC = {"g": (1,)}


class Fake:
    """One honest worker's submissions: its returns so far decide recent_returns and PI, as worker/service.py does."""

    def __init__(self, worker_id: str) -> None:
        self.id = worker_id
        self.returns: list[float] = []

    def sub(self, episode: int, ret: float, gv: float = 1.0, mature: bool = False) -> Submission:
        self.returns.append(ret)
        recent = tuple(self.returns[-PI_WINDOW:])
        tensors = {"g": np.array([gv], np.float32)}
        return Submission(self.id, episode, performance_index(self.returns), ret, recent_returns=recent, steps=int(ret),
                          gradient=None if mature else tensors, params=tensors if mature else None)


def keeper(workers: list[str], policy: str = "weighted", max_episodes: int = 100, timeout: float = 10.0
           ) -> RoundKeeper:
    return RoundKeeper(workers, policy, CARTPOLE, max_episodes=max_episodes, round_timeout=timeout, actor_spec=SPEC)


def fakes(*ids: str) -> dict[str, Fake]:
    return {i: Fake(i) for i in ids}


def outcomes(v: Verdict) -> list:
    assert v.status == "accepted", (v.reason, v.detail)
    return v.outcomes


def mature_after(f: Fake, first: int, k: RoundKeeper, now: float = 0.0, ret: float = 200.0,
                 others: tuple[tuple[Fake, float], ...] = ()) -> Submission:
    """Feed ``f`` honest updates of ``ret`` until it can hand over a mature actor (the caller submits that), each
    round with the ``others``' updates of their returns (a worker plays round r + 1 only after round r's answer)."""
    episode = first
    while len(f.returns) < PI_WINDOW - 1:
        k.submit(f.sub(episode, ret), now)
        for other, other_ret in others:
            k.submit(other.sub(episode, other_ret), now)
        episode += 1
    return f.sub(episode, ret, mature=True)


def test_round_closes_when_all_have_submitted() -> None:
    k, w = keeper(["w0", "w1"]), fakes("w0", "w1")
    assert outcomes(k.submit(w["w0"].sub(1, 50.0, 1.0), now=0.0)) == []
    assert k.waiting_for() == ["w1"]
    [out] = outcomes(k.submit(w["w1"].sub(1, 150.0, 3.0), now=0.1))
    assert (out.kind, out.episode, out.contributors) == ("aggregate", 1, ["w0", "w1"])
    assert out.pis == {"w0": 50.0, "w1": 150.0} and out.strategy == "weighted"
    assert out.weights == pytest.approx({"w0": 0.25, "w1": 0.75})  # Eq. 8
    np.testing.assert_allclose(out.gradient["g"], [0.25 + 2.25])  # Eq. 9
    assert k.episode == 2 and not k.done


def test_a_finished_status_never_drops_the_pending_mature_actor() -> None:
    """The race the review found: MatureParams is pending in the open round when the `finished` status arrives."""
    k, w = keeper(["w0", "w1", "w2"]), fakes("w0", "w1", "w2")
    for e in range(1, PI_WINDOW):
        for f in w.values():
            k.submit(f.sub(e, 100.0 if f.id != "w0" else 200.0), now=0.0)
    verdict = k.submit(w["w0"].sub(PI_WINDOW, 200.0, gv=7.0, mature=True), now=1.0)
    assert verdict.status == "accepted" and verdict.ack is not None and verdict.ack.accepted
    assert k.note_status("w0", "finished", now=1.1) == []  # only news
    assert k.note_status("w0", "offline", now=1.2) == []  # gone, but its mature actor still counts
    k.submit(w["w1"].sub(PI_WINDOW, 100.0), now=1.3)
    [out] = outcomes(k.submit(w["w2"].sub(PI_WINDOW, 100.0), now=1.4))
    assert out.kind == "transfer" and out.source_worker == "w0" and out.finished == ["w0"]
    np.testing.assert_array_equal(out.params["g"], [7.0])
    assert out.keep_weights == pytest.approx({"w1": 100 / 195, "w2": 100 / 195})  # Eq. 10 of each recipient's PI
    assert out.recipient_pis == {"w1": 100.0, "w2": 100.0}
    assert k.workers["w0"].state == "finished" and k.workers["w0"].solved_episode == PI_WINDOW


def test_no_transfer_is_addressed_to_an_offline_worker() -> None:
    """w2 timed out and w3 said it stopped: the transfer of w0's finish goes to w1 only, and the round records both
    as offline; once w2 submits again it is a recipient again."""
    k, w = keeper(["w0", "w1", "w2", "w3"]), fakes("w0", "w1", "w2", "w3")
    for e in range(1, PI_WINDOW):
        for f in w.values():
            k.submit(f.sub(e, 200.0 if f.id == "w0" else 100.0), now=float(e))
    k.submit(w["w1"].sub(PI_WINDOW, 100.0), now=20.0)
    k.submit(w["w0"].sub(PI_WINDOW, 200.0, mature=True), now=20.0)
    assert k.note_status("w3", "stopped", now=20.5) == []  # said it stopped: not waited for, no recipient
    [out] = k.tick(now=30.0)  # w2 is silent: timed out
    assert out.kind == "transfer" and out.timed_out == ["w2"] and out.offline == ["w2", "w3"]
    assert out.keep_weights == pytest.approx({"w1": 100 / 195}) and list(out.recipient_pis) == ["w1"]
    assert out.record()["offline"] == ["w2", "w3"]
    # Nobody offline: the record carries no ``offline``; a worker that is back receives transfers again.
    k2, w2 = keeper(["w0", "w1", "w2"]), fakes("w0", "w1", "w2")
    for e in range(1, PI_WINDOW):
        for f in w2.values():
            k2.submit(f.sub(e, 200.0 if f.id == "w0" else 100.0), now=float(e))
    k2.note_status("w2", "offline", now=9.5)  # a last will, then it submits again: back
    k2.submit(w2["w2"].sub(PI_WINDOW, 100.0), now=10.0)
    k2.submit(w2["w1"].sub(PI_WINDOW, 100.0), now=10.0)
    [out2] = outcomes(k2.submit(w2["w0"].sub(PI_WINDOW, 200.0, mature=True), now=10.0))
    assert out2.kind == "transfer" and sorted(out2.keep_weights) == ["w1", "w2"] and "offline" not in out2.record()


def test_a_finish_with_every_learner_offline_transfers_nothing() -> None:
    k, w = keeper(["w0", "w1"]), fakes("w0", "w1")
    for e in range(1, PI_WINDOW):
        k.submit(w["w0"].sub(e, 200.0), now=float(e))
        k.submit(w["w1"].sub(e, 100.0), now=float(e))
    k.note_status("w1", "error", now=9.5)
    [out] = outcomes(k.submit(w["w0"].sub(PI_WINDOW, 200.0, mature=True), now=10.0))
    assert out.kind == "aggregate" and out.finished == ["w0"] and out.offline == ["w1"] and not out.keep_weights


def test_a_repeated_mature_actor_is_acknowledged_again_and_counted_once() -> None:
    k, w = keeper(["w0", "w1"]), fakes("w0", "w1")
    m = mature_after(w["w0"], 1, k, others=((w["w1"], 20.0),))
    assert k.submit(m, now=1.0).status == "accepted"
    again = k.submit(m, now=2.0)  # the worker missed the first ack and sent it again
    assert again.status == "duplicate" and again.ack is not None and again.ack.accepted and again.outcomes == []
    [out] = outcomes(k.submit(w["w1"].sub(PI_WINDOW, 20.0), now=3.0))
    assert out.contributors == ["w0", "w1"] and out.kind == "transfer"
    late = k.submit(m, now=4.0)  # even after its round closed
    assert late.status == "duplicate" and late.ack is not None and late.ack.accepted


def test_a_repeated_update_is_counted_once() -> None:
    k, w = keeper(["w0", "w1"]), fakes("w0", "w1")
    first = w["w0"].sub(1, 10.0, gv=1.0)
    k.submit(first, now=0.0)
    assert k.submit(first, now=0.1).status == "duplicate"
    [out] = outcomes(k.submit(w["w1"].sub(1, 30.0, gv=3.0), now=0.2))
    assert out.contributors == ["w0", "w1"] and out.weights == pytest.approx({"w0": 0.25, "w1": 0.75})


def test_a_mature_actor_needs_pi_at_tc_over_the_whole_window() -> None:
    k, w = keeper(["w0", "w1"]), fakes("w0", "w1")
    short = w["w0"].sub(1, 200.0, mature=True)  # PI 200, but over one episode
    v = k.submit(short, now=0.0)
    assert (v.status, v.reason) == ("rejected", "not_mature") and v.ack is not None and not v.ack.accepted
    assert "over 1 episodes" in v.ack.reason
    # Refused, it does not occupy the slot: the worker learns on and sends the update for that episode.
    w["w0"].returns.pop()
    assert k.submit(w["w0"].sub(1, 200.0), now=0.1).status == "accepted"
    low = Fake("w1")
    low.returns = [10.0] * (PI_WINDOW - 1)
    v = k.submit(low.sub(1, 10.0, mature=True), now=0.2)  # PI 10 claimed mature
    assert v.reason == "not_mature"


@pytest.mark.parametrize(("change", "reason"), [
    (dict(pi=199.0), "pi_mismatch"),  # PI is not the mean of the returns it came with
    (dict(episode_return=55.0), "inconsistent"),  # the episode's return is not the last recent return
    (dict(recent_returns=(1e9,), episode_return=1e9, pi=1e9), "absurd_return"),
    (dict(recent_returns=(float("inf"),), episode_return=float("inf"), pi=float("inf")), "absurd_return"),
    (dict(recent_returns=()), "invalid"),
    (dict(gradient={"g": np.zeros(3, np.float32)}), "wrong_shape"),
    (dict(episode=1_000_000_000), "out_of_window"),
    (dict(gradient={"g": np.array([3e38], np.float32)}), "absurd_norm"),
    (dict(gradient={"g": np.array([1e300], np.float64)}), "wrong_dtype"),
    (dict(gradient={"g": np.array([1.0], np.float64)}), "wrong_dtype"),
    (dict(worker_id="zz"), "unknown_worker"),
])
def test_lies_and_nonsense_are_refused_and_change_nothing(change: dict, reason: str) -> None:
    from dataclasses import replace

    k = keeper(["w0"])
    honest = Fake("w0").sub(1, 20.0)
    v = k.submit(replace(honest, **change), now=0.0)
    assert (v.status, v.reason) == ("rejected", reason), v.detail
    assert k.episode == 1 and not k.done and k.pending == {} and k.ahead == {} and k.counted == set()


def test_returns_must_agree_with_what_the_worker_said_before() -> None:
    k, w = keeper(["w0", "w1"]), fakes("w0", "w1")
    for e in range(1, PI_WINDOW):
        k.submit(w["w0"].sub(e, 20.0), now=0.0)
        k.submit(w["w1"].sub(e, 20.0), now=0.0)
    liar = Fake("w0")
    liar.returns = [200.0] * (PI_WINDOW - 1)  # rewrites history to look mature
    v = k.submit(liar.sub(PI_WINDOW, 200.0, mature=True), now=1.0)
    assert v.reason == "inconsistent" and "reported as 20.0" in v.detail


def test_episode_one_billion_does_not_end_the_run() -> None:
    k, w = keeper(["w0", "w1"], max_episodes=2000), fakes("w0", "w1")
    assert k.submit(w["w0"].sub(1_000_000_000, 20.0), now=0.0).reason == "out_of_window"
    assert k.submit(w["w0"].sub(1 + AHEAD_WINDOW + 1, 20.0), now=0.0).reason == "out_of_window"
    assert not k.done and k.episode == 1
    # The window is the open round up to AHEAD_WINDOW rounds ahead, and never past M.
    assert k.submit(w["w1"].sub(1 + AHEAD_WINDOW, 20.0), now=0.0).status == "held"  # beyond reach: held
    short = keeper(["w0"], max_episodes=3)
    assert short.submit(Fake("w0").sub(4, 20.0), now=0.0).reason == "out_of_window"


def test_silent_worker_times_out_and_is_not_waited_on_again() -> None:
    k, w = keeper(["w0", "w1", "w2"], timeout=10.0), fakes("w0", "w1", "w2")
    k.submit(w["w0"].sub(1, 10.0), now=0.0)
    k.submit(w["w1"].sub(1, 10.0), now=1.0)
    assert k.tick(now=9.9) == []  # the timeout counts from the round's first submission
    [out] = k.tick(now=10.0)
    assert out.timed_out == ["w2"] and out.contributors == ["w0", "w1"]
    assert k.workers["w2"].state == "lagging"
    k.submit(w["w0"].sub(2, 10.0), now=11.0)
    [out2] = outcomes(k.submit(w["w1"].sub(2, 10.0), now=11.5))  # round 2 no longer waits for the lagging worker
    assert out2.episode == 2 and out2.timed_out == []
    # Its late answer for round 1 is stale: refused, not counted.
    late = k.submit(w["w2"].sub(1, 30.0), now=12.0)
    assert (late.status, late.reason) == ("rejected", "stale") and k.workers["w2"].pi is None
    # Submitting for the open round brings it back: the round now waits for it again.
    k.submit(w["w2"].sub(3, 30.0), now=13.0)
    assert k.workers["w2"].state == "active"
    k.submit(w["w0"].sub(3, 10.0), now=13.1)
    assert k.waiting_for() == ["w1"]


def test_a_last_will_does_not_end_the_wait_but_a_stop_does_and_what_was_sent_counts() -> None:
    k, w = keeper(["w0", "w1", "w2"], timeout=10.0), fakes("w0", "w1", "w2")
    k.submit(w["w0"].sub(1, 10.0), now=0.0)
    k.submit(w["w1"].sub(1, 30.0), now=0.1)
    assert k.note_status("w1", "offline", now=0.2) == []  # its submission stays in the round
    # w2's last will: a broker restart delivers everyone's, so the round still waits for it ...
    assert k.note_status("w2", "offline", now=0.3) == [] and k.waiting_for() == ["w2"]
    assert k.workers["w2"].state == "offline"
    [out] = k.tick(now=10.0)  # ... until it times out
    assert out.contributors == ["w0", "w1"] and out.timed_out == ["w2"]
    # A worker that says it stopped is not waited for at all.
    k.submit(w["w0"].sub(2, 10.0), now=11.0)
    k.submit(w["w1"].sub(2, 30.0), now=11.0)
    assert k.round == 3
    # And a worker whose will arrived but which comes back in time keeps its place.
    k2, f2 = keeper(["a", "b"]), fakes("a", "b")
    k2.submit(f2["a"].sub(1, 10.0), now=0.0)
    k2.note_status("b", "offline", now=0.1)
    [back] = outcomes(k2.submit(f2["b"].sub(1, 30.0), now=0.5))
    assert back.contributors == ["a", "b"] and k2.workers["b"].state == "active"
    k3, f3 = keeper(["a", "b"]), fakes("a", "b")
    k3.submit(f3["a"].sub(1, 10.0), now=0.0)
    [gone] = k3.note_status("b", "error", now=0.1)
    assert gone.contributors == ["a"]


def test_simultaneous_finish_transfers_the_best_and_both_leave() -> None:
    k, w = keeper(["w0", "w1", "w2"]), fakes("w0", "w1", "w2")
    for e in range(1, PI_WINDOW):
        k.submit(w["w0"].sub(e, 196.0), now=0.0)
        k.submit(w["w1"].sub(e, 199.0), now=0.0)
        k.submit(w["w2"].sub(e, 97.5), now=0.0)
    k.submit(w["w0"].sub(PI_WINDOW, 196.0, 7.0, mature=True), now=0.0)
    k.submit(w["w1"].sub(PI_WINDOW, 199.0, 9.0, mature=True), now=0.0)
    [out] = outcomes(k.submit(w["w2"].sub(PI_WINDOW, 97.5), now=0.0))
    assert out.kind == "transfer" and out.source_worker == "w1" and out.source_pi == 199.0
    np.testing.assert_array_equal(out.params["g"], [9.0])
    assert out.finished == ["w0", "w1"]
    assert out.keep_weights == pytest.approx({"w2": 0.5})  # Eq. 10: 97.5 / 195
    assert k.ids_in("active") == ["w2"]
    v = k.submit(w["w2"].sub(PI_WINDOW + 1, 200.0, mature=True), now=1.0)
    assert v.reason == "not_mature"  # PI 107.75: the returns it already reported count


def test_the_last_finisher_leaves_without_a_transfer() -> None:
    k, w = keeper(["w0"]), fakes("w0")
    m = mature_after(w["w0"], 1, k)
    [out] = outcomes(k.submit(m, now=0.0))
    assert out.kind == "aggregate" and out.finished == ["w0"] and out.gradient is None
    assert k.done and k.done_reason == "all workers solved" and k.workers["w0"].steps_at_solve == 200 * PI_WINDOW


def test_plain_policy_is_uniform_and_hard() -> None:
    k, w = keeper(["w0", "w1"], policy="plain"), fakes("w0", "w1")
    for e in range(1, PI_WINDOW):
        k.submit(w["w0"].sub(e, 200.0), now=0.0)
        [agg] = outcomes(k.submit(w["w1"].sub(e, 97.5), now=0.0))
        assert agg.weights == {"w0": 0.5, "w1": 0.5}
    k.submit(w["w0"].sub(PI_WINDOW, 200.0, mature=True), now=0.0)
    [out] = outcomes(k.submit(w["w1"].sub(PI_WINDOW, 97.5), now=0.0))
    assert out.keep_weights == {"w1": 0.0}


def test_independent_policy_shares_nothing() -> None:
    k, w = keeper(["w0", "w1"], policy="independent"), fakes("w0", "w1")
    for e in range(1, PI_WINDOW):
        k.submit(w["w0"].sub(e, 200.0), now=0.0)
        [out] = outcomes(k.submit(w["w1"].sub(e, 30.0), now=0.0))
        assert out.kind == "aggregate" and out.gradient is None and out.weights == {}
    k.submit(w["w0"].sub(PI_WINDOW, 200.0, mature=True), now=1.0)
    [fin] = outcomes(k.submit(w["w1"].sub(PI_WINDOW, 30.0), now=1.0))
    assert fin.kind == "aggregate" and fin.finished == ["w0"] and fin.params is None


@pytest.mark.parametrize("policy", ["median", "trimmed"])
def test_robust_policies_ignore_one_outlier_of_four(policy: str) -> None:
    k, w = keeper(["w0", "w1", "w2", "w3"], policy=policy), fakes("w0", "w1", "w2", "w3")
    for f, gv in zip(w.values(), [1.0, 2.0, 3.0, 1e5], strict=True):
        v = k.submit(f.sub(1, 20.0, gv=gv), now=0.0)
    [out] = outcomes(v)
    np.testing.assert_allclose(out.gradient["g"], [2.5])  # the mean of the two middle values
    assert out.weights == {}


def test_run_ends_after_max_episodes() -> None:
    k, f = keeper(["w0"], max_episodes=2), Fake("w0")
    k.submit(f.sub(1, 1.0), now=0.0)
    assert not k.done
    k.submit(f.sub(2, 1.0), now=1.0)
    assert k.done and "maximum" in (k.done_reason or "")
    assert k.submit(f.sub(3, 1.0), now=2.0).reason == "run_over"


def test_bad_config_raises() -> None:
    with pytest.raises(ValueError):
        keeper([])
    with pytest.raises(ValueError, match="unknown federation policy 'fedavg'"):
        keeper(["w0"], policy="fedavg")


def test_workers_that_went_on_without_an_answer_are_resynchronised() -> None:
    # Both submissions for round 1 were lost (say, a broker restart); the workers timed out and went on.
    # Their round-2 submissions are beyond reach (a forger could have sent them): held, counting nothing, until round
    # 1 times out (the first one held started its clock); round 2 then takes them up, as neither worker's round 1
    # was counted (chief/rounds.py displaces).
    k, w = keeper(["w0", "w1"], timeout=10.0), fakes("w0", "w1")
    w["w0"].returns, w["w1"].returns = [50.0], [150.0]  # their lost episode-1 returns
    assert k.submit(w["w0"].sub(2, 50.0, 1.0), now=0.0).status == "held"
    assert k.submit(w["w1"].sub(2, 150.0, 3.0), now=0.1).status == "held"
    assert k.episode == 1 and k.waiting_for() == ["w0", "w1"] and k.tick(now=9.9) == []
    outs = k.tick(now=10.0)
    assert [v.status for v in outs[0].taken_up] == ["accepted", "accepted"]
    # Round 1 closes empty (timed out), round 2 closes with both submissions.
    assert [(o.episode, o.contributors) for o in outs] == [(1, []), (2, ["w0", "w1"])]
    assert outs[1].weights == pytest.approx({"w0": 0.25, "w1": 0.75})
    assert k.episode == 3


def test_a_worker_ahead_does_not_block_the_round_timeout() -> None:
    k, w = keeper(["w0", "w1", "w2"], timeout=5.0), fakes("w0", "w1", "w2")
    k.submit(w["w0"].sub(1, 10.0), now=0.0)
    w["w1"].returns = [10.0]
    k.submit(w["w1"].sub(2, 10.0), now=0.5)  # w1 skipped round 1 (held: beyond reach)
    [out1, *rest] = k.tick(now=5.0)  # w2 is silent
    assert out1.episode == 1 and out1.timed_out == ["w1", "w2"] and out1.contributors == ["w0"]
    assert rest == [] and k.episode == 2 and set(k.pending) == {"w1"}


def test_a_restarted_clock_gives_the_open_round_a_full_timeout() -> None:
    """A move of workers to another edge (chief/failover.py) restarts the open round's clock: the round that would
    have timed out at 5.0 waits until 3.0 + 5.0 for them, and an unopened round has no clock to restart."""
    k, w = keeper(["w0", "w1"], timeout=5.0), fakes("w0", "w1")
    k.restart_clock(now=1.0)
    assert k.round_opened_at is None
    k.submit(w["w0"].sub(1, 10.0), now=0.0)
    k.restart_clock(now=3.0)
    assert k.tick(now=7.9) == [] and k.episode == 1
    [out] = k.tick(now=8.0)
    assert out.timed_out == ["w1"] and out.contributors == ["w0"]


def test_keep_weight_uses_the_recipients_pi_at_that_round_not_a_later_one() -> None:
    # Under S = 1 a worker may be one round ahead of the open one (in reach: filed ahead at once).
    k = RoundKeeper(["w0", "w1", "w2"], "weighted", CARTPOLE, max_episodes=100, round_timeout=10.0, actor_spec=SPEC,
                    max_staleness=1)
    w = fakes("w0", "w1", "w2")
    m = mature_after(w["w0"], 1, k, others=((w["w1"], 39.0), (w["w2"], 39.0)))
    k.submit(m, now=0.0)
    k.submit(w["w1"].sub(PI_WINDOW, 39.0), now=0.0)
    # w2 skipped round PI_WINDOW: its submission for the next one closes it (nobody else is awaited there).
    [transfer] = outcomes(k.submit(w["w2"].sub(PI_WINDOW + 1, 195.0), now=0.0))
    assert transfer.kind == "transfer" and transfer.episode == PI_WINDOW
    # w2's PI at round PI_WINDOW is from its episode 9 (39.0), not the 54.6 of its later episode.
    assert transfer.recipient_pis == {"w1": 39.0, "w2": 39.0}
    assert transfer.keep_weights == pytest.approx({"w1": 0.2, "w2": 0.2})


def test_one_huge_gradient_is_scaled_to_ten_times_the_median_norm() -> None:
    k, w = keeper(["w0", "w1", "w2", "w3"]), fakes("w0", "w1", "w2", "w3")
    for f, gv in zip(w.values(), [1.0, 2.0, 3.0, 1e5], strict=True):
        v = k.submit(f.sub(1, 100.0, gv=gv), now=0.0)
    [out] = outcomes(v)
    assert out.clipped == pytest.approx({"w3": 25.0 / 1e5})  # the median norm is 2.5: bound 25
    np.testing.assert_allclose(out.gradient["g"], [0.25 * (1 + 2 + 3 + 25)], rtol=1e-6)  # equal PIs: the mean
    assert out.record()["clipped"] == out.clipped


def test_a_strategy_that_shares_nothing_bounds_nothing(caplog: pytest.LogCaptureFixture) -> None:
    """``independent`` shares no gradient, so its workers' outliers are neither scaled nor logged (an off-policy
    learner's honest norms spread far past ten times the median: thousands of such lines per run before)."""
    k, w = keeper(["w0", "w1", "w2", "w3"], policy="independent"), fakes("w0", "w1", "w2", "w3")
    for f, gv in zip(w.values(), [1.0, 2.0, 3.0, 1e5], strict=True):
        v = k.submit(f.sub(1, 100.0, gv=gv), now=0.0)
    [out] = outcomes(v)
    assert out.clipped == {} and out.gradient is None and "scaled by" not in caplog.text


def test_honest_spread_is_not_clipped_and_float32_cannot_overflow() -> None:
    k, w = keeper(["w0", "w1"]), fakes("w0", "w1")
    k.submit(w["w0"].sub(1, 100.0, gv=1.0), now=0.0)
    [out] = outcomes(k.submit(w["w1"].sub(1, 100.0, gv=3.0), now=0.0))
    assert out.clipped == {}
    # At the norm limit, four workers' sum stays far inside float32.
    k4, f4 = keeper(["a", "b", "c", "d"], policy="plain"), fakes("a", "b", "c", "d")
    for f in f4.values():
        v = k4.submit(f.sub(1, 100.0, gv=9e5), now=0.0)
    [big] = outcomes(v)
    assert np.isfinite(big.gradient["g"]).all()


def steps_of(f: Fake, episode: int, ret: float, k: int, gv: float = 1.0) -> list[Submission]:
    """An honest worker's K submissions for one episode under a per-step strategy."""
    from dataclasses import replace

    first = f.sub(episode, ret, gv=gv)
    return [replace(first, step=s, critic_gradient={"c": np.array([10 * gv], np.float32)}) for s in range(k)]


def sync_keeper(max_episodes: int, k: int) -> RoundKeeper:
    return RoundKeeper(["w0", "w1"], "sync", CARTPOLE, max_episodes=max_episodes, round_timeout=10.0,
                       actor_spec=SPEC, critic_spec={"c": (1,)}, shape=RoundShape(per_episode=k))


def test_a_per_step_strategy_has_k_rounds_per_episode() -> None:
    """Under ``sync`` each of the K mini-batch steps is a round: actor and critic gradients are averaged, and a later
    step must follow its episode's step 0 with the same return and PI."""
    from dataclasses import replace

    k, w = sync_keeper(max_episodes=2, k=3), fakes("w0", "w1")
    a1, b1 = steps_of(w["w0"], 1, 20.0, 3, gv=1.0), steps_of(w["w1"], 1, 20.0, 3, gv=3.0)
    assert k.submit(a1[1], now=0.0).status == "held"  # step 1 before step 0: beyond reach
    k.submit(a1[0], now=0.0)
    [out] = outcomes(k.submit(b1[0], now=0.0))
    assert [v.reason for v in out.taken_up] == ["unreachable"]  # it came before the step 0 it follows
    assert (out.round, out.episode, out.step) == (1, 1, 0) and out.weights == {"w0": 0.5, "w1": 0.5}
    np.testing.assert_allclose(out.gradient["g"], [2.0])
    np.testing.assert_allclose(out.critic_gradient["c"], [20.0])
    assert k.round == 2 and k.episode == 1 and k.next_episode == 2
    assert k.submit(replace(a1[1], episode_return=99.0), now=0.0).reason == "inconsistent"  # repeats its episode's
    assert k.submit(replace(a1[1], critic_gradient=None), now=0.0).reason == "invalid"
    assert k.submit(replace(a1[1], step=3), now=0.0).reason == "invalid"
    k.submit(a1[1], now=0.0)
    [out2] = outcomes(k.submit(b1[1], now=0.0))
    assert (out2.round, out2.step) == (2, 1)
    k.submit(a1[2], now=0.0)
    k.submit(b1[2], now=0.0)
    assert k.round == 4 and k.episode == 2 and not k.done
    for a, b in zip(steps_of(w["w0"], 2, 20.0, 3), steps_of(w["w1"], 2, 20.0, 3), strict=True):
        k.submit(a, now=0.0)
        outs = outcomes(k.submit(b, now=0.0))
    assert outs[0].round == 6 and k.done and "maximum of 2 episodes" in (k.done_reason or "")


def test_a_per_step_strategy_keeps_its_finishers_sharing_until_all_have_finished() -> None:
    from dataclasses import replace

    k, w = sync_keeper(max_episodes=100, k=2), fakes("w0", "w1")
    for e in range(1, PI_WINDOW):
        for a, b in zip(steps_of(w["w0"], e, 200.0, 2), steps_of(w["w1"], e, 20.0, 2), strict=True):
            k.submit(a, now=0.0)
            k.submit(b, now=0.0)
    finish = w["w0"].sub(PI_WINDOW, 200.0, mature=True)
    assert k.submit(replace(finish, step=1), now=0.0).reason == "invalid"  # a finish comes at step 0
    k.submit(finish, now=0.0)
    w1_steps = steps_of(w["w1"], PI_WINDOW, 20.0, 2)
    [out] = outcomes(k.submit(w1_steps[0], now=0.0))
    assert out.kind == "aggregate" and out.finished == ["w0"] and out.contributors == ["w0", "w1"]
    assert out.weights == {"w1": 1.0} and out.gradient is not None  # the learner's step is shared, not dropped
    rec = k.workers["w0"]
    assert rec.state == "finished" and rec.helping and rec.solved_episode == PI_WINDOW
    assert k.waiting_for() == ["w1"]  # round (10, 1): the finisher has no step 1 in its finishing episode
    k.submit(w1_steps[1], now=0.0)
    # From the next episode on the finisher is waited for again and its steps count (it helps) ...
    helper, learner = steps_of(w["w0"], PI_WINDOW + 1, 200.0, 2), steps_of(w["w1"], PI_WINDOW + 1, 20.0, 2)
    k.submit(learner[0], now=0.0)
    assert k.waiting_for() == ["w0"]
    [help_out] = outcomes(k.submit(helper[0], now=0.0))
    assert help_out.contributors == ["w0", "w1"] and help_out.weights == {"w0": 0.5, "w1": 0.5}
    # ... but it cannot finish twice, and its solve episode stays.
    again = k.submit(w["w0"].sub(PI_WINDOW + 2, 200.0, mature=True), now=0.0)
    assert again.reason == "finished" and rec.solved_episode == PI_WINDOW


def test_an_interrupted_run_keeps_its_open_round_and_resumes_through_the_saved_state(tmp_path) -> None:
    """Ctrl-C: the run ends as ``interrupted`` with its open round's submissions kept; the saved state says so, and
    a keeper restored from it goes on where it stopped (an aborted run stays over)."""
    from chief import checkpoint
    from chief.records import ServiceState
    from protocol.messages import INTERRUPTED

    k, w = keeper(["w0", "w1"]), fakes("w0", "w1")
    k.submit(w["w0"].sub(1, 20.0), 0.0)
    k.submit(w["w1"].sub(1, 30.0), 0.1)
    k.submit(w["w0"].sub(2, 22.0), 0.2)
    k.interrupt()
    assert (k.done, k.done_reason, k.interrupted, k.aborted, k.resumable) == (True, INTERRUPTED, True, False, True)
    assert k.submit(w["w1"].sub(2, 31.0), 0.3).reason == "run_over"
    k.abort("aborted: later")  # an interrupted run is already over: nothing changes
    assert (k.done_reason, k.aborted) == (INTERRUPTED, False)
    service = ServiceState(run_id="r", session="0" * 16, epoch=0, duplicates=0, hosts={}, update_steps=0, rejects={},
                           metrics_bytes=0, elapsed_s=0.0)
    checkpoint.save(tmp_path, k, service)
    loaded = checkpoint.load(tmp_path, CARTPOLE)
    assert loaded is not None
    back = loaded[0]
    assert (back.interrupted, back.resumable, back.round, sorted(back.pending)) == (True, True, 2, ["w0"])
    back.resume()
    assert (back.done, back.interrupted) == (False, False)
    [out] = outcomes(back.submit(Fake("w1").sub(2, 31.0), 1.0))
    assert (out.round, out.contributors) == (2, ["w0", "w1"])
    over = keeper(["w0"])
    over.abort("aborted: test")
    over.resume()
    assert (over.done, over.resumable) == (True, False)


def test_a_resumed_run_waits_again_for_the_workers_its_stop_left_offline() -> None:
    """A worker's storage fault stops the run resumably; the resumed run waits for that worker again, as the run
    that never stopped would have (it did not: its first round closed with the other worker alone, so that the
    resumed run's per-worker episodes differed from the clean run's). A worker that timed out stays excused."""
    k, w = keeper(["w0", "w1", "w2"], timeout=10.0), fakes("w0", "w1", "w2")
    for i in ("w0", "w1"):
        k.submit(w[i].sub(1, 20.0), 0.0)
    k.tick(11.0)  # w2 timed out: lagging
    assert k.workers["w2"].state == "lagging"
    k.note_status("w1", "storage", 11.5, "No space left on device (ENOSPC)")
    k.interrupt()
    assert (k.workers["w1"].state, k.workers["w1"].excused) == ("offline", True)
    k.resume()
    assert (k.workers["w1"].state, k.workers["w1"].excused) == ("active", False)
    assert k.workers["w2"].excused and k.waiting_for() == ["w0", "w1"]
    assert outcomes(k.submit(w["w0"].sub(2, 21.0), 12.0)) == []  # the round waits for w1
    [out] = outcomes(k.submit(w["w1"].sub(2, 22.0), 12.1))
    assert out.contributors == ["w0", "w1"]


def test_a_worker_that_stopped_learning_is_reported_in_its_own_words() -> None:
    from chief.report import summarize

    k, w = keeper(["w0", "w1"]), fakes("w0", "w1")
    k.submit(w["w0"].sub(1, 20.0), now=1.0)
    k.note_status("w0", "error", now=2.0, detail="ResetFailed: simulated rig could not reset")
    k.note_status("w1", "offline", now=2.0, detail="connection lost")  # a last will: no words of its own
    rows = {r.id: r for r in summarize(k, "aborted").workers}
    assert rows["w0"].state == "offline" and rows["w0"].detail == "error: ResetFailed: simulated rig could not reset"
    assert rows["w1"].detail is None and "detail" not in rows["w1"].dump()


def test_a_fleet_is_drawn_as_one_collection_with_one_legend_entry(tmp_path: Path) -> None:
    """Past LEGEND_WORKERS the learning curve draws every worker's line in one collection under one legend entry
    (a thousand named lines took the chief 20 s at the end of a 1,024-device run)."""
    import matplotlib.image

    from chief.report import LEGEND_WORKERS, plot_learning_curves

    curves = {f"w{i}": [(e, float(e * (i % 7))) for e in range(1, 6)] for i in range(LEGEND_WORKERS + 1)}
    path = plot_learning_curves(tmp_path, curves, 195.0, "many")
    assert path is not None and matplotlib.image.imread(path).shape[0] > 100


def test_a_root_s_saved_state_keeps_its_tier_and_the_edges_partials_of_its_open_round(tmp_path) -> None:
    """A root of edges saved mid-round comes back a root, holding the partial sums, contributors and clipping factors
    (actors' and critics') it had; which edge each worker is behind is part of the service's state."""
    from chief import checkpoint, tiers
    from chief.records import ServiceState

    k = RoundKeeper(["w0", "w1"], "weighted", CARTPOLE, max_episodes=10, round_timeout=10.0, actor_spec=SPEC,
                    tier="root")
    part = tiers.Partial({"g": np.array([0.5], np.float32)}, 2.0, 1)
    k.add_partial(1, "e0", part, ["w0"], {"w0": 0.5}, {"w0": 0.25})
    service = ServiceState(run_id="r", session="0" * 16, epoch=0, duplicates=0, hosts={}, update_steps=0, rejects={},
                           metrics_bytes=0, elapsed_s=0.0, edges={"w0": "e0", "w1": "e1"})
    checkpoint.save(tmp_path, k, service)
    loaded = checkpoint.load(tmp_path, CARTPOLE)
    assert loaded is not None
    back, saved = loaded
    assert back.tier == "root" and saved["edges"] == {"w0": "e0", "w1": "e1"}
    [held] = back.partials[1].values()
    p = held.partial
    assert (p.total, p.count, p.uniform) == (2.0, 1, False)
    assert (held.contributors, held.clipped, held.critic_clipped) == (["w0"], {"w0": 0.5}, {"w0": 0.25})
    assert p.gradient is not None and p.gradient["g"].tolist() == [0.5]


def test_a_late_copy_of_a_partial_excuses_nobody_in_a_later_round() -> None:
    """An edge sends a round's partial again when its answer went missing; a copy that reaches the root after the
    round closed must not excuse, in the open round, the workers that edge had timed out back then (one of them is
    back and the open round waits for it)."""
    import dataclasses

    k = RoundKeeper(["w0", "w1"], "weighted", CARTPOLE, max_episodes=10, round_timeout=10.0, actor_spec=SPEC,
                    tier="root")
    w = fakes("w0", "w1")

    def header(worker: str, episode: int) -> Submission:  # a root takes submissions without their tensors
        return dataclasses.replace(w[worker].sub(episode, 20.0), gradient=None)

    k.submit(header("w0", 1), 0.0)
    [closed] = k.excuse(1, ["w1"], 0.1)  # w1's edge timed it out in round 1
    assert closed.round == 1 and k.workers["w1"].excused
    k.submit(header("w1", 2), 0.2)  # w1 is back
    [closed] = outcomes(k.submit(header("w0", 2), 0.3))
    assert closed.round == 2 and not k.workers["w1"].excused
    k.submit(header("w0", 3), 0.4)
    assert k.excuse(1, ["w1"], 0.5) == []  # the late copy of round 1's partial
    assert k.round == 3 and k.waiting_for() == ["w1"]


def test_a_scaled_critic_gradient_is_recorded_beside_the_actors() -> None:
    """Under a per-step strategy the critics' gradients are bounded too; the round record says by how much (an
    honest off-policy critic can exceed ten times the median: docs/explanation/faults.md)."""
    from dataclasses import replace

    ids = ["w0", "w1", "w2", "w3"]
    k = RoundKeeper(ids, "sync", CARTPOLE, max_episodes=2, round_timeout=10.0, actor_spec=SPEC,
                    critic_spec={"c": (1,)}, shape=RoundShape(per_episode=2))
    w = fakes(*ids)
    for f, cv in zip(w.values(), [1.0, 2.0, 3.0, 1e5], strict=True):
        v = k.submit(replace(f.sub(1, 20.0), step=0, critic_gradient={"c": np.array([cv], np.float32)}), now=0.0)
    [out] = outcomes(v)
    assert out.clipped == {} and out.critic_clipped == pytest.approx({"w3": 25.0 / 1e5})
    np.testing.assert_allclose(out.critic_gradient["c"], [0.25 * (1 + 2 + 3 + 25)], rtol=1e-6)
    record = out.record()
    assert record["critic_clipped"] == out.critic_clipped
    assert RoundRecord.model_validate(record).critic_clipped == out.critic_clipped
    plain = replace(out, critic_clipped={}).record()
    assert "critic_clipped" not in plain and "critic_clipped" not in RoundRecord.model_validate(plain).dump()


def test_a_finish_with_only_lagging_learners_says_why_and_the_summary_keeps_what_a_worker_said() -> None:
    """w2 said it stopped and w1 timed out: w0's finish transfers nothing, and the log says it is the lag (it said
    "policy weighted"); summary.json lists w2 as `stopped`, as it said, not `offline`."""
    from chief.report import summarize

    k, w = keeper(["w0", "w1", "w2"]), fakes("w0", "w1", "w2")
    for e in range(1, PI_WINDOW):
        for f in w.values():
            k.submit(f.sub(e, 200.0 if f.id == "w0" else 100.0), now=float(e))
    k.note_status("w2", "stopped", now=9.5, detail="interrupted")
    k.submit(w["w0"].sub(PI_WINDOW, 200.0, mature=True), now=10.0)
    [out] = k.tick(now=30.0)
    assert out.kind == "aggregate" and out.finished == ["w0"] and out.timed_out == ["w1"]
    assert k.why_no_transfer().startswith("w1 lagging, w2 offline (not answering")
    states = {s.id: s.state for s in summarize(k, "stopped").workers}
    assert states == {"w0": "finished", "w1": "lagging", "w2": "stopped"}
    assert keeper(["w0", "w1"], policy="independent").why_no_transfer() == "policy independent"


def test_reach_and_displacement_are_pure_rules() -> None:
    from chief.rounds import displaces, reachable

    assert reachable(5, 0, 5) == 5 and reachable(5, 2, 5) == 7 and reachable(5, 0, 7) == 7  # S ahead; a joiner
    assert displaces(7, previous_counted=False, already_counted=False) is None  # its worker went on: it counts
    assert "counted from its worker" in (displaces(7, previous_counted=False, already_counted=True) or "")
    assert "could have played round 7" in (displaces(7, previous_counted=True, already_counted=False) or "")


def test_an_update_for_a_round_its_worker_could_not_have_reached_never_displaces_the_real_one() -> None:
    """Issue 32: a forger sends, in w1's name, an update for round r + 2 (return 50, PI 50) while round r is open.
    Held, it counts nothing: w1's real rounds r, r + 1, r + 2 are counted as sent (none is refused as
    `inconsistent` or a duplicate), and the forgery is refused as unreachable when its round opens."""
    k, w = keeper(["w0", "w1"]), fakes("w0", "w1")
    for e in (1, 2):
        k.submit(w["w0"].sub(e, 20.0), now=0.0)
        k.submit(w["w1"].sub(e, 20.0), now=0.0)
    forged = Submission("w1", 5, 50.0, 50.0, recent_returns=(50.0,), steps=50, gradient={"g": np.zeros(1, np.float32)})
    assert k.round == 3 and k.submit(forged, now=0.0).status == "held"
    assert k.submit(forged, now=0.1).status == "duplicate"  # one held per worker and round
    taken: list[Verdict] = []
    for e in (3, 4, 5):
        assert k.submit(w["w0"].sub(e, 20.0), now=1.0).status == "accepted"
        v = k.submit(w["w1"].sub(e, 21.0 + e), now=1.0)
        assert v.status == "accepted", v.detail
        taken += [t for o in v.outcomes for t in o.taken_up]
    assert [(t.round, t.reason) for t in taken] == [(5, "unreachable")]
    assert k.round == 6 and k.workers["w1"].returns[5] == 26.0 and k.workers["w1"].pis[5] != 50.0
