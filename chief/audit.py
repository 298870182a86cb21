"""``python -m chief.audit RUN_DIR``: re-check a run's federation from its records alone.

Reads ``summary.json`` and ``metrics.jsonl`` (what the chief accepted, and every round it closed) and re-derives what
the federation must have done. It exits 0 when every invariant holds, 1 naming the first that does not, 2 when the
folder cannot be read. The invariants, each one function registered in ``CHECKS`` (run in that order, on the records
as runtime/records.py types them):

- ``edge-records``: in a tiered run whose root keeps one record per edge and round (runtime.records.EdgeRecord), each
  contribution the root counted is exactly a record its edge kept (RUN/edges/<edge>/metrics.jsonl: same digest, same
  fields), and each partial's share total, count and ``uniform`` flag are what those records' PIs give (Eq. 8's
  numerators, summed as the edge sums them); the other checks then read the edges' records as the run's;
- ``rounds-contiguous``: rounds are 1, 2, ... without gaps, as many as the summary says, each the round of its
  (episode, step);
- ``counted-once``: no worker's episode (or, under a per-step strategy, step) is counted twice;
- ``contributors``: a round's contributors are exactly the submissions counted for its episode, and every counted
  submission belongs to a round (a run that was aborted may leave some in the round it never closed);
- ``round-pis``: the PIs a round used are the PIs of its counted submissions;
- ``mature``: a mature actor was accepted only with PI >= TC over PI_WINDOW episodes, PI the mean of its returns;
  nothing of a worker was counted after it finished (unless its strategy lets finishers go on sharing);
- ``transfer``: in every round where a worker finished while others were still learning, the best finisher's actor
  went to each of them, with keep weights = Eq. 10 of each recipient's PI at that round (strategies that share),
  except the learners the round records as offline (and only a finishing round's learners can be);
- ``eq8-weights``: every aggregate's weights are the strategy's (Eq. 8 for ``weighted``) of that round's PIs and
  sum to 1;
- ``tiered-edges``: in a tiered run each round's contributors are exactly the disjoint union of those its edges'
  partials summed, and a worker stays behind one edge;
- ``tiered-exact``: every root aggregate the run's witness saw (GRADIENTS) is the flat Eq. 9 of the same submissions
  within chief/tiers.py's derived bound; a round the witness lacks fails, unless it lies in one of the witness's
  recorded gaps, where it is counted as unwitnessed;
- ``quorum``: a round closed without some of the workers it waited for only with at least the run's quorum k of
  contributors, none of them late, and every submission refused as late was for such a round;
- ``delivery``: each worker that took part in a round confirms that it applied the round's answer (same tensor
  digest, same keep weight) with its next submission, or under a bounded staleness S (summary.json
  ``max_staleness``) with one of its next S + 1, by the one for the round S + 1 later if it made that one, or says
  it was started again with new networks (receipt ``restarted``: it had no resumable state, worker/resume.py);
- ``staleness``: each worker applied the chief's answers in round order, each once, each to a round before the
  submission that reports it and at most S + 1 rounds before it, and each receipt's episode (the first the worker
  played with the answer applied) is that submission's episode;
- ``receipts``: every receipt of an applied answer, in any counted submission, names a round the chief closed and
  matches the answer it recorded for that round (kind, tensor digest, the worker's keep weight), including rounds that
  closed with no contributors: a worker applied nothing the chief did not send; a ``restarted`` receipt is only on
  the first submission of new networks (an update for step 0 of the round after the receipt's, PI its one return);
- ``summary``: the summary's solve episodes, steps and totals agree with the records;
- ``played``: each worker's played, counted and refused episodes and env steps in the summary are what the records
  add up to (chief/played.py), counted + refused = played, the run's played and refused totals their sums, and no
  life of a worker was counted more than it said it played;
- ``rig-time``: each rig's balance steps and seconds, reset, idle and rig seconds in the summary are the sums of its
  records (idle modelled from the rounds when not measured, protocol/rigtime.py), rig time = balance + reset, and
  ``last_rig`` is the rig that finished last (QUBE-Servo 2 tasks; nothing to check for the gymnasium tasks).
"""

from __future__ import annotations

import argparse
import bisect
import math
import sys
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from chief import federation, strategies, tiers
from chief.played import played_totals
from chief.rigtime import last_rig, rig_times
from chief.rounds import scaled
from protocol.messages import Receipt
from protocol.rounds import RoundShape
from protocol.tasks import PI_WINDOW, performance_index
from protocol.tensors import digest
from runtime.records import (
    EDGES,
    GRADIENTS,
    ROOT,
    EdgeRecord,
    EpisodeRecord,
    RefusedRecord,
    RoundRecord,
    RunSummary,
    StepRecord,
    WitnessGap,
    gradient_key,
    read_gradients,
    read_metrics,
    record_digest,
)
from runtime.settings import program, returns_code

Submitted = EpisodeRecord | StepRecord
#: Seconds of rig time are summed and rounded to the millisecond (chief/rigtime.py): they agree within this.
RIG_TOLERANCE = 0.0015


class AuditFailure(Exception):
    """An invariant that does not hold: ``invariant`` names it, the message says where."""

    def __init__(self, invariant: str, detail: str) -> None:
        super().__init__(f"{invariant}: {detail}")
        self.invariant = invariant
        self.detail = detail


