"""The chief's saved state stays the same size however long the run (issue 34): a keeper forgets the returns, PIs
and counted rounds no submission can be checked against any more (chief/rounds.py HISTORY), and a chief resumed from
that bounded state decides every later round as the chief that never stopped."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from chief import checkpoint
from chief.rounds import HISTORY, RoundKeeper, Submission
from protocol.tasks import PI_WINDOW, task

SPEC = {"a": (3,)}
WORKERS = [f"w{i}" for i in range(6)]
SERVICE: dict[str, Any] = {"run_id": "bounded", "session": "s" * 16, "epoch": 1, "duplicates": 0, "hosts": {},
                           "update_steps": 10, "rejects": {}, "metrics_bytes": 0, "elapsed_s": 0.0}


def episode_return(i: int, episode: int) -> float:
    """Worker i balances from episode 40 + 15 i on (finishing ten episodes later); w5 never does."""
    return 200.0 if i < 5 and episode >= 40 + 15 * i else 40.0 + (episode * (i + 3)) % 17


class Fleet:
    """Deterministic workers: each submits its update (or, once PI >= TC over PI_WINDOW, its mature actor) every
    round, but w4, which is silent in episodes 20-29 (timed out, lagging) and comes back."""

    def __init__(self) -> None:
        self.returns: dict[str, list[float]] = {w: [] for w in WORKERS}
        self.done: set[str] = set()

    def submissions(self, episode: int) -> list[Submission]:
        out = []
        for i, w in enumerate(WORKERS):
            if w in self.done or (w == "w4" and 20 <= episode < 30):
                continue
            self.returns[w].append(episode_return(i, episode))
            recent = tuple(self.returns[w][-PI_WINDOW:])
            pi = float(np.mean(recent))
            mature = len(recent) == PI_WINDOW and pi >= task("CartPole-v0").tc
            arrays = {"a": np.full(3, 0.01 * (i + 1) * (1 + episode % 5), np.float32)}
            out.append(Submission(w, episode, pi, recent[-1], recent_returns=recent, steps=int(recent[-1]),
                                  gradient=None if mature else arrays, params=arrays if mature else None))
            if mature:
                self.done.add(w)
        return out


def play(keeper: RoundKeeper, fleet: Fleet, episodes: range) -> list[Any]:
    """Every round of ``episodes``: each verdict's (status, reason) and each closed round's record; a copy of the
    previous round's first submission is sent again each round (it is a duplicate, answered again)."""
    seen: list[Any] = []
    previous: list[Submission] = []
    for e in episodes:
        now = float(e * 10)
        subs = fleet.submissions(e)
        for sub in subs + previous[:1]:
            verdict = keeper.submit(sub, now)
            seen.append((sub.worker_id, sub.episode, verdict.status, verdict.reason,
                         [o.record() for o in verdict.outcomes]))
        seen += [o.record() for o in keeper.tick(now + 5.0)]
        previous = subs
    return seen


def test_a_resumed_keeper_decides_as_the_one_that_never_stopped_and_its_state_stays_bounded(tmp_path: Path) -> None:
    spec = task("CartPole-v0")

    def keeper() -> RoundKeeper:
        return RoundKeeper(WORKERS, "weighted", spec, 200, 1.0, actor_spec=SPEC)

    def size(k: RoundKeeper, name: str) -> int:
        folder = tmp_path / name
        folder.mkdir()
        return checkpoint.save(folder, k, SERVICE).stat().st_size

    straight, straight_fleet = keeper(), Fleet()
    play(straight, straight_fleet, range(1, 101))
    after = play(straight, straight_fleet, range(101, 160))

    stopped, fleet = keeper(), Fleet()
    play(stopped, fleet, range(1, 61))
    early = size(stopped, "early")
    play(stopped, fleet, range(61, 101))
    checkpoint.save(tmp_path, stopped, SERVICE)
    loaded = checkpoint.load(tmp_path, spec)
    assert loaded is not None
    resumed = loaded[0]
    assert play(resumed, fleet, range(101, 160)) == after  # every verdict and every round, as without the stop
    assert sorted(int(w[1:]) for w in WORKERS if resumed.workers[w].state == "finished") == [0, 1, 2, 3, 4]
    late = size(resumed, "late")
    assert late <= early * 1.05, (early, late)  # what grew with the run is forgotten
    for rec in resumed.workers.values():
        assert len(rec.returns) <= HISTORY + 16 and len(rec.pis) <= HISTORY + 17


def test_a_per_step_episode_longer_than_the_kept_answers_is_still_counted_step_by_step() -> None:
    """Under a per-step strategy an episode may have more rounds than the keeper keeps answers for (ANSWERS_KEPT):
    the counted round of its step 0, which each later step is checked against, is not forgotten before the episode
    ends (forgetting it refused every later step as ``out_of_order``, found by bench.behaviour's DQN sync run)."""
    from chief.rounds import ANSWERS_KEPT
    from protocol.rounds import RoundShape

    steps = ANSWERS_KEPT + 8
    k = RoundKeeper(["w0", "w1"], "sync", task("CartPole-v0"), 3, 1.0, actor_spec=SPEC, critic_spec=SPEC,
                    shape=RoundShape(per_episode=steps))
    returns: list[float] = []
    for episode in (1, 2, 3):
        returns.append(20.0 + episode)
        recent = tuple(returns[-PI_WINDOW:])
        for step in range(steps):
            for w in ("w0", "w1"):
                arrays = {"a": np.full(3, 0.01, np.float32)}
                verdict = k.submit(Submission(w, episode, float(np.mean(recent)), recent[-1], recent_returns=recent,
                                              steps=20, gradient=arrays, critic_gradient=arrays, step=step),
                                   float(episode * 1000 + step))
                assert verdict.status == "accepted", (episode, step, verdict.reason, verdict.detail)
    assert k.done


def test_the_state_is_built_as_its_models_would_dump_it() -> None:
    """``checkpoint.encoded`` builds the state's data without its models (a 1,024-worker root saves every round):
    its bytes are what ChiefState validates and dumps again, field for field, for a flat keeper mid-run (pending,
    held and finished workers, kept answers) and for a root holding an edge's partial of its open round."""
    import msgpack

    from chief import tiers
    from chief.records import ChiefState

    def fixed_point(k: RoundKeeper) -> None:
        raw = checkpoint.encoded(k, SERVICE)
        state = ChiefState.model_validate(msgpack.unpackb(raw, raw=False, strict_map_key=False))
        assert msgpack.packb(state.model_dump(), use_bin_type=True) == raw

    flat, fleet = RoundKeeper(WORKERS, "weighted", task("CartPole-v0"), 200, 1.0, actor_spec=SPEC), Fleet()
    play(flat, fleet, range(1, 70))
    for sub in fleet.submissions(70)[:2]:  # an open round with submissions pending
        flat.submit(sub, 700.0)
    assert flat.pending and flat.ids_in("finished")
    fixed_point(flat)

    root = RoundKeeper(WORKERS, "weighted", task("CartPole-v0"), 200, 1.0, actor_spec=SPEC, tier="root")
    root.add_partial(1, "e0", tiers.Partial({"a": np.ones(3, np.float32)}, 2.0, 3), WORKERS[:3], {"w1": 0.5})
    fixed_point(root)
