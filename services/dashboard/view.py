"""The dashboard's pure core: ``RunView`` folds decoded messages of one run into a JSON-ready state.

``apply(topic, message, now)`` takes one decoded message and returns the events it caused (small dicts the page
applies to its copy of the state); ``snapshot()`` is the whole state, for a page that just connected. No MQTT, no
HTTP, no threads here; tensors (gradients, actors) are never kept, only the scalar fields next to them.

Events (``type`` plus fields):

- ``run``: the run's settings and progress (env, policy, TC, workers, open round, who solved, how it ended, the rig
  time of its last rig so far);
  rounds are numbered as the chief's answers number them (K per episode under a per-step strategy such as ``sync``);
  ``round_label`` and ``no_transfer`` are the page's words for them (a run that is over has no open round, and its
  workers that did not finish never will);
- ``worker``: one worker's summary (state, episode, PI, last return, weights; on a QUBE-Servo 2 task its ``rig``
  time: balance steps and seconds, reset, idle and rig seconds, protocol/rigtime.py) without its curve;
- ``point``: one new point of a worker's curve, ``[episode, PI, return]``;
- ``round``: one closed round (its number, episode and step; aggregate or transfer: weights, contributors, source,
  keep weights);
- ``rig``: one QUBE-Servo 2 rig's phase and loop timing, or ``note`` saying why there is none;
- ``reset``: a new run under the same id started; the page clears what it has.

In a tiered run (docs/explanation/tiered.md) each worker's progress also comes from its edge's partials, the
submissions the root counted (without tensors): a dashboard that does not see the workers' own topics (a site
broker that keeps them) still shows every worker's episodes, and one that sees both shows one point per episode.

With the run's key, every chief (and edge) message is checked as the workers (and the root) check it, and every
worker message as the chief does (protocol/auth.py): one without its sender's valid tag changes nothing shown; it is
counted in ``refused`` (by reason and kind), which the page's footer shows.
"""

from __future__ import annotations

from collections import Counter, deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

from protocol.auth import TAG_FIELD, WorkerKeys, chief_key_of, refusal
from protocol.messages import (
    ChiefAggregate,
    ChiefTransfer,
    Contribution,
    EdgePartial,
    MatureParams,
    Message,
    QubeStatus,
    QubeTelemetry,
    RunStart,
    RunStop,
    WorkerHello,
    WorkerStatus,
    WorkerUpdate,
)
from protocol.rigtime import EpisodeTime, IdleModel, RigTotals
from protocol.routes import CHIEF, EDGE, WORKER, route_of

Event = dict[str, Any]


def _round(value: float | None, digits: int = 4) -> float | None:
    return None if value is None else round(float(value), digits)


@dataclass
class WorkerView:
    """What the page knows about one worker."""

    id: str
    status: str = "waiting"  # from WorkerStatus / updates; ``lagging`` is derived in ``summary``
    episode: int = 0
    pi: float | None = None
    ret: float | None = None
    steps: int = 0
    solved_episode: int | None = None
    weight: float | None = None  # its w_n in the last aggregate it took part in (Eq. 8)
    keep: float | None = None  # its w_T in the last transfer it received (Eq. 10)
    detail: str = ""
    host: str = ""
    last_seen: float = 0.0
    points: list[list[float | None]] = field(default_factory=list)  # [episode, PI, return], thinned past max_points
    rig: RigTotals | None = None  # its rig's time (QUBE-Servo 2 tasks), summed from its submissions
    idle_measured: bool = False  # idle seconds as its worker measured them (else modelled from the rounds)
    timed: set[int] = field(default_factory=set)  # episodes whose rig time is summed (a resend is summed once)

    def rig_row(self, modelled_idle: float) -> Event | None:
        """Its rig time as the page shows it (None without a rig)."""
        if self.rig is None:
            return None
        if not self.idle_measured:
            self.rig.idle_s = modelled_idle
        return {**self.rig.fields(), "idle": "measured" if self.idle_measured else "modelled"}

    def summary(self, last_episode: int, last_contributors: frozenset[str]) -> Event:
        """Its row; ``last_episode`` and ``last_contributors`` are those of the last closed round."""
        state = self.status
        if state == "training" and last_episode and self.episode < last_episode and self.id not in last_contributors:
            state = "lagging"
        return {"type": "worker", "id": self.id, "state": state, "episode": self.episode, "pi": _round(self.pi),
                "ret": _round(self.ret), "steps": self.steps, "solved_episode": self.solved_episode,
                "weight": _round(self.weight), "keep": _round(self.keep), "detail": self.detail,
                "host": self.host, "last_seen": round(self.last_seen, 3), "points": len(self.points)}


