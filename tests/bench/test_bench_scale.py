"""bench.scale's machinery on a small point: devices spread over processes reach a tiered federation of real
chief processes over Mosquitto, every round closes, and the audit passes on the run."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench.cost import actor_arrays
from bench.scale import point


@pytest.mark.slow
def test_devices_in_several_processes_federate_through_edges(tmp_path: Path) -> None:
    row = point(6, "tiered", 2, 3, actor_arrays("CartPole-v0"), tmp_path, netns=False, per_process=4)
    assert (row["n"], row["topology"], row["edges"], row["edge_hosts"]) == (6, "tiered", 2, "127.0.0.1")
    assert row["audit"].startswith("3 rounds, 18 counted submissions")  # every device of both processes, every round
    # The root reads two partials per round, not six updates: about two updates' worth.
    assert row["root_bytes_per_round"] < 3 * row["update_bytes"]
    assert row["round_ms"] > 0 and row["root_ms_per_round"] >= 0
