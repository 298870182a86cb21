"""One implementation, two transports: the in-process runner (deploy/inprocess.py, the services on the in-memory
hub) and the same services over a real MQTT broker (real sockets) give, for one seed, the same per-worker episodes
and steps and the same records (every submission and every round: weights, contributors, digests; not the times)
under every strategy. The benchmarks' numbers come from the in-process runs: this is what makes them the system's."""

from __future__ import annotations

import json
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from chief import strategies
from chief.audit import audit
from chief.service import ChiefService, Outputs
from chief.settings import ChiefSettings
from services.broker.embedded import start_broker_process, stop_process
from tests.federations import run_in_threads
from worker.service import WorkerService
from worker.settings import WorkerSettings

pytestmark = pytest.mark.slow

ENV, SEED, WORKERS, EPISODES = "CartPole-v0", 101, 2, 30  # w0 finishes at 28 under weighted


@pytest.fixture(scope="module")
def broker(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """One embedded amqtt broker for every run of this module (each run has its own run id)."""
    log = (tmp_path_factory.mktemp("broker") / "amqtt.log").open("wb")
    proc, port = start_broker_process("127.0.0.1", stdout=log, stderr=subprocess.STDOUT)
    try:
        yield f"mqtt://127.0.0.1:{port}"
    finally:
        stop_process(proc)
        log.close()


def over_mqtt(url: str, policy: str, run_dir: Path) -> None:
    """The chief and the workers, each on its own MQTT connection to the broker, in threads of this process."""
    run_id = f"eq-{policy}"
    chief = ChiefService(ChiefSettings.given(broker=url, run_id=run_id, workers=WORKERS, env=ENV, policy=policy,
                                             seed=SEED, max_episodes=EPISODES, round_timeout=600.0, run_dir=run_dir),
                         outputs=Outputs(tensorboard=False, plot=False, progress=False))
    services = [chief] + [WorkerService(WorkerSettings.given(broker=url, run_id=run_id, worker_id=f"w{i}", env=ENV))
                          for i in range(WORKERS)]
    run_in_threads([s.run for s in services], timeout=900)


def records(run_dir: Path) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The submissions' records per worker and round, and the round records in order; without their times and
    the workers' life tokens."""
    lines = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines() if line.strip()]
    for line in lines:
        line.pop("t")
        if isinstance(line.get("played"), dict):
            line["played"].pop("life")  # a random token per worker process (protocol.messages.Played)
    subs = sorted((r for r in lines if r["type"] != "round"), key=lambda r: (r["worker"], r["round"]))
    return subs, [r for r in lines if r["type"] == "round"]


def per_worker(run_dir: Path) -> list[tuple[Any, ...]]:
    summary = json.loads((run_dir / "summary.json").read_text())
    return [(w["id"], w["episodes"], w["steps"], w["final_pi"], w["state"]) for w in summary["workers"]]


@pytest.mark.parametrize("policy", strategies.names())
def test_in_process_and_over_mqtt_give_the_same_federation(broker: str, tmp_path: Path, policy: str) -> None:
    from deploy.inprocess import run_federation

    over_mqtt(broker, policy, tmp_path / "mqtt")
    summary = run_federation(ENV, policy, SEED, WORKERS, EPISODES, tmp_path / "inprocess", plot=False,
                             tensorboard_files=False)
    assert summary["mode"] == "in-process"
    assert per_worker(tmp_path / "inprocess") == per_worker(tmp_path / "mqtt")
    subs, rounds = records(tmp_path / "inprocess")
    assert (subs, rounds) == records(tmp_path / "mqtt")
    assert len(rounds) == summary["rounds"] > 0
    assert audit(tmp_path / "inprocess").transfers == audit(tmp_path / "mqtt").transfers
