"""bench.lab's table (bench/lab.py ``aggregate``): a lab that ended without a pretrained controller is in every
column, its rigs counted as not balanced zero-shot and its last rig as unfinished."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

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


def test_the_first_worker_to_meet_tc_is_counted_beside_the_chosen_warm_start() -> None:
    """The zero-shot of the controller the pipeline chose, and apart, of the pretrain's first worker to meet TC (the
    warm start before the choice): the target judges the chosen one; a file from before has no second count."""
    results = [{**finished([MAX_RETURN] * 3), "zero_shot_first_returns": [MAX_RETURN, 159.0, 174.0]},
               {**finished([MAX_RETURN] * 3), "zero_shot_first_returns": [MAX_RETURN] * 3}]
    table = lab.aggregate(results, workers=3)
    assert table["zero_shot"] == "6 of 6 rigs" and table["zero_shot_first"] == "4 of 6 rigs"
    assert table["targets"]["zero_shot"]
    text = lab.render({"results": results, "workers": 3, "env": "qube-local", "family": "combined",
                       "qube_actions": "paper", "seeds": "501-502", "cpus": 2, "load_at_start": 1.0,
                       "command": "python -m bench.lab"}, "lab.json")
    assert "| 6 of 6 rigs |" in text and "first worker to meet TC" in text and "balanced 4 of 6 rigs zero-shot" in text
    assert "zero_shot_first" not in lab.aggregate([finished([MAX_RETURN] * 3)], workers=3)


def test_the_repeated_zero_shot_counts_episodes_and_rigs_that_always_held() -> None:
    """Beside the target's one episode per rig, the greedy episodes a lab's warm start balanced of those it played
    and the rigs it held in every one; a lab without a controller has its rigs counted with none balanced."""
    top = MAX_RETURN
    results = [{**finished([top] * 3), "zero_shot_repeated_returns": [[top] * 4, [top, 90.0, top, top], [top] * 4]},
               {"seed": 2, "finished": False, "zero_shot_returns": None, "zero_shot_repeated_returns": None}]
    z = lab.aggregate(results, workers=3)["zero_shot_repeated"]
    assert z == {"balanced": 11, "episodes": 24, "per_rig": 4, "rigs": 6, "rigs_always": 2}
    text = lab.render({"results": results, "workers": 3, "env": "qube-local", "family": "combined",
                       "qube_actions": "paper", "seeds": "501-502", "cpus": 2, "load_at_start": 1.0,
                       "command": "python -m bench.lab"}, "lab.json")
    assert "4 greedy episodes on each rig" in text and "11 of 24 balanced" in text and "2 of 6 rigs" in text
    assert "zero_shot_repeated" not in lab.aggregate([finished([top] * 3)], workers=3)  # a file from before


def test_zero_shot_episodes_must_be_positive(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        lab.main(["--zero-shot-episodes", "0", "--report"])
    assert "--zero-shot-episodes must be at least 1" in capsys.readouterr().err


def settings(**changed: object) -> dict[str, object]:
    return {"family": "combined", "env": "qube-local", "workers": 3, "qube_actions": "paper", "warm_lr": 0.1,
            "warm_temperature": 1.0, "zero_shot_episodes": 10, **changed}


def test_merge_takes_the_labs_not_run_here_from_an_earlier_file_of_the_same_settings() -> None:
    """``--collect --merge FILE``: a seed without a folder here comes from FILE where it has it (a table whose labs ran
    in two invocations), in seed order; a seed neither has stays not run; the part merged is named with its note."""
    here = [{**finished([MAX_RETURN] * 3), "seed": 508}]
    earlier = {**settings(), "command": "python -m bench.lab --collect", "note": "Ran on another VM.",
               "results": [{**finished([MAX_RETURN] * 3), "seed": s} for s in (501, 502, 508)]}
    results, not_run, merged = lab.merge(here, [501, 502, 509], earlier, "lab.json", settings())
    assert [r["seed"] for r in results] == [501, 502, 508] and results[2] is here[0]  # the folder here wins
    assert not_run == [509] and merged is not None and merged["seeds"] == [501, 502]
    text = lab.render({**settings(), "results": results, "seeds": "501-509", "cpus": 2, "load_at_start": 1.0,
                       "command": "python -m bench.lab", "not_run": not_run, "merged": [merged]}, "lab.json")
    assert "Seeds 501, 502 are from `lab.json`: Ran on another VM." in text and "seeds 509 were not run" in text
    brief = lab.render({**settings(), "results": results, "seeds": "501-509", "cpus": 2, "load_at_start": 1.0,
                        "command": "python -m bench.lab", "not_run": not_run, "merged": [merged], "note": "Here."},
                       "lab.json", notes=False)  # the README's: the same table, the notes on the lab page
    assert "another VM" not in brief and "Here." not in brief and lab.NOTES_LINK in brief
    assert brief.split("\n")[1:] == text.split("\n")[1:] and "seeds 509 were not run" in brief
    assert lab.merge(here, [509], earlier, "lab.json", settings()) == (here, [509], None)


def test_merge_refuses_a_file_of_other_settings(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A results file made with another fine-tune (or family, action set...) cannot join the table: one line naming
    the setting, before any lab is measured."""
    with pytest.raises(ValueError, match=r"warm_temperature 0\.5, here 1\.0"):
        lab.merge([], [501], {**settings(warm_temperature=0.5), "results": []}, "old.json", settings())
    old = tmp_path / "old.json"
    old.write_text(json.dumps({**settings(warm_lr=1.0), "results": []}))
    for argv, said in ((["--collect", "--merge", str(old), "--runs-dir", str(tmp_path)], "warm_lr 1.0, here 0.1"),
                       (["--merge", str(old)], "--merge goes with --collect"),
                       (["--collect", "--merge", str(tmp_path / "none.json")], "is none")):
        with pytest.raises(SystemExit):
            lab.main(argv)
        assert said in capsys.readouterr().err