@dataclass
class AuditReport:
    """What the audit checked."""

    rounds: int = 0
    submissions: int = 0
    transfers: int = 0
    transfer_deliveries: int = 0
    receipts: int = 0
    staleness: int = 0
    tiered: int = 0
    unwitnessed: int = 0  # root aggregates ``tiered-exact`` skipped: missing from the witness, inside one of its gaps
    edge_records: int = 0
    uncounted: list[tuple[str, int]] = field(default_factory=list)

    def __str__(self) -> str:
        text = (f"{self.rounds} rounds, {self.submissions} counted submissions, {self.transfers} transfers "
                f"({self.transfer_deliveries} recipients), {self.receipts} receipts confirmed"
                + (f" (max staleness {self.staleness})" if self.staleness else "")
                + (f"; {self.tiered} tiered aggregates within the bound of the flat Eq. 9" if self.tiered else "")
                + (f"; {self.unwitnessed} root aggregate{'s' if self.unwitnessed > 1 else ''} not witnessed (inside "
                   "the witness's gaps: its broker lost its session), not checked" if self.unwitnessed else "")
                + (f"; {self.edge_records} edge records agree with the edges' own" if self.edge_records else ""))
        if self.uncounted:
            text += (f"; {len(self.uncounted)} submissions left in a round the run never closed (an aborted run, "
                     "or a finished helper's after the last finish)")
        return text


def _close(a: float | None, b: float | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12)


def load(run_dir: Path) -> tuple[RunSummary, list[EpisodeRecord], list[StepRecord], list[RoundRecord],
                                 list[RefusedRecord]]:
    """summary, episode records, later-step records, round records and refused submissions' records of a run folder
    (OSError/ValueError when unreadable); a tiered root's EdgeRecords stand for the edges' records they count
    (``edge_submissions``)."""
    summary = RunSummary.read(run_dir)
    records = read_metrics(run_dir)
    edged = [r for r in records if isinstance(r, EdgeRecord)]
    if edged:
        records = [*records, *edge_submissions(edged, edge_records(run_dir, edged))]
    return (summary, [r for r in records if isinstance(r, EpisodeRecord)],
            [r for r in records if isinstance(r, StepRecord)], [r for r in records if isinstance(r, RoundRecord)],
            [r for r in records if isinstance(r, RefusedRecord)])


def edge_records(run_dir: Path, edged: list[EdgeRecord]) -> dict[str, list[Submitted]]:
    """Each edge's records of its workers' submissions (RUN/edges/<edge>/metrics.jsonl; [] when it has none)."""
    out: dict[str, list[Submitted]] = {}
    for edge in sorted({r.edge for r in edged}):
        folder = run_dir / EDGES / edge
        out[edge] = [r for r in read_metrics(folder) if isinstance(r, (EpisodeRecord, StepRecord))]
    return out


def edge_submissions(edged: list[EdgeRecord], kept: dict[str, list[Submitted]]) -> list[Submitted]:
    """The edges' records of the contributions the root counted, in the root's order: for each, the edge's record
    whose digest it carries (the first of its worker and round when none has: ``edge-records`` names it)."""
    index: dict[tuple[str, str, int], list[Submitted]] = defaultdict(list)
    for edge, records in kept.items():
        for rec in records:
            index[(edge, rec.worker, rec.round)].append(rec)
    out: list[Submitted] = []
    for r in edged:
        for c in r.contributions:
            found = index.get((r.edge, c.worker_id, r.round), [])
            out += [next((e for e in found if record_digest(e) == c.digest), found[0])] if found else []
    return out


