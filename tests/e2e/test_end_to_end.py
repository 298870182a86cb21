"""End to end: the chief and 4 PPO workers as separate processes over a real broker learn CartPole-v0 under every
strategy of the registry, and the audit re-checks from the run folder what the federation did: every early
finisher's actor reached every worker still learning, weights are the strategy's, nothing was counted twice, and
every answer was applied by the worker it was meant for. The same seed gives the same federation over Mosquitto
under extra CPU load (record by record, up to past its first transfers): timing does not decide the result."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from chief import strategies
from chief.audit import AuditFailure, audit
from tests.federations import WORKERS, Runs, cpu_load, federate, per_worker_up_to, records_up_to, warnings_of

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("e2e")]  # one process computes the shared runs


def per_worker(run_dir: Path) -> list[tuple[str, int, int]]:
    summary = json.loads((run_dir / "summary.json").read_text())
    return [(w["id"], w["episodes"], w["steps"]) for w in summary["workers"]]


def early_finishers(run_dir: Path) -> dict[str, int]:
    """Workers that solved while another was still learning, with their solve episode."""
    summary = json.loads((run_dir / "summary.json").read_text())
    last = summary["episodes_to_all_solved"]
    return {w["id"]: w["episodes"] for w in summary["workers"] if w["episodes"] < last}


@pytest.mark.parametrize("policy", strategies.names())
def test_four_workers_learn_and_the_audit_passes(runs: Runs, policy: str) -> None:
    run_dir = runs[policy]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["policy"] == policy and all(w["solved"] for w in summary["workers"])
    assert summary["rejected_messages"] == {}, warnings_of(run_dir)
    assert sorted(p.name for p in (run_dir / "models").iterdir()) == [f"w{i}.pt" for i in range(WORKERS)]
    assert (run_dir / "learning_curve.png").stat().st_size > 1000
    report = audit(run_dir)  # raises AuditFailure naming the first violated invariant
    if not strategies.get(policy).rounds(summary["rounds_per_episode"]).per_step:
        assert report.submissions == sum(w["episodes"] for w in summary["workers"])
    # Every answer but the first round's was confirmed (under sync, a finisher confirms the rounds of its finishing
    # episode, whose answers it caught up with, by the receipt of its rejoining submission).
    assert report.receipts == report.submissions - WORKERS


@pytest.mark.parametrize("policy", [p for p in strategies.names() if strategies.get(p).keep_weight(0.5) is not None])
def test_every_early_finisher_hands_its_actor_to_the_others(runs: Runs, policy: str) -> None:
    run_dir = runs[policy]
    early = early_finishers(run_dir)
    assert early, "seed 3 should have workers finishing before the last"
    rounds = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    transfers = {r["round"]: r for r in rounds if r["type"] == "round" and r["kind"] == "transfer"}
    for worker, episode in early.items():
        t = transfers.get(episode)
        assert t is not None and worker in t["finished"], f"{worker} finished at {episode}: no transfer"
        learning = {w for w, e in per_worker_solved(run_dir).items() if e > episode}
        assert set(t["keep_weights"]) == learning
    if policy == "plain":
        assert all(k == 0.0 for t in transfers.values() for k in t["keep_weights"].values())


def per_worker_solved(run_dir: Path) -> dict[str, int]:
    return {w: e for w, e, _ in per_worker(run_dir)}


def test_independent_workers_share_nothing(runs: Runs) -> None:
    rounds = [json.loads(x) for x in (runs["independent"] / "metrics.jsonl").read_text().splitlines()]
    assert all(r["kind"] == "aggregate" and r["digest"] == "" for r in rounds if r["type"] == "round")


def test_sync_workers_share_every_step(runs: Runs) -> None:
    summary = json.loads((runs["sync"] / "summary.json").read_text())
    lines = [json.loads(x) for x in (runs["sync"] / "metrics.jsonl").read_text().splitlines()]
    rounds = [r for r in lines if r["type"] == "round"]
    assert summary["rounds_per_episode"] == 10 and len(rounds) == summary["rounds"]
    assert {r["step"] for r in rounds} == set(range(10))
    assert all(r["digest"] and not r["keep_weights"] for r in rounds if r["contributors"] and not r["finished"])


def test_the_audit_fails_on_a_doctored_real_run(runs: Runs, tmp_path: Path) -> None:
    run_dir = tmp_path / "doctored"
    shutil.copytree(runs["weighted"], run_dir)
    lines = (run_dir / "metrics.jsonl").read_text().splitlines()
    # Drop the first transfer's first recipient, as if the chief had skipped it.
    for i, line in enumerate(lines):
        record = json.loads(line)
        if record["type"] == "round" and record["kind"] == "transfer":
            record["keep_weights"].pop(sorted(record["keep_weights"])[0])
            lines[i] = json.dumps(record)
            break
    (run_dir / "metrics.jsonl").write_text("\n".join(lines) + "\n")
    with pytest.raises(AuditFailure, match=r"^transfer: "):
        audit(run_dir)


#: The loaded run's cap: past the first finishers of the ``weighted`` run (episodes 22, 32 and 32 for this seed), so
#: that the transfers are in it; the last worker goes on alone after that (84), which the shared run covers.
LOADED_EPISODES = 36


@pytest.mark.parametrize("policy", ["weighted"])  # every strategy in process against amqtt: test_inprocess_equivalence
def test_same_seed_same_result_over_mosquitto_under_cpu_load(
    runs: Runs, mosquitto_broker: str, tmp_path: Path, policy: str
) -> None:
    with cpu_load():
        run_dir = federate(tmp_path, f"mosquitto-{policy}", policy, broker=mosquitto_broker,
                           max_episodes=LOADED_EPISODES)
    assert json.loads((run_dir / "summary.json").read_text())["broker"] == mosquitto_broker
    # Up to the cap, the shared amqtt run record by record (every submission, every round's answer bit for bit), and
    # worker by worker the same episodes and env steps.
    assert records_up_to(run_dir, LOADED_EPISODES) == records_up_to(runs[policy], LOADED_EPISODES)
    assert per_worker(run_dir) == per_worker_up_to(runs[policy], LOADED_EPISODES)
    assert audit(run_dir).transfers > 0


def test_the_shared_runs_stay_in_one_test_process(request: pytest.FixtureRequest) -> None:
    """Under ``make test`` (pytest-xdist, --dist loadgroup) the group marks hold: the e2e tests run in one process,
    so each federation is made once (pytest 9.2 made xdist 3.8 ignore the marks, and the runs were made twice)."""
    if request.config.getoption("dist", "no") == "loadgroup":
        assert request.node.nodeid.endswith("@e2e")
