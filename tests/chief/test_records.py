"""runtime/records.py: the run folder's records read back as written (same keys, same bytes), a bad line is named, and
the chief's saved state restores every worker's record field by field."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import msgpack
import pytest

from chief import checkpoint
from chief.records import SavedWorker, ServiceState
from chief.rounds import RoundKeeper, WorkerRecord
from protocol.tasks import task
from runtime.records import RoundRecord, RunSummary, StepRecord, line, parse_record, read_metrics
from tests.chief.test_audit import simulate

SERVICE = ServiceState(run_id="r", session="0" * 16, epoch=1, duplicates=2, hosts={"w0": "h"}, update_steps=3,
                       rejects={"stale": 1}, metrics_bytes=10, elapsed_s=1.5)


@pytest.mark.parametrize("policy", ["weighted", "sync"])
def test_every_line_reads_back_as_written(tmp_path: Path, policy: str) -> None:
    """A run folder written by the chief's writer: each line re-dumped from its model is the same bytes, and so is
    summary.json."""
    simulate(tmp_path, policy)
    texts = (tmp_path / "metrics.jsonl").read_text().splitlines()
    records = read_metrics(tmp_path)
    assert [line(r) for r in records] == texts
    assert {r.type for r in records} == ({"episode", "round", "step"} if policy == "sync" else {"episode", "round"})
    summary = RunSummary.read(tmp_path)
    assert json.dumps(summary.dump(), indent=2) + "\n" == (tmp_path / "summary.json").read_text()
    assert "mode" not in summary.dump() and summary.dump()["seed"] == 0  # left out when not given; null kept


def test_optional_fields_appear_only_when_carried() -> None:
    step = StepRecord(worker="w0", round=2, episode=1, step=1, t=0.5)
    assert "stats" not in line(step) and '"receipt":null' in line(step)
    with_stats = parse_record({**step.dump(), "stats": {"entropy": None}})
    assert line(with_stats).endswith('"stats":{"entropy":null}}')
    old = parse_record({**step.dump(), "ppo": {"entropy": 0.5}})  # a run folder from before learners had names
    assert old == with_stats.model_copy(update={"stats": {"entropy": 0.5}}) and '"ppo"' not in line(old)


def test_a_bad_line_is_named(tmp_path: Path) -> None:
    good = RoundRecord(round=1, episode=1, kind="aggregate", strategy="weighted", contributors=["w0"])
    (tmp_path / "metrics.jsonl").write_text(line(good) + "\n" + json.dumps({**good.dump(), "rogue": 1}) + "\n")
    with pytest.raises(ValueError, match=r"metrics\.jsonl line 2"):
        read_metrics(tmp_path)
    with pytest.raises(ValueError):
        parse_record({"type": "mystery"})


def test_the_saved_worker_is_the_worker_record_field_by_field() -> None:
    assert set(SavedWorker.model_fields) == {f.name for f in dataclasses.fields(WorkerRecord)}


def test_the_saved_state_restores_by_field_name(tmp_path: Path) -> None:
    keeper = RoundKeeper(["w0", "w1"], "weighted", task("CartPole-v0"), 50, 30.0, actor_spec={"g": (2,)})
    rec = keeper.workers["w1"]
    rec.state, rec.pi, rec.last_episode, rec.solved_episode, rec.steps = "finished", 196.0, 14, 14, 900
    rec.steps_at_solve, rec.last_round, rec.excused, rec.helping = 900, 15, True, True
    rec.returns, rec.pis = {13: 190.0, 14: 200.0}, {13: 180.0, 14: 196.0}
    keeper.round, keeper.counted = 15, {("w1", 14)}
    checkpoint.save(tmp_path, keeper, SERVICE)
    loaded = checkpoint.load(tmp_path, task("CartPole-v0"))
    assert loaded is not None
    restored, service = loaded
    assert restored.workers == keeper.workers and restored.round == 15 and restored.counted == {("w1", 14)}
    assert restored.actor_spec == {"g": (2,)} and ServiceState.model_validate(service) == SERVICE
    # the keys on disk are the fields' names
    state = msgpack.unpackb((tmp_path / checkpoint.FILENAME).read_bytes(), raw=False, strict_map_key=False)
    assert state["keeper"]["workers"][1]["worker_id"] == "w1" and state["service"]["metrics_bytes"] == 10


def test_a_saved_state_with_an_unknown_field_is_refused(tmp_path: Path) -> None:
    keeper = RoundKeeper(["w0"], "weighted", task("CartPole-v0"), 50, 30.0)
    checkpoint.save(tmp_path, keeper, SERVICE)
    path = tmp_path / checkpoint.FILENAME
    state = msgpack.unpackb(path.read_bytes(), raw=False, strict_map_key=False)
    state["keeper"]["workers"][0]["mood"] = "happy"
    path.write_bytes(msgpack.packb(state, use_bin_type=True))
    with pytest.raises(ValueError, match="cannot resume from"):
        checkpoint.load(tmp_path, task("CartPole-v0"))