@dataclass
class Run:
    """A run folder's records, indexed for the checks (an index keeps the first of two records for one key: the
    counted-once check names the second)."""

    summary: RunSummary
    episodes: list[EpisodeRecord]
    steps: list[StepRecord]
    rounds: list[RoundRecord]
    refused: list[RefusedRecord] = field(default_factory=list)
    report: AuditReport = field(default_factory=AuditReport)
    gradients: dict[str, np.ndarray] | None = None  # a tiered run's witness (GRADIENTS), when it has one
    gaps: list[WitnessGap] = field(default_factory=list)  # where that witness may have missed messages
    edged: list[EdgeRecord] = field(default_factory=list)  # a tiered root's records of its edges' partials
    kept: dict[str, list[Submitted]] = field(default_factory=dict)  # each edge's own records of its submissions

    @classmethod
    def read(cls, run_dir: Path) -> Run:
        summary, episodes, steps, rounds, refused = load(run_dir)
        witness = run_dir / GRADIENTS
        gradients, gaps = read_gradients(witness) if witness.exists() else (None, [])
        edged = [r for r in read_metrics(run_dir) if isinstance(r, EdgeRecord)]
        return cls(summary, episodes, steps, rounds, refused,
                   AuditReport(rounds=len(rounds), submissions=len(episodes) + len(steps)), gradients, gaps, edged,
                   edge_records(run_dir, edged) if edged else {})

    # -- rounds: the run's shape (protocol.rounds) maps (episode, step) to a round number and back --------------

    @property
    def shape(self) -> RoundShape:
        return RoundShape(per_episode=self.summary.rounds_per_episode)

    def round_of(self, episode: int, step: int) -> int:
        """Round number of (episode, step); a place outside the run's shape is a violation of the calling check."""
        try:
            return self.shape.number(episode, step)
        except ValueError as err:
            raise _Violated(str(err)) from None

    def place_of(self, round_: int) -> tuple[int, int]:
        """(episode, step) of a round number."""
        place = self.shape.of(round_)
        return place.episode, place.step

    # -- indexes ---------------------------------------------------------------------------------------------

    @property
    def strategy(self) -> strategies.Strategy:
        return strategies.get(self.summary.policy)

    @property
    def workers(self) -> list[str]:
        return [w.id for w in self.summary.workers]

    @property
    def submissions(self) -> list[Submitted]:
        return [*self.episodes, *self.steps]

    @staticmethod
    def step(e: Submitted) -> int:
        return e.step if isinstance(e, StepRecord) else 0

    @cached_property
    def by_round(self) -> dict[tuple[str, int], Submitted]:
        """Counted submissions by (worker, round of their episode and step)."""
        out: dict[tuple[str, int], Submitted] = {}
        for e in self.submissions:
            out.setdefault((e.worker, self.round_of(e.episode, self.step(e))), e)
        return out

    @cached_property
    def by_episode(self) -> dict[tuple[str, int], EpisodeRecord]:
        """Episode records by (worker, episode)."""
        out: dict[tuple[str, int], EpisodeRecord] = {}
        for e in self.episodes:
            out.setdefault((e.worker, e.episode), e)
        return out

    @cached_property
    def per_round(self) -> dict[int, dict[str, Submitted]]:
        """Round number -> worker -> its counted submission."""
        out: dict[int, dict[str, Submitted]] = defaultdict(dict)
        for (w, n), e in self.by_round.items():
            out[n][w] = e
        return out

    @cached_property
    def finished_in(self) -> dict[str, int]:
        """The round of each worker's (first) counted mature actor."""
        out: dict[str, int] = {}
        for (w, n), e in sorted(self.by_round.items(), key=lambda kv: kv[0][1]):
            if _mature(e):
                out.setdefault(w, n)
        return out

    @cached_property
    def solved_at(self) -> dict[str, int]:
        """The episode of each worker's (first) counted mature actor."""
        return {w: self.place_of(n)[0] for w, n in self.finished_in.items()}

    def pi_at(self, worker: str, episode: int) -> float | None:
        """The PI of the worker's latest counted submission up to ``episode`` (what the chief's Eq. 10 used)."""
        eps = sorted(ep for (x, ep) in self.by_episode if x == worker)
        i = bisect.bisect_right(eps, episode)
        return self.by_episode[(worker, eps[i - 1])].pi if i else None

    def progress(self, pi: float | None) -> float:
        s = self.summary
        return federation.progress(s.r_floor if pi is None else pi, s.tc, s.r_floor)

    @property
    def ended_normally(self) -> bool:
        return self.summary.end_reason.startswith(("all workers solved", "reached the maximum"))


def _mature(e: Submitted) -> bool:
    return isinstance(e, EpisodeRecord) and e.kind == "mature"


# -- the invariants: one check each, run in this order by ``audit`` ------------------------------------------------


class _Violated(Exception):
    """Raised by a check; ``audit`` names the check's invariant."""


def _holds(ok: bool, detail: str) -> None:
    if not ok:
        raise _Violated(detail)


@dataclass(frozen=True)
class Check:
    """One invariant: its name (what a failure says) and the function that checks it."""

    invariant: str
    run: Callable[[Run], None]


CHECKS: list[Check] = []


def check(invariant: str) -> Callable[[Callable[[Run], None]], Callable[[Run], None]]:
    """Register the decorated function as the check of ``invariant`` (in definition order)."""
    def register(fn: Callable[[Run], None]) -> Callable[[Run], None]:
        CHECKS.append(Check(invariant, fn))
        return fn
    return register


@check("edge-records")
def edge_records_agree(run: Run) -> None:
    """Algorithm 1's messages of a round, kept at two levels (docs/explanation/tiered.md): every contribution a
    tiered root counted from an edge's partial is a record that edge kept (the digest the partial carried, the same
    episode, step, PI, return, env steps and played counts), and the partial's share total T_e, count N_e and
    ``uniform`` flag are what Eq. 8's numerators of those records' PIs sum to, as the edge sums them (exactly)."""
    kept = {(edge, record_digest(e)): e for edge, records in run.kept.items() for e in records}
    for r in run.edged:
        matures = set(r.matures or ())
        progress = {}
        for c in r.contributions:
            e = kept.get((r.edge, c.digest))
            e = e if e is not None and (e.worker, e.round) == (c.worker_id, r.round) else None
            _holds(e is not None, f"round {r.round}: the root counted {c.worker_id}'s submission from edge {r.edge} "
                   f"with digest {c.digest}, and that edge kept no such record of it")
            assert e is not None
            step = run.step(e)
            mature = isinstance(e, EpisodeRecord) and e.kind == "mature"
            same = (e.episode, step, c.worker_id in matures) == (c.episode, c.step, mature)
            if isinstance(e, EpisodeRecord):
                same = same and (e.pi, e.return_, e.steps, e.played) == (c.pi, c.episode_return, c.steps, c.played)
            _holds(same, f"round {r.round}: edge {r.edge}'s record of {c.worker_id} is not the contribution the root "
                   f"counted ({c})")
            if not mature:
                progress[c.worker_id] = run.progress(c.pi)
        got, want = (r.total, r.count, r.uniform), tiers.expected_totals(run.strategy, progress)
        _holds(got == want, f"round {r.round}: edge {r.edge}'s partial says (total, count, uniform) {got}, its "
               f"records give {want}")
        run.report.edge_records += 1


