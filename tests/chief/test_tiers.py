"""The partial-sum algebra of edge aggregation (chief/tiers.py): partials of any split of the contributors combine
to the flat Eq. 8-9 aggregate within the derived bound, for every strategy that can be split."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest

from chief import strategies, tiers

SPLITTABLE = [s for s in strategies.names() if tiers.decomposable(strategies.get(s))]


def _round(n: int, seed: int, zeros: int = 0) -> tuple[dict, dict]:
    rng = np.random.default_rng(seed)
    grads = {f"w{i:02d}": {"a": rng.normal(0, 10.0 ** rng.integers(-3, 3), (7, 5)).astype(np.float32),
                           "b": rng.normal(0, 1, 5).astype(np.float32)} for i in range(n)}
    progress = {w: (0.0 if i < zeros else float(rng.uniform(0, 1))) for i, w in enumerate(sorted(grads))}
    return grads, progress


def _split(ids: list[str], edges: int, seed: int) -> list[list[str]]:
    rng = np.random.default_rng(seed)
    cut = sorted(rng.choice(np.arange(1, len(ids)), size=edges - 1, replace=False).tolist()) if edges > 1 else []
    order = list(rng.permutation(ids))
    return [sorted(order[a:b]) for a, b in itertools.pairwise([0, *cut, len(ids)])]


def _tiered(strategy: strategies.Strategy, grads: dict, progress: dict, groups: list[list[str]]) -> dict | None:
    parts = [tiers.partial(strategy, {w: grads[w] for w in g}, progress) for g in groups]
    return tiers.combine(parts)[0]


def test_the_split_strategies_are_the_weighted_sums() -> None:
    assert SPLITTABLE == ["independent", "plain", "sync", "weighted"]
    for name in ("median", "trimmed"):
        assert not tiers.decomposable(strategies.get(name))
        assert "runs flat" in tiers.why_flat(strategies.get(name))


@pytest.mark.parametrize("policy", ["plain", "sync", "weighted"])
@pytest.mark.parametrize(("n", "edges", "zeros"), [(2, 2, 0), (5, 2, 1), (16, 4, 0), (33, 5, 3), (64, 16, 0),
                                                   (6, 3, 6), (9, 3, 4)])
def test_partials_combine_to_the_flat_aggregate(policy: str, n: int, edges: int, zeros: int) -> None:
    strategy = strategies.get(policy)
    for seed in range(3):
        grads, progress = _round(n, seed, zeros)
        flat = strategy.aggregate(grads, progress)
        assert flat.gradient is not None and flat.weights is not None
        assert tiers.weights(tiers.shares(strategy, progress)) == flat.weights  # Eq. 8, bit for bit
        tiered = _tiered(strategy, grads, progress, _split(sorted(grads), edges, seed))
        assert tiered is not None
        assert tiers.excess(grads, flat.weights, edges, flat.gradient, tiered) <= 1.0
        # one edge holding everyone is the flat round
        whole = _tiered(strategy, grads, progress, [sorted(grads)])
        assert whole is not None and tiers.excess(grads, flat.weights, 1, flat.gradient, whole) <= 1.0


def test_weights_are_normalised_over_all_contributors_not_per_edge() -> None:
    """Two edges with different share totals: averaging the edges' own means would weigh them equally."""
    strategy = strategies.get("weighted")
    grads = {"a": {"x": np.array([1.0], np.float32)}, "b": {"x": np.array([3.0], np.float32)},
             "c": {"x": np.array([10.0], np.float32)}}
    progress = {"a": 0.5, "b": 0.5, "c": 0.25}
    tiered = _tiered(strategy, grads, progress, [["a", "b"], ["c"]])
    assert tiered is not None
    assert tiered["x"][0] == pytest.approx((0.5 * 1 + 0.5 * 3 + 0.25 * 10) / 1.25)


def test_an_edge_of_workers_at_the_floor_adds_nothing_unless_everyone_is() -> None:
    strategy = strategies.get("weighted")
    grads = {"a": {"x": np.array([1.0], np.float32)}, "b": {"x": np.array([5.0], np.float32)}}
    low = tiers.partial(strategy, {"a": grads["a"]}, {"a": 0.0})
    assert low.uniform and low.total == 0.0
    high = tiers.partial(strategy, {"b": grads["b"]}, {"b": 0.3})
    assert tiers.combine([low, high])[0]["x"][0] == pytest.approx(5.0)  # type: ignore[index]
    both_low = tiers.partial(strategy, {"b": grads["b"]}, {"b": 0.0})
    assert tiers.combine([low, both_low])[0]["x"][0] == pytest.approx(3.0)  # type: ignore[index]


def test_nothing_to_share_and_the_bound_catches_a_wrong_sum() -> None:
    grads, progress = _round(4, 0)
    assert tiers.combine([tiers.partial(strategies.get("independent"), grads, progress)]) == (None, None)
    strategy = strategies.get("weighted")
    flat = strategy.aggregate(grads, progress)
    assert flat.gradient is not None and flat.weights is not None
    wrong = {k: v * np.float32(1.0001) for k, v in flat.gradient.items()}
    assert tiers.excess(grads, flat.weights, 2, flat.gradient, wrong) > 1.0


