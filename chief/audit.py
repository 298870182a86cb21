"""``python -m chief.audit RUN_DIR``: re-check a run's federation from its records alone.

Reads ``summary.json`` and ``metrics.jsonl`` (what the chief accepted, and every round it closed) and re-derives what
the federation must have done. It exits 0 when every invariant holds, 1 naming the first that does not, 2 when the
folder cannot be read. The invariants:

- ``counted-once``: no worker's episode (or, under a per-step strategy, step) is counted twice;
- ``rounds-contiguous``: rounds are 1, 2, ... without gaps, as many as the summary says, each the round of its
  (episode, step);
- ``contributors``: a round's contributors are exactly the submissions counted for its episode, and every counted
  submission belongs to a round (a run that was aborted may leave some in the round it never closed);
- ``round-pis``: the PIs a round used are the PIs of its counted submissions;
- ``mature``: a mature actor was accepted only with PI >= TC over PI_WINDOW episodes, PI the mean of its returns;
  nothing of a worker was counted after it finished (unless its strategy lets finishers go on sharing);
- ``eq8-weights``: every aggregate's weights are the strategy's (Eq. 8 for ``weighted``) of that round's PIs and
  sum to 1;
- ``transfer``: in every round where a worker finished while others were still learning, the best finisher's actor
  went to each of them, with keep weights = Eq. 10 of each recipient's PI at that round (strategies that share);
- ``delivery``: each worker that took part in a round confirms with its next submission that it applied the round's
  answer (same tensor digest, same keep weight);
- ``summary``: the summary's solve episodes, steps and totals agree with the records.
"""

from __future__ import annotations

import argparse
import bisect
import json
import math
import sys
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from chief import federation, strategies
from protocol.rounds import RoundShape
from protocol.settings import program, returns_code
from protocol.tasks import PI_WINDOW, performance_index


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
    uncounted: list[tuple[str, int]] = field(default_factory=list)

    def __str__(self) -> str:
        text = (f"{self.rounds} rounds, {self.submissions} counted submissions, {self.transfers} transfers "
                f"({self.transfer_deliveries} recipients), {self.receipts} receipts confirmed")
        if self.uncounted:
            text += (f"; {len(self.uncounted)} submissions left in a round the run never closed (an aborted run, "
                     "or a finished helper's after the last finish)")
        return text


def _close(a: float | None, b: float | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12)


def _require(ok: bool, invariant: str, detail: str) -> None:
    if not ok:
        raise AuditFailure(invariant, detail)


def load(run_dir: Path) -> tuple[dict[str, Any], list[dict[str, Any]], list[dict[str, Any]], list[dict[str, Any]]]:
    """summary, episode records, later-step records and round records of a run folder (OSError/ValueError when
    unreadable)."""
    summary = json.loads((run_dir / "summary.json").read_text(encoding="utf-8"))
    found: dict[str, list[dict[str, Any]]] = {"episode": [], "step": [], "round": []}
    for number, line in enumerate((run_dir / "metrics.jsonl").read_text(encoding="utf-8").splitlines(), 1):
        if not line.strip():
            continue
        record = json.loads(line)
        kind = record.get("type")
        if kind not in found:
            raise ValueError(f"metrics.jsonl line {number}: unknown record type {kind!r}")
        found[kind].append(record)
    return summary, found["episode"], found["step"], found["round"]


