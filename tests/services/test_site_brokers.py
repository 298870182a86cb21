"""Brokers per site joined to a core (deploy/sites.py), on real Mosquitto processes on free loopback ports.

One broker node dies (``kill -9``: it saves nothing more) and comes back on its port. The bridges queue what crosses
while the other side is down; what the dead node had taken and not passed on, the processes send again (a worker
resends an unanswered update, the chief answers a closed round again), and each side applies a message once. The
federation ends as the uninterrupted one, and its audit passes.
"""

from __future__ import annotations

import json
import queue
import time
from pathlib import Path

import pytest

from chief.audit import audit
from deploy.sites import CORE, LoopbackSites
from protocol.mqtt import BrokerAddress, MqttConnection
from tests.conftest import mosquitto_available
from tests.federations import federate_through, per_worker

pytestmark = pytest.mark.skipif(not mosquitto_available(),
                                reason="mosquitto is not installed (apt-get install mosquitto)")

SEED, WORKERS, EPISODES = 2, 2, 25
UPDATE, ANSWER = "fedrl/r/worker/w0/update", "fedrl/r/chief/aggregate"


def listen(url: str, name: str, topic: str) -> tuple[MqttConnection, queue.Queue[bytes]]:
    """A persistent QoS 1 subscription (as every process of a run has), its messages on a queue."""
    got: queue.Queue[bytes] = queue.Queue()
    conn = MqttConnection(BrokerAddress.parse(url), name).start()
    conn.subscribe(topic, lambda t, payload: got.put(payload))
    return conn, got


def test_the_bridge_keeps_what_crosses_while_the_other_side_is_down(tmp_path: Path) -> None:
    """An update sent while the core is dead, and an answer sent while the site's broker is dead, arrive once it is
    back: the bridge's persistent session (``cleansession false``) has each side queue for the other. At least once:
    a broker back from a save older than its last acknowledgement sends a copy again (seen here under load), which
    the processes drop (the next test)."""
    with LoopbackSites(tmp_path, ["a"]) as sites:
        chief, at_chief = listen(sites.url(CORE), "chief", UPDATE)
        worker, at_worker = listen(sites.url("a"), "worker", ANSWER)
        try:
            time.sleep(1.5)  # the bridge's and the clients' sessions are in both persistence files
            sites.kill(CORE)
            worker.publish(UPDATE, b"sent while the core was down").wait_for_publish(5)
            sites.start(CORE)
            assert at_chief.get(timeout=15) == b"sent while the core was down"
            time.sleep(1.5)
            sites.kill("a")
            chief.publish(ANSWER, b"sent while the site was down").wait_for_publish(5)
            sites.start("a")
            assert at_worker.get(timeout=15) == b"sent while the site was down"
        finally:
            chief.stop()
            worker.stop()


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory: pytest.TempPathFactory) -> list[tuple[str, int, int]]:
    """The same federation without a fault (in one process: the same logic, the same result)."""
    from deploy.inprocess import run_federation

    run_dir = tmp_path_factory.mktemp("uninterrupted") / "run"
    run_federation("CartPole-v0", "weighted", SEED, WORKERS, EPISODES, run_dir, plot=False)
    return per_worker(run_dir)


@pytest.mark.slow
@pytest.mark.parametrize(("dies", "autosave"), [("a", 1), (CORE, 3600)], ids=["site-broker", "core-broker"])
def test_a_broker_node_dies_and_no_update_is_lost_or_applied_twice(
        tmp_path: Path, uninterrupted: list[tuple[str, int, int]], dies: str, autosave: int) -> None:
    """The chief on the core, worker w0 at site a, w1 at site b; one broker is killed after round 10 and restarted
    on its port a second later. The site broker comes back from a save at most a second old (its sessions, stale
    queues: copies of what was already delivered); the core from no save at all (no sessions: whatever it held
    is gone, and the workers at the sites saw nothing of it)."""
    with LoopbackSites(tmp_path / "brokers", ["a", "b"], autosave=autosave) as sites:
        def fault() -> None:
            sites.kill(dies)
            time.sleep(1.0)
            sites.start(dies)

        run_dir = federate_through(
            tmp_path, fault, ["--workers", str(WORKERS), "--seed", str(SEED), "--max-episodes", str(EPISODES),
                              "--broker", sites.url(CORE), "--site-brokers", f"{sites.url('a')},{sites.url('b')}",
                              "--dashboard-port", "off"],
            {}, name="sites")  # the launcher has workers at sites resend every deploy.sites.RESEND_INTERVAL
    assert per_worker(run_dir) == uninterrupted
    audit(run_dir)  # among its invariants: nothing counted twice
    logs = {p.stem: p.read_text() for p in (run_dir / "logs").glob("*.log")}
    noticed = [name for name, text in logs.items() if "lost the broker" in text]
    assert noticed == (["chief"] if dies == CORE else ["worker-w0"])  # only the dead node's own clients
    assert not any("going on alone" in text for text in logs.values())
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["end_reason"] != "aborted"
