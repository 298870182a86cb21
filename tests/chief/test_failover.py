"""chief/failover.py: when an edge is dead, and where its workers go (pure, time passed in)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

from chief import failover
from chief.failover import WILL_GRACE, EdgeWatch, dead, fail_over, groups_of, silence_limit, stand_in
from chief.rounds import RoundKeeper, Submission
from chief.tiers import Partial
from protocol.rounds import RoundShape
from protocol.tasks import task
from protocol.topics import ROOT_EDGE

EDGES = {"w0": "e0", "w1": "e1", "w2": "e0", "w3": "e1", "w4": "e2"}


def test_an_edge_is_dead_after_its_will_and_a_grace_or_after_a_silence() -> None:
    assert not dead(last_heard=10.0, will_at=11.0, now=11.0 + WILL_GRACE - 0.01, round_timeout=30)
    assert dead(last_heard=10.0, will_at=11.0, now=11.0 + WILL_GRACE, round_timeout=30)
    # a will older than its last word: a broker restart delivered it, and the edge said online again since
    assert not dead(last_heard=12.0, will_at=11.0, now=13.5, round_timeout=30)
    assert silence_limit(30) == 10 and silence_limit(600) == failover.SILENCE_LIMIT and silence_limit(3) == 3
    assert not dead(last_heard=0.0, will_at=None, now=9.99, round_timeout=30)
    assert dead(last_heard=0.0, will_at=None, now=10.0, round_timeout=30)


def test_the_watch_finds_each_death_once_and_a_return() -> None:
    watch = EdgeWatch()
    watch.expect({"e0", "e1"}, now=0.0)
    watch.status("e0", True, 0.5, started=True)
    watch.status("e1", True, 0.5, started=True)
    watch.status("e0", False, 1.0)  # its will
    watch.status("e1", True, 1.5, started=True)
    assert watch.newly_dead(1.0 + WILL_GRACE - 0.1, 30) == []
    assert watch.newly_dead(1.0 + WILL_GRACE, 30) == ["e0"]
    assert watch.newly_dead(5.0, 30) == [] and watch.alive() == {"e1"}
    watch.alive_now("e0", 5.0)  # a late partial of the dead edge brings nothing back
    assert watch.alive() == {"e1"}
    assert watch.status("e0", True, 6.0, started=False)  # back
    assert watch.alive() == {"e0", "e1"}
    assert watch.status("e1", True, 6.0, started=False)  # it held the run, now says it holds none: it restarted
    assert not watch.status("e1", True, 7.0, started=False)
    assert watch.newly_dead(7.0 + silence_limit(30), 30) == ["e0", "e1"]


def test_a_dead_edges_group_goes_to_the_least_loaded_live_edge_of_its_site() -> None:
    watch = EdgeWatch()
    for e, site in (("e0", None), ("e1", None), ("e2", None)):
        watch.status(e, True, 0.0, site=site)
    watch.found_dead.add("e0")
    assert fail_over(["e0"], EDGES, {}, watch) == {"e0": "e2"}  # e2 serves 1 worker, e1 2
    assert groups_of("e2", EDGES, {"e0": "e2"}) == {"e0": ["w0", "w2"], "e2": ["w4"]}
    watch.found_dead.add("e2")  # then its stand-in dies: both groups go to the one left
    assert fail_over(["e2"], EDGES, {"e0": "e2"}, watch) == {"e0": "e1", "e2": "e1"}
    watch.status("e0", True, 9.0, started=False)  # e0 back; then e1 dies: every group goes to e0, its own back home
    watch.found_dead.add("e1")
    assert fail_over(["e1"], EDGES, {"e0": "e1", "e2": "e1"}, watch) == {"e1": "e0", "e2": "e0"}


def test_no_live_edge_of_its_site_sends_a_group_to_the_root() -> None:
    """A site with one edge (site brokers, Swarm, Kubernetes): its dead edge's workers go to the root itself, which
    is never a regular stand-in (it is not in the watch), and they stay there when their edge comes back."""
    watch = EdgeWatch()
    watch.status("a", True, 0.0, site="a")
    watch.status("b", True, 0.0, site="b")
    watch.found_dead.add("a")
    assert stand_in("a", watch.sites, watch.alive(), {}) == ROOT_EDGE
    moved = fail_over(["a"], {"w0": "a", "w1": "b"}, {}, watch)
    assert moved == {"a": ROOT_EDGE} and failover.served_by_root(moved) == ["a"]
    assert groups_of(ROOT_EDGE, {"w0": "a", "w1": "b"}, moved) == {"a": ["w0"]}
    watch.status("a", True, 5.0, started=False)  # back: the root keeps the group
    assert fail_over([], {"w0": "a", "w1": "b"}, moved, watch) == moved
    watch.status(ROOT_EDGE, True, 5.0, site="a")  # even were it heard, the root is no edge of a site
    watch.found_dead.add("b")
    assert fail_over(["b"], {"w0": "a", "w1": "b"}, moved, watch) == {"a": ROOT_EDGE, "b": ROOT_EDGE}


def test_a_keeper_that_joins_mid_run_starts_at_the_roots_round() -> None:
    """An edge that joins at round 8 of a per-step run (3 rounds an episode: episode 3, step 1): a later step of
    an episode whose step 0 came before it joined is not refused as out of order (the root checks it)."""
    keeper = RoundKeeper(["w0"], "sync", task("CartPole-v0"), 10, 30.0, shape=RoundShape(per_episode=3), tier="edge")
    keeper.join_at(8)  # episode 3, step 1
    assert keeper.round == 8 and keeper.joined == 8
    g = {"w": np.ones(3, np.float32)}
    verdict = keeper.submit(Submission("w0", 3, 9.0, 9.0, (9.0,), step=1, gradient=g, critic_gradient=g), 0.0)
    assert verdict.status == "accepted", verdict


def test_a_root_sums_no_worker_twice_from_overlapping_partials_of_one_group() -> None:
    """A dead edge's partial {w0} (it timed w2 out) and its stand-in's {w0, w2} of the same round: the fuller one
    supersedes; one that overlaps without holding the held one is not summed."""
    keeper = RoundKeeper(["w0", "w1", "w2"], "plain", task("CartPole-v0"), 10, 30.0, tier="root")
    one = Partial({"w": np.ones(2, np.float32)}, 1.0, 1)
    keeper.add_partial(1, "e0", one, ["w0"], {})
    keeper.add_partial(1, "e1", one, ["w1"], {})
    keeper.add_partial(1, "e0", Partial({"w": np.full(2, 2, np.float32)}, 2.0, 2), ["w0", "w2"], {})
    assert sorted(keeper.partials[1]) == [("e0", ("w0", "w2")), ("e1", ("w1",))]
    keeper.add_partial(1, "e0", one, ["w2", "w9"], {})
    assert sorted(keeper.partials[1]) == [("e0", ("w0", "w2")), ("e1", ("w1",))]


def test_a_launcher_reads_which_edge_the_root_found_dead() -> None:
    """deploy.run_local starts an edge again once the root's log says it is dead (``DEAD``, written and read here)."""
    from chief.failover import DEAD, dead_edge_in

    assert dead_edge_in(f"2026-12-05 05:10:17,660 chief WARNING {DEAD.format('e12')} (its last will)") == "e12"
    assert dead_edge_in("chief WARNING round 9: the workers of edge e0 go through edge e1 from now on") is None
    assert dead_edge_in("chief WARNING edge e0 is back: it rejoins at round 12") is None


