"""bench.ood: the out-of-distribution sweep's settings, its stage skipping (a resumable results file) and its tables.
Nothing here trains or identifies: the units are planned, and results are put in by hand."""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from bench import ood
from bench.output import write_block
from runtime.records import RigTime, RunSummary, WorkerSummary


def args(tmp_path: Path, *extra: str) -> object:
    return ood.parse(["--out", str(tmp_path / "ood.json"), "--runs-dir", str(tmp_path / "runs"), *extra])


def test_settings_are_lab_the_sweep_off_one_combined_and_course() -> None:
    names = ood.settings()
    assert names[0] == "lab" and names[-2:] == ["combined", "course"]
    assert "Dp-x1" not in names and "loop_delay-x0" in names and "loop_delay-x1" in names
    assert {"arm_friction-x3", "Dp-x0.1", "Dp-x10", "Dr-x0.2", "Dr-x6", "arm_inertia-x4", "motor-x0.8",
            "motor-x1.2"} <= set(names)
    assert len(names) == len(set(names)) == 28


def test_parse_picks_subsets_and_refuses_unknown_names(tmp_path: Path) -> None:
    a = args(tmp_path, "--measures", "reset", "--settings", "combined,Dp-x10", "--seeds", "601-603",
             "--model", "paper=x/pretrain")
    assert a.measures == ["reset"] and a.settings == ["combined", "Dp-x10"] and a.seeds == [601, 602, 603]
    assert a.model == {"paper": Path("x/pretrain")}
    assert len(args(tmp_path, "--settings", "sweep").settings) == 25
    assert args(tmp_path, "--settings", "extremes").settings == [
        "lab", "arm_friction-x0.5", "arm_friction-x3", "Dp-x0.1", "Dp-x10", "Dr-x0.2", "Dr-x6",
        "arm_inertia-x4", "motor-x0.8", "motor-x1.2", "loop_delay-x0", "loop_delay-x1", "combined", "course"]
    assert args(tmp_path).variants == ["nominal", "identified"]
    for bad in (["--measures", "speed"], ["--settings", "Dp-x7"], ["--model", "paper"], ["--variants", "true"]):
        with pytest.raises(SystemExit):
            args(tmp_path, *bad)


def test_identifications_are_planned_for_the_identified_variant_and_skipped_once_done(tmp_path: Path) -> None:
    a = args(tmp_path, "--measures", "selftest", "--settings", "combined", "--seeds", "601")
    store = ood.Store(a.out)
    first = ood.prerequisites(a, store)
    assert [u.key for u in first] == [f"identify/combined/s601/rig{i}" for i in range(3)]
    assert [u.kwargs["seed"] for u in first] == [601000, 601001, 601002]
    for u in first:
        Path(u.kwargs["out"]).parent.mkdir(parents=True, exist_ok=True)
        Path(u.kwargs["out"]).write_text("{}")
        store.put(u, {"ok": u.key.endswith(("rig0", "rig1")), "file": u.kwargs["out"], "rig_s": 110.0,
                      "attempts": 1 if u.key.endswith(("rig0", "rig1")) else 2})
    assert ood.prerequisites(a, ood.Store(a.out)) == []  # read back from the file: resumable
    store.put(first[2], {"ok": False, "detail": "overfitted"})  # refused before a refusal was recorded again
    assert [u.key for u in ood.prerequisites(a, store)] == ["identify/combined/s601/rig2"]
    store.put(first[2], {"ok": False, "detail": "overfitted", "attempts": 2})
    units = {u.key: u for u in ood.measures(a, store)}
    assert set(units) == {"selftest/combined/nominal/s601", "selftest/combined/identified/s601"}
    models = units["selftest/combined/identified/s601"].kwargs["models"]
    assert models[:2] == [first[0].kwargs["out"], first[1].kwargs["out"]] and models[2] == "missing"
    assert units["selftest/combined/nominal/s601"].kwargs["models"] == [None] * 3


def test_identifications_are_made_again_in_another_runs_folder_or_when_their_profile_is_gone(tmp_path: Path) -> None:
    a = args(tmp_path, "--measures", "selftest", "--settings", "combined", "--seeds", "601")
    store = ood.Store(a.out)
    for u in ood.prerequisites(a, store):
        Path(u.kwargs["out"]).parent.mkdir(parents=True, exist_ok=True)
        Path(u.kwargs["out"]).write_text("{}")
        store.put(u, {"ok": True, "file": u.kwargs["out"], "rig_s": 110.0})
    gone = ood.identified_file(a.runs_dir, "combined", 601, 1)
    gone.unlink()  # a runs folder cleaned up since: rig1's profile is no longer there
    assert [u.key for u in ood.prerequisites(a, store)] == ["identify/combined/s601/rig1"]
    elsewhere = args(tmp_path, "--measures", "selftest", "--settings", "combined", "--seeds", "601",
                     "--runs-dir", str(tmp_path / "other-runs"))
    assert len(ood.prerequisites(elsewhere, store)) == 3  # not the profiles of another folder


