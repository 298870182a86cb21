"""k-of-n rounds across edges (docs/explanation/tiered.md): each edge closes its part of a round with its share of k
(chief/tiers.py ``edge_quorum``), forwards a late worker's submission in a partial of its own, and the root counts k
across the partials, closing the rounds a flat keeper with the same quorum closes on the same arrivals."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from chief import checkpoint, tiers
from chief.checkpoint import ServiceState
from chief.rounds import RoundKeeper, RoundOutcome, Submission, Verdict
from tests.chief.test_rounds import CARTPOLE, SPEC, fakes, outcomes

IDS = ["w0", "w1", "w2", "w3"]
BEHIND = {"w0": "e0", "w2": "e0", "w1": "e1", "w3": "e1"}


@pytest.mark.parametrize(("k", "n", "behind", "share"), [
    (0, 4, 2, 0),  # no quorum: every worker
    (4, 4, 2, 2),  # k = n: every worker of the edge
    (3, 4, 2, 1),  # the round may miss one: so may each edge
    (15, 16, 4, 3),  # one straggler in 16 over 4 edges
    (1, 16, 4, 1),  # never below one
    (12, 16, 8, 4),
])
def test_an_edge_s_share_of_the_quorum(k: int, n: int, behind: int, share: int) -> None:
    assert tiers.edge_quorum(k, n, behind) == share


@pytest.mark.parametrize(("k", "n", "behind"), [(5, 4, 2), (3, 4, 5), (3, 4, 0)])
def test_an_impossible_share_is_refused(k: int, n: int, behind: int) -> None:
    with pytest.raises(ValueError, match="quorum"):
        tiers.edge_quorum(k, n, behind)


class Tiered:
    """Two edge keepers (their shares of k) and a root keeper (k), wired as chief/edge.py and chief/service.py wire
    them: an edge's every outcome goes to the root as a partial, then its contributors' submissions without tensors."""

    def __init__(self, k: int) -> None:
        def make(workers: list[str], tier: str, quorum: int) -> RoundKeeper:
            return RoundKeeper(workers, "weighted", CARTPOLE, 100, 10.0, actor_spec=dict(SPEC), tier=tier,  # type: ignore[arg-type]
                               quorum=quorum)

        self.root = make(IDS, "root", k)
        mine = {e: sorted(w for w in IDS if BEHIND[w] == e) for e in ("e0", "e1")}
        self.edges = {e: make(ws, "edge", tiers.edge_quorum(k, len(IDS), len(ws))) for e, ws in mine.items()}
        self.root_verdicts: list[Verdict] = []
        self.held: dict[tuple[str, int], Submission] = {}  # what an edge counted, until it is in a partial

    def submit(self, sub: Submission) -> tuple[Verdict, list[RoundOutcome]]:
        """The edge's verdict on ``sub``, and the root's outcomes of what the edge forwarded."""
        e = BEHIND[sub.worker_id]
        verdict = self.edges[e].submit(sub, 0.0)
        if verdict.status == "accepted":
            self.held[(sub.worker_id, verdict.round)] = sub
        closed: list[RoundOutcome] = []
        for part in verdict.outcomes:
            assert part.kind == "partial" and part.partial is not None
            if part.round >= self.root.round:
                self.root.add_partial(part.round, e, part.partial, part.contributors, part.clipped)
            for w in part.contributors:
                root_verdict = self.root.submit(replace(self.held.pop((w, part.round)), gradient={}), 0.0)
                self.root_verdicts.append(root_verdict)
                closed += root_verdict.outcomes
        return verdict, closed


def test_k_is_counted_across_edges_and_a_late_worker_is_forwarded_then_dropped_at_the_root() -> None:
    """Quorum 3 of 4 over 2 edges of 2: each edge's share is 1, so each forwards its first worker; the root has 2 of
    3. The next (w2, late at its edge) goes in a partial of its own and closes the root's round, as a flat keeper
    closes it on the same arrivals; the last (w3) is forwarded too, and the root refuses it as late."""
    flat, tiered, w = RoundKeeper(IDS, "weighted", CARTPOLE, 100, 10.0, actor_spec=dict(SPEC), quorum=3), Tiered(3), \
        fakes(*IDS)
    order = ["w0", "w1", "w2", "w3"]
    subs = {x: w[x].sub(1, 20.0 + 10 * i, gv=float(i + 1)) for i, x in enumerate(order)}
    expected: list[RoundOutcome] = []
    got: list[RoundOutcome] = []
    for x in order:
        flat_verdict = flat.submit(subs[x], 0.0)
        expected += flat_verdict.outcomes
        verdict, closed = tiered.submit(subs[x])
        assert verdict.status == "accepted", (x, verdict.reason)  # every edge forwards: the root decides
        got += closed
    [want], [out] = expected, got
    assert (out.contributors, out.late, out.weights) == (want.contributors, want.late, want.weights)
    assert out.contributors == ["w0", "w1", "w2"] and out.late == ["w3"]
    assert out.edges == {"e0": ["w0", "w2"], "e1": ["w1"]} and out.parts == 3 and out.record()["partials"] == 3
    assert out.gradient is not None and want.gradient is not None
    learners = {x: subs[x].gradient for x in want.contributors}
    assert tiers.excess(learners, out.weights, out.parts, want.gradient, out.gradient) <= 1.0  # type: ignore[arg-type]
    last = tiered.root_verdicts[-1]
    assert (last.status, last.reason) == ("rejected", "late") and last.replay is out  # as the flat keeper's
    assert (flat_verdict.reason, flat.round, tiered.root.round) == ("late", 2, 2)
    # the straggler is waited for again in round 2, at its edge and at the root
    assert "w3" in tiered.edges["e1"].waiting_for() and "w3" in tiered.root.waiting_for()


def test_a_late_mature_actor_stays_refused_at_its_edge() -> None:
    """A finish is the root's to accept with its round: one that comes late to its edge is refused there as late,
    as a flat keeper refuses it (the worker finishes with a later episode)."""
    edge = RoundKeeper(["w0", "w2"], "weighted", CARTPOLE, 100, 10.0, actor_spec=dict(SPEC), tier="edge", quorum=1)
    w = fakes("w0", "w2")
    assert len(outcomes(edge.submit(w["w0"].sub(1, 20.0), 0.0))) == 1
    late = edge.submit(w["w2"].sub(1, 200.0, mature=True), 0.0)
    assert (late.status, late.reason) == ("rejected", "late") and late.ack is not None and not late.ack.accepted


def test_a_late_gradient_is_bounded_against_its_round(tmp_path: Path) -> None:
    """A late worker's gradient is bounded against the norms of its round's gradients at the edge (alone it would be
    its own median); and a root holding two partials of one edge saves and restores both."""
    edge = RoundKeeper(["w0", "w1", "w2"], "weighted", CARTPOLE, 100, 10.0, actor_spec=dict(SPEC), tier="edge",
                       quorum=2)
    w = fakes("w0", "w1", "w2")
    assert outcomes(edge.submit(w["w0"].sub(1, 20.0, gv=1.0), 0.0)) == []
    [first] = outcomes(edge.submit(w["w1"].sub(1, 20.0, gv=1.0), 0.0))
    [late] = outcomes(edge.submit(w["w2"].sub(1, 20.0, gv=1000.0), 0.0))
    assert late.contributors == ["w2"] and late.clipped == {"w2": pytest.approx(0.01)}
    root = RoundKeeper(IDS, "weighted", CARTPOLE, 100, 10.0, actor_spec=dict(SPEC), tier="root", quorum=3)
    for part in (first, late):
        assert part.partial is not None
        root.add_partial(1, "e0", part.partial, part.contributors, part.clipped)
    root.add_partial(1, "e0", first.partial, first.contributors, first.clipped)  # a copy sent again
    service = ServiceState(run_id="r", session="0" * 16, epoch=0, duplicates=0, hosts={}, update_steps=0, rejects={},
                           metrics_bytes=0, elapsed_s=0.0, edges={w: BEHIND[w] for w in IDS})
    checkpoint.save(tmp_path, root, service)
    loaded = checkpoint.load(tmp_path, CARTPOLE)
    assert loaded is not None
    assert sorted(loaded[0].partials[1]) == [("e0", ("w0", "w1")), ("e0", ("w2",))]
