"""Issue 19, counting: env steps and episodes count everything a worker played, including episodes whose submission
the chief refused (stale, out of window), reported apart from what it counted (summary.json, chief/played.py)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from chief.audit import audit
from chief.played import played_totals
from protocol.messages import ChiefAck, ChiefAggregate, Played, WorkerUpdate
from protocol.tensors import pack_arrays
from runtime.records import parse_record
from tests.chief.test_chief_service import HISTORY, ScriptedWorkers, mature, start_chief, update

STEPS = 10  # the scripted workers' env steps per episode (tests/chief/test_chief_service.py)


def played(worker: str, episodes: int) -> Played:
    """What a scripted worker that played ``episodes`` episodes says it played."""
    return Played(life=f"{sum(map(ord, worker)):016x}", episodes=episodes, steps=STEPS * episodes)


def test_a_stale_workers_episodes_are_played_not_counted(amqtt_broker: str, tmp_path: Path) -> None:
    """w1 stalls after episode 1; round 2 times out without it and w0 goes on alone. w1 then sends episodes 2-9,
    applying each closed round's answer as it comes back (as a real worker does): stale, refused, yet its env steps
    are on record: it played 10 episodes, 2 were counted."""
    run_dir = tmp_path / "run"
    chief = start_chief(amqtt_broker, run_dir, workers=2, round_timeout=1.0)
    fake = ScriptedWorkers(amqtt_broker)
    HISTORY.clear()
    try:
        fake.join("w0", "w1")
        for w in ("w0", "w1"):
            fake.send(w, update(w, 1, 200.0, [1.0, 1.0]).model_copy(update={"played": played(w, 1)}))
        answer = first = fake.expect(ChiefAggregate, timeout=10)
        assert answer.episode == 1
        for e in range(2, 10):  # w1 is silent: round 2 waits out its timeout, then w0 alone closes each round
            mine = update("w0", e, 200.0, [1.0, 1.0], after=answer)
            fake.send("w0", mine.model_copy(update={"played": played("w0", e)}))
            answer = fake.expect(ChiefAggregate, timeout=10)
            assert answer.episode == e
        late = first
        for e in range(2, 10):  # w1 wakes up: its episodes are for closed rounds
            mine = update("w1", e, 200.0, [1.0, 1.0], after=late)
            fake.send("w1", mine.model_copy(update={"played": played("w1", e)}))
            late = fake.expect(ChiefAggregate, timeout=10)
            assert late.episode == e  # the round's answer, again
        HISTORY["w1"] = [200.0] * 9
        finish = mature("w1", 10, 200.0, [1.0, 1.0], after=late)
        fake.send("w1", finish.model_copy(update={"played": played("w1", 10)}))
        assert fake.expect(ChiefAck, timeout=10).accepted  # w1 is back: round 10 waits for w0 again
        finish = mature("w0", 10, 200.0, [1.0, 1.0], after=answer)
        fake.send("w0", finish.model_copy(update={"played": played("w0", 10)}))
        assert chief.wait(timeout=20) == 0
    finally:
        fake.conn.stop()
        if chief.poll() is None:
            chief.kill()
    summary = json.loads((run_dir / "summary.json").read_text())
    rows = {w["id"]: w for w in summary["workers"]}
    assert rows["w1"]["played"] == {"episodes": 10, "steps": 100, "counted_episodes": 2, "counted_steps": 20,
                                    "refused_episodes": 8, "refused_steps": 80}
    assert rows["w1"]["played"]["steps"] > rows["w1"]["played"]["counted_steps"] == rows["w1"]["steps"]
    assert rows["w0"]["played"]["refused_steps"] == 0 and rows["w0"]["played"]["steps"] == 100
    assert (summary["total_steps"], summary["played_steps"], summary["refused_steps"]) == (120, 200, 80)
    assert summary["rejected_messages"] == {"stale": 8}
    lines = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    refused = [x for x in lines if x["type"] == "refused"]
    assert [(x["worker"], x["episode"], x["reason"]) for x in refused] == [("w1", e, "stale") for e in range(2, 10)]
    audit(run_dir)


def test_a_restarted_worker_counts_its_lives_apart() -> None:
    """A worker that restarted (a new life) starts its counts again: what it played is the sum over its lives; an
    older count on record (a refused resend) lowers nothing."""
    def played_(life: str, episodes: int) -> dict:
        return {"life": life * 16, "episodes": episodes, "steps": STEPS * episodes}

    def counted(n: int, life: str, episodes: int) -> dict:
        return {"type": "episode", "worker": "w0", "round": n, "episode": n, "return": 1.0, "pi": 1.0, "steps": STEPS,
                "kind": "update", "played": played_(life, episodes)}

    refused = {"type": "refused", "worker": "w0", "round": 1, "episode": 1, "kind": "update", "reason": "stale",
               "steps": STEPS, "played": played_("a", 2)}
    records = [parse_record(x) for x in (counted(1, "a", 1), counted(2, "a", 3), refused, counted(3, "b", 1),
                                         counted(4, "b", 2))]
    totals = played_totals(records)["w0"]
    assert (totals.episodes, totals.steps, totals.counted_episodes, totals.counted_steps) == (5, 50, 4, 40)
    assert (totals.refused_episodes, totals.refused_steps) == (1, 10)


def test_played_counts_below_the_episode_are_refused_in_one_line() -> None:
    with pytest.raises(ValidationError, match=r"played.steps 5 is less than this episode's 10 steps"):
        WorkerUpdate(worker_id="w0", episode=1, episode_return=1.0, pi=1.0, recent_returns=(1.0,), steps=10,
                     gradient=pack_arrays({"w": np.zeros(2, np.float32)}),
                     played=Played(life="0" * 16, episodes=1, steps=5))
