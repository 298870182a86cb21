"""The run folder's records as types: each line of ``metrics.jsonl``, ``summary.json`` and the keys of
``gradients.npz`` (with the witness's gaps).

They live in runtime, below the chief that writes them and every reader (chief/audit.py, chief/tensorboard.py,
runtime/model_file.py, deploy/, bench/): one writer (chief/report.py) and every reader go through these models, so a
record's fields are declared once and no reader parses a run file as a dict (chief/records.py adds the chief's saved
state). On disk the files keep their keys: a line is the model's fields in declared order, compact JSON, without the
optional fields a record does not carry (``recent_returns`` only on a mature actor's record, ``stats`` only where
update statistics were sent), so an existing run folder still reads. Unknown fields are errors (a reader says which
line is bad rather than guessing).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from pydantic import AliasChoices, BaseModel, ConfigDict, Field, TypeAdapter

from protocol.messages import Contribution, Played, Receipt
from runtime.storage import atomic_write

METRICS = "metrics.jsonl"
SUMMARY = "summary.json"
#: Where a tiered run's edges keep their workers' records: RUN/edges/<edge>/metrics.jsonl (chief/edge.py).
EDGES = "edges"
#: A tiered run's witness (written by an observer of the wire, deploy/witness.py): every worker's actor gradient and
#: every aggregate the root sent, so the audit can check the root's Eq. 9 against the flat one, keyed by
#: ``gradient_key``; and under WITNESS_GAPS the rounds whose messages the witness may have missed (WitnessGap).
GRADIENTS = "gradients.npz"
#: The key in GRADIENTS of the witness's gaps: an integer array with one row per WitnessGap, the episode and step of
#: its start and of its end (-1 -1 for an open end); no rows when the witness missed nothing. No tensor's key can be
#: it (theirs have a '/'). A GRADIENTS from before witnesses recorded gaps has no such key: read as no gaps.
WITNESS_GAPS = "witness_gaps"

#: A round's place in the run: (episode, step).
Place = tuple[int, int]


def gradient_key(episode: int, step: int, who: str, name: str) -> str:
    """The key of one tensor in GRADIENTS: round (episode, step), the worker (or ``ROOT``), the tensor's name."""
    return f"e{episode}s{step}/{who}/{name}"


#: Whose tensor in GRADIENTS is the root's aggregate (no worker id can be it: '@' is no id character).
ROOT = "@root"


@dataclass(frozen=True)
class WitnessGap:
    """Rounds whose messages the witness may have missed: its connection came back without the broker holding its
    session (a broker that restarted empty), so what was published before it subscribed again never reached it.
    ``start``: the place of the last message it witnessed before (None: from the beginning); ``end``: the place of
    the first it witnessed after (None: to the end); both rounds included."""

    start: Place | None
    end: Place | None

    def covers(self, place: Place) -> bool:
        """Whether the round at ``place`` lies in this gap (its bounds included)."""
        return (self.start is None or self.start <= place) and (self.end is None or place <= self.end)


def write_gradients(path: Path, tensors: Mapping[str, np.ndarray], gaps: Sequence[WitnessGap]) -> Path:
    """Save a witness as GRADIENTS: its tensors and its gaps (WITNESS_GAPS)."""
    rows = [[*(g.start or (-1, -1)), *(g.end or (-1, -1))] for g in gaps]
    arrays = {**tensors, WITNESS_GAPS: np.array(rows, np.int64).reshape(len(rows), 4)}
    np.savez_compressed(path, **arrays)  # type: ignore[arg-type]
    return path


def read_gradients(path: Path) -> tuple[dict[str, np.ndarray], list[WitnessGap]]:
    """A witness's tensors by key and its gaps (none in a file from before gaps were recorded); OSError or
    ValueError when unreadable."""
    with np.load(path) as data:
        tensors = {k: data[k] for k in data.files}
    rows = tensors.pop(WITNESS_GAPS, np.zeros((0, 4), np.int64))
    if rows.ndim != 2 or rows.shape[1] != 4:
        raise ValueError(f"{path.name}: {WITNESS_GAPS} has shape {rows.shape}, not (gaps, 4)")

    def place(episode: int, step: int) -> Place | None:
        return None if episode < 0 else (episode, step)

    return tensors, [WitnessGap(place(*row[:2]), place(*row[2:])) for row in rows.tolist()]


WorkerState = Literal["active", "lagging", "offline", "finished"]
#: A worker's state in summary.json: the keeper's, or ``stopped`` when an offline worker said so itself.
SummaryState = Literal["active", "lagging", "offline", "finished", "stopped"]