def test_a_unit_is_measured_again_when_its_parameters_change(tmp_path: Path) -> None:
    a = args(tmp_path, "--measures", "reset", "--settings", "lab", "--seeds", "601", "--variants", "nominal",
             "--resets", "4")
    store = ood.Store(a.out)
    [unit] = ood.measures(a, store)
    assert unit.kwargs["seeds"] == [601000, 601001, 601002, 601000] and unit.kwargs["starts"] == [60100 + k for k
                                                                                               in range(4)]
    store.put(unit, {"resets": 4, "ready": 4})
    assert ood.measures(a, store) == []
    more = args(tmp_path, "--measures", "reset", "--settings", "lab", "--seeds", "601", "--variants", "nominal",
                "--resets", "5")
    assert [u.key for u in ood.measures(more, store)] == [unit.key]
    again = args(tmp_path, "--measures", "reset", "--settings", "lab", "--seeds", "601", "--variants", "nominal",
                 "--resets", "4", "--again")
    assert [u.key for u in ood.measures(again, store)] == [unit.key]  # stored with the same parameters: measured again


def test_controller_units_wait_for_a_model_and_a_refused_rig_ends_the_lab(tmp_path: Path) -> None:
    a = args(tmp_path, "--measures", "zeroshot,finetune", "--settings", "course", "--seeds", "601",
             "--actions", "paper")
    store = ood.Store(a.out)
    assert next(u.key for u in ood.prerequisites(a, store)) == "pretrain/paper"
    assert ood.measures(a, store) == []  # no controller yet: nothing to measure
    store.entries["pretrain/paper"] = {"finished": True, "model": "runs/pretrain-paper"}
    units = {u.key: u for u in ood.measures(a, store)}
    assert set(units) == {f"{m}/course/paper/{v}/s601" for m in ("zeroshot", "finetune")
                          for v in ("nominal", "identified")}
    assert units["finetune/course/paper/identified/s601"].run is ood._not_identified  # no rig identified
    nominal = units["finetune/course/paper/nominal/s601"].kwargs
    assert nominal["options"]["qube_clock"] == "delayed" and "rig_model" not in nominal["options"]
    assert nominal["options"]["rig_profile"].endswith("truth-course.json") and nominal["identify_s"] == [0.0] * 3


def test_last_rig_is_the_one_with_most_rig_minutes_identification_included() -> None:
    def rig(rig_s: float) -> RigTime:
        return RigTime(balance_steps=0, balance_s=0.0, reset_s=rig_s, idle_s=0.0, rig_s=rig_s, idle="modelled")

    workers = [WorkerSummary(id=f"w{i}", index=i, solved=True, episodes=episodes, steps=0, state="finished",
                             rig=rig(rig_s)) for i, (episodes, rig_s) in enumerate(((10, 200.0), (14, 150.0)))]
    summary = RunSummary(env="qube-local", policy="plain", tc=1.0, r_floor=0.0, max_episodes=20, workers=workers,
                         total_steps=0, rounds=14, end_reason="all solved")
    assert ood.last_rig(summary, [0.0, 120.0]) == {"finished": True, "episodes": 14, "rig_min": round(270 / 60, 3),
                                                   "stopped": 0, "end_reason": "all solved"}
    workers[1] = workers[1].model_copy(update={"solved": False, "state": "stopped"})
    last = ood.last_rig(summary.model_copy(update={"workers": workers}), [0.0, 0.0])
    assert last["episodes"] is None and last["stopped"] == 1