@check("rounds-contiguous")
def rounds_contiguous(run: Run) -> None:
    """Algorithm 1's loop ``for i = 1, 2, ..., M``: the closed rounds are 1..M without a gap, as many as the summary
    says, each at its (episode, step), and every counted submission is filed under the round of its (episode,
    step)."""
    for e in run.submissions:
        n = run.round_of(e.episode, run.step(e))
        _holds(e.round == n, f"{e.worker}'s episode {e.episode} step {run.step(e)} is filed as round {e.round}, "
               f"not {n}")
    numbers = [r.round for r in run.rounds]
    _holds(numbers == list(range(1, len(numbers) + 1)), f"rounds are {numbers[:5]}...{numbers[-5:]}, not "
           f"1..{len(numbers)}")
    _holds(run.summary.rounds == len(numbers), f"the summary says {run.summary.rounds} rounds, the records have "
           f"{len(numbers)}")
    for r in run.rounds:
        _holds((r.episode, r.step) == run.place_of(r.round), f"round {r.round} says episode {r.episode} step {r.step}")


@check("counted-once")
def counted_once(run: Run) -> None:
    """Algorithm 1 receives one message m_n per worker n in a round, and Eq. 9 sums each worker's gradient once: no
    worker's episode (or, under a per-step strategy, step) is counted twice, and only the run's workers count."""
    seen: set[tuple[str, int]] = set()
    for e in run.submissions:
        key = (e.worker, run.round_of(e.episode, run.step(e)))
        _holds(key not in seen, f"{e.worker}'s episode {e.episode} (step {run.step(e)}) is counted twice")
        _holds(e.worker in run.workers, f"a submission of {e.worker}, who is not in the run, was counted")
        seen.add(key)


@check("contributors")
def contributors(run: Run) -> None:
    """Algorithm 1's P (the messages of round i) is exactly what Eq. 9 sums over: a round's contributors are the
    submissions counted for it, and every counted submission belongs to a closed round (an aborted run may leave
    some in the round it never closed; so may a finished helper, after the last finish)."""
    last = len(run.rounds)
    for n in sorted(run.per_round):
        if n <= last:
            continue
        # A worker that finished and keeps helping (finishers_help) may have its next submission accepted before
        # the last learner's finish ends the run: that round is legitimately never closed.
        helpers_only = run.strategy.finishers_help and all(run.finished_in.get(w, n) < n for w in run.per_round[n])
        _holds(not run.ended_normally or helpers_only, f"round {n} of {sorted(run.per_round[n])} was counted but "
               f"never closed, although the run ended normally ({run.summary.end_reason})")
        run.report.uncounted += [(w, n) for w in sorted(run.per_round[n])]
    for r in run.rounds:
        counted = sorted(run.per_round.get(r.round, {}))
        _holds(sorted(r.contributors) == counted, f"round {r.round} lists {sorted(r.contributors)} but the counted "
               f"submissions are {counted}")


@check("round-pis")
def round_pis(run: Run) -> None:
    """Eq. 8 weighs each gradient by its worker's PI^n: the PIs a round used are those of its counted submissions
    (a later step repeats its episode's PI)."""
    for r in run.rounds:
        episode = run.place_of(r.round)[0]
        expected = {w: run.by_episode[(w, episode)].pi for w in run.per_round.get(r.round, {})
                    if (w, episode) in run.by_episode}
        _holds(set(r.pis) == set(expected) and all(_close(r.pis[w], expected[w]) for w in expected),
               f"round {r.round} used PIs {r.pis}, the counted submissions say {expected}")


@check("mature")
def mature(run: Run) -> None:
    """Algorithm 1's mature actor theta_n: accepted only with PI >= TC over PI_WINDOW (10) episodes, PI the mean of
    their returns (the paper's Performance Index), those returns the ones the worker reported; a worker finishes
    once, and nothing of it is counted after it finished (unless its strategy lets finishers go on sharing)."""
    tc, solved = run.summary.tc, set()
    for (w, ep), e in sorted(run.by_episode.items(), key=lambda kv: kv[0][1]):
        if e.kind != "mature":
            continue
        recent = e.recent_returns or []
        pi = performance_index(recent) if recent else float("nan")
        _holds(len(recent) >= PI_WINDOW and _close(pi, e.pi) and pi >= tc, f"{w}'s mature actor of episode {ep} was "
               f"accepted with PI {e.pi} over {len(recent)} returns (mean {pi}); TC is {tc} over {PI_WINDOW}")
        for back, value in enumerate(reversed(recent)):
            known = run.by_episode.get((w, ep - back))
            _holds(known is None or _close(known.return_, value), f"{w}'s mature PI counts a return of {value} for "
                   f"episode {ep - back}, which it reported as {known and known.return_}")
        _holds(w not in solved, f"{w} finished twice (episodes {run.solved_at.get(w)} and {ep})")
        solved.add(w)
    if not run.strategy.finishers_help:
        late = sorted((w, e.episode) for (w, _), e in run.by_round.items()
                      if e.episode > run.solved_at.get(w, math.inf))
        _holds(not late, f"submissions counted after their worker had finished: {late[:3]}")