class Record(BaseModel):
    """A record of the run folder: unknown fields are errors; ``dump`` is what is written."""

    model_config = ConfigDict(extra="forbid", populate_by_name=True)

    #: Fields written only when set (not None).
    OPTIONAL: ClassVar[frozenset[str]] = frozenset()

    def dump(self) -> dict[str, Any]:
        """The record as JSON data, keyed as on disk (optional fields left out when None)."""
        drop = {name for name in self.OPTIONAL if getattr(self, name) is None}
        return self.model_dump(mode="json", by_alias=True, exclude=drop)


class EpisodeRecord(Record):
    """A worker's counted episode (its submission for step 0 of the episode's rounds): an update, or its mature
    actor (``kind: mature``, with the ``recent_returns`` its PI is the mean of). ``stats``: the learner's update
    statistics (protocol.messages.STAT_BOUNDS; None values where not sent; absent for a mature actor; run folders
    from before learners had names call them ``ppo``, read as ``stats``). The rig-time fields (protocol/rigtime.py;
    QUBE-Servo 2 tasks only, absent otherwise): the episode's balance steps and seconds, its reset seconds and the
    worker's measured idle seconds since its last submission (absent when its rig's clock is simulated). ``played``:
    what the worker had played when it sent this (protocol.messages.Played; absent when it did not say)."""

    OPTIONAL = frozenset({"recent_returns", "stats", "played", "balance_steps", "balance_s", "reset_s", "idle_s",
                          "earlier_receipts"})

    type: Literal["episode"] = "episode"
    worker: str
    round: int
    episode: int
    return_: float = Field(alias="return")
    pi: float
    steps: int
    kind: Literal["update", "mature"]
    receipt: Receipt | None = None
    t: float = 0.0
    earlier_receipts: list[Receipt] | None = None
    recent_returns: list[float] | None = None
    stats: dict[str, float | None] | None = Field(default=None, validation_alias=AliasChoices("stats", "ppo"))
    played: Played | None = None
    balance_steps: int | None = Field(default=None, ge=0)
    balance_s: float | None = Field(default=None, ge=0)
    reset_s: float | None = Field(default=None, ge=0)
    idle_s: float | None = Field(default=None, ge=0)

    @property
    def receipts(self) -> list[Receipt]:
        """Every answer the worker applied since its previous submission, oldest first (see protocol.messages)."""
        return _receipts(self.earlier_receipts, self.receipt)


def _receipts(earlier: list[Receipt] | None, last: Receipt | None) -> list[Receipt]:
    return [*(earlier or []), *([last] if last is not None else [])]


class StepRecord(Record):
    """A counted later mini-batch step (``step`` >= 1) of a per-step strategy's episode."""

    OPTIONAL = frozenset({"stats", "earlier_receipts"})

    type: Literal["step"] = "step"
    worker: str
    round: int
    episode: int
    step: int
    receipt: Receipt | None = None
    t: float = 0.0
    earlier_receipts: list[Receipt] | None = None
    stats: dict[str, float | None] | None = Field(default=None, validation_alias=AliasChoices("stats", "ppo"))

    @property
    def receipts(self) -> list[Receipt]:
        """Every answer the worker applied since its previous submission, oldest first."""
        return _receipts(self.earlier_receipts, self.receipt)


class RoundRecord(Record):
    """A closed round and the chief's answer to it (chief.rounds.RoundOutcome without its tensors). ``offline``:
    in a round where a worker finished, the learners the chief knew were offline and left out of the transfer
    (absent when none). ``edges``: in a tiered run (docs/explanation/tiered.md), each edge whose partial the root
    combined, with the contributors it summed (absent in a flat run). ``late``: in a run with a quorum, the workers
    the round closed without (absent when none). ``critic_clipped``: under a per-step strategy, the factors the
    critics' gradients were scaled by, as ``clipped`` for the actors' (absent when none)."""

    OPTIONAL = frozenset({"critic_clipped", "offline", "edges", "late"})

    type: Literal["round"] = "round"
    round: int
    episode: int
    step: int = 0
    kind: Literal["aggregate", "transfer"]
    strategy: str
    contributors: list[str]
    pis: dict[str, float] = Field(default_factory=dict)
    weights: dict[str, float] = Field(default_factory=dict)
    digest: str = ""
    source: str | None = None
    source_pi: float | None = None
    keep_weights: dict[str, float] = Field(default_factory=dict)
    recipient_pis: dict[str, float | None] = Field(default_factory=dict)
    finished: list[str] = Field(default_factory=list)
    timed_out: list[str] = Field(default_factory=list)
    clipped: dict[str, float] = Field(default_factory=dict)
    critic_clipped: dict[str, float] | None = None  # per-step strategies: the factors of the critics' gradients
    t: float = 0.0
    offline: list[str] | None = None
    edges: dict[str, list[str]] | None = None
    partials: int | None = None  # a root's round that summed more partials than edges (an edge's late workers')
    late: list[str] | None = None


