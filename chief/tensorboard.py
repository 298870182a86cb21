"""TensorBoard event files of a run, made from the chief's records: ``RUN_DIR/tensorboard/<worker>/events.out.*``.

``tensorboard --logdir RUN_DIR/tensorboard`` shows one run per worker. The x axis (global step) is that worker's env
steps so far, as counted by the chief (its accepted episodes' ``steps``). Tags, CleanRL's names where CleanRL has one:

- ``charts/episodic_return``, ``charts/episodic_length``, ``charts/performance_index``: every accepted episode;
- ``losses/policy_loss``, ``losses/value_loss``, ``losses/entropy``, ``losses/approx_kl``, ``losses/clipfrac``: the
  update statistics the worker sent with its update (the means over the episode's K mini-batch steps; under a
  per-step strategy the mean of the steps' own); none for the episode it finished with (no update) or what it did
  not send (SAC and DQN send no ``approx_kl`` or ``clip_fraction``, which are PPO's, and DQN no entropy);
- ``federation/contribution_weight``: its weight w_n in each aggregate it contributed to (Eq. 8 for ``weighted``;
  under a per-step strategy the mean over the episode's K rounds); ``federation/keep_weight``: its w_T in each
  transfer it received (Eq. 10); ``federation/transfers``: how many transfers it has received. These are drawn at
  the worker's env steps when the round closed.

Only what ``metrics.jsonl`` holds is drawn (what the chief accepted), through one translation (``Translator``): the
chief writes live, record by record as it appends them (``open_board``), and ``python -m chief.tensorboard RUN_DIR``
(re)builds the files from a run's ``metrics.jsonl`` afterwards. A run of more than ``LIVE_WORKERS`` workers is drawn
once, at its end (``live``): a live board holds a writer per worker (an open file and a thread each) and would cost
the chief time in every round; the rebuild opens at most ``LIVE_WORKERS`` writers at a time. Writing needs
``tensorboardX`` (``pip install .[tb]``); without it the chief logs one line and runs on without event files.
"""

from __future__ import annotations

import argparse
import datetime as dt
import logging
import sys
import time
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from runtime.records import (
    METRICS,
    AnyRecord,
    EdgeRecord,
    EpisodeRecord,
    RoundRecord,
    RunSummary,
    StepRecord,
    read_metrics,
)

Line = EpisodeRecord | StepRecord | RoundRecord

log = logging.getLogger(__name__)

FOLDER = "tensorboard"
EVENT_FILES = "events.out.tfevents.*"
#: The most workers whose event files the chief writes live, and the most writers open at once in a rebuild.
LIVE_WORKERS = 64

#: WorkerUpdate's PPO statistics (protocol.messages.STAT_BOUNDS) -> CleanRL's tags.
LOSS_TAGS = {
    "actor_loss": "losses/policy_loss",
    "critic_loss": "losses/value_loss",
    "entropy": "losses/entropy",
    "approx_kl": "losses/approx_kl",
    "clip_fraction": "losses/clipfrac",
}
RETURN_TAG = "charts/episodic_return"
LENGTH_TAG = "charts/episodic_length"
PI_TAG = "charts/performance_index"
WEIGHT_TAG = "federation/contribution_weight"
KEEP_TAG = "federation/keep_weight"
TRANSFERS_TAG = "federation/transfers"


@dataclass(frozen=True)
class Point:
    """One scalar of one worker's run."""

    worker: str
    tag: str
    value: float
    step: int
    t: float  # seconds since the chief started (the record's ``t``)


@dataclass
class _Worker:
    env_steps: int = 0
    transfers: int = 0
    last_step: int = 0
    pending: list[dict[str, float | None]] = field(default_factory=list)  # a per-step episode's statistics so far
    pending_at: tuple[int, float] = (0, 0.0)


