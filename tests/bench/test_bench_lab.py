"""bench.lab's table (bench/lab.py ``aggregate``): a lab that ended without a pretrained controller is in every
column, its rigs counted as not balanced zero-shot and its last rig as unfinished."""

from __future__ import annotations

from bench import lab
from protocol.qube import MAX_RETURN


def finished(returns: list[float]) -> dict[str, object]:
    last = {"episodes": 10, "balance_steps": 24_500, "rig_min": 4.5}
    return {"finished": True, "last": last, "stopped": 0, "zero_shot_returns": returns}


def test_a_lab_without_a_controller_counts_its_rigs_as_not_balanced() -> None:
    results = [finished([MAX_RETURN] * 3), finished([MAX_RETURN, MAX_RETURN, 800.0]),
               {"finished": False, "zero_shot_returns": None, "stages_done": ["identify"]}]
    table = lab.aggregate(results, workers=3)
    assert table["zero_shot"] == "5 of 9 rigs" and not table["targets"]["zero_shot"]
    assert table["finished"] == 2 and table["episodes"]["median"] == 10  # the unfinished lab counted as worse
    assert lab.aggregate(results[:1], workers=3)["targets"]["zero_shot"]
