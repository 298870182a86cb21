"""The chief's saved state as types (chief-state.msgpack, written and read by chief/checkpoint.py), on the run
folder's records (runtime/records.py)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field

from runtime.records import InitModelRecord, Record, WorkerState


class SavedWorker(Record):
    """A chief.rounds.WorkerRecord, field by field (its per-episode returns and PIs as sorted pairs)."""

    worker_id: str
    state: WorkerState
    pi: float | None
    last_episode: int
    solved_episode: int | None
    steps: int
    steps_at_solve: int | None
    last_round: int
    excused: bool
    helping: bool
    detail: str = ""
    returns: list[tuple[int, float]]
    pis: list[tuple[int, float]]


class KeeperState(Record):
    """Everything a chief.rounds.RoundKeeper needs to go on. Submissions and answers keep their tensors as
    protocol.tensors.TensorBlob data (chief/checkpoint.py translates them)."""

    policy: str
    env_id: str
    max_episodes: int
    round_timeout: float
    actor_spec: dict[str, list[int]] | None
    critic_spec: dict[str, list[int]] | None
    rounds_per_episode: int
    max_staleness: int = 0
    quorum: int = 0
    round: int
    workers: list[SavedWorker]
    pending: list[dict[str, Any]]
    ahead: list[dict[str, Any]]
    counted: list[tuple[str, int]]  # (worker, round) pairs, as states before ``counted_rounds`` kept them
    answers: list[dict[str, Any]]
    done_reason: str | None
    aborted: bool
    interrupted: bool = False  # ended by Ctrl-C or SIGTERM: a chief started again resumes it
    tier: Literal["flat", "root"] = "flat"  # a root of edges (docs/explanation/tiered.md) or a flat chief
    partials: list[dict[str, Any]] = Field(default_factory=list)  # a root's: the edges' partials of open rounds
    #: The counted (worker, round) pairs, compactly: per worker, a little-endian bit mask of its rounds from
    #: ``counted_from`` (bit i: round counted_from + i), so the state's size does not grow with its pairs.
    counted_from: int = 0
    counted_rounds: dict[str, bytes] = Field(default_factory=dict)


class ServiceState(Record):
    """The chief service's own part of its saved state."""

    run_id: str
    session: str
    epoch: int
    duplicates: int
    hosts: dict[str, str]
    update_steps: int
    rejects: dict[str, int]
    metrics_bytes: int = Field(ge=0)
    elapsed_s: float
    init_model: InitModelRecord | None = None  # the run's model, once decided (None: from scratch or not yet)
    init_model_known: bool = False
    claimed_since: float = 0.0  # when this session first claimed the run (chief/claim.py); 0: a state from before
    algo: str = "ppo"  # the run's learner (protocol/learners.py); a state from before learners had names ran PPO
    edges: dict[str, str] = Field(default_factory=dict)  # a root's workers: the edge each is behind
    stand_ins: dict[str, str] = Field(default_factory=dict)  # a root's dead edges -> their stand-ins (failover.py)
    moves: int = 0  # how often a root's edges changed (RunStart ``moves``)


class ChiefState(Record):
    """chief-state.msgpack."""

    version: Literal[1] = 1
    keeper: KeeperState
    service: ServiceState