class Translator:
    """metrics.jsonl records -> scalar points, one record at a time (pure: no files).

    ``rounds_per_episode`` (K) > 1 is a per-step strategy: an episode's statistics come in K records (the episode and
    its later steps) and are drawn as their mean once its last step is in (or the next episode, or ``finish``).
    """

    def __init__(self, rounds_per_episode: int = 1) -> None:
        """``rounds_per_episode``: K of the run (1 for the paper's strategies)."""
        self.rounds_per_episode = max(1, rounds_per_episode)
        self.workers: dict[str, _Worker] = defaultdict(_Worker)
        self._weights: dict[str, list[float]] = defaultdict(list)  # the open episode's rounds' weights, per worker
        self._weights_episode = 0
        self._weights_t = 0.0

    def feed(self, record: EpisodeRecord | StepRecord | RoundRecord) -> list[Point]:
        """The points a record adds."""
        if isinstance(record, EpisodeRecord):
            return self._episode(record)
        if isinstance(record, StepRecord):
            w = self.workers[record.worker]
            if record.stats is not None:
                w.pending.append(record.stats)
            if record.step >= self.rounds_per_episode - 1:
                return self._flush(record.worker)
            return []
        return self._round(record)

    def finish(self) -> list[Point]:
        """What is still held back (a per-step episode whose last step never came)."""
        return self._flush_weights() + [p for worker in list(self.workers) for p in self._flush(worker)]

    def _point(self, worker: str, tag: str, value: float, t: float, step: int | None = None) -> Point:
        w = self.workers[worker]
        # Never backwards within a worker's file: TensorBoard drops what lies after a step that goes back.
        w.last_step = max(w.last_step, w.env_steps if step is None else step)
        return Point(worker, tag, float(value), w.last_step, t)

    def _episode(self, record: EpisodeRecord) -> list[Point]:
        worker, t = record.worker, record.t
        points = self._flush(worker)
        w = self.workers[worker]
        w.env_steps += record.steps
        points.append(self._point(worker, LENGTH_TAG, record.steps, t))
        points.append(self._point(worker, RETURN_TAG, record.return_, t))
        points.append(self._point(worker, PI_TAG, record.pi, t))
        w.pending = [record.stats] if record.stats is not None else []
        w.pending_at = (w.env_steps, t)
        if self.rounds_per_episode == 1:
            points += self._flush(worker)
        return points

    def _flush_weights(self) -> list[Point]:
        """Each worker's contribution weight in the rounds of one episode (their mean, with K rounds per episode)."""
        weights, self._weights = self._weights, defaultdict(list)
        return [self._point(w, WEIGHT_TAG, sum(v) / len(v), self._weights_t) for w, v in sorted(weights.items())]

    def _flush(self, worker: str) -> list[Point]:
        w = self.workers[worker]
        stats, w.pending = w.pending, []
        step, t = w.pending_at
        points = []
        for key, tag in LOSS_TAGS.items():
            values = [v for s in stats if (v := s.get(key)) is not None]
            if values:
                points.append(self._point(worker, tag, sum(values) / len(values), t, step))
        return points

    def _round(self, record: RoundRecord) -> list[Point]:
        episode, t = record.episode, record.t
        points = self._flush_weights() if episode != self._weights_episode else []
        self._weights_episode, self._weights_t = episode, t
        for w, weight in record.weights.items():
            self._weights[w].append(weight)
        if record.step >= self.rounds_per_episode - 1:
            points += self._flush_weights()
        if record.kind == "transfer":
            for w, keep in sorted(record.keep_weights.items()):
                self.workers[w].transfers += 1
                points.append(self._point(w, KEEP_TAG, keep, t))
                points.append(self._point(w, TRANSFERS_TAG, self.workers[w].transfers, t))
        return points


class Board:
    """Writes a run's points into one event-file folder per worker (tensorboardX), from the records fed to it."""

    def __init__(self, root: Path, translator: Translator, wall_start: float, writer_class: Any,
                 only: set[str] | None = None) -> None:
        """``only``: write these workers' points alone (a rebuild in groups; the translation still sees every
        record)."""
        self.root = root
        self.translator = translator
        self.wall_start = wall_start
        self._writer_class = writer_class
        self._writers: dict[str, Any] = {}
        self.only = only
        self.points = 0
        self.failed = False

    def record(self, record: EpisodeRecord | StepRecord | RoundRecord) -> None:
        """Draw one metrics.jsonl record. A failure to write is logged once and ends the event files, not the run."""
        if self.failed:
            return
        try:
            self._write(self.translator.feed(record))
        except Exception:
            self.failed = True
            log.exception("writing the TensorBoard event files in %s failed; the run goes on without them", self.root)

    def close(self) -> None:
        """Draw what is held back, flush and close every file."""
        try:
            if not self.failed:
                self._write(self.translator.finish())
            for writer in self._writers.values():
                writer.close()
        except Exception:
            self.failed = True
            log.exception("closing the TensorBoard event files in %s failed", self.root)
        finally:
            self._writers.clear()

    def _write(self, points: list[Point]) -> None:
        for p in points:
            if self.only is not None and p.worker not in self.only:
                continue
            writer = self._writers.get(p.worker)
            if writer is None:
                # flush_secs: what is written shows up in TensorBoard within a few seconds
                writer = self._writers[p.worker] = self._writer_class(logdir=str(self.root / p.worker), flush_secs=5)
            writer.add_scalar(p.tag, p.value, global_step=p.step, walltime=self.wall_start + p.t)
            self.points += 1


def _writer_class() -> Any:
    """tensorboardX's SummaryWriter, or None when it is not installed.

    tensorboardX imports torch where it is installed (only to accept tensors, which the chief never passes); in a
    process that has not imported torch (the chief) that import is made to fail, which tensorboardX allows for, so the
    chief stays torch-free: 185 MiB less resident memory (measured with ``bench.soak``)."""
    block = "torch" not in sys.modules
    if block:
        sys.modules["torch"] = None  # type: ignore[assignment]  # `import torch` raises ImportError
    try:
        from tensorboardX import SummaryWriter
    except ImportError:
        return None
    finally:
        if block:
            del sys.modules["torch"]
    return SummaryWriter