class RefusedRecord(Record):
    """A submission the chief refused (``reason``: stale, out_of_window...; chief.rounds.Verdict.refusal) that tells
    more of what its worker ``played`` than the records held before: its episodes and env steps, not counted. Only
    such submissions are recorded, so a worker's resends add nothing."""

    type: Literal["refused"] = "refused"
    worker: str
    round: int
    episode: int
    step: int = 0
    kind: Literal["update", "mature"]
    reason: str
    steps: int = Field(ge=0)
    played: Played
    t: float = 0.0


class EdgeRecord(Record):
    """A tiered root's record of one edge's partial of a round (docs/explanation/tiered.md): the contributions it
    counted from it (protocol.messages.Contribution: worker, episode, step, PI, return, env steps, the digest of the
    edge's record of it, played, rig time), the partial's share total, count and ``uniform`` flag, and ``matures``:
    the contributors whose submission was a mature actor (absent when none). The edge keeps each contribution's full
    record (EDGES); the audit reads both levels and checks they agree (chief/audit.py ``edge-records``)."""

    OPTIONAL = frozenset({"matures"})

    type: Literal["edge"] = "edge"
    edge: str
    round: int
    episode: int
    step: int = 0
    contributions: list[Contribution]
    total: float = 0.0
    count: int = 0
    uniform: bool = False
    matures: list[str] | None = None
    t: float = 0.0

    def submissions(self) -> list[EpisodeRecord | StepRecord]:
        """Its contributions as the root's own (partial) records of them: what the root's summary, played counts,
        rig time and curves are made of (receipts, statistics and returns are in the edge's records)."""
        out: list[EpisodeRecord | StepRecord] = []
        matures = set(self.matures or ())
        for c in self.contributions:
            if c.step:
                out.append(StepRecord.model_construct(worker=c.worker_id, round=self.round, episode=c.episode,
                                                      step=c.step, receipt=None, t=self.t, earlier_receipts=None,
                                                      stats=None))
                continue
            balance_steps, balance_s, reset_s, idle_s = c.rig or (None, None, None, None)
            out.append(EpisodeRecord.model_construct(
                worker=c.worker_id, round=self.round, episode=c.episode, return_=c.episode_return, pi=c.pi,
                steps=c.steps, kind="mature" if c.worker_id in matures else "update", receipt=None, t=self.t,
                earlier_receipts=None, recent_returns=None, stats=None, played=c.played, balance_steps=balance_steps,
                balance_s=balance_s, reset_s=reset_s, idle_s=idle_s))
        return out


def record_digest(record: AnyRecord) -> str:
    """The digest of a record as an edge writes it (its line): the 16 hex digits a Contribution carries."""
    return hashlib.blake2b(line(record).encode(), digest_size=8).hexdigest()


Submitted = EpisodeRecord | StepRecord
AnyRecord = EpisodeRecord | StepRecord | RoundRecord | RefusedRecord | EdgeRecord
MetricsRecord = Annotated[AnyRecord, Field(discriminator="type")]
_LINE: TypeAdapter[AnyRecord] = TypeAdapter(MetricsRecord)


def parse_record(data: Any) -> AnyRecord:
    """A record from its JSON data (a dict, or a model already); pydantic.ValidationError (a ValueError) if bad."""
    if isinstance(data, (EpisodeRecord, StepRecord, RoundRecord, RefusedRecord, EdgeRecord)):
        return data
    return _LINE.validate_python(data)


def line(record: AnyRecord) -> str:
    """The record's line in metrics.jsonl (compact JSON, no newline)."""
    return json.dumps(record.dump(), separators=(",", ":"))


def read_metrics(run_dir: Path) -> list[AnyRecord]:
    """metrics.jsonl's records in order ([] when there is none yet); ValueError naming the first bad line."""
    path = run_dir / METRICS
    if not path.exists():
        return []
    out = []
    for number, text in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if not text.strip():
            continue
        try:
            out.append(parse_record(json.loads(text)))
        except ValueError as err:
            raise ValueError(f"{METRICS} line {number}: {err}") from None
    return out