def audit(run_dir: Path) -> AuditReport:
    """Check every invariant; raises AuditFailure at the first one violated."""
    summary, episodes, steps_done, rounds = load(run_dir)
    strategy = strategies.get(summary["policy"])
    tc, r_floor = float(summary["tc"]), float(summary["r_floor"])
    shape = RoundShape(per_episode=int(summary.get("rounds_per_episode", 1)))
    workers = [w["id"] for w in summary["workers"]]
    report = AuditReport(rounds=len(rounds), submissions=len(episodes) + len(steps_done))

    def progress(pi: float | None) -> float:
        return federation.progress(r_floor if pi is None else pi, tc, r_floor)

    # counted-once: every counted submission by (worker, round); the episode records by (worker, episode)
    by_key: dict[tuple[str, int], dict[str, Any]] = {}
    by_round: dict[tuple[str, int], dict[str, Any]] = {}
    for e in episodes + steps_done:
        step = int(e.get("step", 0))
        key = (e["worker"], shape.number(int(e["episode"]), step))
        _require(int(e.get("round", key[1])) == key[1], "rounds-contiguous",
                 f"{e['worker']}'s episode {e['episode']} step {step} is filed as round {e.get('round')}, not {key[1]}")
        _require(key not in by_round, "counted-once",
                 f"{key[0]}'s episode {e['episode']} (step {step}) is counted twice")
        _require(key[0] in workers, "counted-once", f"a submission of {key[0]}, who is not in the run, was counted")
        by_round[key] = e
        if e["type"] == "episode":
            by_key[(e["worker"], int(e["episode"]))] = e

    # rounds-contiguous
    numbers = [int(r["round"]) for r in rounds]
    _require(numbers == list(range(1, len(rounds) + 1)), "rounds-contiguous",
             f"rounds are {numbers[:5]}...{numbers[-5:]}, not 1..{len(rounds)}")
    _require(summary["rounds"] == len(rounds), "rounds-contiguous",
             f"the summary says {summary['rounds']} rounds, the records have {len(rounds)}")
    last_round = len(rounds)

    # contributors
    per_round: dict[int, dict[str, dict[str, Any]]] = defaultdict(dict)
    for (w, n), e in by_round.items():
        per_round[n][w] = e
    aborted = not str(summary.get("end_reason", "")).startswith(("all workers solved", "reached the maximum"))
    finished_in: dict[str, int] = {}  # the round of each worker's counted mature actor
    for (w, n), e in sorted(by_round.items(), key=lambda kv: kv[0][1]):
        if e.get("kind") == "mature":
            finished_in.setdefault(w, n)
    for n in sorted(per_round):
        if n > last_round:
            # A worker that finished and keeps helping (finishers_help) may have its next submission accepted
            # before the last learner's finish ends the run: that round is legitimately never closed.
            helpers_only = strategy.finishers_help and all(finished_in.get(w, n) < n for w in per_round[n])
            _require(aborted or helpers_only, "contributors",
                     f"round {n} of {sorted(per_round[n])} was counted but never closed, "
                     f"although the run ended normally ({summary.get('end_reason')})")
            report.uncounted += [(w, n) for w in sorted(per_round[n])]
    for r in rounds:
        n = int(r["round"])
        counted = sorted(per_round.get(n, {}))
        _require(sorted(r["contributors"]) == counted, "contributors",
                 f"round {n} lists {sorted(r['contributors'])} but the counted submissions are {counted}")

    # round-pis and mature
    for r in rounds:
        n = int(r["round"])
        _require((int(r.get("episode", n)), int(r.get("step", 0))) == shape.of(n),
                 "rounds-contiguous", f"round {n} says episode {r.get('episode')} step {r.get('step')}")
        episode_n = shape.episode_of(n)
        expected = {w: by_key[(w, episode_n)]["pi"] for w in per_round.get(n, {}) if (w, episode_n) in by_key}
        _require(set(r["pis"]) == set(expected) and all(_close(r["pis"][w], expected[w]) for w in expected),
                 "round-pis", f"round {n} used PIs {r['pis']}, the counted submissions say {expected}")
    solved_at: dict[str, int] = {}
    for (w, ep), e in sorted(by_key.items(), key=lambda kv: kv[0][1]):
        if e["kind"] != "mature":
            continue
        recent = e.get("recent_returns") or []
        pi = performance_index(recent) if recent else float("nan")
        _require(len(recent) >= PI_WINDOW and _close(pi, e["pi"]) and pi >= tc, "mature",
                 f"{w}'s mature actor of episode {ep} was accepted with PI {e['pi']} over {len(recent)} returns "
                 f"(mean {pi}); TC is {tc} over {PI_WINDOW}")
        for back, value in enumerate(reversed(recent)):
            known = by_key.get((w, ep - back))
            _require(known is None or _close(known["return"], value), "mature",
                     f"{w}'s mature PI counts a return of {value} for episode {ep - back}, which it reported as "
                     f"{known and known['return']}")
        _require(w not in solved_at, "mature", f"{w} finished twice (episodes {solved_at.get(w)} and {ep})")
        solved_at[w] = ep
    if not strategy.finishers_help:
        late = sorted((w, int(e["episode"])) for (w, _), e in by_round.items() if int(e["episode"]) > solved_at.get(
            w, math.inf))
        _require(not late, "mature", f"submissions counted after their worker had finished: {late[:3]}")

    # eq8-weights and transfer
    counted_eps = {w: sorted(ep for (x, ep) in by_key if x == w) for w in workers}

    def pi_at(worker: str, episode: int) -> float | None:
        """The PI of the worker's latest counted submission up to ``episode`` (what the chief's Eq. 10 used)."""
        eps = counted_eps[worker]
        i = bisect.bisect_right(eps, episode)
        return by_key[(worker, eps[i - 1])]["pi"] if i else None

    for r in rounds:
        n = int(r["round"])
        episode_n = shape.episode_of(n)
        finished = sorted(w for w, e in per_round.get(n, {}).items() if e.get("kind") == "mature")
        _require(sorted(r["finished"]) == finished, "transfer",
                 f"round {n} says {sorted(r['finished'])} finished, the counted mature actors are {finished}")
        learners = sorted(w for w in workers if solved_at.get(w, math.inf) > episode_n)
        keeps = {w: strategy.keep_weight(progress(pi_at(w, episode_n))) for w in learners}
        transfers = bool(learners) and all(k is not None for k in keeps.values())
        if finished and transfers:
            _require(r["kind"] == "transfer", "transfer",
                     f"round {n}: {finished} finished while {learners} were learning, but no transfer was sent")
            best = federation.best_mature({w: per_round[n][w]["pi"] for w in finished})
            _require(r["source"] == best and _close(r["source_pi"], per_round[n][best]["pi"]), "transfer",
                     f"round {n} transferred {r['source']}'s actor; the best finisher was {best}")
            _require(sorted(r["keep_weights"]) == learners, "transfer",
                     f"round {n}'s transfer went to {sorted(r['keep_weights'])}, the workers still learning were "
                     f"{learners}")
            for w in learners:
                _require(_close(r["recipient_pis"].get(w), pi_at(w, episode_n)), "transfer",
                         f"round {n}: {w}'s PI at that round was {pi_at(w, episode_n)}, the transfer used "
                         f"{r['recipient_pis'].get(w)}")
                _require(_close(r["keep_weights"][w], keeps[w]), "transfer",
                         f"round {n}: {w} kept {r['keep_weights'][w]} of its actor, Eq. 10 gives {keeps[w]}")
            report.transfers += 1
            report.transfer_deliveries += len(learners)
            continue
        _require(r["kind"] == "aggregate", "transfer", f"round {n} sent a transfer, but nobody both finished and "
                 "left others learning under a strategy that transfers")
        contributors = sorted(w for w in r["contributors"] if w not in finished)  # the finishers only leave
        if not contributors:
            _require(not r["weights"] and not r["digest"], "eq8-weights", f"round {n} had no contributors but "
                     "shared a gradient")
            continue
        zeros = {w: {"x": np.zeros(1, np.float32)} for w in contributors}
        expected_w = strategy.aggregate(zeros, {w: progress(r["pis"][w]) for w in contributors}).weights or {}
        _require(set(r["weights"]) == set(expected_w)
                 and all(_close(r["weights"][w], expected_w[w]) for w in expected_w), "eq8-weights",
                 f"round {n}'s weights are {r['weights']}, {strategy.name} gives {expected_w} for PIs {r['pis']}")
        if expected_w:
            _require(math.isclose(sum(r["weights"].values()), 1.0, abs_tol=1e-9), "eq8-weights",
                     f"round {n}'s weights sum to {sum(r['weights'].values())}")

    # delivery: every worker that took part in a round (and did not finish in it) confirms, with its next counted
    # submission, what it applied of that round's answer
    for r in rounds:
        n = int(r["round"])
        for w in sorted(set(r["contributors"]) - set(r["finished"])):
            nxt = by_round.get((w, n + 1))
            if nxt is None:
                continue
            receipt = nxt.get("receipt")
            if receipt is None or int(receipt.get("round", -1)) != n:
                raise AuditFailure("delivery", f"{w}'s submission for round {n + 1} carries no receipt of round {n} "
                                   f"({receipt})")
            _require(receipt["applied"] != "missed", "delivery", f"round {n}'s {r['kind']} never reached {w}")
            _require(receipt["applied"] == r["kind"] and receipt.get("digest", "") == r["digest"], "delivery",
                     f"{w} applied {receipt['applied']} {receipt.get('digest')!r} as round {n}'s answer, the chief "
                     f"sent {r['kind']} {r['digest']!r}")
            if r["kind"] == "transfer":
                _require(_close(receipt.get("keep"), r["keep_weights"].get(w)), "delivery",
                         f"{w} kept {receipt.get('keep')} of its actor in round {n}, the chief said "
                         f"{r['keep_weights'].get(w)}")
            report.receipts += 1

    # delivery to helpers: a finisher that goes on sharing (finishers_help) skipped the other rounds of its finishing
    # episode; its first submission after them confirms the round just before, so it applied every answer it missed
    # and its networks are the others' again
    if strategy.finishers_help:
        closed = {int(r["round"]): r for r in rounds}
        for w, n in finished_in.items():
            later = min((m for (x, m) in by_round if x == w and m > n), default=None)
            if later is None or later - 1 not in closed:
                continue
            receipt, before = by_round[(w, later)].get("receipt") or {}, closed[later - 1]
            _require(int(receipt.get("round", -1)) == later - 1 and receipt.get("applied") == before["kind"]
                     and receipt.get("digest", "") == before["digest"], "delivery",
                     f"{w} finished in round {n} and rejoined in round {later} without confirming round "
                     f"{later - 1}'s answer ({receipt or None}): it missed the answers of its finishing episode")
            report.receipts += 1

    # summary
    steps: dict[str, int] = defaultdict(int)
    for (w, ep), e in sorted(by_key.items(), key=lambda kv: kv[0][1]):
        if ep <= solved_at.get(w, math.inf):
            steps[w] += int(e["steps"])
    for s in summary["workers"]:
        w = s["id"]
        _require(bool(s["solved"]) == (w in solved_at), "summary",
                 f"the summary says {w} solved={s['solved']}, the records {'do' if w in solved_at else 'do not'} "
                 "hold its mature actor")
        if s["solved"]:
            _require(s["episodes"] == solved_at[w], "summary",
                     f"the summary says {w} solved at episode {s['episodes']}, the records at {solved_at[w]}")
            _require(s.get("steps", steps[w]) == steps[w], "summary",
                     f"the summary gives {w} {s.get('steps')} env steps, the records {steps[w]}")
    all_solved = len(solved_at) == len(workers)
    expected_last = max(solved_at.values()) if all_solved else None
    _require(summary["episodes_to_all_solved"] == expected_last, "summary",
             f"episodes_to_all_solved is {summary['episodes_to_all_solved']}, the records give {expected_last}")
    return report


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
