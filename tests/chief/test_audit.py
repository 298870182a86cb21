"""``python -m chief.audit``: passes on the records of an honest federation, and names the invariant a doctored
run folder violates."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from chief import strategies
from chief.audit import CHECKS, AuditFailure, audit, main
from chief.report import MetricsLog, run_summary, write_summary
from chief.rounds import RoundKeeper, Submission
from protocol.tasks import PI_WINDOW, performance_index, task
from runtime.records import GRADIENTS, ROOT, WitnessGap, gradient_key, write_gradients

SOLVE_AT = {"w0": 12, "w1": 15, "w2": 21}  # episodes at which each simulated worker hands over its actor
#: w2 also played an episode of this many env steps whose submission never arrived: played, never counted.
LOST_STEPS = 17


def simulate(run_dir: Path, policy: str = "weighted", restart: tuple[str, int] | None = None,
             witness: dict[str, np.ndarray] | None = None) -> None:
    """Drive the real RoundKeeper with three honest workers and write the run folder the chief would write (three
    rounds per episode under a per-step strategy). ``restart``: that worker is started again at that episode with
    new networks and no resumable state (worker/resume.py), as worker/federated.py's Algorithm2 then reports it.
    ``witness``: filled with every worker's actor gradient and every aggregate, keyed as in GRADIENTS."""
    shape = strategies.get(policy).rounds(3)
    per_step = shape.per_episode
    keeper = RoundKeeper(sorted(SOLVE_AT), policy, task("CartPole-v0"), max_episodes=100, round_timeout=30.0,
                         actor_spec={"g": (2,)}, critic_spec={"c": (1,)}, shape=shape)
    returns: dict[str, list[float]] = {w: [] for w in SOLVE_AT}
    receipts: dict[str, dict[str, Any] | None] = {w: None for w in SOLVE_AT}
    played = {w: {"life": f"{index:016x}", "episodes": 0, "steps": 0} for index, w in enumerate(sorted(SOLVE_AT))}
    played["w2"].update(episodes=1, steps=LOST_STEPS)
    metrics = MetricsLog(run_dir)  # the chief's writer
    episode = 1
    while not keeper.done:
        for step in range(per_step):
            for index, w in enumerate(sorted(SOLVE_AT)):
                rec = keeper.workers[w]
                if keeper.done or (rec.state == "finished" and not rec.helping) or (step and episode == SOLVE_AT[w]):
                    continue
                if (w, episode, step) == (*(restart or ("", 0)), 0):
                    returns[w], receipts[w] = [], {"round": keeper.shape.number(episode) - 1, "applied": "restarted"}
                if step == 0:
                    returns[w].append(200.0 if episode > SOLVE_AT[w] - PI_WINDOW else 20.0 + 10 * index + episode)
                    played[w].update(episodes=played[w]["episodes"] + 1, steps=played[w]["steps"] + int(returns[w][-1]))
                ret = returns[w][-1]
                mature = episode == SOLVE_AT[w]
                tensors = {"g": np.array([episode + step, -index], np.float32)}
                critic = {"c": np.array([step + 1.0], np.float32)} if per_step > 1 and not mature else None
                verdict = keeper.submit(Submission(
                    w, episode, performance_index(returns[w]), ret, recent_returns=tuple(returns[w][-PI_WINDOW:]),
                    steps=int(ret), gradient=None if mature else tensors, params=tensors if mature else None,
                    receipt=receipts[w], step=step, critic_gradient=critic, played=dict(played[w])),
                    now=float(episode))
                assert verdict.status == "accepted", verdict.detail
                metrics.episode(verdict.record(float(episode)))
                if witness is not None and not mature:
                    witness[gradient_key(episode, step, w, "g")] = tensors["g"]
                for outcome in verdict.outcomes:
                    if witness is not None and outcome.gradient is not None:
                        witness[gradient_key(outcome.episode, outcome.step, ROOT, "g")] = outcome.gradient["g"]
                    metrics.round({**outcome.record(), "t": float(episode)})
                    for r in SOLVE_AT:  # what each worker applies, as worker/service.py reports it
                        receipts[r] = {"round": outcome.round, "applied": outcome.kind, "digest": outcome.digest,
                                       "keep": outcome.keep_weights.get(r) if outcome.kind == "transfer" else None}
        episode += 1
    metrics.close()
    write_summary(run_dir, run_summary(keeper, keeper.done_reason or "", played=metrics.played, run_id="sim",
                                       seed=0))