def entries() -> dict[str, dict]:
    e: dict[str, dict] = {}
    for setting in ("lab", "Dp-x10", "combined"):
        for variant, ready in (("nominal", 4), ("identified", 5)):
            e[f"selftest/{setting}/{variant}/s601"] = {"rigs": 3, "passed": 3, "cpu_s": 0.1}
            e[f"reset/{setting}/{variant}/s601"] = {"resets": 5, "ready": ready, "cpu_s": 1.0}
            e[f"zeroshot/{setting}/paper/{variant}/s601"] = {"rigs": 3, "balanced": 2, "cpu_s": 30.0}
            for seed, episodes in ((601, 12), (602, None)):
                e[f"finetune/{setting}/paper/{variant}/s{seed}"] = {
                    "finished": episodes is not None, "episodes": episodes, "rig_min": 4.5 if episodes else None,
                    "cpu_s": 300.0}
    e["identify/combined/s601/rig0"] = {"ok": True, "cpu_s": 40.0}
    e["pretrain/levels"] = {"finished": True, "episodes": None, "end_reason": "reached the maximum", "cpu_s": 500.0}
    return e


def test_the_tables_sum_the_seeds_and_count_unfinished_runs_as_worse() -> None:
    data = {"config": {"command": "python -m bench.sim2real ood", "clock": "delayed"}, "entries": entries()}
    docs = ood.render_docs(data, "ood.json")
    assert "| `lab` | 3/3 | 3/3 | 4/5 | 5/5 |" in docs
    assert "**Actions `paper`**" in docs and "| `Dp-x10` | 2/3 | 2/3 | 1/2 | 1/2 |" in docs
    assert "finetune 300 s (12 units)" in docs and "identify 40 s (1 units)" in docs
    assert "- The `levels` pretrain (`lab`, +-20%): not every worker met TC (reached the maximum); the controller is " \
        "the first to meet it." in docs
    readme = ood.render_readme(data, "ood.json")
    assert ("| sweep (1 settings) | identified (`lab` pretrain) | 3/3 (100%) | 5/5 (100%) | 2/3 (67%) | "
            "unfinished (1 of 2) |") in readme
    assert "zero-shot combined `paper` (identified) >= 90% **missed**" in readme
    assert "self-test on every rig met" in readme
    only_resets = {k: v for k, v in entries().items() if k.startswith(("selftest/", "reset/"))}
    partial = ood.render_readme({**data, "entries": only_resets}, "ood.json").splitlines()
    assert partial[2:4] == ["| rigs | bridge model (controller) | self-test passed | resets ready |",
                            "| --- | --- | --- | --- |"]  # as many cells as the columns measured
    assert all(line.count("|") == 5 for line in partial if line.startswith("|"))


def test_report_writes_between_the_markers_only(tmp_path: Path) -> None:
    out = tmp_path / "ood.json"
    out.write_text(json.dumps({"config": {}, "entries": entries()}))
    pages = []
    for name in ("README.md", "ood.md"):
        page = tmp_path / name
        page.write_text(f"# head\n{ood.BEGIN}\nold\n{ood.END}\ntail\n")
        pages.append(page)
    ood.write_pages(out, *pages)
    for page in pages:
        text = page.read_text()
        assert text.startswith(f"# head\n{ood.BEGIN}\n") and text.endswith(f"{ood.END}\ntail\n")
        assert "old" not in text and ("| setting |" in text or "| rigs |" in text)
    with pytest.raises(ValueError, match="no"):
        write_block([tmp_path / "ood.json"], ood.BEGIN, ood.END, "x")


def test_run_units_stores_each_result_as_it_comes(tmp_path: Path) -> None:
    store = ood.Store(tmp_path / "ood.json")
    unit = ood.Unit("finetune/lab/paper/identified/s601", ood._not_identified, {}, {"model": "m"})
    broken = ood.Unit("zeroshot/lab/paper/nominal/s601", ood.zeroshot, {}, {})  # missing arguments: it raises
    assert ood.run_units([broken, unit], store, jobs=1, executor=ThreadPoolExecutor) == 1
    assert not store.done(broken)
    saved = json.loads((tmp_path / "ood.json").read_text())["entries"][unit.key]
    assert saved["end_reason"] == "a rig was not identified" and saved["params"] == {"model": "m"}
    assert ood.Store(tmp_path / "ood.json").done(unit)


def test_the_self_test_passes_on_lab_rigs_and_counts_a_rig_not_identified() -> None:
    result = ood.selftest("lab", [601000, 601001], [None, "missing"])
    assert result["passed"] == 1 and result["failures"] == ["rig 601001: not identified"]


