"""``python -m deploy.lab``: a lab's rigs identified, a pretrain around them, a warm-started fine-tune, end to end with
simulated rigs in process (qube-local) and over MQTT (qube). The pretrain itself is a federation to TC (minutes), so
the end-to-end runs here start the fine-tune from a given model (``--init-model``); the pretrain stage is checked
apart, up to the federation it starts (bench/lab.py runs the whole pipeline and measures it)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from bench.lab import measure
from chief.audit import audit
from deploy.lab import (
    COLLAPSED,
    PRETRAIN_SET,
    LabSettings,
    child_env,
    finetune_command,
    how_far,
    pretrain_command,
)
from runtime.records import EpisodeRecord, RoundRecord
from services.qube_sim import families
from services.qube_sim.pretrain import for_lab
from services.qube_sim.profile import load_profile
from tests.paths import ROOT

pytestmark = pytest.mark.slow


def model_of(path: Path, env: str) -> Path:
    """An untrained PPO model of ``env`` with its provenance (the fine-tune's starting point)."""
    from worker.episode import build_learner_and_env
    from worker.model import provenance

    _, learner = build_learner_and_env(env, seed=0, device_noise=0.0, spec_only=True)
    learner.save(path, provenance(env, {}, 0, 1, 1, 1, None, "w0", "made"))
    return path


def lab(args: list[str], truth: Path, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("FEDRL_")}
    env.update(FEDRL_RIG_PROFILE=str(truth), PYTHONUNBUFFERED="1")
    return subprocess.run([sys.executable, "-m", "deploy.lab", *args], capture_output=True, text=True, env=env,
                          cwd=ROOT, timeout=timeout)


@pytest.fixture(scope="module")
def truth(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The rigs' true physics: the combined family (outside lab), which only the simulators read."""
    path = tmp_path_factory.mktemp("truth") / "combined.json"
    path.write_text(families.combined().to_json())
    return path


def test_settings_are_checked_before_anything_starts(tmp_path: Path, truth: Path) -> None:
    for args, expected in ((["--algo", "dqn", "--qube-actions", "voltage"], "needs discrete actions"),
                           (["--qube-clock", "realtime"], "runs on a simulated clock"),
                           (["--broker", "mqtt://127.0.0.1:1"], "--broker is for --env qube"),
                           (["--identify-attempts", "0"], "identify-attempts"),
                           (["--pretrain-set", "entropy=0.1"], "expected KEY=VALUE with KEY one of")):
        proc = lab([*args, "--run-dir", str(tmp_path / "x")], truth, timeout=120)
        assert proc.returncode == 2 and expected in proc.stderr and proc.stderr.count("\n") == 1, proc.stderr
    assert not (tmp_path / "x").exists()
    assert LabSettings.given().qube_actions == "paper"


@pytest.mark.parametrize("env", ["qube-local", "qube"])
def test_the_pipeline_identifies_every_rig_and_fine_tunes_them(env: str, tmp_path: Path, truth: Path) -> None:
    """Identification of every rig (in process, or asked over MQTT), then the fine-tune over MQTT with each rig's
    identified model for its resets; the report's identification seconds land in summary.json beside rig_s."""
    folder = tmp_path / "lab"
    model = model_of(tmp_path / "m.pt", env)
    args = ["--env", env, "--workers", "2", "--seed", "7", "--run-dir", str(folder), "--max-episodes", "1",
            "--init-model", str(model)]
    proc = lab(args, truth)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr
    for i in range(2):
        profile = load_profile(folder / "identified" / f"rig{i}.json")
        assert profile.identified is not None and 60 < profile.identified.rig_seconds < 240
        true = families.combined()
        # the rig's own physics is the family's spread by its seed: the fit lands near it, not on lab's values
        assert abs(profile.Dp / true.Dp - 1) < 0.6 and abs(profile.km / true.km - 1) < 0.2, profile
    assert "stage 1 of 3" in proc.stdout and "[lab pretrain] skipped" in proc.stdout
    assert proc.stdout.count("mN m the `paper` actions give at standstill") == 2  # each rig's authority
    progress = json.loads((folder / "lab.json").read_text())
    assert progress["done"] == ["identify", "finetune"]
    summary = json.loads((folder / "finetune" / "summary.json").read_text())
    assert summary["env"] == env and all(w["episodes"] == 1 for w in summary["workers"])
    for w, row in zip(summary["workers"], progress["rigs"], strict=True):
        assert w["rig"]["identify_s"] == pytest.approx(row["identify_s"], abs=0.1) and row["identify_s"] > 60
    assert audit(folder / "finetune").rounds >= 1  # the fine-tune is a federation the audit re-checks
    measured = measure(folder)  # bench.lab's reading of the same folder
    assert [r["episodes"] for r in measured["rigs"]] == [1, 1] and measured["stopped"] == 0
    if env == "qube":  # the recordings came over MQTT and are kept beside the profiles
        assert (folder / "identified" / "rig0.recording.json.gz").stat().st_size > 10_000

    if env == "qube-local":  # a finished pipeline (whatever its rigs): every stage is kept, the report made again
        again = lab(args, truth)
        assert again.returncode == 0 and again.stdout.count("done before: skipped") == 2, again.stdout[-2000:]


def test_the_pretrain_randomises_around_the_identified_rigs_and_resumes_there(tmp_path: Path, truth: Path) -> None:
    folder = tmp_path / "lab"
    args = ["--workers", "1", "--seed", "8", "--run-dir", str(folder), "--pretrain-episodes", "1",
            "--pretrain-workers", "1"]
    proc = lab(args, truth)
    assert proc.returncode == 1, proc.stdout[-3000:] + proc.stderr
    assert "no pretrain ended with a controller that meets TC (2 attempts" in proc.stderr
    assert "the same command resumes at this stage" in proc.stderr
    assert "rig0's arm breakaway takes" in proc.stderr and "(`--qube-actions levels`: " in proc.stderr  # its authority
    assert "attempt 2 of 2, seed 10008" in proc.stdout  # a pretrain without TC is tried again with its own seed
    assert json.loads((folder / "lab.json").read_text())["done"] == ["identify"]
    rig = load_profile(folder / "identified" / "rig0.json")
    expected = for_lab([rig], "paper", name="around-1-identified")
    assert "arm friction at most" in proc.stdout
    assert "actions give the median rig at standstill; --pretrain-authority 0.9)" in proc.stdout
    assert "eased in over each worker's first 150 episodes (--pretrain-ease-in)" in proc.stdout
    assert "no controller met TC (attempt 1: " in proc.stdout and "; best PI w0 " in proc.stdout  # how far it got
    assert load_profile(folder / "pretrain-profile.json") == expected
    for run_dir, seed in (("pretrain", 8), ("pretrain-2", 10008)):
        summary = json.loads((folder / run_dir / "summary.json").read_text())
        assert summary["env_options"]["rig_profile"] == str(folder / "pretrain-profile.json")  # never the truth
        assert summary["env_options"]["rig_model"] == "drawn"  # each draw's resets as its identified rig's would be
        assert summary["seed"] == seed and summary["max_episodes"] == 1
        assert summary.get("learner_set") == (list(PRETRAIN_SET) or None)  # the pretrain's own learner overrides

    again = lab([*args, "--pretrain-attempts", "3"], truth)  # resumes at the pretrain's third attempt
    assert again.returncode == 1 and "[lab identify] done before: skipped" in again.stdout
    assert "attempt 3 of 3, seed 20008" in again.stdout and again.stdout.count("$ ") == 1, again.stdout[-2000:]


def test_each_action_set_keeps_its_own_results_file_and_table(tmp_path: Path) -> None:
    """bench.lab --qube-actions levels writes lab-levels.json (never the paper's lab.json) and its table goes between
    its own markers; an --out that holds another set's table is refused before anything runs."""
    from bench import lab

    assert lab.results_file("paper") == lab.OUT
    assert lab.results_file("levels") == lab.OUT.with_name("lab-levels.json")
    assert lab.markers("paper") == (lab.BEGIN, lab.END)
    assert lab.markers("levels")[0] != lab.BEGIN and "lab-levels:begin" in lab.markers("levels")[0]
    paper = tmp_path / "lab.json"
    paper.write_text(json.dumps({"qube_actions": "paper"}))
    with pytest.raises(ValueError, match=r"lab-levels\.json"):
        lab.check_out(paper, "levels")
    lab.check_out(paper, "paper")  # the same set: replaced, as before
    with pytest.raises(SystemExit):
        lab.main(["--qube-actions", "levels", "--out", str(paper), "--runs-dir", str(tmp_path / "runs")])
    assert not (tmp_path / "runs").exists()


def test_a_run_kept_apart_leaves_the_pages_alone(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """bench.lab --out elsewhere (tuning seeds, a trial) writes its file and says how to show it, but never puts its
    table on the README or the lab page, which show the report seeds' results file; the default --out does."""
    from bench import lab

    monkeypatch.setattr(lab, "run_seed", lambda seed, family, args, runs: {"seed": seed, "not_run": True})
    written: list[Path] = []
    monkeypatch.setattr(lab, "write_pages", lambda source, pages=None: written.append(source))
    out = tmp_path / "tuning.json"
    assert lab.main(["--seeds", "521-522", "--out", str(out), "--runs-dir", str(tmp_path / "runs")]) == 0
    assert json.loads(out.read_text())["not_run"] == [521, 522] and written == []
    assert f"python -m bench.lab --report --out {out}" in capsys.readouterr().err
    monkeypatch.setattr(lab, "results_file", lambda actions: out)  # the default file: its table goes on the pages
    assert lab.main(["--seeds", "521-522", "--runs-dir", str(tmp_path / "runs")]) == 0
    assert written == [out]


def test_the_warm_start_comes_from_the_first_pretrain_that_met_tc(tmp_path: Path) -> None:
    from deploy.lab import attempt_dir, pretrain_dir, pretrain_met, pretrained
    from runtime.records import RunSummary, WorkerSummary

    def ended(attempt: int, solved: bool) -> None:
        worker = WorkerSummary(id="w0", index=0, solved=solved, episodes=5, steps=50, state="finished" if solved else
                               "active")
        summary = RunSummary(env="qube-local", policy="plain", tc=2450, r_floor=0, max_episodes=5, workers=[worker],
                             total_steps=50, rounds=5, end_reason="all workers solved" if solved else "max episodes")
        attempt_dir(tmp_path, attempt).mkdir()
        summary.write(attempt_dir(tmp_path, attempt))

    assert pretrain_met(tmp_path) is None and pretrain_dir(tmp_path) == tmp_path / "pretrain"
    ended(1, solved=False)
    ended(2, solved=True)
    assert pretrain_met(tmp_path) == 2 and pretrain_dir(tmp_path) == tmp_path / "pretrain-2"
    assert pretrained(LabSettings.given(init_model=tmp_path / "m.pt"), tmp_path) == tmp_path / "m.pt"


def test_choose_takes_the_controller_that_balances_the_most_identified_rigs() -> None:
    from deploy.lab import choose

    assert choose([[2450, 300, 2450], [2450, 2450, 150]]) == 0  # a tie on rigs balanced: the larger sum
    assert choose([[2450, 100, 2000], [2450, 2450, 150]]) == 1  # more rigs to the end beats a larger sum
    assert choose([[300, 200], [300, 200]]) == 0  # a full tie: the first to meet TC
    with pytest.raises(ValueError, match="no candidate"):
        choose([])


def test_the_rigs_start_from_the_pretrain_controller_the_identified_rigs_balance_best(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every pretrain worker that met TC is a candidate, in the order they met it; each plays a greedy episode on each
    identified rig's simulation (its identified profile, a validation seed, never the truth); the choice is kept."""
    import worker.evaluate
    from deploy.lab import VALIDATION_SEED, attempt_dir, choice_file, chosen, identified_files, pretrained
    from runtime.records import RunSummary, WorkerSummary
    from services.qube_sim.profile import LAB

    s = LabSettings.given(workers=2, seed=7)
    for path in identified_files(s, tmp_path):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(LAB.to_json())
    run = attempt_dir(tmp_path, 1)
    (run / "models").mkdir(parents=True)
    workers = [WorkerSummary(id=f"w{i}", index=i, solved=solved, episodes=episodes, steps=50, state="finished")
               for i, (solved, episodes) in enumerate(((True, 9), (True, 5), (False, 20)))]
    RunSummary(env="qube-local", policy="plain", tc=2450, r_floor=0, max_episodes=20, workers=workers,
               total_steps=50, rounds=20, end_reason="max episodes").write(run)
    for name in ("w0", "w1", "w2"):
        model_of(run / "models" / f"{name}.pt", "qube-local")
    played: list[tuple[str, int, str]] = []
    scripted = {"w1": [2450.0, 300.0], "w0": [2450.0, 2450.0]}  # w1 met TC first; w0 balances both identified rigs

    def fake(model: Path, env_id: str, episodes: int = 10, seed: int = 0, **kw: object) -> worker.evaluate.Evaluation:
        assert env_id == "qube-local" and episodes == 1 and kw["rig_profile"] == kw["rig_model"]
        rig = int(Path(str(kw["rig_profile"])).stem[-1])
        played.append((model.stem, seed, Path(str(kw["rig_profile"])).name))
        r = scripted[model.stem][rig]
        return worker.evaluate.Evaluation(model=str(model), env=env_id, episodes=1, seed=seed, device_noise=None,
                                          returns=[r], steps=[1], mean=r, std=0.0, min=r, max=r, tc=2450.0,
                                          reached_tc=r >= 2450)

    monkeypatch.setattr(worker.evaluate, "evaluate", fake)
    assert pretrained(s, tmp_path) == run / "models" / "w0.pt"
    assert played == [("w1", 7000 + VALIDATION_SEED, "rig0.json"), ("w1", 7001 + VALIDATION_SEED, "rig1.json"),
                      ("w0", 7000 + VALIDATION_SEED, "rig0.json"), ("w0", 7001 + VALIDATION_SEED, "rig1.json")]
    kept = json.loads(choice_file(tmp_path).read_text())
    assert kept["chosen"] == 1 and [c["returns"] for c in kept["candidates"]] == [scripted["w1"], scripted["w0"]]
    monkeypatch.setattr(worker.evaluate, "evaluate", None)  # chosen once: a resumed fine-tune plays nothing again
    assert pretrained(s, tmp_path) == chosen(tmp_path) == run / "models" / "w0.pt"

    monkeypatch.undo()  # the real evaluation, on a simulated identified rig, of the one candidate left
    choice_file(tmp_path).unlink()
    (run / "models" / "w0.pt").unlink()
    assert pretrained(s, tmp_path) == run / "models" / "w1.pt"
    returns = json.loads(choice_file(tmp_path).read_text())["candidates"][0]["returns"]
    assert len(returns) == 2 and all(0 <= r <= 2450 for r in returns)


def finished_pretrain(run: Path, solved: bool) -> None:
    """A fake pretrain attempt's run folder: two workers that all met TC (models/<id>.pt) or none did, each having
    played its 20 episodes (models/<id>.last.pt)."""
    from runtime.model_file import last_model, mature_model
    from runtime.records import RunSummary, WorkerSummary

    (run / "models").mkdir(parents=True)
    workers = [WorkerSummary(id=f"w{i}", index=i, solved=solved, episodes=9 + i if solved else 20, steps=50,
                             state="finished" if solved else "stopped") for i in range(2)]
    RunSummary(env="qube-local", policy="plain", tc=2450, r_floor=0, max_episodes=20, workers=workers,
               total_steps=50, rounds=20,
               end_reason="all workers solved" if solved else "reached the maximum of 20 episodes").write(run)
    for w in workers:
        (mature_model if solved else last_model)(run / "models", w.id).write_bytes(b"")


def test_a_pretrain_whose_controllers_fall_on_an_identified_rig_is_tried_again_and_pooled(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """Attempt 1 met TC but none of its controllers balanced every identified rig in simulation: attempt 2 runs, and
    the rigs start from the best controller of both; each attempt is played once (kept), and a third never runs once
    one controller holds every rig. With the attempts spent, the best of those that met TC is taken."""
    import deploy.lab as lab_module
    from deploy.lab import attempt_dir, identified_files, pretrain, validation_file, warm_start
    from services.qube_sim.profile import LAB
    from tests.services.test_pretrain import identified

    s = LabSettings.given(workers=2, seed=7, pretrain_attempts=3)
    for path in identified_files(s, tmp_path):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(identified(LAB).to_json())
    ran: list[int] = []

    def child(stage: str, command: list[str], env: dict[str, str]) -> int:
        run = Path(command[command.index("--run-dir") + 1])
        ran.append(1 if run.name == "pretrain" else int(run.name.split("-")[1]))
        finished_pretrain(run, solved=True)
        return 0

    scripted = {("pretrain", "w0"): [2450.0, 300.0], ("pretrain", "w1"): [200.0, 2450.0],
                ("pretrain-2", "w0"): [2450.0, 900.0], ("pretrain-2", "w1"): [2450.0, 2450.0]}
    played: list[tuple[str, str]] = []

    def returns(model: Path, rigs: list[Path], seed: int) -> list[float]:
        assert seed == 7 and [r.name for r in rigs] == ["rig0.json", "rig1.json"]
        played.append((model.parent.parent.name, model.stem))
        return scripted[(model.parent.parent.name, model.stem)]

    monkeypatch.setattr(lab_module, "run_child", child)
    monkeypatch.setattr(lab_module, "validation_returns", returns)
    pretrain(s, tmp_path)
    assert ran == [1, 2] and len(played) == 4  # attempt 2 held both rigs: no attempt 3
    out = capsys.readouterr().out
    assert "attempt 1: no controller that met TC balanced every identified rig; attempt 2 adds" in out
    assert warm_start(s, tmp_path) == attempt_dir(tmp_path, 2) / "models" / "w1.pt" and len(played) == 4  # kept
    assert json.loads((tmp_path / "warm-start.json").read_text())["chosen"] == 3
    pretrain(s, tmp_path)  # resumed: nothing runs or plays again
    assert ran == [1, 2] and len(played) == 4 and validation_file(tmp_path, 2).exists()

    spent = tmp_path / "spent"  # two attempts, neither holds both rigs: the best of the two
    for path in identified_files(s, spent):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(identified(LAB).to_json())
    scripted[("pretrain-2", "w1")] = [2450.0, 1000.0]
    ran.clear()
    two = LabSettings.given(workers=2, seed=7, pretrain_attempts=2)
    pretrain(two, spent)
    assert ran == [1, 2] and "no controller that met TC balanced every identified rig\n" in capsys.readouterr().out
    assert warm_start(two, spent) == attempt_dir(spent, 2) / "models" / "w1.pt"  # 1 rig each: the largest sum


def test_with_no_attempt_meeting_tc_the_rigs_start_from_the_best_last_controller(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """No pretrain attempt met TC: the workers' last controllers (models/<id>.last.pt) of every attempt play the
    identified rigs, and the rigs start from the one that balanced the most; when none balanced any, the stage
    fails with one line."""
    import deploy.lab as lab_module
    from deploy.lab import StageFailed, attempt_dir, identified_files, pretrain, warm_start
    from services.qube_sim.profile import LAB
    from tests.services.test_pretrain import identified

    def child(stage: str, command: list[str], env: dict[str, str]) -> int:
        run = Path(command[command.index("--run-dir") + 1])
        finished_pretrain(run, solved=False)
        return 0

    scripted = {("pretrain", "w0"): [300.0, 200.0], ("pretrain", "w1"): [2450.0, 200.0],
                ("pretrain-2", "w0"): [2450.0, 900.0], ("pretrain-2", "w1"): [100.0, 100.0]}
    played: list[tuple[str, str]] = []

    def returns(model: Path, rigs: list[Path], seed: int) -> list[float]:
        played.append((model.parent.parent.name, model.name))
        return scripted[(model.parent.parent.name, model.name.split(".")[0])]

    monkeypatch.setattr(lab_module, "run_child", child)
    monkeypatch.setattr(lab_module, "validation_returns", returns)
    s = LabSettings.given(workers=2, seed=7, pretrain_attempts=2)
    for folder in (tmp_path / "some", tmp_path / "none"):
        for path in identified_files(s, folder):
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(identified(LAB).to_json())
    pretrain(s, tmp_path / "some")
    out = capsys.readouterr().out
    assert "controllers last of workers that did not meet TC" in out and "balanced 1 of 2 identified rigs" in out
    assert sorted(played) == [("pretrain", "w0.last.pt"), ("pretrain", "w1.last.pt"),
                              ("pretrain-2", "w0.last.pt"), ("pretrain-2", "w1.last.pt")]
    assert warm_start(s, tmp_path / "some") == attempt_dir(tmp_path / "some", 2) / "models" / "w0.last.pt"
    assert len(played) == 4 and "did not meet TC" in capsys.readouterr().out  # played once, kept

    scripted.update({k: [100.0, 100.0] for k in scripted})
    with pytest.raises(StageFailed, match="no worker's last controller balanced an identified rig"):
        pretrain(s, tmp_path / "none")


def test_a_lab_reused_keeps_its_rigs_and_pretrains_and_resumes_at_the_pretrain(tmp_path: Path) -> None:
    """The pretrain stage runs again over the attempts kept: only what the pipeline adds to them (the choice's
    validation, another attempt) runs before the fine-tune."""
    from bench.lab import not_reusable, reuse

    source, folder = tmp_path / "before" / "combined-paper-s7", tmp_path / "after" / "combined-paper-s7"
    for part in ("identified", "pretrain", "pretrain-2", "finetune"):
        (source / part).mkdir(parents=True)
        (source / part / "x.json").write_text(part)
    (source / "pretrain-profile.json").write_text("{}")
    (source / "warm-start.json").write_text("{}")
    (source / "lab.json").write_text(json.dumps({"done": []}))
    assert "no identified rigs to reuse" in (not_reusable(source) or "")
    with pytest.raises(ValueError, match="no identified rigs to reuse"):
        reuse(source, folder)
    (source / "lab.json").write_text(json.dumps({"done": ["identify", "pretrain", "finetune"]}))
    reuse(source, folder)
    assert sorted(p.name for p in folder.iterdir()) == ["identified", "lab.json", "pretrain", "pretrain-2",
                                                        "pretrain-profile.json"]  # never the fine-tune or its choice
    assert json.loads((folder / "lab.json").read_text())["done"] == ["identify"]
    assert (folder / "pretrain-2" / "x.json").read_text() == "pretrain-2"


def test_a_failed_pretrain_names_the_rig_with_the_least_authority_left(tmp_path: Path) -> None:
    """The arm's breakaway torque against what the action set gives at standstill (breakaway_share): a rig stickier
    than the paper's actions can overcome with much to spare is named, with the stronger set's share."""
    from deploy.lab import authority_hint, identified_files
    from services.qube_sim.pretrain import breakaway_share
    from services.qube_sim.profile import LAB

    s = LabSettings.given(workers=2)
    for path, static in zip(identified_files(s, tmp_path), (LAB.static_arm, 5.5e-3), strict=True):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(LAB.model_copy(update={"static_arm": static}).to_json())
    share, torque = breakaway_share(LAB, "paper")
    assert 6e-3 < torque < 8e-3 and share == pytest.approx(LAB.static_arm / torque)
    assert breakaway_share(LAB, "levels")[0] == pytest.approx(share * 60 / 150, rel=0.05)
    hint = authority_hint(s, tmp_path)
    assert hint.startswith("; rig1's arm breakaway takes 7") and "`--qube-actions levels`: 3" in hint, hint
    assert authority_hint(LabSettings.given(workers=2, qube_actions="levels"), tmp_path) == ""


def test_a_pretrain_that_met_no_tc_says_how_far_each_worker_got_and_whose_policy_collapsed() -> None:
    """The failure line of a pretrain attempt: each worker's best PI and its policy's last entropy, naming a worker
    whose entropy fell below COLLAPSED (a deterministic policy that no longer explores, as lab 532's w0)."""
    def episode(worker: str, n: int, pi: float, entropy: float | None) -> EpisodeRecord:
        stats = None if entropy is None else {"entropy": entropy}
        return EpisodeRecord(worker=worker, round=n, episode=n, return_=pi, pi=pi, steps=20, kind="update",
                             stats=stats)

    records = [episode("w0", 1, 20.0, 1.09), episode("w1", 1, 30.0, 1.05), episode("w0", 2, 245.3, 0.0),
               episode("w1", 2, 120.0, 0.27), episode("w1", 3, 90.0, None),
               RoundRecord(round=1, episode=1, kind="aggregate", strategy="plain", contributors=["w0", "w1"])]
    text = how_far(records)
    assert text.startswith("; best PI w0 245, w1 120; policy entropy at the end w0 0.00, w1 0.27 nats")
    assert f"(w0 below {COLLAPSED:g}: a policy that no longer explores" in text
    assert "collapsed" not in how_far(records[:2]) and "below" not in how_far(records[:2])
    assert how_far([]) == ""


def test_the_pretrain_gets_its_learner_overrides_and_the_fine_tune_does_not(tmp_path: Path) -> None:
    default = pretrain_command(LabSettings.given(), tmp_path, 1)
    assert [default[i + 1] for i, word in enumerate(default) if word == "--set"] == list(PRETRAIN_SET)
    given = pretrain_command(LabSettings.given(pretrain_set=["actor_lr=1e-4", "hidden_sizes=(64, 64)"]), tmp_path, 2)
    assert given[given.index("--set"):] == ["--set", "actor_lr=1e-4", "--set", "hidden_sizes=(64, 64)"]
    assert "--set" not in finetune_command(LabSettings.given(init_model=tmp_path / "m.pt"), tmp_path)


def test_set_reaches_both_stages_and_the_variable_is_read_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``--set`` (FEDRL_LEARNER_SET) goes to the pretrain, before ``--pretrain-set``, and to the fine-tune, on their
    command lines; the stages' environment does not carry the variable, so it is not read twice or behind --set."""
    s = LabSettings.given(learner_set=["entropy_coef=0.02"], pretrain_set=["entropy_coef=0.03"],
                          init_model=tmp_path / "m.pt")
    pre, fine = pretrain_command(s, tmp_path, 1), finetune_command(s, tmp_path)
    assert pre[pre.index("--set"):] == ["--set", "entropy_coef=0.02", "--set", "entropy_coef=0.03"]
    assert fine[fine.index("--set"):fine.index("--set") + 2] == ["--set", "entropy_coef=0.02"]
    monkeypatch.setenv("FEDRL_LEARNER_SET", "entropy_coef=0.02")
    monkeypatch.setenv("FEDRL_SEED", "3")
    assert "FEDRL_LEARNER_SET" not in child_env() and child_env()["FEDRL_SEED"] == "3"