@dataclass
class RigView:
    """One QUBE-Servo 2 rig: its phase (QubeStatus) and loop timing (QubeTelemetry)."""

    id: str
    phase: str = "?"
    detail: str = ""
    episode: int = 0
    ticks: int = 0
    deadline_misses: int = 0
    late_actions: int = 0
    faults: int = 0
    latency_ms: dict[str, float] = field(default_factory=dict)
    jitter_ms: dict[str, float] = field(default_factory=dict)
    last_seen: float = 0.0
    telemetry: bool = False  # a QubeTelemetry arrived

    def summary(self) -> Event:
        return {"type": "rig", "id": self.id, "phase": self.phase, "detail": self.detail, "episode": self.episode,
                "telemetry": self.telemetry, "note": "" if self.telemetry else NO_TELEMETRY, "ticks": self.ticks,
                "deadline_misses": self.deadline_misses, "late_actions": self.late_actions,
                "faults": self.faults, "latency_ms": dict(self.latency_ms), "jitter_ms": dict(self.jitter_ms),
                "last_seen": round(self.last_seen, 3)}


#: Why a rig's loop timing is missing: a lockstep rig (the simulator's default clock) publishes no telemetry.
NO_TELEMETRY = ("no loop telemetry: a lockstep rig sends none (its clock advances only with the worker's answers, so "
                "it has no real-time loop to time); a real-time rig reports every second")
#: The transfers panel without any: while the run goes on, and once it is over.
NO_TRANSFER_YET, NO_TRANSFER = "No worker has finished yet.", "No worker finished."
#: ... and when workers finished, each solving on its own (every sync and independent run, a one-round warm start).
SOLVED_WITHOUT_TRANSFER = "No transfer: every worker that finished solved on its own."


def no_transfer_text(stopped: bool, solved: int) -> str:
    """What the transfers panel says while it has no transfer, ``solved`` workers having finished."""
    if solved:
        return SOLVED_WITHOUT_TRANSFER
    return NO_TRANSFER if stopped else NO_TRANSFER_YET


def place(points: list[list[float | None]], point: list[float | None]) -> None:
    """Put ``point`` ([episode, PI, return]) on a curve kept in episode order: it replaces the point of its episode
    (a resent submission, or the same one seen again in its edge's partial), else goes where its episode belongs."""
    i = len(points)
    while i > 0 and (points[i - 1][0] or 0) > (point[0] or 0):  # older than the newest: a partial seen late
        i -= 1
    if i > 0 and points[i - 1][0] == point[0]:
        points[i - 1] = point
    else:
        points.insert(i, point)