@check("transfer")
def transfer(run: Run) -> None:
    """Algorithm 1's transfer branch with Eq. 10: in every round where a worker finished while others were still
    learning (under a strategy that transfers), the best finisher's actor went to each of them but those the chief
    knew were offline (the round's ``offline``: learners of a finishing round only), each keeping w_T = Eq. 10 of
    its PI at that round; every other round is an aggregate."""
    for r in run.rounds:
        episode = run.place_of(r.round)[0]
        finished = sorted(w for w, e in run.per_round.get(r.round, {}).items() if _mature(e))
        _holds(sorted(r.finished) == finished, f"round {r.round} says {sorted(r.finished)} finished, the counted "
               f"mature actors are {finished}")
        learning = sorted(w for w in run.workers if run.solved_at.get(w, math.inf) > episode)
        offline = sorted(r.offline or [])
        _holds(not offline or (bool(finished) and set(offline) <= set(learning)), f"round {r.round} left {offline} "
               f"out as offline, but only a finishing round's learners {learning if finished else []} can be")
        learners = [w for w in learning if w not in offline]
        keeps = {w: run.strategy.keep_weight(run.progress(run.pi_at(w, episode))) for w in learners}
        if finished and learners and all(k is not None for k in keeps.values()):
            _transfer_round(run, r, finished, learners, keeps)
            continue
        _holds(r.kind == "aggregate", f"round {r.round} sent a transfer, but nobody both finished and left others "
               "learning under a strategy that transfers")


def _transfer_round(run: Run, r: RoundRecord, finished: list[str], learners: list[str],
                    keeps: dict[str, float | None]) -> None:
    """One round that must be a transfer: its source, recipients, their PIs and keep weights (Eq. 10)."""
    n, episode = r.round, run.place_of(r.round)[0]
    _holds(r.kind == "transfer", f"round {n}: {finished} finished while {learners} were learning, but no transfer "
           "was sent")
    pis = {w: run.by_episode[(w, episode)].pi for w in finished}  # a mature actor is its episode's record
    best = federation.best_mature(pis)
    _holds(r.source == best and _close(r.source_pi, pis[best]), f"round {n} transferred {r.source}'s actor; the "
           f"best finisher was {best}")
    _holds(sorted(r.keep_weights) == learners, f"round {n}'s transfer went to {sorted(r.keep_weights)}, the workers "
           f"still learning were {learners}")
    for w in learners:
        _holds(_close(r.recipient_pis.get(w), run.pi_at(w, episode)), f"round {n}: {w}'s PI at that round was "
               f"{run.pi_at(w, episode)}, the transfer used {r.recipient_pis.get(w)}")
        _holds(_close(r.keep_weights[w], keeps[w]), f"round {n}: {w} kept {r.keep_weights[w]} of its actor, Eq. 10 "
               f"gives {keeps[w]}")
    run.report.transfers += 1
    run.report.transfer_deliveries += len(learners)


@check("eq8-weights")
def eq8_weights(run: Run) -> None:
    """Eq. 8 (w_n = progress_n / sum of progress, for ``weighted``; each strategy its own rule) and Eq. 9's
    weighted sum: every aggregate's weights are the strategy's weights of that round's PIs and sum to 1; a round
    without contributors shares nothing."""
    for r in run.rounds:
        if r.kind != "aggregate":
            continue
        sharing = sorted(w for w in r.contributors if w not in r.finished)  # the finishers only leave
        if not sharing:
            _holds(not r.weights and not r.digest, f"round {r.round} had no contributors but shared a gradient")
            continue
        zeros = {w: {"x": np.zeros(1, np.float32)} for w in sharing}
        expected = run.strategy.aggregate(zeros, {w: run.progress(r.pis[w]) for w in sharing}).weights or {}
        _holds(set(r.weights) == set(expected) and all(_close(r.weights[w], expected[w]) for w in expected),
               f"round {r.round}'s weights are {r.weights}, {run.strategy.name} gives {expected} for PIs {r.pis}")
        if expected:
            total = sum(r.weights.values())
            _holds(math.isclose(total, 1.0, abs_tol=1e-9), f"round {r.round}'s weights sum to {total}")


@check("tiered-edges")
def tiered_edges(run: Run) -> None:
    """Algorithm 1's P across levels (docs/explanation/tiered.md): in a tiered run each round's contributors, whose
    gradients Eq. 9 sums, are exactly the disjoint union of the contributors its edges' partials summed, and a worker
    stays behind one edge."""
    edge_of: dict[str, str] = {}
    for r in run.rounds:
        if r.edges is None:
            continue
        listed = sorted(w for ws in r.edges.values() for w in ws)
        _holds(listed == sorted(r.contributors), f"round {r.round}'s edges summed {listed}, its contributors are "
               f"{sorted(r.contributors)}")
        _holds(r.partials is None or len(r.edges) < r.partials <= len(r.edges) + len(r.contributors),
               f"round {r.round} summed {r.partials} partials of {len(r.edges)} edges and {len(r.contributors)} "
               "contributors (an edge's further partial has contributors of its own)")
        for e, ws in r.edges.items():
            for w in ws:
                _holds(edge_of.setdefault(w, e) == e, f"{w} is behind edge {edge_of[w]} and, in round {r.round}, {e}")