@pytest.fixture(scope="module")
def honest(tmp_path_factory: pytest.TempPathFactory) -> Path:
    run_dir = tmp_path_factory.mktemp("audit") / "honest"
    simulate(run_dir)
    return run_dir


def records(run_dir: Path) -> list[dict[str, Any]]:
    return [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]


def rewrite(run_dir: Path, lines: list[dict[str, Any]]) -> None:
    (run_dir / "metrics.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))


def first(lines: list[dict[str, Any]], **match: Any) -> dict[str, Any]:
    return next(x for x in lines if all(x.get(k) == v for k, v in match.items()))


@pytest.mark.parametrize("policy", strategies.names())
def test_an_honest_federation_passes(tmp_path: Path, policy: str) -> None:
    simulate(tmp_path / policy, policy)
    report = audit(tmp_path / policy)
    if strategies.get(policy).rounds(3).per_step:  # 3 rounds per episode; a finisher's episode has one; finishers help
        # 20 episodes of 3 steps and a last step 0, all three workers (finishers help), less the steps 1-2 of
        # w0's and w1's finishing episodes.
        assert report.rounds == 20 * 3 + 1 and report.submissions == 3 * (20 * 3 + 1) - 2 * 2
        # every answer confirmed but the first round's: 3 workers x 61 rounds - 4 skipped submissions - 3 first
        # rounds; w0's and w1's finishing rounds are confirmed by their rejoining submissions (the answers they
        # caught up with)
        assert report.transfers == 0 and report.receipts == 176
        return
    assert report.rounds == 21 and report.submissions == 12 + 15 + 21
    # w0 and w1 finished while others were learning: one transfer each, to 2 and then 1 recipients.
    expected = (0, 0) if strategies.get(policy).keep_weight(0.5) is None else (2, 3)
    assert (report.transfers, report.transfer_deliveries) == expected
    assert report.receipts == 12 + 15 + 21 - 3


def doctor_weight(lines: list[dict]) -> None:
    r = first(lines, type="round", round=3)
    r["weights"] = {w: 1 / len(r["weights"]) for w in r["weights"]}


def doctor_keep(lines: list[dict]) -> None:
    first(lines, type="round", kind="transfer")["keep_weights"]["w2"] = 0.0


def doctor_recipients(lines: list[dict]) -> None:
    t = first(lines, type="round", kind="transfer")
    del t["keep_weights"]["w1"]


def doctor_offline_recipient(lines: list[dict]) -> None:
    first(lines, type="round", kind="transfer")["offline"] = ["w1"]  # said offline, yet sent the transfer


def doctor_offline_aggregate(lines: list[dict]) -> None:
    first(lines, type="round", round=3)["offline"] = ["w1"]  # nobody finished: nobody is left out of a transfer


def doctor_drop_transfer(lines: list[dict]) -> None:
    t = first(lines, type="round", kind="transfer")
    t.update(kind="aggregate", keep_weights={}, source=None, digest="")


def doctor_duplicate(lines: list[dict]) -> None:
    lines.insert(5, dict(first(lines, type="episode", worker="w1", episode=2)))


def doctor_spoofed(lines: list[dict]) -> None:
    lines.insert(5, {**first(lines, type="episode", worker="w1", episode=2), "worker": "mallory"})


def doctor_round_gap(lines: list[dict]) -> None:
    lines.remove(first(lines, type="round", round=4))


def doctor_contributors(lines: list[dict]) -> None:
    first(lines, type="round", round=5)["contributors"].pop()


def doctor_pi(lines: list[dict]) -> None:
    first(lines, type="round", round=6)["pis"]["w0"] = 190.0


def doctor_immature(lines: list[dict]) -> None:
    m = first(lines, type="episode", kind="mature", worker="w0")
    m["recent_returns"] = m["recent_returns"][-3:]


def doctor_receipt(lines: list[dict]) -> None:
    first(lines, type="episode", worker="w2", episode=13)["receipt"]["digest"] = "0" * 16


def doctor_applied_twice(lines: list[dict]) -> None:
    """w2 reports round 12's answer twice in one submission: applied twice (Algorithm 2 applies each once)."""
    e = first(lines, type="episode", worker="w2", episode=13)
    e["earlier_receipts"] = [dict(e["receipt"])]


def doctor_missed(lines: list[dict]) -> None:
    first(lines, type="episode", worker="w2", episode=8)["receipt"] = {"round": 7, "applied": "missed"}


def doctor_misfiled(lines: list[dict]) -> None:
    first(lines, type="episode", worker="w1", episode=4)["round"] = 5


def doctor_round_place(lines: list[dict]) -> None:
    first(lines, type="round", round=7)["episode"] = 8


def doctor_mature_returns(lines: list[dict]) -> None:
    """w0's mature PI counts another return for an episode than it reported (the mean and TC still hold)."""
    m = first(lines, type="episode", kind="mature", worker="w0")
    m["recent_returns"][0], m["recent_returns"][1] = m["recent_returns"][0] + 1, m["recent_returns"][1] - 1


def doctor_transfer_keep_receipt(lines: list[dict]) -> None:
    t = first(lines, type="round", kind="transfer")
    first(lines, type="episode", worker="w2", round=t["round"] + 1)["receipt"]["keep"] = 0.5


def doctor_weights_sum(lines: list[dict]) -> None:
    r = first(lines, type="round", round=3)
    r["weights"] = {w: 2 * v for w, v in r["weights"].items()}


def doctor_fakexfer(lines: list[dict]) -> None:
    """Issue 19's "fakexfer" run: round 2 closed with no contributors (every submission of episode 2 was late), and a
    worker applied, as its answer, a transfer the chief never sent (a forger's): ``delivery`` has nobody to check."""
    lines[:] = [x for x in lines if not (x["type"] == "episode" and x["episode"] == 2)]
    first(lines, type="round", round=2).update(contributors=[], pis={}, weights={}, digest="")
    first(lines, type="episode", worker="w2", episode=3)["receipt"] = {"round": 2, "applied": "transfer",
                                                                      "digest": "f" * 16, "keep": 0.0}


def doctor_played_under(lines: list[dict]) -> None:
    """w0 said it played 1 env step in every submission, yet the chief counted more."""
    for x in lines:
        if x["type"] == "episode" and x["worker"] == "w0":
            x["played"]["steps"] = 1


def test_a_worker_started_again_with_new_networks_passes(tmp_path: Path) -> None:
    """A worker started again without its resumable state says so in its first receipt (``restarted``): ``delivery``
    accepts exactly that in place of the previous round's answer."""
    simulate(tmp_path / "run", restart=("w2", 6))
    report = audit(tmp_path / "run")
    assert first(records(tmp_path / "run"), type="episode", worker="w2", episode=6)["receipt"]["applied"] == "restarted"
    assert report.receipts == 12 + 15 + 21 - 3 - 1


def doctor_restarted(lines: list[dict]) -> None:
    """A worker that says it restarted with new networks, yet its PI averages earlier returns."""
    first(lines, type="episode", worker="w2", episode=8)["receipt"] = {"round": 7, "applied": "restarted"}


def doctor_restarted_round(lines: list[dict]) -> None:
    """A restart receipt that names another round than the one before."""
    first(lines, type="episode", worker="w2", episode=8)["receipt"] = {"round": 5, "applied": "restarted"}


def doctor_edges(lines: list[dict]) -> None:
    r = first(lines, type="round", round=3)
    r["edges"] = {"e0": r["contributors"][:1], "e1": []}  # a tiered round whose edges summed too few


def doctor_late(lines: list[dict]) -> None:
    first(lines, type="round", round=3)["late"] = ["w0"]  # a round that closed without a worker, and no quorum


DOCTORED = [
    (doctor_edges, "tiered-edges"),
    (doctor_late, "quorum"),
    (doctor_played_under, "played"),
    (doctor_restarted, "receipts"),
    (doctor_restarted_round, "delivery"),
    (doctor_fakexfer, "receipts"),
    (doctor_weight, "eq8-weights"),
    (doctor_weights_sum, "eq8-weights"),
    (doctor_keep, "transfer"),
    (doctor_recipients, "transfer"),
    (doctor_drop_transfer, "transfer"),
    (doctor_offline_recipient, "transfer"),
    (doctor_offline_aggregate, "transfer"),
    (doctor_duplicate, "counted-once"),
    (doctor_spoofed, "counted-once"),
    (doctor_round_gap, "rounds-contiguous"),
    (doctor_contributors, "contributors"),
    (doctor_pi, "round-pis"),
    (doctor_immature, "mature"),
    (doctor_receipt, "delivery"),
    (doctor_missed, "delivery"),
    (doctor_applied_twice, "staleness"),
    (doctor_transfer_keep_receipt, "delivery"),
    (doctor_misfiled, "rounds-contiguous"),
    (doctor_round_place, "rounds-contiguous"),
    (doctor_mature_returns, "mature"),
]


def test_every_invariant_has_a_doctored_record_and_cites_the_paper() -> None:
    """Each registered check is failed by some doctored run folder below (``summary`` by a doctored summary.json,
    ``rig-time`` by a doctored rig's record in tests/chief/test_rigtime.py, ``tiered-exact`` by a doctored witness and
    ``edge-records`` by a doctored edge record in tests/e2e/test_tiered.py), and its docstring says which equation,
    algorithm or figure of the paper it protects."""
    assert ({invariant for _, invariant in DOCTORED} | {"summary", "rig-time", "tiered-exact", "edge-records"}
            == {c.invariant for c in CHECKS})
    assert len({c.invariant for c in CHECKS}) == len(CHECKS) == 17
    for c in CHECKS:
        assert c.run.__doc__ and any(cite in c.run.__doc__ for cite in ("Eq. ", "Algorithm ", "Fig. ")), c.invariant


@pytest.mark.parametrize(("doctor", "invariant"), DOCTORED)
def test_a_doctored_record_names_the_violated_invariant(
    honest: Path, tmp_path: Path, doctor: Callable[[list[dict]], None], invariant: str
) -> None:
    run_dir = tmp_path / "doctored"
    shutil.copytree(honest, run_dir)
    lines = records(run_dir)
    doctor(lines)
    rewrite(run_dir, lines)
    with pytest.raises(AuditFailure) as failure:
        audit(run_dir)
    assert failure.value.invariant == invariant, str(failure.value)


@pytest.mark.parametrize(("field", "value"), [("episodes_to_all_solved", 15), ("rounds", 20)])
def test_a_doctored_summary_fails(honest: Path, tmp_path: Path, field: str, value: int) -> None:
    run_dir = tmp_path / "doctored"
    shutil.copytree(honest, run_dir)
    summary = json.loads((run_dir / "summary.json").read_text())
    summary[field] = value
    (run_dir / "summary.json").write_text(json.dumps(summary))
    with pytest.raises(AuditFailure, match=r"summary|rounds-contiguous"):
        audit(run_dir)
    summary = json.loads((honest / "summary.json").read_text())
    summary["workers"][1]["episodes"] = 14
    (run_dir / "summary.json").write_text(json.dumps(summary))
    with pytest.raises(AuditFailure, match="summary: the summary says w1 solved at episode 14"):
        audit(run_dir)


def test_played_steps_are_counted_and_refused_apart(honest: Path, tmp_path: Path) -> None:
    """summary.json gives each worker everything it played, what the chief counted and the rest apart (w2's lost
    episode), the run's totals too; a doctored count fails the ``played`` invariant."""
    summary = json.loads((honest / "summary.json").read_text())
    played = {w["id"]: w["played"] for w in summary["workers"]}
    counted = {w: sum(x["steps"] for x in records(honest) if x["type"] == "episode" and x["worker"] == w)
               for w in SOLVE_AT}
    assert played["w2"] == {"episodes": 22, "steps": counted["w2"] + LOST_STEPS, "counted_episodes": 21,
                            "counted_steps": counted["w2"], "refused_episodes": 1, "refused_steps": LOST_STEPS}
    assert played["w0"]["refused_steps"] == 0 and played["w0"]["steps"] == counted["w0"]
    assert summary["played_steps"] == summary["total_steps"] + LOST_STEPS and summary["refused_steps"] == LOST_STEPS
    run_dir = tmp_path / "doctored"
    shutil.copytree(honest, run_dir)
    for doctored in ({"workers": 2, "refused_steps": 0}, {"workers": 0, "counted_steps": 1}, {"refused_steps": 0}):
        data = json.loads((honest / "summary.json").read_text())
        row = data["workers"][doctored.pop("workers")]["played"] if "workers" in doctored else data
        row.update(doctored)
        (run_dir / "summary.json").write_text(json.dumps(data))
        with pytest.raises(AuditFailure, match=r"^played: "):
            audit(run_dir)


def test_the_command_exits_non_zero_naming_the_invariant(honest: Path, tmp_path: Path) -> None:
    ok = subprocess.run([sys.executable, "-m", "chief.audit", str(honest)], capture_output=True, text=True)
    assert ok.returncode == 0 and "audit passed" in ok.stdout and "2 transfers" in ok.stdout
    run_dir = tmp_path / "doctored"
    shutil.copytree(honest, run_dir)
    lines = records(run_dir)
    doctor_keep(lines)
    rewrite(run_dir, lines)
    bad = subprocess.run([sys.executable, "-m", "chief.audit", str(run_dir)], capture_output=True, text=True)
    assert bad.returncode == 1 and "audit FAILED" in bad.stdout and "transfer:" in bad.stdout
    missing = subprocess.run([sys.executable, "-m", "chief.audit", str(tmp_path / "nope")], capture_output=True,
                             text=True)
    assert missing.returncode == 2 and "cannot read" in missing.stderr


@pytest.mark.parametrize("policy", ["sync", "weighted"])
def test_a_finished_helpers_submission_may_outlive_the_run(tmp_path: Path, policy: str) -> None:
    """Under a strategy whose finishers keep helping (sync), a finished worker's next submission can be accepted
    just before the last learner's finish ends the run; its round is never closed, and that is no violation. Under
    any other strategy a counted submission in a round that never closed is one."""
    simulate(tmp_path / policy, policy)
    lines = records(tmp_path / policy)
    last = max(int(x["round"]) for x in lines if x["type"] == "round")
    episode, step = strategies.get(policy).rounds(3).of(last + 1)
    early = [x for x in lines if x["type"] == "episode" and x["worker"] == "w0"][-1]
    closing = first(lines, type="round", round=last)
    receipt = {"round": last, "applied": closing["kind"], "digest": closing["digest"], "keep": None}
    late = {"episode": episode, "round": last + 1, "receipt": receipt}
    lines.append({"type": "step", "worker": "w0", "step": step, "t": 0.0, **late} if step else {**early, **late})
    rewrite(tmp_path / policy, lines)
    if not strategies.get(policy).finishers_help:
        with pytest.raises(AuditFailure, match=r"contributors: round .* was counted but never closed"):
            audit(tmp_path / policy)
        return
    assert audit(tmp_path / policy).uncounted == [("w0", last + 1)]


def test_a_helper_that_did_not_catch_up_fails_delivery(tmp_path: Path) -> None:
    """Under sync a finisher skips the other steps of its finishing episode; rejoining with the receipt of the round
    before its finish (the answers it skipped never applied, so its networks differ from the others') is caught."""
    simulate(tmp_path / "sync", "sync")
    lines = records(tmp_path / "sync")
    mature = first(lines, type="episode", kind="mature", worker="w0")
    rejoin = next(x for x in lines if x["type"] in ("episode", "step") and x["worker"] == "w0"
                  and x["round"] > mature["round"])
    rejoin["receipt"] = dict(mature["receipt"])
    rewrite(tmp_path / "sync", lines)
    with pytest.raises(AuditFailure, match=r"delivery: w0 finished in round .* without confirming"):
        audit(tmp_path / "sync")


@pytest.fixture(scope="module")
def tiered(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, np.ndarray]]:
    """The honest run as a tiered root records it (every round's contributors behind edge e0, so ``tiered-exact``
    checks each aggregate) and its witness's tensors, not yet saved."""
    run_dir = tmp_path_factory.mktemp("audit") / "tiered"
    witness: dict[str, np.ndarray] = {}
    simulate(run_dir, witness=witness)
    lines = records(run_dir)
    for x in lines:
        if x["type"] == "round":
            x["edges"] = {"e0": x["contributors"]}
    rewrite(run_dir, lines)
    return run_dir, witness