def test_the_roots_edge_id_is_no_one_elses(tmp_path: Path) -> None:
    """ROOT_EDGE names the root standing in: an edge chief, a worker's --edge, a site (whose edge is named after it)
    and make-users.sh's --edge refuse it, with one clear line; the ACLs let the root publish as it, and let workers
    behind edges read the root's own topics."""
    from chief.settings import ChiefSettings
    from deploy.sites import Site
    from services.broker.embedded import run_acl
    from tests.paths import ROOT
    from worker.settings import WorkerSettings

    for make in (lambda: ChiefSettings.given(run_id="r", role="edge", edge_id=ROOT_EDGE),
                 lambda: WorkerSettings.given(run_id="r", worker_id="w0", edge=ROOT_EDGE),
                 lambda: Site.parse(f"{ROOT_EDGE}=2")):
        with pytest.raises(ValueError, match="root chief's"):
            make()
    done = subprocess.run([str(ROOT / "deploy" / "mosquitto" / "make-users.sh"), "--acl-only", "-o",
                           str(tmp_path / "out"), "--edge", ROOT_EDGE], capture_output=True, text=True)
    assert done.returncode == 2 and "root chief's own" in done.stderr and not (tmp_path / "out").exists()
    acl = run_acl("r", ["w0"], {}, {"w0": "e0"})
    assert "fedrl/r/edge/root/#" in acl["publish"]["chief"]
    assert "fedrl/r/chief/#" in acl["subscribe"]["w0"]
