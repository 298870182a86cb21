"""Pydantic models for every message on the wire. Each carries ``schema_version`` and a ``kind`` tag.

Federation (paper Algorithms 1-2): WorkerHello, WorkerStatus, WorkerUpdate (actor gradient + PI),
MatureParams (a finished worker's actor), ChiefAggregate (Eq. 9 mean gradient), ChiefTransfer (Eq. 10-11),
ChiefAck (the chief holds a worker's mature actor, or refuses it), RunStart, RunStop. The chief's answers carry the
number of the round they answer (protocol/rounds.py) next to its episode and step, and the chief's ``session``;
ChiefClaim is a chief's exclusive, retained claim of a run. EdgePartial is an edge chief's part of a round, for the root
chief (a tiered run). Every message of the federation carries ``tag``: its HMAC-SHA256 under its sender's key
(protocol/auth.py: a worker's own key, the chief key, or the run key for a partial or a claim), empty when the run
has no key.
Rigs (QUBE-Servo 2): QubeState, QubeAction, QubeReset, QubeIdentify, QubeRecording, QubeStatus, QubeTelemetry.
"""

from __future__ import annotations

from typing import Annotated, Final, Literal, NamedTuple

from pydantic import BaseModel, ConfigDict, Field, StringConstraints, model_validator

from protocol.qube import Phase, RigState
from protocol.rigtime import SECONDS_LIMIT
from protocol.rounds import MAX_PER_EPISODE, STALENESS_LIMIT, RoundShape
from protocol.tasks import PI_WINDOW
from protocol.tensors import TensorDict

SCHEMA_VERSION: Final = 1