@check("tiered-exact")
def tiered_exact(run: Run) -> None:
    """Eq. 8-9 across levels: every aggregate the root of a tiered run sent (the run's GRADIENTS witness, when it has
    one) is the flat Eq. 9 of the same submissions (bounded as the edges bounded them, with the round's Eq. 8
    weights) within chief/tiers.py's derived float32/float64 bound, and it is what the round's digest says. A round
    whose tensors the witness lacks fails, unless it lies in one of the witness's gaps (its broker lost its session
    meanwhile): then it is counted as unwitnessed, not checked."""
    if run.gradients is None:
        return
    for r in run.rounds:
        if r.edges is None or r.kind != "aggregate" or not r.digest:
            continue
        episode, step = run.place_of(r.round)
        root = _witnessed(run.gradients, episode, step, ROOT)
        learners = sorted(w for w in r.contributors if w not in r.finished)
        grads = {w: scaled(_witnessed(run.gradients, episode, step, w), r.clipped.get(w, 1.0)) for w in learners}
        if not (root and all(grads.values())) and any(gap.covers((episode, step)) for gap in run.gaps):
            run.report.unwitnessed += 1
            continue
        _holds(bool(root) and all(grads.values()), f"round {r.round}: the witness lacks the root's aggregate or a "
               "contributor's gradient")
        if not run.shape.per_step:
            _holds(digest(root) == r.digest, f"round {r.round}: the witnessed aggregate is not the recorded one")
        flat = run.strategy.aggregate(grads, {w: run.progress(r.pis[w]) for w in learners})
        assert flat.gradient is not None
        worst = tiers.excess(grads, r.weights, r.partials or len(r.edges), flat.gradient, root)
        _holds(worst <= 1.0, f"round {r.round}: the root's aggregate is {worst:.3g} times the derived bound away "
               "from the flat Eq. 9 of the same submissions")
        run.report.tiered += 1


@check("quorum")
def quorum(run: Run) -> None:
    """Algorithm 1's wait for the round's messages, k of n (summary.json ``quorum`` k, docs/explanation/tiered.md):
    a round closed without some of the workers it waited for (``late``) only with at least k contributors, none of
    them late; a run without a quorum has no late worker; and every submission refused as ``late`` was for a round
    that closed without its worker, whose gradient Eq. 9 then left out."""
    k = run.summary.quorum
    for r in run.rounds:
        if not r.late:
            continue
        _holds(k is not None, f"round {r.round} closed without {r.late}, and the run has no quorum")
        assert k is not None
        _holds(len(r.contributors) >= k and not set(r.late) & set(r.contributors), f"round {r.round} closed with "
               f"{len(r.contributors)} contributors {r.contributors}, late {r.late}, under a quorum of {k}")
    late = {r.round: set(r.late or ()) for r in run.rounds}
    for e in run.refused:
        _holds(e.reason != "late" or e.worker in late.get(e.round, set()), f"{e.worker}'s submission for round "
               f"{e.round} was refused as late, but that round did not close without it")


def _witnessed(gradients: dict[str, np.ndarray], episode: int, step: int, who: str) -> dict[str, np.ndarray]:
    """One sender's tensors of round (episode, step) in a GRADIENTS witness, by name."""
    prefix = gradient_key(episode, step, who, "")
    return {k[len(prefix):]: v for k, v in gradients.items() if k.startswith(prefix)}


@check("delivery")
def delivery(run: Run) -> None:
    """Algorithm 2 applies each answer (Eq. 9's g_bar, or Eq. 11's blend with w_T): each worker that took part in a
    round (and did not finish in it) confirms with its next counted submission that it applied the round's answer
    (same tensor digest, same keep weight); under a bounded staleness S, with one of its submissions for the next
    S + 1 rounds, at the latest with the one for round + S + 1 when it made it. A finisher that goes on helping
    confirms, when it rejoins, the answers of its finishing episode it caught up with."""
    stale = run.summary.max_staleness
    for r in run.rounds:
        for w in sorted(set(r.contributors) - set(r.finished)):
            later = [run.by_round[(w, m)] for m in range(r.round + 1, r.round + stale + 2) if (w, m) in run.by_round]
            found = next((rc for e in later for rc in e.receipts if rc.round == r.round), None)
            if found is None and (w, r.round + stale + 1) not in run.by_round:
                continue  # it has not (yet) had to apply it: it went on alone, finished or stopped
            run.report.receipts += _receipt(r, w, found)
    if run.strategy.finishers_help:
        _rejoined(run)


def _receipt(r: RoundRecord, w: str, receipt: Receipt | None) -> int:
    """``receipt``, the one of ``w``'s submissions after round ``r`` that reports on it, confirms its answer (1), or
    says the worker restarted with new networks (0)."""
    n = r.round
    _holds(receipt is not None, f"{w}'s submissions after round {n} carry no receipt of round {n}")
    assert receipt is not None
    if receipt.applied == "restarted":
        return 0  # new networks, which applied no earlier answer: ``receipts`` checks that they are
    _holds(receipt.applied != "missed", f"round {n}'s {r.kind} never reached {w}")
    _holds(receipt.applied == r.kind and receipt.digest == r.digest, f"{w} applied {receipt.applied} "
           f"{receipt.digest!r} as round {n}'s answer, the chief sent {r.kind} {r.digest!r}")
    if r.kind == "transfer":
        _holds(_close(receipt.keep, r.keep_weights.get(w)), f"{w} kept {receipt.keep} of its actor in round {n}, "
               f"the chief said {r.keep_weights.get(w)}")
    return 1