class RunView:
    """The state of one run (``run_id``) as the page shows it; fed decoded messages, one at a time."""

    def __init__(self, run_id: str, max_points: int = 4000, max_rounds: int = 300, key: bytes | None = None) -> None:
        """``key``: the run's key (None: every message is trusted). Every chief message shown must be tagged with the
        chief key derived from it, every worker message with its worker's key (protocol/auth.py)."""
        if max_points < 2:
            raise ValueError("max_points must be at least 2")
        self.run_id = run_id
        self.key = key
        self.chief_key = chief_key_of(key)
        self.worker_keys = WorkerKeys(key)
        self.refused: Counter[str] = Counter()  # messages without their sender's valid tag: "<reason> <kind>" -> count
        self.max_points = max_points
        self.max_rounds = max_rounds
        self.kinds: Counter[str] = Counter()  # messages applied, by kind
        self.ignored: Counter[str] = Counter()  # valid messages of kinds the page does not show
        self._handlers: dict[str, Callable[[Any, float], list[Event]]] = {
            "hello": self._on_hello, "status": self._on_status, "update": self._on_update,
            "mature": self._on_mature, "ack": self._on_ack, "run_start": self._on_run_start,
            "run_stop": self._on_run_stop, "aggregate": self._on_aggregate, "transfer": self._on_transfer,
            "partial": self._on_partial,
            "qube_status": self._on_qube_status, "qube_telemetry": self._on_qube_telemetry,
        }
        self._clear()

    def _clear(self) -> None:
        self.start: RunStart | None = None
        self.stop: RunStop | None = None
        self.started_at: float | None = None
        self.stopped_at: float | None = None
        self.first_point_at: float | None = None
        self.env_id: str | None = None
        self.workers: dict[str, WorkerView] = {}
        self.rigs: dict[str, RigView] = {}
        self.rounds: deque[Event] = deque(maxlen=self.max_rounds)
        self.transfers: list[Event] = []
        self.round_count = 0
        self.last_round = 0  # number of the last closed round
        self.last_episode = 0  # and its episode
        self.last_contributors: frozenset[str] = frozenset()
        self.idle_model = IdleModel()  # idle seconds of rigs on a simulated clock, round by round
        self.spent: dict[int, dict[str, float]] = {}  # open round -> contributor -> rig seconds of its submission

    # -- feeding ---------------------------------------------------------------------------------------------

    def apply(self, topic: str, msg: Message, now: float) -> list[Event]:
        """Fold one decoded message in; returns the events for the page (empty when nothing shown changed)."""
        kind = str(getattr(msg, "kind", type(msg).__name__))
        handler = self._handlers.get(kind)
        route = route_of(topic)
        if route is not None and route.publisher == EDGE and kind != "partial":
            handler = None  # an edge's copy of the chief's answer: the chief's own is shown
        if handler is None:
            self.ignored[kind] += 1
            return []
        if route is not None and route.publisher in (CHIEF, EDGE, WORKER) and TAG_FIELD in type(msg).model_fields:
            refused = self._refusal(msg, route.publisher)
            if refused is not None:  # not its sender's: shown as refused, never as the run's state
                self.refused[f"{refused[0]} {kind}"] += 1
                return []
        self.kinds[kind] += 1
        return handler(msg, now)

    def _refusal(self, msg: Message, publisher: str) -> tuple[str, str] | None:
        """Why a message is not its sender's (protocol/auth.py): a worker's is under its own key, an edge's partial
        under the run's key, any other chief or edge message under the chief key."""
        if publisher == WORKER:
            return self.worker_keys.refusal(msg)
        if getattr(msg, "kind", "") == "partial":
            return refusal(msg, self.key, "the run's key")
        return refusal(msg, self.chief_key, "the chief key")

    def _worker(self, worker_id: str) -> WorkerView:
        if worker_id not in self.workers:
            self.workers[worker_id] = WorkerView(worker_id)
        return self.workers[worker_id]

    def _worker_event(self, w: WorkerView) -> Event:
        return {**w.summary(self.last_episode, self.last_contributors),
                "rig": w.rig_row(self.idle_model.idle.get(w.id, 0.0))}

    def _timed(self, w: WorkerView, msg: WorkerUpdate | MatureParams) -> None:
        """Sum a submission's rig time (once per episode) and note what it spent for its round's idle model."""
        step = msg.step if isinstance(msg, WorkerUpdate) else 0
        if self.start is None or (msg.balance_steps is None and step == 0):
            return
        number = self.start.shape.number(msg.episode, step)
        if step > 0 or msg.balance_steps is None:
            self.spent.setdefault(number, {})[w.id] = 0.0
            return
        spent = EpisodeTime(msg.balance_steps, msg.balance_s or 0.0, msg.reset_s or 0.0, msg.idle_s)
        self.spent.setdefault(number, {})[w.id] = spent.rig_s
        if msg.episode in w.timed:
            return
        w.timed.add(msg.episode)
        w.rig = w.rig or RigTotals()
        w.rig.add(spent)
        w.idle_measured |= msg.idle_s is not None

    def _last_rig(self) -> Event | None:
        """The rig time of the rig that is last so far (the most rig time plus idle)."""
        rows = {w.id: row for w in self.workers.values() if (row := self._worker_event(w)["rig"]) is not None}
        if not rows:
            return None
        last = max(rows, key=lambda k: (rows[k]["rig_s"] + rows[k]["idle_s"], rows[k]["rig_s"]))
        return {"id": last, **rows[last]}

    def _all_workers(self) -> list[Event]:
        return [self._worker_event(w) for w in self.workers.values()]

    def _on_hello(self, msg: WorkerHello, now: float) -> list[Event]:
        w = self._worker(msg.worker_id)
        w.host, w.last_seen = msg.host, now
        out: list[Event] = []
        if self.env_id is None:
            self.env_id = msg.env_id
            out.append(self.run_summary())
        return [*out, self._worker_event(w)]

    def _on_status(self, msg: WorkerStatus, now: float) -> list[Event]:
        w = self._worker(msg.worker_id)
        w.last_seen = now
        w.detail = msg.detail
        if msg.state == "online":
            w.status = "waiting" if self.start is None else "training"
        elif msg.state == "finished":
            w.status = "finished"
            w.solved_episode = w.solved_episode or msg.episode or None
        elif w.status != "finished" or msg.state == "error":
            w.status = msg.state
        if msg.pi is not None:
            w.pi = msg.pi
        w.episode = max(w.episode, msg.episode)
        return [self._worker_event(w)]

    def _point(self, w: WorkerView, episode: int, pi: float, ret: float, now: float) -> list[Event]:
        """One submission on the worker's curve; a point event when it is (or replaces) the newest point (the
        page's curve takes no older point: a partial behind the worker's own newer update is in the snapshot)."""
        newest = not w.points or episode >= (w.points[-1][0] or 0)
        if newest:
            w.pi, w.ret = pi, ret
        w.episode, w.last_seen = max(w.episode, episode), now
        if self.first_point_at is None:
            self.first_point_at = now
        point = [episode, _round(pi), _round(ret)]
        place(w.points, point)
        if len(w.points) > self.max_points:  # thin: keep every other point (always the newest)
            w.points = w.points[-1::-2][::-1]
        return [{"type": "point", "worker": w.id, "point": point}] if newest else []

    def _on_update(self, msg: WorkerUpdate, now: float) -> list[Event]:
        w = self._worker(msg.worker_id)
        out: list[Event] = []
        if w.status == "finished" and msg.episode > (w.solved_episode or 0):  # its finish was refused: it goes on
            w.status, w.solved_episode = "training", None
            out.append(self.run_summary())
        elif w.status in ("waiting", "offline", "stopped", "error"):
            w.status = "training"
        w.steps = msg.steps
        self._timed(w, msg)
        return [*self._point(w, msg.episode, msg.pi, msg.episode_return, now), self._worker_event(w), *out]

    def _on_mature(self, msg: MatureParams, now: float) -> list[Event]:
        w = self._worker(msg.worker_id)
        w.status, w.solved_episode, w.steps = "finished", msg.episode, msg.steps
        self._timed(w, msg)
        return [*self._point(w, msg.episode, msg.pi, msg.episode_return, now), self._worker_event(w),
                self.run_summary()]

    def _on_partial(self, msg: EdgePartial, now: float) -> list[Event]:
        """An edge's part of a round (a tiered run): its workers' submissions as the root counts them."""
        out: list[Event] = []
        finishers = {m.worker_id for m in msg.matures}
        for update in [*msg.updates, *(as_update(c) for c in msg.contributions if c.worker_id not in finishers)]:
            out += self._on_update(update, now)
        for mature in msg.matures:
            out += self._on_mature(mature, now)
        return out

    def _on_ack(self, msg: Any, now: float) -> list[Event]:
        """The chief's answer to a mature actor (a newer message kind): a refusal means the worker goes on."""
        worker_id = getattr(msg, "worker_id", None)
        if worker_id not in self.workers or getattr(msg, "accepted", True):
            return []
        w = self.workers[worker_id]
        if w.status == "finished" and w.solved_episode == getattr(msg, "episode", None):
            w.status, w.solved_episode = "training", None
            w.detail = f"finish refused: {getattr(msg, 'reason', '')}".strip()
        return [self._worker_event(w), self.run_summary()]

    def _on_run_start(self, msg: RunStart, now: float) -> list[Event]:
        if msg.run_id != self.run_id:
            return []
        out: list[Event] = []
        if self.stop is not None:  # the same run id again after a stop: a new run
            self._clear()
            out.append({"type": "reset"})
        if self.start is None:
            self.started_at = now
        self.start, self.env_id = msg, msg.env_id
        self.idle_model.staleness = msg.max_staleness  # rigs may play on with up to S rounds unanswered
        for wid in msg.workers:
            w = self._worker(wid)
            if w.status == "waiting":
                w.status = "training"
        return [*out, self.run_summary(), *self._all_workers()]

    def _on_run_stop(self, msg: RunStop, now: float) -> list[Event]:
        if msg.run_id != self.run_id:
            return []
        self.stop, self.stopped_at = msg, now
        for w in self.workers.values():
            if w.status in ("training", "waiting"):
                w.status = "stopped"
        return [self.run_summary(), *self._all_workers()]

    def _close_round(self, msg: ChiefAggregate | ChiefTransfer, record: Event, contributors: Iterable[str]) -> None:
        self.round_count += 1
        if msg.round >= self.last_round:
            self.last_round, self.last_episode = msg.round, msg.episode
        self.last_contributors = frozenset(contributors)
        self.rounds.append(record)
        spent = self.spent.pop(msg.round, {})
        for old in [r for r in self.spent if r < msg.round]:  # rounds closed while the page was away
            del self.spent[old]
        if spent:
            self.idle_model.close({w: spent.get(w, 0.0) for w in self.last_contributors if w in spent})

    def _on_aggregate(self, msg: ChiefAggregate, now: float) -> list[Event]:
        record = {"type": "round", "round": msg.round, "episode": msg.episode, "step": msg.step, "kind": "aggregate",
                  "t": round(now, 3), "contributors": list(msg.contributors), "shared": msg.gradient is not None,
                  "weights": {k: _round(v) for k, v in msg.weights.items()}}
        self._close_round(msg, record, msg.contributors)
        for wid, weight in msg.weights.items():
            self._worker(wid).weight = weight
        return [record, self.run_summary(), *self._all_workers()]

    def _on_transfer(self, msg: ChiefTransfer, now: float) -> list[Event]:
        contributors = sorted({*msg.keep_weights, *msg.finished})
        record = {"type": "round", "round": msg.round, "episode": msg.episode, "step": 0, "kind": "transfer",
                  "t": round(now, 3),
                  "source": msg.source_worker, "source_pi": _round(msg.source_pi),
                  "keep_weights": {k: _round(v) for k, v in msg.keep_weights.items()},
                  "finished": list(msg.finished), "contributors": contributors}
        self._close_round(msg, record, contributors)
        self.transfers.append(record)
        for wid, keep in msg.keep_weights.items():
            self._worker(wid).keep = keep
        for wid in msg.finished:
            w = self._worker(wid)
            w.status = "finished"
            w.solved_episode = w.solved_episode or msg.episode
        return [record, self.run_summary(), *self._all_workers()]

    def _rig(self, rig_id: str) -> RigView:
        if rig_id not in self.rigs:
            self.rigs[rig_id] = RigView(rig_id)
        return self.rigs[rig_id]

    def _on_qube_status(self, msg: QubeStatus, now: float) -> list[Event]:
        rig = self._rig(msg.rig_id)
        rig.phase, rig.detail, rig.episode, rig.last_seen = msg.state, msg.detail, msg.episode, now
        return [rig.summary()]

    def _on_qube_telemetry(self, msg: QubeTelemetry, now: float) -> list[Event]:
        rig = self._rig(msg.rig_id)
        rig.ticks, rig.deadline_misses, rig.late_actions, rig.faults = (msg.ticks, msg.deadline_misses,
                                                                         msg.late_actions, msg.faults)
        rig.latency_ms = {k: round(v, 3) for k, v in msg.latency_ms.items()}
        rig.jitter_ms = {k: round(v, 3) for k, v in msg.jitter_ms.items()}
        rig.last_seen, rig.telemetry = now, True
        return [rig.summary()]

    # -- reading ---------------------------------------------------------------------------------------------

    @property
    def tiered(self) -> bool:
        """Whether the run goes through edge chiefs (its RunStart names each worker's edge)."""
        return self.start is not None and bool(self.start.edges)

    def run_summary(self) -> Event:
        start, stop = self.start, self.stop
        solved = sorted(((w.id, w.solved_episode) for w in self.workers.values() if w.status == "finished"),
                        key=lambda x: (x[1] or 0, x[0]))
        if stop is not None:
            phase = "stopped"
        elif start is not None:
            phase = "running"
        else:
            phase = "waiting"
        return {
            "type": "run", "run_id": self.run_id, "phase": phase, "env": self.env_id,
            "policy": start.policy if start else None, "seed": start.seed if start else None,
            "tc": start.tc if start else None, "r_floor": start.r_floor if start else None,
            "max_episodes": start.max_episodes if start else None,
            "workers": list(start.workers) if start else sorted(self.workers),
            "round": self.last_round + 1 if start else None, "rounds": self.round_count,
            "round_label": "rounds" if stop is not None else "open round",
            "no_transfer": no_transfer_text(stop is not None, len(solved)),
            "episode": start.shape.episode_of(self.last_round + 1) if start else None,
            "rounds_per_episode": start.rounds_per_episode if start else None,
            "transfers": len(self.transfers), "solved": [{"worker": w, "episode": e} for w, e in solved],
            "stop": {"reason": stop.reason, "episodes": stop.episodes, "all_solved": stop.all_solved} if stop else None,
            "started_at": self.started_at, "stopped_at": self.stopped_at, "first_point_at": self.first_point_at,
            "last_rig": self._last_rig(),
        }

    def snapshot(self) -> dict[str, Any]:
        """The whole state: run, workers with their curves, recent rounds, every transfer, rigs."""
        workers = []
        for w in self.workers.values():
            item = self._worker_event(w)
            item["curve"] = [list(p) for p in w.points]
            workers.append(item)
        return {
            "run": self.run_summary(),
            "workers": workers,
            "rounds": list(self.rounds),
            "transfers": list(self.transfers),
            "rigs": [r.summary() for r in self.rigs.values()],
            "kinds": dict(self.kinds),
            "ignored": dict(self.ignored),
            "refused": dict(self.refused),
        }


def as_update(c: Contribution) -> WorkerUpdate:
    """A partial's Contribution as the update it stands for, with the fields the view reads (no tensors)."""
    balance_steps, balance_s, reset_s, idle_s = c.rig or (None, None, None, None)
    return WorkerUpdate.model_construct(worker_id=c.worker_id, episode=c.episode, step=c.step, pi=c.pi,
                                        episode_return=c.episode_return, recent_returns=(c.episode_return,),
                                        steps=c.steps, gradient={}, played=c.played,
                                        balance_steps=balance_steps, balance_s=balance_s, reset_s=reset_s,
                                        idle_s=idle_s)