def test_the_around_variant_pretrains_per_lab_once_its_rigs_are_identified(tmp_path: Path) -> None:
    a = args(tmp_path, "--measures", "zeroshot,selftest", "--settings", "combined", "--seeds", "601",
             "--actions", "paper", "--variants", "around", "--model", "paper=m")
    store = ood.Store(a.out)
    assert ood.around_pretrains(a, store) == []  # nothing identified yet
    for u in ood.prerequisites(a, store):
        Path(u.kwargs["out"]).parent.mkdir(parents=True, exist_ok=True)
        Path(u.kwargs["out"]).write_text("{}")
        store.put(u, {"ok": True, "file": u.kwargs["out"], "rig_s": 110.0})
    [unit] = ood.around_pretrains(a, store)
    assert unit.key == "pretrain/paper/around/combined/s601" and len(unit.kwargs["identified"]) == 3
    assert ood.measures(a, store) == []  # no rig measure for around, and its controller is not made yet
    store.put(unit, {"finished": True, "model": "runs/around"})
    [shot] = ood.measures(a, store)
    assert shot.key == "zeroshot/combined/paper/around/s601" and shot.kwargs["model"] == "runs/around"
    # no attempt met TC: deploy.lab would stop, so none of the lab's rigs balanced zero-shot (counted, not left out)
    store.put(unit, {"finished": False, "model": None})
    [none] = ood.measures(a, store)
    assert none.key == shot.key and none.run(**none.kwargs)["balanced"] == 0
    store.put(none, none.run(**none.kwargs))
    assert ood.summary_rows(store.entries)["combined/around"]["zeroshot-paper"] == (0, 3)
    # only the around variant: no lab-randomised pretrain is made for it
    alone = args(tmp_path, "--measures", "zeroshot", "--settings", "combined", "--seeds", "601", "--actions",
                 "paper", "--variants", "around")
    assert not [u for u in ood.prerequisites(alone, ood.Store(alone.out)) if u.key.startswith("pretrain/")]


def test_an_around_pretrain_that_met_no_tc_is_tried_again_with_deploy_labs_next_seed(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from types import SimpleNamespace

    from deploy.lab import PRETRAIN_SEED_STEP

    ran: list[tuple[str, int]] = []

    def fake(folder: Path, seed: int, *rest: object) -> SimpleNamespace:
        ran.append((folder.name, seed))
        return SimpleNamespace(workers=[SimpleNamespace(solved=len(ran) == 2)], end_reason="x",
                               episodes_to_all_solved=None)

    monkeypatch.setattr(ood, "_pretrain", fake)
    result = ood.pretrain("paper", str(tmp_path / "s601"), 10, "ppo", seed=601, identified=["a"], attempts=2)
    assert ran == [("s601", 601), ("s601-2", 601 + PRETRAIN_SEED_STEP)]
    assert result["finished"] and result["model"] == str(tmp_path / "s601-2") and result["attempt"] == 2
    assert "candidates" not in result  # no worker's model kept: the run folder's answer


def test_an_around_pretrain_starts_from_the_worker_deploy_lab_would_choose(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Its workers that met TC, in that order, each played on every identified rig of the lab (the lab's seed)."""
    from types import SimpleNamespace

    import deploy.lab

    monkeypatch.setattr(ood, "_pretrain", lambda *a: SimpleNamespace(workers=[SimpleNamespace(solved=True)],
                                                                       end_reason="x", episodes_to_all_solved=40))
    first, better = tmp_path / "w2.pt", tmp_path / "w0.pt"
    monkeypatch.setattr(deploy.lab, "candidates", lambda run: [first, better])
    played: list[tuple[str, list[str], int]] = []

    def returns(model: Path, rigs: list[Path], seed: int) -> list[float]:
        played.append((model.stem, [r.name for r in rigs], seed))
        return [2450.0, 2450.0] if model == better else [2450.0, 180.0]

    monkeypatch.setattr(deploy.lab, "validation_returns", returns)
    result = ood.pretrain("paper", str(tmp_path / "s601"), 10, "ppo", seed=601, identified=["r0.json", "r1.json"])
    assert played == [("w2", ["r0.json", "r1.json"], 601), ("w0", ["r0.json", "r1.json"], 601)]
    assert result["model"] == str(better) and result["chosen"] == 1
    assert [c["returns"] for c in result["candidates"]] == [[2450.0, 180.0], [2450.0, 2450.0]]


def test_bench_sim2real_ood_is_this_command(capsys: pytest.CaptureFixture[str]) -> None:
    from bench import sim2real

    with pytest.raises(SystemExit) as stop:
        sim2real.main(["ood", "--settings", "Dp-x7"])
    assert stop.value.code == 2 and "python -m bench.sim2real ood: error: --settings" in capsys.readouterr().err
