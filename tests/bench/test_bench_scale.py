"""bench.scale's machinery on a small point: devices spread over processes reach a tiered federation of real
chief processes over Mosquitto, every round closes, and the audit passes on the run."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from bench.cost import actor_arrays
from bench.fleets import SpreadFleet
from bench.rigs import RigProcess
from bench.scale import check_counted, gone, point, rig_row
from runtime.records import RoundRecord


@pytest.mark.slow
def test_devices_in_several_processes_federate_through_edges(tmp_path: Path) -> None:
    row = point(6, "tiered", 2, 3, actor_arrays("CartPole-v0"), tmp_path, netns=False, per_process=4)
    assert (row["n"], row["topology"], row["edges"], row["edge_hosts"]) == (6, "tiered", 2, "127.0.0.1")
    assert row["audit"].startswith("3 rounds, 18 counted submissions")  # every device of both processes, every round
    # The root reads two partials per round, not six updates: about two updates' worth.
    assert row["root_bytes_per_round"] < 3 * row["update_bytes"]
    assert row["round_ms"] > 0 and row["root_ms_per_round"] >= 0


def test_devices_waiting_for_a_dead_federation_fail_at_once(mosquitto_broker: str) -> None:
    """A device process waits for its answer as long as the federation can give one: when a process of it has
    failed (the watch names it), the command fails at once with that reason, whatever the timeout."""
    failed: list[str] = []
    fleet = SpreadFleet(mosquitto_broker, 2, {"w": np.zeros((2, 2), np.float32)}, per_process=1,
                        watch=lambda: failed[0] if failed else None)
    failed.append("the root chief exited with code 1")
    try:
        began = time.monotonic()
        with pytest.raises(RuntimeError, match="waits in vain: the root chief exited with code 1"):
            fleet.join(timeout=600)  # no chief: nobody will ever start the run
        assert time.monotonic() - began < 60
    finally:
        fleet.stop()


class Exited:
    """A process that has ended with ``code`` (None: still running)."""

    def __init__(self, code: int | None) -> None:
        self.returncode = code

    def poll(self) -> int | None:
        return self.returncode


def test_a_federation_is_gone_when_a_process_of_it_failed() -> None:
    assert gone([("the root chief", Exited(None)), ("edge chief e0", Exited(None))]) is None  # type: ignore[list-item]
    assert gone([("the root chief", Exited(0))]) is None  # type: ignore[list-item]  # its run ended
    assert gone([("the root chief", Exited(None)), ("edge chief e1", Exited(-9))]  # type: ignore[list-item]
                ) == "edge chief e1 exited with code -9"


def test_a_point_whose_root_gave_up_on_devices_is_an_error(tmp_path: Path) -> None:
    rounds = [RoundRecord(round=1, episode=1, kind="aggregate", strategy="weighted", contributors=["w0", "w1"]),
              RoundRecord(round=2, episode=2, kind="aggregate", strategy="weighted", contributors=["w0"],
                          timed_out=["w1"])]
    (tmp_path / "metrics.jsonl").write_text("".join(r.model_dump_json() + "\n" for r in rounds))
    with pytest.raises(RuntimeError, match=r"round 2 counted 1 of 2 devices \(timed out: 1\)"):
        check_counted(tmp_path, 2)


@pytest.mark.slow
def test_a_rig_answered_from_its_own_process_reports_what_it_saw(mosquitto_broker: str) -> None:
    """bench.rigs: a real-time simulated rig answered from a process of its own; its measurement is the rig's own
    telemetry (ticks in time or missed), and its worker answered states."""
    rig = RigProcess(mosquitto_broker, "test-rig", timeout=120)
    try:
        rig.answering()
        time.sleep(1.0)
        stats = rig.finish()
    except BaseException:
        rig.kill()
        raise
    assert stats["ticks_answered"] > 0 and stats["latency_ms"]["n"] + stats["deadline_misses"] > 0
    row = rig_row([stats])
    assert row["rig_answered_from"] == "its own process" and 0 <= row["rig_miss_rate"] <= 1
    assert rig.proc.returncode == 0


def test_the_scale_table_says_what_the_rigs_saw() -> None:
    """bench.report's rig column: misses of the rig's own ticks for rows measured with bench.rigs; rows from before
    (their rig answered from the benchmark's process) keep their old column."""
    from bench.report import _rig_cell, _rig_header

    new = {"rigs": 1, "rig_state_to_action_p99_ms": 6.25, "rig_deadline_misses": 61, "rig_deadline_ticks": 524,
           "rig_miss_rate": 0.1164, "rig_ticks": 500}
    old = {"rigs": 1, "rig_state_to_action_p99_ms": 6.3, "rig_deadline_misses": 51, "rig_ticks": 324}
    assert _rig_cell(new) == "6.2 (61 of 524, 11.6 %)" and _rig_cell(old) == "6.3 (51, 324)"
    assert "own process" in _rig_header([old, new])
    assert _rig_header([old]).endswith("(deadline misses, states answered)")
    assert _rig_cell({"n": 4}) == "-"


def test_scripted_devices_wait_until_every_edge_has_passed_the_run_start_on(mosquitto_broker: str) -> None:
    """A device behind an edge that starts late reads the RunStart later than the others: the fleet starts its rounds
    only when every device has read it (an update sent before its edge serves it is lost, and the round hangs)."""
    from bench.cost import RUN, ScriptedFleet
    from protocol import topics
    from protocol.mqtt import BrokerAddress
    from protocol.transport import connector

    fleet = ScriptedFleet(mosquitto_broker, 2, {"w": np.zeros((2, 2), np.float32)}, edges=2)
    relay = connector(BrokerAddress.parse(mosquitto_broker))(f"{RUN}-relay").start(10.0)
    try:
        relay.publish(topics.relayed(RUN, "e0", topics.START), b"start", qos=1)  # e0 passed it on; e1 not yet
        with pytest.raises(TimeoutError, match=r"never started the run for w1$"):
            fleet.join(timeout=3)
        relay.publish(topics.relayed(RUN, "e1", topics.START), b"start", qos=1)
        fleet.join(timeout=30)
        assert fleet.started == {"w0", "w1"}
    finally:
        relay.stop()
        fleet.stop()