def _rejoined(run: Run) -> None:
    """A finisher that goes on sharing (finishers_help) skipped the other rounds of its finishing episode; its first
    submission after them confirms the round just before, so it applied every answer it missed and its networks are
    the others' again."""
    closed = {r.round: r for r in run.rounds}
    for w, n in run.finished_in.items():
        later = min((m for (x, m) in run.by_round if x == w and m > n), default=None)
        if later is None or later - 1 not in closed:
            continue
        receipt, before = run.by_round[(w, later)].receipt, closed[later - 1]
        _holds(receipt is not None and receipt.round == later - 1 and receipt.applied == before.kind
               and receipt.digest == before.digest, f"{w} finished in round {n} and rejoined in round {later} "
               f"without confirming round {later - 1}'s answer ({receipt and receipt.model_dump()}): it missed the "
               "answers of its finishing episode")
        run.report.receipts += 1


@check("receipts")
def receipts(run: Run) -> None:
    """Algorithm 2 applies only the chief's answers (Eq. 9's g_bar, Eq. 11's blend): every receipt of an applied
    answer in a counted submission names a closed round and matches what the chief recorded for it (kind, digest and
    this worker's w_T), also for a round that closed with no contributors (whose answer ``delivery`` cannot check):
    an answer the chief never sent (a forged or another chief's) shows here."""
    closed = {r.round: r for r in run.rounds}
    for e, receipt in ((sub, rc) for sub in run.submissions for rc in sub.receipts):
        if receipt.applied == "restarted":
            _restarted(run, e, receipt)
        if receipt.applied in ("missed", "restarted"):
            continue
        r = closed.get(receipt.round)
        _holds(r is not None, f"{e.worker} applied a {receipt.applied} as the answer to round {receipt.round}, which "
               "the chief never closed")
        assert r is not None
        _holds(receipt.applied == r.kind and receipt.digest == r.digest, f"{e.worker} applied {receipt.applied} "
               f"{receipt.digest!r} as round {r.round}'s answer, the chief recorded {r.kind} {r.digest!r}")
        if r.kind == "transfer":
            _holds(_close(receipt.keep, r.keep_weights.get(e.worker)), f"{e.worker} kept {receipt.keep} of its actor "
                   f"in round {r.round}, the chief recorded {r.keep_weights.get(e.worker)}")


@check("staleness")
def staleness(run: Run) -> None:
    """Algorithm 2 under a bounded staleness (summary.json ``max_staleness`` S; 0: every answer before the next
    submission): each worker applied the chief's answers in round order and each once; the submission for round R
    that reports an answer (its receipts, oldest first) reports one of a round in R - S - 1 .. R - 1, so the worker
    was never more than S of its rounds behind; and the receipt's episode, the first the worker played with the
    answer applied, is that submission's episode (receipts from workers that did not record it have none)."""
    stale = run.summary.max_staleness
    for w in run.workers:
        last = 0
        for (x, n), e in sorted(run.by_round.items(), key=lambda kv: kv[0][1]):
            if x != w:
                continue
            for rc in e.receipts:
                _holds(rc.round > last, f"{w} applied round {rc.round}'s answer after round {last}'s (reported in "
                       f"round {n}): answers out of order, or one applied twice")
                _holds(n - stale - 1 <= rc.round < n, f"{w}'s submission for round {n} reports round {rc.round}'s "
                       f"answer, outside rounds {max(1, n - stale - 1)}..{n - 1} (max_staleness {stale})")
                _holds(rc.episode is None or rc.episode == e.episode, f"{w} applied round {rc.round}'s answer "
                       f"before episode {rc.episode}, but reported it with episode {e.episode}")
                last = rc.round
    run.report.staleness = stale


def _restarted(run: Run, e: Submitted, receipt: Receipt) -> None:
    """A ``restarted`` receipt is a worker's first submission with new networks: an update for step 0 of the round
    right after the receipt's, with no answer digest or keep weight, and a PI window of this one episode's return."""
    where = f"{e.worker}'s submission for episode {e.episode} says it restarted after round {receipt.round}"
    _holds(isinstance(e, EpisodeRecord) and e.kind == "update" and run.round_of(e.episode, 0) == receipt.round + 1,
           f"{where}, but it is not an update for the next round")
    assert isinstance(e, EpisodeRecord)
    _holds(receipt.digest == "" and receipt.keep is None, f"{where}, and names an answer {receipt.model_dump()}")
    _holds(e.pi == e.return_, f"{where}, but its PI {e.pi} is not its one return {e.return_}: it has earlier ones")


