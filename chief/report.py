"""The run folder: ``metrics.jsonl`` (one line per accepted worker episode and per round: the records
``python -m chief.audit`` re-checks; one per refused submission that tells more of what its worker played),
``summary.json`` and ``learning_curve.png`` (each worker's last-10 average
return against episodes, TC dotted, like the paper's Fig. 5)."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol, TextIO

from chief.played import PlayedTally
from chief.rigtime import last_rig, rig_times
from chief.rounds import RoundKeeper, WorkerRecord
from protocol.messages import Played
from runtime.records import (
    METRICS,
    AnyRecord,
    EdgeRecord,
    EpisodeRecord,
    PlayedTotals,
    RefusedRecord,
    RigTime,
    RoundRecord,
    RunSummary,
    StepRecord,
    SummaryState,
    WorkerSummary,
    line,
    parse_record,
    read_metrics,
)
from runtime.storage import storage_errors

log = logging.getLogger(__name__)

Line = EpisodeRecord | StepRecord | RoundRecord
#: The most workers the learning curve names in its legend (beyond: one entry for them all).
LEGEND_WORKERS = 32


class RecordSink(Protocol):
    """Something fed every counted submission's and round's record as it is written (chief/tensorboard.py's Board)."""

    def record(self, record: Line) -> None: ...

    def close(self) -> None: ...


class MetricsLog:
    """Appends JSON lines to ``metrics.jsonl`` (each one a chief.records model), keeps each worker's PI curve for
    the plot and its played counts (chief/played.py), and passes every counted submission's and round's record on to
    the attached sinks."""

    def __init__(self, run_dir: Path, resume_at: int | None = None) -> None:
        """A new file, or (``resume_at``) the existing one cut back to that many bytes, its curves re-read."""
        self.path = run_dir / METRICS
        self.curves: dict[str, list[tuple[int, float]]] = {}
        self._timed: list[EpisodeRecord | StepRecord] = []  # what rig time is summed from (chief/rigtime.py)
        self._played = PlayedTally()
        self.sinks: list[RecordSink] = []
        with storage_errors(self.path):  # a full, read-only or foreign folder: one line, exit 5
            run_dir.mkdir(parents=True, exist_ok=True)
            if resume_at is None:
                self._file: TextIO = self.path.open("w", encoding="utf-8")
                return
            with self.path.open("r+b") as fh:
                fh.truncate(resume_at)
        for record in read_metrics(run_dir):
            self._note(record)
        self._file = self.path.open("a", encoding="utf-8")

    @property
    def offset(self) -> int:
        """Bytes written so far, on disk (what a saved state covers)."""
        self.flush()
        return self._file.tell()

    def flush(self) -> None:
        """Hand what was appended to the file system (the chief does after every message it handles: one write
        for an edge's partial of many records, not one per record)."""
        with storage_errors(self.path):
            self._file.flush()

    def episode(self, record: EpisodeRecord | StepRecord | Mapping[str, Any]) -> None:
        """An accepted submission (``type: episode``, or ``step`` for a later step of a per-step strategy); only what
        the chief counted is written."""
        typed = parse_record(record)
        if not isinstance(typed, (EpisodeRecord, StepRecord)):
            raise ValueError(f"not a submission's record: {typed.type}")
        self._write(typed)

    def refused(self, record: RefusedRecord | Mapping[str, Any]) -> bool:
        """A refused submission (chief.rounds.Verdict.refusal): written only when it tells more of what its worker
        played than the records hold; whether it was."""
        typed = record if isinstance(record, RefusedRecord) else RefusedRecord.model_validate(record)
        if not self._played.advances(typed.worker, typed.played):
            return False
        self._write(typed)
        return True

    def edge(self, record: EdgeRecord) -> None:
        """A tiered root's record of an edge's partial (runtime.records.EdgeRecord; built unchecked by the root from
        a message already validated): one line for all of its contributions."""
        self._write(record)

    def round(self, record: RoundRecord | Mapping[str, Any]) -> None:
        """A closed round (chief.rounds.RoundOutcome.record, with its time ``t``)."""
        self._write(record if isinstance(record, RoundRecord) else RoundRecord.model_validate(
            {"type": "round", **record}))

    def attach(self, sink: RecordSink | None) -> None:
        """Pass every record written from now on to ``sink`` too (None: nothing), and close it with the log."""
        if sink is not None:
            self.sinks.append(sink)

    def rigs(self, staleness: int = 0) -> dict[str, RigTime]:
        """Each rig's time so far ({} for the gymnasium tasks), its workers leaving up to ``staleness`` rounds
        unanswered."""
        return rig_times(self._timed, staleness)

    @property
    def played(self) -> dict[str, PlayedTotals]:
        """Each worker's played, counted and refused episodes and env steps so far ({} when no worker said)."""
        return self._played.totals()

    def _note(self, record: AnyRecord) -> None:
        if isinstance(record, EdgeRecord):
            if any(c.step or c.rig is not None for c in record.contributions):
                for sub in record.submissions():  # rig time is summed from records (chief/rigtime.py)
                    self._note(sub)
                return
            # Its counted episodes, noted as their records would be, without building them (a root notes 1,024 a
            # round; tests/chief/test_report.py holds the two ways to the same curves and counts).
            for c in record.contributions:
                self._counted(c.worker_id, c.episode, c.pi, c.steps, c.played)
            return
        if isinstance(record, EpisodeRecord):
            self._counted(record.worker, record.episode, record.pi, record.steps, record.played)
        else:
            self._played.add(record)
        if isinstance(record, StepRecord) or (isinstance(record, EpisodeRecord) and record.balance_steps is not None):
            self._timed.append(record)

    def _counted(self, worker: str, episode: int, pi: float, steps: int, played: Played | None) -> None:
        """A counted episode, from its record or an edge's contribution: its worker's counts, a point of its curve."""
        self._played.count(worker, steps, played)
        self.curves.setdefault(worker, []).append((episode, pi))

    def _write(self, record: AnyRecord) -> None:
        self._note(record)
        with storage_errors(self.path):
            self._file.write(line(record) + "\n")
        if isinstance(record, RefusedRecord):
            return
        if not self.sinks:
            return
        subs: list[Line] = [*record.submissions()] if isinstance(record, EdgeRecord) else [record]
        for sub in subs:  # a tiered root's edge record: its contributions, as the sinks took them from its partials
            for sink in self.sinks:
                sink.record(sub)

    def close(self) -> None:
        with storage_errors(self.path):
            self._file.close()
        for sink in self.sinks:
            sink.close()
        self.sinks.clear()


def summary_state(rec: WorkerRecord) -> SummaryState:
    """A worker's state in summary.json: ``stopped`` when it said so itself before it went (the keeper has it
    offline, excused), else the keeper's state (``offline``: its will, or an error, which ``detail`` words)."""
    if rec.state == "offline" and rec.excused and (rec.detail or "").split(":", 1)[0] == "stopped":
        return "stopped"
    return rec.state


def summarize(keeper: RoundKeeper, reason: str, rigs: Mapping[str, RigTime] | None = None,
              played: Mapping[str, PlayedTotals] | None = None, **meta: Any) -> RunSummary:
    """summary.json: the task, the strategy, each worker's result (episodes and env steps until it solved, or so
    far; ``played``: everything it played, counted and refused apart, chief/played.py; ``rigs``: its rig time,
    chief/rigtime.py), the last worker's episodes and steps, the run's totals, the last rig's time, and ``meta``
    (run id, seed, wall time, broker, reject counts)."""
    rigs, played = rigs or {}, played or {}
    workers = []
    for index, (w, rec) in enumerate(keeper.workers.items()):
        solved = rec.state == "finished"
        workers.append(WorkerSummary(id=w, index=index, solved=solved,
                                     episodes=rec.solved_episode if solved else rec.last_episode,
                                     steps=rec.steps_at_solve if solved else rec.steps,
                                     final_pi=rec.pi, state=summary_state(rec), played=played.get(w), rig=rigs.get(w),
                                     detail=rec.detail or None if not solved else None))
    all_solved = all(w.solved for w in workers)
    last = max(workers, key=lambda x: (x.episodes, x.steps))
    return RunSummary(
        env=keeper.task.env_id, policy=keeper.policy, tc=keeper.tc, r_floor=keeper.r_floor,
        max_episodes=keeper.max_episodes, workers=workers,
        episodes_to_all_solved=last.episodes if all_solved else None,
        steps_of_last_worker=last.steps if all_solved else None,
        total_steps=sum(rec.steps for rec in keeper.workers.values()),
        played_steps=sum(p.steps for p in played.values()) if played else None,
        refused_steps=sum(p.refused_steps for p in played.values()) if played else None, rounds=keeper.round - 1,
        rounds_per_episode=keeper.rounds_per_episode, max_staleness=keeper.max_staleness,
        quorum=keeper.quorum or None, end_reason=reason,
        last_rig=last_rig(dict(rigs)), **meta)


def run_summary(keeper: RoundKeeper, reason: str, rigs: Mapping[str, RigTime] | None = None,
                played: Mapping[str, PlayedTotals] | None = None, **meta: Any) -> dict[str, Any]:
    """``summarize`` as the JSON data summary.json holds (what the launchers return)."""
    return summarize(keeper, reason, rigs, played, **meta).dump()


def write_summary(run_dir: Path, summary: RunSummary | Mapping[str, Any]) -> Path:
    """Write summary.json (a RunSummary, or its JSON data: validated first)."""
    typed = summary if isinstance(summary, RunSummary) else RunSummary.model_validate(summary)
    return typed.write(run_dir)


def plot_learning_curves(
    run_dir: Path, curves: dict[str, list[tuple[int, float]]], tc: float, title: str
) -> Path | None:
    """Fig. 5-style plot; returns None (and logs why) when matplotlib is missing or there is nothing to draw."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        log.warning("matplotlib is not installed; skipping learning_curve.png (pip install .[learn])")
        return None
    if not curves:
        log.warning("no episodes recorded; skipping learning_curve.png")
        return None
    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=110)
    if len(curves) <= LEGEND_WORKERS:
        for worker_id in sorted(curves):
            points = sorted(curves[worker_id])
            ax.plot([p[0] for p in points], [p[1] for p in points], label=worker_id, linewidth=1.4)
    else:  # one collection, one legend entry: a thousand lines and names would take the chief seconds to draw
        from matplotlib.collections import LineCollection

        ax.add_collection(LineCollection([sorted(c) for c in curves.values()], linewidths=0.5, alpha=0.5,
                                         label=f"{len(curves)} workers, one line each"))
        ax.autoscale_view()
    ax.axhline(tc, color="black", linestyle=":", linewidth=1.5, label=f"TC = {tc:g}")
    ax.set_xlabel("episode")
    ax.set_ylabel("average return of the last 10 episodes (PI)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    path = run_dir / "learning_curve.png"
    fig.savefig(path)
    plt.close(fig)
    return path
