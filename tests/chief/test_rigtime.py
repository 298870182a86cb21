"""Rig time (protocol/rigtime.py, chief/rigtime.py): the idle model, a qube-local federation's summary, the audit's
``rig-time`` check and the dashboard's rows."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from chief.audit import AuditFailure, audit
from chief.rigtime import last_rig, rig_times
from protocol.qube import PERIOD_S
from protocol.rigtime import IdleModel, model_idle
from runtime.records import EpisodeRecord, RoundRecord, RunSummary, StepRecord


def test_a_round_closes_when_its_slowest_rig_is_ready() -> None:
    # Round 1: a 3 s, b 5 s -> closes at 5, a waits 2. Round 2: a 4 s (ready 9), b 1 s (ready 6) -> b waits 3.
    assert model_idle([{"a": 3.0, "b": 5.0}, {"a": 4.0, "b": 1.0}]) == {"a": 2.0, "b": 3.0}


def test_a_rig_that_sits_a_round_out_neither_waits_nor_moves() -> None:
    model = IdleModel()
    assert model.close({"a": 1.0, "b": 2.0}) == 2.0
    assert model.close({"b": 5.0}) == 7.0  # a finished: b alone, nobody waits
    assert model.idle == {"a": 1.0, "b": 0.0}
    assert model.close({"a": 1.0, "b": 0.0}) == 7.0  # a rejoins from its own clock (2 + 1 = 3): waits 4 for b
    assert model.idle == {"a": 5.0, "b": 0.0}
    assert model.close({}) == 7.0 and model_idle([]) == {}


def test_a_per_step_round_spends_no_rig_time() -> None:
    # K = 2: step 0 carries the episode's rig time, step 1 none; nobody waits at step 1.
    assert model_idle([{"a": 2.0, "b": 1.0}, {"a": 0.0, "b": 0.0}]) == {"a": 0.0, "b": 1.0}


def _ep(worker: str, round_: int, steps: int, reset: float, idle: float | None = None) -> EpisodeRecord:
    return EpisodeRecord(worker=worker, round=round_, episode=round_, **{"return": float(steps)}, pi=1.0,
                         steps=steps, kind="update", balance_steps=steps, balance_s=steps * PERIOD_S, reset_s=reset,
                         idle_s=idle)


def test_rig_times_sum_the_records_and_model_idle_only_when_not_measured() -> None:
    records: list[EpisodeRecord | StepRecord | RoundRecord] = [
        _ep("a", 1, 100, 3.0), _ep("b", 1, 200, 1.0, idle=0.5), _ep("a", 2, 100, 1.0), _ep("b", 2, 100, 1.0, idle=9)]
    rigs = rig_times(records)
    assert rigs["a"].balance_steps == 200 and rigs["a"].balance_s == pytest.approx(1.4)
    assert rigs["a"].reset_s == 4.0 and rigs["a"].rig_s == pytest.approx(5.4) and rigs["a"].idle == "modelled"
    # a: round 1 ready at 3.7, b at 2.4 -> closes 3.7; round 2: a ready 5.4, b 5.1 -> a never waits.
    assert rigs["a"].idle_s == 0.0
    assert rigs["b"].idle == "measured" and rigs["b"].idle_s == 9.5
    last = last_rig(rigs)
    assert last is not None and last.id == "b"  # 4.1 s of rig time and 9.5 s idle: it finished last
    assert rig_times([EpisodeRecord(worker="a", round=1, episode=1, **{"return": 1.0}, pi=1.0, steps=1,
                                    kind="update")]) == {}


@pytest.fixture(scope="module")
def rig_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from deploy.inprocess import run_federation
    from deploy.settings import InprocessSettings

    run_dir = tmp_path_factory.mktemp("rigtime") / "run"
    run_federation(InprocessSettings.given(env="qube-local", policy="plain", seed=3, workers=2, max_episodes=4,
                   run_dir=run_dir), plot=False, tensorboard_files=False)
    return run_dir


def test_a_qube_local_federation_reports_each_rigs_time(rig_run: Path) -> None:
    summary = json.loads((rig_run / "summary.json").read_text())
    for w in summary["workers"]:
        rig = w["rig"]
        assert rig["balance_steps"] == w["steps"] > 0  # no worker solved in 4 episodes: every step counted
        assert rig["balance_s"] == pytest.approx(rig["balance_steps"] * 0.007, abs=1e-3)
        assert rig["reset_s"] > 0 and rig["rig_s"] == pytest.approx(rig["balance_s"] + rig["reset_s"], abs=1e-3)
        assert rig["idle"] == "modelled" and rig["idle_s"] >= 0
    # Each round waits for its slowest rig: some rig waited, and the last rig is the one whose clock ended latest.
    rigs = {w["id"]: w["rig"] for w in summary["workers"]}
    assert max(r["idle_s"] for r in rigs.values()) > 0
    last = summary["last_rig"]
    assert last["id"] == max(rigs, key=lambda w: rigs[w]["rig_s"] + rigs[w]["idle_s"])
    ends = {w: r["rig_s"] + r["idle_s"] for w, r in rigs.items()}  # every rig contributed to every round: all equal
    assert max(ends.values()) == pytest.approx(min(ends.values()), abs=2e-3)
    audit(rig_run)


def test_a_doctored_rig_record_fails_the_audit(rig_run: Path, tmp_path: Path) -> None:
    run_dir = tmp_path / "doctored"
    shutil.copytree(rig_run, run_dir)
    lines = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    next(x for x in lines if x["type"] == "episode")["reset_s"] += 10.0
    (run_dir / "metrics.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))
    with pytest.raises(AuditFailure) as failure:
        audit(run_dir)
    assert failure.value.invariant == "rig-time", str(failure.value)


def test_a_gymnasium_record_carries_no_rig_time() -> None:
    from runtime.records import line

    record = EpisodeRecord(worker="a", round=1, episode=1, **{"return": 1.0}, pi=1.0, steps=1, kind="update")
    assert "balance_s" not in line(record) and "reset_s" not in line(record)


def test_the_console_summary_prints_each_rigs_time(rig_run: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from deploy.run_local import print_rig_time

    summary = RunSummary.read(rig_run)
    print_rig_time(summary)
    out = capsys.readouterr().out
    assert summary.last_rig is not None and "balance steps" in out and f"last: {summary.last_rig.id}" in out
    assert all(w.rig is not None and f"{w.rig.rig_s:.1f}" in out for w in summary.workers)
    without = [w.model_copy(update={"rig": None}) for w in summary.workers]
    print_rig_time(summary.model_copy(update={"workers": without}))
    assert capsys.readouterr().out == ""