@check("summary")
def summary(run: Run) -> None:
    """The reported result (the paper's episodes to solve, Fig. 5): the summary's solve episodes, env steps and
    episodes_to_all_solved agree with the records."""
    steps: dict[str, int] = defaultdict(int)
    for (w, ep), e in sorted(run.by_episode.items(), key=lambda kv: kv[0][1]):
        if ep <= run.solved_at.get(w, math.inf):
            steps[w] += e.steps
    for s in run.summary.workers:
        w = s.id
        _holds(s.solved == (w in run.solved_at), f"the summary says {w} solved={s.solved}, the records "
               f"{'do' if w in run.solved_at else 'do not'} hold its mature actor")
        if s.solved:
            _holds(s.episodes == run.solved_at[w], f"the summary says {w} solved at episode {s.episodes}, the "
                   f"records at {run.solved_at[w]}")
            _holds(s.steps == steps[w], f"the summary gives {w} {s.steps} env steps, the records {steps[w]}")
    expected = max(run.solved_at.values()) if len(run.solved_at) == len(run.workers) else None
    _holds(run.summary.episodes_to_all_solved == expected, f"episodes_to_all_solved is "
           f"{run.summary.episodes_to_all_solved}, the records give {expected}")


@check("played")
def played(run: Run) -> None:
    """Algorithm 2's work as it was done: every episode a worker played and its env steps (rig time, on a rig), counted
    by the chief or refused, are what the records say, and the chief counted no more of a worker's life than it
    played."""
    counted: dict[tuple[str, str], int] = defaultdict(int)
    said: dict[tuple[str, str], int] = defaultdict(int)
    for e in run.episodes:
        if e.played is not None:
            counted[e.worker, e.played.life] += e.steps
    records: list[EpisodeRecord | RefusedRecord] = [*run.episodes, *run.refused]
    for rec in records:
        if rec.played is not None:
            said[rec.worker, rec.played.life] = max(said[rec.worker, rec.played.life], rec.played.steps)
    for (w, life), steps in counted.items():
        _holds(steps <= said[w, life], f"{w} was counted {steps} env steps in its life {life}, more than the "
               f"{said[w, life]} it played")
    expected = played_totals(records)
    for s in run.summary.workers:
        got, want = s.played, expected.get(s.id)
        _holds(got == want, f"the summary gives {s.id} played {got.dump() if got else None}, the records "
               f"{want.dump() if want else None}")
        if got is not None:
            _holds(got.counted_steps + got.refused_steps == got.steps and got.counted_episodes + got.refused_episodes
                   == got.episodes, f"{s.id}'s counted and refused episodes and steps do not add up to its played")
    totals = [w.played for w in run.summary.workers if w.played is not None]
    for name, value, total in (("played_steps", run.summary.played_steps, sum(p.steps for p in totals)),
                               ("refused_steps", run.summary.refused_steps, sum(p.refused_steps for p in totals))):
        _holds(value == (total if totals else None), f"the summary's {name} is {value}, its workers' sum "
               f"{total if totals else None}")


@check("rig-time")
def rig_time(run: Run) -> None:
    """The headline figure of a rig learning by Algorithm 2 (chief/rigtime.py): the summary's rig time is what the
    records add up to."""
    expected = rig_times(sorted(run.submissions, key=lambda e: e.round), run.summary.max_staleness)
    for s in run.summary.workers:
        got, want = s.rig, expected.get(s.id)
        _holds((got is None) == (want is None), f"the summary gives {s.id} {'no ' if got is None else ''}rig time, "
               f"the records {'none' if want is None else 'some'}")
        if got is None or want is None:
            continue
        for name in ("balance_steps", "balance_s", "reset_s", "idle_s", "rig_s"):
            a, b = getattr(got, name), getattr(want, name)
            _holds(abs(a - b) <= RIG_TOLERANCE, f"the summary gives {s.id} {name} {a}, the records {b}")
        _holds(got.idle == want.idle, f"the summary says {s.id}'s idle seconds are {got.idle}, the records "
               f"{want.idle}")
        _holds(abs(got.rig_s - got.balance_s - got.reset_s) <= RIG_TOLERANCE, f"{s.id}'s rig time {got.rig_s} s is "
               f"not its balance {got.balance_s} s plus its reset {got.reset_s} s")
    last = last_rig(expected)
    _holds((run.summary.last_rig is None) == (last is None) and (last is None or (
        run.summary.last_rig is not None and run.summary.last_rig.id == last.id)),
        f"the summary's last rig is {run.summary.last_rig.id if run.summary.last_rig else None}, the records' "
        f"{last.id if last else None}")


def audit(run_dir: Path) -> AuditReport:
    """Check every invariant (CHECKS, in order); raises AuditFailure at the first one violated."""
    run = Run.read(run_dir)
    for c in CHECKS:
        try:
            c.run(run)
        except _Violated as violation:
            raise AuditFailure(c.invariant, str(violation)) from None
    return run.report

@returns_code
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=program("python -m chief.audit"), description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a run folder (summary.json + metrics.jsonl)")
    args = parser.parse_args(argv)
    try:
        report = audit(args.run_dir)
    except AuditFailure as failure:
        print(f"audit FAILED in {args.run_dir}: {failure}")
        return 1
    except (OSError, ValueError, KeyError, TypeError) as err:
        print(f"audit: cannot read the run folder {args.run_dir}: {type(err).__name__}: {err}", file=sys.stderr)
        return 2
    print(f"audit passed for {args.run_dir}: {report}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