def test_per_step_critics_are_split_too() -> None:
    strategy = strategies.get("sync")
    grads, progress = _round(6, 1)
    critics, _ = _round(6, 2)
    flat = strategy.aggregate(critics, progress)
    assert flat.gradient is not None and flat.weights is not None
    parts = [tiers.partial(strategy, {w: grads[w] for w in g}, progress, {w: critics[w] for w in g})
             for g in (["w00", "w03"], ["w01", "w02", "w04", "w05"])]
    critic = tiers.combine(parts)[1]
    assert critic is not None and tiers.excess(critics, flat.weights, 2, flat.gradient, critic) <= 1.0


def test_edge_and_root_keepers_close_the_flat_round() -> None:
    """Two edge keepers and a root keeper (chief/rounds.py tiers) close the rounds a flat keeper closes on the same
    submissions: the same contributors, Eq. 8 weights and, within the bound, Eq. 9 (transfers through the edges:
    tests/e2e/test_tiered.py)."""
    from chief.rounds import RoundKeeper
    from tests.chief.test_rounds import CARTPOLE, SPEC, fakes

    ids = ["w0", "w1", "w2", "w3"]
    behind = {"e0": ["w0", "w2"], "e1": ["w1", "w3"]}

    def make(workers: list[str], tier: str) -> RoundKeeper:
        return RoundKeeper(workers, "weighted", CARTPOLE, 100, 10.0, actor_spec=dict(SPEC), tier=tier)  # type: ignore[arg-type]

    flat, root = make(ids, "flat"), make(ids, "root")
    edges = {e: make(ws, "edge") for e, ws in behind.items()}
    w = fakes(*ids)
    for episode in range(1, 4):
        subs = {x: w[x].sub(episode, 20.0 + 10 * i, gv=float(i + 1)) for i, x in enumerate(ids)}
        [expected] = [o for x in ids for o in flat.submit(subs[x], 0.0).outcomes]
        for e, ws in behind.items():
            [part] = [o for x in ws for o in edges[e].submit(subs[x], 0.0).outcomes]
            assert part.kind == "partial" and part.partial is not None and part.contributors == ws
            root.add_partial(part.round, e, part.partial, part.contributors, part.clipped)
            outs = [o for x in ws for o in root.submit(replace(subs[x], gradient={}), 0.0).outcomes]
        [got] = outs
        assert (got.contributors, got.weights, got.edges) == (expected.contributors, expected.weights, behind)
        assert got.gradient is not None and expected.gradient is not None
        learners = {x: subs[x].gradient for x in ids}
        assert tiers.excess(learners, got.weights, 2, expected.gradient, got.gradient) <= 1.0  # type: ignore[arg-type]


def test_the_root_records_the_factors_its_edges_scaled_critics_by() -> None:
    """Under a per-step strategy an edge bounds its workers' critics as a flat chief does (chief/rounds.py
    bound_norms, against the edge's median); its partial carries the factors, and the root's round says them as a
    flat round would (``critic_clipped``), beside the actors' (``clipped``)."""
    from chief.rounds import RoundKeeper, RoundShape
    from protocol.messages import EdgePartial
    from tests.chief.test_rounds import CARTPOLE, SPEC, fakes

    ids = ["w0", "w1", "w2", "w3", "w4", "w5"]
    behind = {"e0": ["w0", "w1", "w2"], "e1": ["w3", "w4", "w5"]}

    def make(workers: list[str], tier: str) -> RoundKeeper:
        return RoundKeeper(workers, "sync", CARTPOLE, 2, 10.0, actor_spec=dict(SPEC), critic_spec={"c": (1,)},
                           shape=RoundShape(per_episode=2), tier=tier)  # type: ignore[arg-type]

    root, edges, w = make(ids, "root"), {e: make(ws, "edge") for e, ws in behind.items()}, fakes(*ids)
    critic = dict(zip(ids, [1.0, 2.0, 1e5, 1.0, 1.0, 1.0], strict=True))  # w2's critic: far above its edge's median
    subs = {x: replace(w[x].sub(1, 20.0), step=0, critic_gradient={"c": np.array([critic[x]], np.float32)})
            for x in ids}
    outs = []
    for e, ws in behind.items():
        [part] = [o for x in ws for o in edges[e].submit(subs[x], 0.0).outcomes]
        assert part.critic_clipped == (pytest.approx({"w2": 20.0 / 1e5}) if e == "e0" else {})
        wire = EdgePartial(edge_id=e, round=1, episode=1, clipped=part.clipped, critic_clipped=part.critic_clipped)
        assert EdgePartial.model_validate(wire.model_dump()).critic_clipped == part.critic_clipped
        assert part.partial is not None
        root.add_partial(1, e, part.partial, part.contributors, part.clipped, wire.critic_clipped)
        outs += [o for x in ws for o in root.submit(replace(subs[x], gradient={}, critic_gradient=None), 0.0).outcomes]
    [got] = outs
    assert got.clipped == {} and got.critic_clipped == pytest.approx({"w2": 20.0 / 1e5})
    assert got.record()["critic_clipped"] == got.critic_clipped