class RigTime(Record):
    """A rig's time over every episode its worker had counted (protocol/rigtime.py): balance steps and seconds,
    reset seconds, idle seconds waiting for the federation (``idle``: ``measured`` by the worker, or ``modelled``
    from the records when its rig's clock is simulated) and rig time = balance + reset seconds."""

    balance_steps: int = Field(ge=0)
    balance_s: float = Field(ge=0)
    reset_s: float = Field(ge=0)
    idle_s: float = Field(ge=0)
    rig_s: float = Field(ge=0)
    idle: Literal["measured", "modelled"]
    #: Rig seconds of the rig's identification before the run (deploy.lab writes it; no chief knows it).
    identify_s: float | None = Field(default=None, ge=0)


class LastRig(RigTime):
    """summary.json's ``last_rig``: the rig time of the rig that finished last (the most rig time plus idle)."""

    id: str


class PlayedTotals(Record):
    """Everything a worker played (chief/played.py): its ``episodes`` and env ``steps``, the sums over its lives of
    the last ``played`` counts on record, apart into what the chief counted (its counted episodes' records) and what
    it refused or never got (``refused_*`` = played - counted)."""

    episodes: int = Field(ge=0)
    steps: int = Field(ge=0)
    counted_episodes: int = Field(ge=0)
    counted_steps: int = Field(ge=0)
    refused_episodes: int
    refused_steps: int


class WorkerSummary(Record):
    """One worker's result in summary.json: episodes and env steps until it solved, or so far; everything it
    ``played``, counted and refused apart (absent when its submissions did not say); its ``rig`` time on a QUBE-Servo
    2 task (absent for the gymnasium tasks)."""

    OPTIONAL = frozenset({"played", "rig", "detail"})

    id: str
    index: int
    solved: bool
    episodes: int
    steps: int
    final_pi: float | None = None
    state: SummaryState
    played: PlayedTotals | None = None
    rig: RigTime | None = None
    #: Why a worker that did not solve stopped learning, in its own words (its error or stopped status).
    detail: str | None = None


class InitModelRecord(Record):
    """The model a warm-started run's workers started from: its path as given (to the chief, or else to its first
    worker) and its network digest (runtime/model_file.py)."""

    path: str
    digest: str


class RunSummary(Record):
    """summary.json: the task, the strategy, each worker's result, the last worker's episodes and steps, and what the
    launcher adds (``mode``, wall time, broker, reject counts...; left out when not given); ``algo`` is the run's
    learner. ``total_steps`` are the env steps the chief counted, ``played_steps`` every env step the workers played and
    ``refused_steps`` those it did not count (absent when no worker's submissions said). ``last_rig``: the rig time of
    the run's last rig (QUBE-Servo 2 tasks only). ``init_model``: the model every worker started from (absent from
    scratch). ``env_options``: the workers' task options an in-process launcher gave (qube-local's rig profile,
    randomisation and clock; absent when none); ``learner_set``: the fields of the learner's preset it replaced
    (``--set``; absent when none)."""

    OPTIONAL = frozenset({"quorum", "mode", "wall_s", "finished_at", "broker", "rejected_messages", "duplicates",
                          "restarts", "played_steps", "refused_steps", "last_rig", "init_model", "env_options",
                          "learner_set"})

    run_id: str = ""
    env: str
    policy: str
    algo: str = "ppo"  # the learner every worker ran (protocol/learners.py)
    seed: int | None = None
    tc: float
    r_floor: float
    max_episodes: int
    workers: list[WorkerSummary]
    episodes_to_all_solved: int | None = None
    steps_of_last_worker: int | None = None
    total_steps: int
    played_steps: int | None = None
    refused_steps: int | None = None
    rounds: int
    rounds_per_episode: int = 1
    max_staleness: int = 0
    quorum: int | None = None
    end_reason: str
    mode: str | None = None
    wall_s: float | None = None
    finished_at: str | None = None
    broker: str | None = None
    rejected_messages: dict[str, int] | None = None
    duplicates: int | None = None
    restarts: int | None = None
    last_rig: LastRig | None = None
    init_model: InitModelRecord | None = None
    env_options: dict[str, Any] | None = None
    learner_set: list[str] | None = None

    def dump(self) -> dict[str, Any]:
        """As Record.dump, each worker's row without its optional fields when None too."""
        data = super().dump()
        data["workers"] = [w.dump() for w in self.workers]
        return data

    @classmethod
    def read(cls, run_dir: Path) -> RunSummary:
        """A run folder's summary.json (OSError, ValueError when missing or bad)."""
        return cls.model_validate(json.loads((run_dir / SUMMARY).read_text(encoding="utf-8")))

    def write(self, run_dir: Path) -> Path:
        """Write summary.json atomically (a StorageError, one line and exit 5, on a full or read-only disk)."""
        return atomic_write(run_dir / SUMMARY, (json.dumps(self.dump(), indent=2) + "\n").encode())