#: Ids appear inside topic names, so MQTT wildcards and separators are not allowed in them.
Ident = Annotated[str, StringConstraints(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.:-]+$")]
#: A federation strategy's name. Which names exist is the chief's registry (chief/strategies/), not the wire's:
#: workers only apply what the chief sends, whatever the strategy.
PolicyName = Annotated[str, StringConstraints(min_length=1, max_length=32, pattern=r"^[a-z][a-z0-9_-]*$")]
#: A learner's name (protocol/learners.py); a name the chief does not run is its roster's to refuse, not the codec's.
LearnerId = Annotated[str, StringConstraints(min_length=1, max_length=32, pattern=r"^[a-z][a-z0-9_-]*$")]
#: PI is the mean of at most this many recent returns (protocol.tasks.PI_WINDOW).
RecentReturns = Annotated[tuple[float, ...], Field(min_length=1, max_length=PI_WINDOW)]

#: The largest magnitude of a training statistic on the wire (every float is also finite).
STAT_LIMIT = 1e9
#: The update statistics a WorkerUpdate may carry, with their bounds (the fields below use the same ones): a worker
#: sends None for a value outside them or one its learner lacks (PPO's names), and the chief refuses a message that
#: carries one outside them.
STAT_BOUNDS: dict[str, tuple[float, float]] = {
    "actor_loss": (-STAT_LIMIT, STAT_LIMIT),
    "critic_loss": (0.0, STAT_LIMIT),
    "entropy": (-STAT_LIMIT, STAT_LIMIT),
    "approx_kl": (0.0, STAT_LIMIT),
    "clip_fraction": (0.0, 1.0),
}
Stat = Annotated[float, Field(ge=-STAT_LIMIT, le=STAT_LIMIT)]
NonNegativeStat = Annotated[float, Field(ge=0.0, le=STAT_LIMIT)]
Fraction = Annotated[float, Field(ge=0.0, le=1.0)]
#: Seconds of rig time on the wire (protocol/rigtime.py): finite, 0..SECONDS_LIMIT.
RigSeconds = Annotated[float, Field(ge=0.0, le=SECONDS_LIMIT)]
BalanceSteps = Annotated[int, Field(ge=0, le=10**9)]
#: The most episodes, and env steps, a worker's ``played`` counts may carry.
PLAYED_EPISODES_LIMIT, PLAYED_STEPS_LIMIT = 10**9, 10**12
#: A message's authenticator: HMAC-SHA256 (hex) under its sender's key (protocol/auth.py); empty without a key.
Tag = Annotated[str, StringConstraints(max_length=64, pattern=r"^([0-9a-f]{64})?$")]


class Strict(BaseModel):
    """Unknown fields are errors, floats must be finite, values are immutable."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)


class Message(Strict):
    """Common base of every payload: strict fields and a schema version."""

    schema_version: Literal[1] = SCHEMA_VERSION


# --- federation --------------------------------------------------------------------------------------------


class WorkerHello(Message):
    """A worker announces itself (repeated until the chief's RunStart names it)."""

    kind: Literal["hello"] = "hello"
    worker_id: Ident
    env_id: str
    actor_spec: dict[str, tuple[int, ...]]
    critic_spec: dict[str, tuple[int, ...]] = Field(default_factory=dict)
    update_steps: int = Field(default=0, ge=0, le=1000)  # K, the learner's mini-batch steps per episode
    algo: LearnerId = "ppo"  # the worker's learner (protocol/learners.py)
    host: str = ""
    pid: int = 0
    #: The network digest (runtime/model_file.py) of the model this worker was warm-started from; None from scratch.
    init_model: str | None = Field(default=None, pattern=r"^[0-9a-f]{64}$")
    init_model_path: str = Field(default="", max_length=1000)  # that model's path as the worker was given it
    #: The edge chief this worker's rounds go through (docs/explanation/tiered.md); None: straight to the chief.
    edge: Ident | None = None
    tag: Tag = ""


class WorkerStatus(Message):
    """Lifecycle of a worker; ``offline`` is also its MQTT last will; ``storage``: it stopped on a storage fault (a
    full or read-only disk, ``detail`` names the path and the errno), and the chief stops the run resumably."""

    kind: Literal["status"] = "status"
    worker_id: Ident
    state: Literal["online", "training", "finished", "stopped", "offline", "error", "storage"]
    episode: int = Field(default=0, ge=0)
    pi: float | None = None
    detail: str = Field(default="", max_length=2000)
    tag: Tag = ""


class Receipt(Strict):
    """What a worker did with the chief's answer to round ``round``: applied an aggregate or a transfer (with the
    answer's tensor digest and, for a transfer, the keep weight it used), ``missed`` it (no answer in time), or
    ``restarted``: the worker joined the run after round ``round`` with new networks (it was started again without
    a resumable state, worker/resume.py), so it holds none of the answers before.

    Every submission carries the receipt of the last answer the worker applied before it, so the chief's records
    show what reached whom, and when: ``episode`` is the first episode the worker played (or, under a per-step
    strategy, the episode of the first step it computed) with the answer applied (None from older workers). Under a
    bounded staleness (RunStart.max_staleness) a worker may apply several answers between two submissions: the
    earlier ones travel in the submission's ``earlier_receipts``.
    """

    round: int = Field(ge=1)
    applied: Literal["aggregate", "transfer", "missed", "restarted"]
    digest: str = Field(default="", max_length=64)
    keep: float | None = Field(default=None, ge=0.0, le=1.0)
    episode: int | None = Field(default=None, ge=1)


class Played(Strict):
    """What a worker has played in this run since it started (``life``: a token drawn at its start, so a restarted
    worker counts anew): its episodes and env steps, this one included, whether or not the chief counted them. Every
    submission carries it; the chief records it even for one it refuses (stale, out of window...), so the run folder
    shows the env steps a worker took (rig time, on a rig) apart from those the federation counted."""

    life: Annotated[str, StringConstraints(min_length=8, max_length=32, pattern=r"^[0-9a-f]+$")]
    episodes: int = Field(ge=1, le=PLAYED_EPISODES_LIMIT)
    steps: int = Field(ge=0, le=PLAYED_STEPS_LIMIT)


class WorkerSubmission(Message):
    """What a worker's submissions (WorkerUpdate, MatureParams) share: ``played`` counts at least this episode."""

    @model_validator(mode="after")
    def _played_covers_the_episode(self) -> WorkerSubmission:
        played: Played | None = getattr(self, "played", None)
        steps: int = getattr(self, "steps", 0)
        if played is not None and played.steps < steps:
            raise ValueError(f"played.steps {played.steps} is less than this episode's {steps} steps")
        return self


class WorkerUpdate(WorkerSubmission):
    """Algorithm 2, end of an episode: the episode's actor gradient g_theta^n and the Performance Index.

    ``recent_returns`` are the returns PI is the mean of (oldest first, this episode's last), so the chief can
    check PI against the returns it was told before. Under a per-step strategy (RunStart.rounds_per_episode = K)
    a worker sends K of them per episode, ``step`` 0..K-1, each with that mini-batch step's actor and critic
    gradients; the episode's fields are repeated.

    The update statistics, PPO's names (``actor_loss`` = -L^CLIP minus the entropy bonus, ``critic_loss`` = L^V,
    ``entropy``, ``approx_kl``, ``clip_fraction``; SAC's J_pi, J_Q and entropy estimate, DQN's TD loss as both
    losses), are the means over the episode's K mini-batch steps (that step's own under a per-step strategy); None
    when not usable (not finite, outside STAT_BOUNDS, or not the learner's: SAC and DQN send no ``approx_kl`` or
    ``clip_fraction``, DQN no ``entropy``).
    """

    kind: Literal["update"] = "update"
    worker_id: Ident
    episode: int = Field(ge=1)
    episode_return: float
    pi: float
    recent_returns: RecentReturns
    steps: int = Field(ge=0)
    gradient: TensorDict
    receipt: Receipt | None = None
    played: Played | None = None
    earlier_receipts: tuple[Receipt, ...] = Field(default=(), max_length=STALENESS_LIMIT)
    step: int = Field(default=0, ge=0)
    critic_gradient: TensorDict | None = None
    actor_loss: Stat | None = None
    critic_loss: NonNegativeStat | None = None
    entropy: Stat | None = None
    approx_kl: NonNegativeStat | None = None
    clip_fraction: Fraction | None = None
    balance_steps: BalanceSteps | None = None
    balance_s: RigSeconds | None = None
    reset_s: RigSeconds | None = None
    idle_s: RigSeconds | None = None
    tag: Tag = ""


class MatureParams(WorkerSubmission):
    """Algorithm 2, learning finished (PI >= TC over PI_WINDOW episodes): the worker's mature actor theta_n.

    This is the worker's finish. It sends it again until a ChiefAck for this episode arrives. The ``played`` counts
    and the rig-time fields are those of WorkerUpdate.
    """

    kind: Literal["mature"] = "mature"
    worker_id: Ident
    episode: int = Field(ge=1)
    episode_return: float
    pi: float
    recent_returns: RecentReturns
    steps: int = Field(default=0, ge=0)
    params: TensorDict
    receipt: Receipt | None = None
    played: Played | None = None
    earlier_receipts: tuple[Receipt, ...] = Field(default=(), max_length=STALENESS_LIMIT)
    balance_steps: BalanceSteps | None = None
    balance_s: RigSeconds | None = None
    reset_s: RigSeconds | None = None
    idle_s: RigSeconds | None = None
    tag: Tag = ""


class ChiefAggregate(Message):
    """Algorithm 1, no worker finished: the weighted mean gradient g_bar (Eq. 8-9), or None (no sharing), answering
    round ``round`` = (``episode``, ``step``). Under a per-step strategy it answers step ``step`` of the episode and
    carries the mean critic gradient too."""

    kind: Literal["aggregate"] = "aggregate"
    round: int = Field(ge=1)
    episode: int = Field(ge=1)
    gradient: TensorDict | None
    weights: dict[str, float]
    contributors: tuple[Ident, ...]
    step: int = Field(default=0, ge=0)
    critic_gradient: TensorDict | None = None
    session: str = Field(default="", max_length=32)
    tag: Tag = ""


class ChiefTransfer(Message):
    """Algorithm 1, a worker finished: its actor theta_bar for the others, with each recipient's w_T (Eq. 10).
    It answers round ``round``, step 0 of ``episode`` (a finish always comes at step 0)."""

    kind: Literal["transfer"] = "transfer"
    round: int = Field(ge=1)
    episode: int = Field(ge=1)
    source_worker: Ident
    source_pi: float
    params: TensorDict
    keep_weights: dict[str, Annotated[float, Field(ge=0.0, le=1.0)]]
    finished: tuple[Ident, ...]
    session: str = Field(default="", max_length=32)
    tag: Tag = ""


class ChiefAck(Message):
    """The chief's answer to a MatureParams: ``accepted`` (it holds the actor and counts the worker as finished at
    ``episode``; repeated for a repeated MatureParams) or refused with the reason (the worker then goes on learning).
    ``round`` is the round of that MatureParams (step 0 of ``episode``).
    """

    kind: Literal["ack"] = "ack"
    worker_id: Ident
    round: int = Field(ge=1)
    episode: int = Field(ge=1)
    accepted: bool
    reason: str = Field(default="", max_length=2000)
    session: str = Field(default="", max_length=32)
    tag: Tag = ""


class RunStart(Message):
    """The chief starts (or re-announces) the run; a worker's index is its position in ``workers``.

    ``first_episode`` is the open round's episode (the next one when the open round is a later step of its episode):
    a worker that restarts mid-run numbers its episodes from there. ``session`` names this run of the chief (kept
    when it resumes): a worker acts only on answers (aggregate, transfer, acknowledgement, RunStop) of the session
    of the RunStart that named it. ``epoch`` counts the chief's restarts: a
    worker waiting for an answer sends its submission again when it sees a new one. ``rounds_per_episode`` is K of the
    run's round shape (``shape``): 1 for the paper's strategies, the PPO steps per episode for a per-step strategy.
    ``finishers_help``: a worker whose mature actor was acknowledged goes on playing and sharing until the RunStop.
    ``max_staleness`` (S, per-episode strategies only): a worker may play its next episode while up to S of its own
    rounds are still unanswered; it applies their answers in round order as they arrive (0: it waits for each).
    ``quorum`` (k of a k-of-n round, 0: every worker): an edge chief of a tiered run closes its part of a round with
    its share of k (docs/explanation/tiered.md).
    """

    kind: Literal["run_start"] = "run_start"
    run_id: Ident
    env_id: str
    policy: PolicyName
    seed: int
    max_episodes: int = Field(ge=1)
    algo: LearnerId = "ppo"  # the learner every worker runs
    tc: float
    r_floor: float
    workers: tuple[Ident, ...]
    first_episode: int = Field(default=1, ge=1)
    session: str = Field(default="", max_length=32)
    epoch: int = Field(default=0, ge=0)
    rounds_per_episode: int = Field(default=1, ge=1, le=MAX_PER_EPISODE)
    finishers_help: bool = False
    max_staleness: int = Field(default=0, ge=0, le=STALENESS_LIMIT)
    quorum: int = Field(default=0, ge=0)
    #: Worker -> the edge its rounds go through (a tiered run, docs/explanation/tiered.md); empty: a flat run.
    edges: dict[Ident, Ident] = Field(default_factory=dict)
    #: A tiered run's open round: an edge that joins mid-run (restarted, or standing in) starts its rounds there.
    round: int = Field(default=1, ge=1)
    #: A dead edge -> the live edge that stands in for it: its workers' rounds go through that edge now
    #: (chief/failover.py); the edge sums them in a partial of their own, as the dead edge would have.
    stand_ins: dict[Ident, Ident] = Field(default_factory=dict)
    #: How often the run's edges changed (an edge failed over or rejoined): a worker sends its unanswered round
    #: again once the edge it goes through passes on a RunStart with a higher count (that edge now takes it).
    moves: int = Field(default=0, ge=0)
    tag: Tag = ""

    @property
    def shape(self) -> RoundShape:
        """How this run numbers its rounds."""
        return RoundShape(per_episode=self.rounds_per_episode)


#: A record digest: the first 16 hex digits of the BLAKE2b digest of an edge's record line (chief/records.py).
RecordDigest = Annotated[str, StringConstraints(min_length=16, max_length=16, pattern=r"^[0-9a-f]{16}$")]
#: A rig-time quadruple on the wire: balance steps, balance seconds, reset seconds, measured idle seconds (or None).
RigQuad = tuple[BalanceSteps, RigSeconds, RigSeconds, RigSeconds | None]


class Contribution(NamedTuple):
    """One submission an edge counted, as its partial carries it to the root (docs/explanation/tiered.md): what the
    root's round needs (who, which episode and step, its PI and return, its env steps, what it ``played`` and its
    ``rig`` time, for the root's summary) and the ``digest`` of the edge's full record of it (its receipts, returns,
    statistics), which the edge keeps and the audit checks. On the wire an array, not a map: about 70 bytes."""

    worker_id: Ident
    episode: Annotated[int, Field(ge=1)]
    step: Annotated[int, Field(ge=0)]
    pi: float
    episode_return: float
    steps: Annotated[int, Field(ge=0)]
    digest: RecordDigest
    played: Played | None = None
    rig: RigQuad | None = None


class EdgePartial(Message):
    """An edge chief closed its workers' part of round ``round`` (docs/explanation/tiered.md, chief/tiers.py): the
    submissions it counted as ``contributions`` (no tensors, no receipts: the edge keeps their full records), a
    finisher's MatureParams whole besides (``matures``), and the unnormalised Eq. 9 sum of their (bounded) gradients:
    the
    sum of share_n g_n (``gradient``, float32), the share total ``total`` and the count ``count`` (``uniform``: the
    plain sum, every share being 0), the critic's under a per-step strategy. ``clipped``: the factor a gradient was
    scaled by (chief/rounds.py bound_norms, against the edge's own median), ``critic_clipped`` the same for the
    critics' under a per-step strategy; ``timed_out``: the edge's workers it stopped waiting for. ``updates``: the
    whole submissions (each WorkerUpdate with an empty ``gradient``), as edges sent them before ``contributions``:
    a root still takes them, and records them as a flat chief does."""

    kind: Literal["partial"] = "partial"
    edge_id: Ident
    round: int = Field(ge=1)
    episode: int = Field(ge=1)
    step: int = Field(default=0, ge=0)
    contributions: tuple[Contribution, ...] = ()
    updates: tuple[WorkerUpdate, ...] = ()
    matures: tuple[MatureParams, ...] = ()
    gradient: TensorDict | None = None
    critic_gradient: TensorDict | None = None
    total: float = Field(default=0.0, ge=0.0)
    count: int = Field(default=0, ge=0)
    uniform: bool = False
    clipped: dict[Ident, Annotated[float, Field(gt=0.0, le=1.0)]] = Field(default_factory=dict)
    critic_clipped: dict[Ident, Annotated[float, Field(gt=0.0, le=1.0)]] = Field(default_factory=dict)
    timed_out: tuple[Ident, ...] = ()
    #: The edge whose workers this partial sums, when the sender stands in for it (a dead edge, chief/failover.py).
    group: Ident | None = None
    #: Only its submissions, passed on for the root to answer a closed round again (a worker sent the round to an
    #: edge that joined after it closed): no part of any sum.
    again: bool = False
    tag: Tag = ""


class EdgeStatus(Message):
    """An edge chief is ``online`` (every ``chief.failover.HEARTBEAT`` seconds while it runs; ``started``: it holds
    the run's RunStart; ``site``: where it runs, None for the run's one broker), or ``offline`` (its MQTT last will).
    The root moves a dead edge's workers to another edge (chief/failover.py)."""

    kind: Literal["edge_status"] = "edge_status"
    edge_id: Ident
    state: Literal["online", "offline"]
    started: bool = False
    site: Ident | None = None
    tag: Tag = ""


#: RunStop.reason (and summary.json's ``end_reason``) of a run the operator interrupted (Ctrl-C, SIGTERM): it is
#: resumable, so a worker saves its resumable state before it exits (worker/resume.py).
INTERRUPTED: Final = "interrupted"


class RunStop(Message):
    """The run is over; workers stop. ``episodes``: the episode of the last closed round. ``aborted``: it ended early
    (e.g. every worker offline), not by its rule; ``reason`` INTERRUPTED: it ended early and resumably."""

    kind: Literal["run_stop"] = "run_stop"
    run_id: Ident
    reason: str
    episodes: int = Field(ge=0)
    all_solved: bool
    aborted: bool = False
    session: str = Field(default="", max_length=32)
    tag: Tag = ""


class ChiefClaim(Message):
    """A chief holds run ``run_id``: published retained (the one retained message of the contract), so a chief that
    starts later sees it. ``since`` (Unix time) is when ``session`` first took the run; a chief resumed from its saved
    state claims again with both. Of two claims the older wins (then the smaller session); an empty retained message
    clears the claim at the run's end (chief/claim.py)."""

    kind: Literal["claim"] = "claim"
    run_id: Ident
    session: str = Field(min_length=1, max_length=32)
    since: float = Field(ge=0.0)
    host: str = Field(default="", max_length=255)
    pid: int = Field(default=0, ge=0)
    tag: Tag = ""


# --- QUBE-Servo 2 rigs --------------------------------------------------------------------------------------


class QubeState(Message):
    """One control tick of a rig: angles in rad (alpha = 0 upright), velocities in rad/s.

    ``episode`` is the request id of the reset that started the episode; ``phase`` the bridge's phase
    (rpi_bridge/control.py): a worker answers states in ``ready``/``running``; ``fallen``/``fault`` end an episode.
    """

    kind: Literal["qube_state"] = "qube_state"
    rig_id: Ident
    seq: int = Field(ge=0)
    t: float
    theta: float
    alpha: float
    theta_dot: float
    alpha_dot: float
    episode: int = Field(default=0, ge=0)
    phase: Phase = "running"


class QubeAction(Message):
    """The motor command for state ``seq``: SPI counts -999..999 (10 x PWM duty %)."""

    kind: Literal["qube_action"] = "qube_action"
    rig_id: Ident
    seq: int = Field(ge=0)
    command: int = Field(ge=-999, le=999)


class QubeReset(Message):
    """Ask a rig for a new episode: swing up and hold the pendulum, then hand over."""

    kind: Literal["qube_reset"] = "qube_reset"
    rig_id: Ident
    request_id: int = Field(ge=0)


#: The most identification attempts a host may ask a rig for (QubeIdentify.attempt is below it).
IDENTIFY_ATTEMPTS_LIMIT: Final = 10


class QubeIdentify(Message):
    """Ask a rig to run the identification protocol (rpi_bridge/identify.py) and send back what it recorded.
    ``attempt``: 0 the protocol's own excitation; n > 0 its n-th other PRBS sequence (the host asks again so when it
    refused the fit of a recording)."""

    kind: Literal["qube_identify"] = "qube_identify"
    rig_id: Ident
    request_id: int = Field(ge=0)
    attempt: int = Field(default=0, ge=0, lt=IDENTIFY_ATTEMPTS_LIMIT)


#: The largest recording a rig sends (gzip JSON): a 3-minute protocol at 7 ms compresses to about 0.3 MB.
MAX_RECORDING_BYTES = 3_500_000


class QubeRecording(Message):
    """A rig's answer to a QubeIdentify: ``outcome`` "complete" with the recording (rpi_bridge/identify.py
    ``Recording`` as gzip-compressed JSON), or the one-line reason it has none (the protocol could not finish
    safely, the start-up checks failed)."""

    kind: Literal["qube_recording"] = "qube_recording"
    rig_id: Ident
    request_id: int = Field(ge=0)
    outcome: str = Field(min_length=1, max_length=2000)
    recording: bytes = Field(default=b"", max_length=MAX_RECORDING_BYTES)


class QubeStatus(Message):
    """Rig state changes: start-up checks (calibrating, self_test), ready (after a reset), running, fault (amplifier
    disabled), reset failed."""

    kind: Literal["qube_status"] = "qube_status"
    rig_id: Ident
    state: RigState
    request_id: int = Field(default=-1, ge=-1)
    episode: int = Field(default=0, ge=0)
    detail: str = Field(default="", max_length=2000)


class QubeTelemetry(Message):
    """Loop timing of a rig over the last reporting window."""

    kind: Literal["qube_telemetry"] = "qube_telemetry"
    rig_id: Ident
    ticks: int = Field(ge=0)
    deadline_misses: int = Field(ge=0)
    late_actions: int = Field(ge=0)
    faults: int = Field(ge=0)
    jitter_ms: dict[str, float]
    latency_ms: dict[str, float]
    late_at_motor: int = Field(default=0, ge=0)  # arrived in time but not written to the motor within the deadline
    motor_ms: dict[str, float] = Field(default_factory=dict)  # state read -> motor write of applied actions
    period_ms: dict[str, float] = Field(default_factory=dict)  # measured time between reads


# --- transport ------------------------------------------------------------------------------------------------


class Chunk(Message):
    """One piece of a payload too large for the broker's packet limit (protocol/mqtt.py splits and rejoins them on
    the message's own topic, so services never see chunks)."""

    kind: Literal["chunk"] = "chunk"
    id: Annotated[str, StringConstraints(min_length=8, max_length=32, pattern=r"^[0-9a-f]+$")]
    index: int = Field(ge=0)
    count: int = Field(ge=1, le=4096)
    total: int = Field(ge=1)
    data: bytes


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.model_fields["kind"].default: cls
    for cls in (
        WorkerHello,
        WorkerStatus,
        WorkerUpdate,
        MatureParams,
        ChiefAggregate,
        ChiefTransfer,
        ChiefAck,
        RunStart,
        RunStop,
        EdgePartial,
        EdgeStatus,
        ChiefClaim,
        QubeState,
        QubeAction,
        QubeReset,
        QubeIdentify,
        QubeRecording,
        QubeStatus,
        QubeTelemetry,
        Chunk,
    )
}
