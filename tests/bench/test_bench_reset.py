"""bench.reset's command line: the hold's weights to try (``--hold-weights``) reach the trials and the results file,
and a bad value is one line before any trial."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench import reset


def test_hold_weights_reach_the_results_file(tmp_path: Path) -> None:
    out = tmp_path / "reset.json"
    assert reset.main(["--only", "lab-arm_friction-x1", "--models", "true", "--resets", "1", "--rig-seed", "0",
                       "--start", "0", "--hold-weights", "1,10,0,0", "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["hold_weights"] == [1.0, 10.0, 0.0, 0.0]
    row = data["results"][0]
    assert row["ready"] == 1 and row["handover_arm_speed_median"] is not None and "calm_handovers" in row
    assert "calm handovers" in reset.markdown(data)


@pytest.mark.parametrize(("value", "said"), [("1,10,0", "four weights, not 3"), ("1,x,0,0", "could not convert"),
                                            ("0,0,0,0", "hold_weights must be four weights")])
def test_bad_hold_weights_are_one_line(value: str, said: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        reset.main(["--hold-weights", value, "--out", "/nonexistent/never-written.json"])
    assert said in capsys.readouterr().err