def witnessed(tiered: tuple[Path, dict[str, np.ndarray]], tmp_path: Path, gaps: list[WitnessGap] | None,
              missing: tuple[int, int] | None = None) -> Path:
    """A copy of the tiered run with its witness saved, without the root's aggregate of round (episode, step)
    ``missing``; with ``gaps``, or as a witness from before gaps were recorded (None: no such key)."""
    run_dir = tmp_path / "run"
    shutil.copytree(tiered[0], run_dir)
    tensors = {k: v for k, v in tiered[1].items() if missing is None or k != gradient_key(*missing, ROOT, "g")}
    if gaps is None:
        np.savez_compressed(run_dir / GRADIENTS, **tensors)  # type: ignore[arg-type]
    else:
        write_gradients(run_dir / GRADIENTS, tensors, gaps)
    return run_dir


#: Round 7's place (episode 7, step 0): its aggregate is the one the witness misses below.
MISSED = (7, 0)
AGGREGATES = 21 - 3  # the honest run's rounds less its two transfers and its last (w2 finished: nothing shared)


@pytest.mark.parametrize("gaps", [None, [], [WitnessGap((2, 0), (5, 0))]], ids=["older-file", "no-gap", "elsewhere"])
def test_a_root_aggregate_the_witness_lacks_outside_its_gaps_fails(
        tiered: tuple[Path, dict[str, np.ndarray]], tmp_path: Path, gaps: list[WitnessGap] | None) -> None:
    """Every aggregate the witness holds is checked; one it lacks where it recorded no gap fails ``tiered-exact``,
    in a GRADIENTS without gaps (an older run's) as before."""
    report = audit(witnessed(tiered, tmp_path / "whole", gaps))
    assert (report.tiered, report.unwitnessed) == (AGGREGATES, 0)
    with pytest.raises(AuditFailure, match=r"tiered-exact: round 7: the witness lacks the root's aggregate"):
        audit(witnessed(tiered, tmp_path / "lacking", gaps, missing=MISSED))


