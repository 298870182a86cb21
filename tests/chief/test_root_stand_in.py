"""chief/edge.py RootStandIn: the root's own edge serves the groups a RunStart gives it before the root publishes that
RunStart, over the root's own connection (in-memory hub here; over MQTT: tests/e2e/test_edge_failover.py and
tests/services/test_site_brokers.py), and a root whose edge has ended is never held up by it."""

from __future__ import annotations

import secrets
import time
from pathlib import Path

from chief.edge import RootStandIn
from chief.settings import ChiefSettings
from protocol.memory import Hub
from protocol.messages import RunStart
from protocol.tasks import task
from protocol.topics import ROOT_EDGE

RUN = "standin"


def start(round_: int) -> RunStart:
    spec = task("CartPole-v0")
    return RunStart(run_id=RUN, env_id="CartPole-v0", policy="weighted", seed=1, max_episodes=50, tc=spec.tc,
                    r_floor=spec.r_floor, workers=("w0", "w1"), session="s", edges={"w0": "e0", "w1": "e1"},
                    round=round_, stand_ins={"e0": ROOT_EDGE}, moves=1)


def test_the_roots_edge_serves_its_groups_before_the_runstart_goes_out(tmp_path: Path) -> None:
    hub = Hub()
    conn = hub.connect("root")
    conn.start()
    cfg = ChiefSettings.given(run_id=RUN, run_key=secrets.token_hex(32), edges=2, run_dir=tmp_path)
    root = RootStandIn(cfg, conn, {"w0": ({"w": (2,)}, {})})
    try:
        assert root.take(start(7), timeout=30)
        edge = root.edge
        assert edge.group_of == {"w0": "e0"} and edge.first_round == {"e0": 7} and edge.keepers["e0"].round == 7
        assert edge.watched == {"w0"}  # subscribed on the root's connection before take returned
        assert root.take(start(8), timeout=30) and edge.first_round == {"e0": 7}  # the same group: kept as it is
    finally:
        root.stop()
    assert root.exit is not None and not root._thread.is_alive()  # type: ignore[union-attr]
    assert (tmp_path / "edges" / ROOT_EDGE / "metrics.jsonl").exists()
    conn.stop()


def test_a_root_whose_edge_ended_is_not_held_up(tmp_path: Path) -> None:
    hub = Hub()
    conn = hub.connect("root")
    conn.start()
    cfg = ChiefSettings.given(run_id=RUN, run_key=secrets.token_hex(32), edges=2, run_dir=tmp_path)
    root = RootStandIn(cfg, conn, {})

    def fail() -> int:
        raise RuntimeError("boom")

    root.edge.run = fail  # type: ignore[method-assign]
    began = time.monotonic()
    assert not root.take(start(3), timeout=60)
    assert time.monotonic() - began < 30  # not the timeout: the thread was seen to have ended
    root.stop()
    conn.stop()