def live(workers: int) -> bool:
    """Whether the chief of a run of ``workers`` writes its event files live (else once, at the end: ``rebuild``)."""
    return workers <= LIVE_WORKERS


def open_board(run_dir: Path, rounds_per_episode: int = 1, wall_start: float | None = None) -> Board | None:
    """The run's event files, rebuilt from the records ``metrics.jsonl`` already holds (none for a new run; a resumed
    chief's, cut back to its saved state), ready for the records still to come. None (logged once) without
    tensorboardX or when the folder cannot be redrawn: the run never fails for its event files.

    ``wall_start``: the wall-clock time of the records' t = 0 (default: estimated from the run folder)."""
    drawn = _redraw(run_dir, wall_start)
    if drawn is None:
        return None
    writer_class, records, wall_start = drawn
    board = Board(run_dir / FOLDER, Translator(rounds_per_episode), wall_start, writer_class)
    for record in records:
        board.record(record)
    return board


def _redraw(run_dir: Path, wall_start: float | None) -> tuple[Any, list[Line], float] | None:
    """The writer class, the records to draw and their t = 0 on the wall clock, the old event files gone; None
    (logged once) without tensorboardX or when the folder cannot be redrawn."""
    writer_class = _writer_class()
    if writer_class is None:
        log.warning("tensorboardX is not installed: no TensorBoard event files for this run (pip install .[tb], "
                    "or later: python -m chief.tensorboard %s)", run_dir)
        return None
    root = run_dir / FOLDER
    try:
        for old in root.glob(f"*/{EVENT_FILES}"):
            old.unlink()
        for folder in root.glob("*/"):
            if not any(folder.iterdir()):
                folder.rmdir()  # a worker of an earlier run in this folder
        records = [s for r in read_metrics(run_dir) for s in (r.submissions() if isinstance(r, EdgeRecord) else [r])
                   if isinstance(s, (EpisodeRecord, StepRecord, RoundRecord))]  # a tiered root's: its partials'
    except (OSError, ValueError) as err:
        log.warning("cannot redraw the TensorBoard event files in %s (%s); the run goes on without them", root, err)
        return None
    return writer_class, records, _estimate_wall_start(run_dir, records) if wall_start is None else wall_start


def _estimate_wall_start(run_dir: Path, records: list[EpisodeRecord | StepRecord | RoundRecord]) -> float:
    """When a finished run's t = 0 was: its summary's end minus its wall time, else the records' file's last
    change minus its last t, else now."""
    try:
        summary = RunSummary.read(run_dir)
        if summary.finished_at is not None and summary.wall_s is not None:
            return dt.datetime.fromisoformat(summary.finished_at).timestamp() - summary.wall_s
    except (OSError, ValueError):
        pass
    last_t = max((r.t for r in records), default=0.0)
    path = run_dir / METRICS
    return (path.stat().st_mtime if path.exists() else time.time()) - last_t


def rounds_per_episode_of(run_dir: Path, records: Sequence[AnyRecord]) -> int:
    """K of a finished run: its summary's, else one more than the highest step its records name."""
    try:
        return RunSummary.read(run_dir).rounds_per_episode
    except (OSError, ValueError):
        return 1 + max((r.step for r in records if isinstance(r, StepRecord)), default=0)


def rebuild(run_dir: Path, group: int | None = None) -> Board | None:
    """(Re)write a run's event files from its metrics.jsonl, ``group`` (default LIVE_WORKERS) workers at a time (one
    pass over the records each, so that few files and threads are open at once); the last closed Board (its
    ``points`` and translation cover every group), or None without tensorboardX or when the folder cannot be
    redrawn."""
    group = group or LIVE_WORKERS
    drawn = _redraw(run_dir, None)
    if drawn is None:
        return None
    writer_class, records, wall_start = drawn
    k = rounds_per_episode_of(run_dir, records)
    workers = sorted({r.worker for r in records if not isinstance(r, RoundRecord)})
    points = 0
    board = None
    for i in range(0, max(len(workers), 1), group):
        board = Board(run_dir / FOLDER, Translator(k), wall_start, writer_class, only=set(workers[i:i + group]))
        for record in records:
            board.record(record)
        board.close()
        points += board.points
        if board.failed:
            break
    assert board is not None
    board.points = points
    return board


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m chief.tensorboard",
                                     description="(Re)build a run's TensorBoard event files from its metrics.jsonl "
                                     f"into RUN_DIR/{FOLDER}/<worker>/ (needs tensorboardX: pip install .[tb]).")
    parser.add_argument("run_dir", type=Path, help="the run folder")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if not (args.run_dir / METRICS).is_file():
        print(f"{args.run_dir}: no metrics.jsonl", file=sys.stderr)
        return 2
    board = rebuild(args.run_dir)
    if board is None or board.failed:
        return 1  # logged why
    workers = len(board.translator.workers)
    print(f"wrote {board.points} points for {workers} workers into {board.root}; view them with the TensorBoard "
          f"viewer: make tensorboard RUN={board.root.parent} (it installs the viewer extra first), or "
          f"python -m pip install tensorboard, then tensorboard --logdir {board.root}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