@pytest.mark.parametrize("gap", [WitnessGap((6, 0), (8, 0)), WitnessGap((7, 0), (7, 0)), WitnessGap(None, (7, 0)),
                                 WitnessGap((7, 0), None)], ids=["between", "bounds", "from-start", "to-end"])
def test_a_root_aggregate_missing_inside_a_witness_gap_is_counted_unwitnessed(
        tiered: tuple[Path, dict[str, np.ndarray]], tmp_path: Path, gap: WitnessGap) -> None:
    """A round the witness lacks inside a gap it recorded (its bounds included, an open end from the beginning or to
    the end) is counted as unwitnessed and not checked; the audit's output says how many."""
    run_dir = witnessed(tiered, tmp_path, [WitnessGap((1, 0), (1, 0)), gap], missing=MISSED)
    report = audit(run_dir)
    assert (report.tiered, report.unwitnessed) == (AGGREGATES - 1, 1)
    assert "1 root aggregate not witnessed" in str(report)


def test_the_command_prints_the_unwitnessed_rounds(tiered: tuple[Path, dict[str, np.ndarray]], tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    assert main([str(witnessed(tiered, tmp_path, [WitnessGap((6, 0), (8, 0))], missing=MISSED))]) == 0
    out = capsys.readouterr().out
    assert (f"{AGGREGATES - 1} tiered aggregates within the bound" in out
            and "1 root aggregate not witnessed (inside the witness's gaps" in out), out
