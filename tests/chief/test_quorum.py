"""k-of-n rounds (RoundKeeper quorum k, docs/explanation/tiered.md): a round closes when k of the workers it waits
for submitted; a later submission for it is dropped (refused as ``late``, answered with the round's answer), and the
straggler is waited for again in the next round."""

from __future__ import annotations

import pytest

from chief.rounds import RoundKeeper
from protocol.rounds import RoundShape
from tests.chief.test_rounds import CARTPOLE, SPEC, fakes, outcomes


def test_a_round_closes_with_its_quorum_and_drops_the_late_submission() -> None:
    k = RoundKeeper(["w0", "w1", "w2", "w3"], "weighted", CARTPOLE, 100, 10.0, actor_spec=dict(SPEC), quorum=3)
    w = fakes("w0", "w1", "w2", "w3")
    assert outcomes(k.submit(w["w0"].sub(1, 50.0), 0.0)) == []
    assert outcomes(k.submit(w["w1"].sub(1, 60.0), 0.1)) == []
    [out] = outcomes(k.submit(w["w2"].sub(1, 70.0), 0.2))
    assert out.contributors == ["w0", "w1", "w2"] and out.late == ["w3"] and out.record()["late"] == ["w3"]
    assert sorted(out.weights) == ["w0", "w1", "w2"]  # Eq. 8 over the round's contributors
    late = k.submit(w["w3"].sub(1, 80.0), 0.3)
    assert (late.status, late.reason) == ("rejected", "late") and late.replay is out
    assert k.waiting_for() == ["w0", "w1", "w2", "w3"]  # the straggler is not excused: waited for in round 2
    for i, wid in enumerate(["w3", "w1", "w0"]):
        outs = k.submit(w[wid].sub(2, 90.0), 1.0 + i)
    assert [o.late for o in outcomes(outs)] == [["w2"]]


def test_fewer_workers_left_than_the_quorum_means_all_of_them() -> None:
    k = RoundKeeper(["w0", "w1"], "plain", CARTPOLE, 100, 10.0, actor_spec=dict(SPEC), quorum=2)
    w = fakes("w0", "w1")
    assert outcomes(k.submit(w["w0"].sub(1, 50.0), 0.0)) == []
    [out] = outcomes(k.submit(w["w1"].sub(1, 50.0), 0.1))
    assert out.late == [] and "late" not in out.record()


@pytest.mark.parametrize(("policy", "quorum", "tier"), [("sync", 2, "flat"), ("weighted", 5, "flat"),
                                                        ("weighted", 4, "root"), ("sync", 2, "edge")])
def test_a_quorum_needs_a_per_episode_strategy_and_enough_workers(policy: str, quorum: int,
                                                                             tier: str) -> None:
    with pytest.raises(ValueError, match="quorum"):
        RoundKeeper(["w0", "w1", "w2"], policy, CARTPOLE, 100, 10.0, quorum=quorum, tier=tier,  # type: ignore[arg-type]
                    shape=RoundShape(per_episode=3 if policy == "sync" else 1))
