"""Warm start (``--init-model``): a federation started from a trained model plays well from its first episode; the
model's digest, what the chief admits and what summary.json names; a model for another task is one line and exit 2;
the run-folder form of the path; the provenance a saved model records; evaluate without --env."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch

from chief.roster import Roster
from chief.service import ChiefService, Outputs
from chief.settings import ChiefSettings
from deploy.inprocess import run_federation
from deploy.settings import InprocessSettings
from protocol.memory import Hub, MemoryConnection
from protocol.messages import WorkerHello
from runtime.model_file import InitModel, ModelFileError, network_digest, provenance, resolve
from runtime.records import InitModelRecord, RunSummary, WorkerSummary
from worker.__main__ import main as worker_main
from worker.evaluate import main as evaluate_main

pytestmark = pytest.mark.xdist_group("test_warm_start")  # its module fixture is made once, in one test process

#: CartPole-v0's random policy scores about 22; a solved one 200.
GOOD_RETURN = 150.0


@pytest.fixture(scope="module")
def pretrained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run folder of one in-process worker that solved CartPole-v0 (seed 101: 55 episodes), with its model."""
    run_dir = tmp_path_factory.mktemp("pretrain")
    summary = run_federation(InprocessSettings.given(env="CartPole-v0", policy="weighted", seed=101, workers=1,
                             max_episodes=120, run_dir=run_dir), plot=False, tensorboard_files=False)
    assert summary.episodes_to_all_solved is not None, "the pretraining did not solve CartPole-v0"
    return run_dir


def test_warm_started_federation_plays_well_from_its_first_episode(pretrained: Path, tmp_path: Path) -> None:
    model = pretrained / "models" / "w0.pt"
    summary = run_federation(InprocessSettings.given(env="CartPole-v0", policy="weighted", seed=7, workers=2,
                             max_episodes=12, run_dir=tmp_path, init_model=pretrained), plot=False,
                             tensorboard_files=False)  # the run-folder form
    firsts = {r["worker"]: r["return"] for r in map(json.loads, (tmp_path / "metrics.jsonl").open())
              if r["type"] == "episode" and r["episode"] == 1}
    assert set(firsts) == {"w0", "w1"} and min(firsts.values()) >= GOOD_RETURN, firsts
    assert summary.episodes_to_all_solved is not None and summary.episodes_to_all_solved <= 12
    assert summary.init_model == InitModelRecord(path=str(pretrained), digest=network_digest(model))
    prov = provenance(tmp_path / "models" / "w0.pt")
    assert prov is not None and prov["task"] == "CartPole-v0" and prov["run_seed"] == 7 and prov["seed"] == 7000
    assert prov["init_model"] == {"path": str(pretrained), "digest": network_digest(model)}
    assert prov["episodes"] == summary.workers[0].episodes and prov["env_steps"] > 0 and prov["code_version"]
    # The fine-tuned networks are another model: a run warm-started from it would have another digest.
    assert network_digest(tmp_path / "models" / "w0.pt") != network_digest(model)


def test_a_worker_that_does_not_meet_tc_saves_its_last_networks_apart(tmp_path: Path) -> None:
    """Its episodes played without meeting TC, a worker saves its last networks as models/<id>.last.pt (with their
    provenance), never as the solver's <id>.pt: a run folder still names no model, the file itself warm-starts."""
    summary = run_federation(InprocessSettings.given(env="CartPole-v0", policy="weighted", seed=7, workers=2,
                             max_episodes=3, run_dir=tmp_path / "run"), plot=False, tensorboard_files=False)
    assert not any(w.solved for w in summary.workers)
    models = tmp_path / "run" / "models"
    assert sorted(p.name for p in models.iterdir()) == ["w0.last.pt", "w1.last.pt"]
    prov = provenance(models / "w1.last.pt")
    assert prov is not None and prov["episodes"] == 3 and prov["worker_id"] == "w1" and prov["seed"] == 7001
    with pytest.raises(ModelFileError, match=r"no worker of the run .* solved"):
        resolve(tmp_path / "run")
    assert InitModel.open(models / "w1.last.pt").digest == network_digest(models / "w1.last.pt")


def test_digest_covers_the_networks_only(pretrained: Path, tmp_path: Path) -> None:
    model = pretrained / "models" / "w0.pt"
    state = torch.load(model, weights_only=True)
    state["provenance"] = {"task": "CartPole-v0", "note": "copied"}
    state["actor_optimizer"]["state"] = {}
    torch.save(state, tmp_path / "resaved.pt")
    assert network_digest(tmp_path / "resaved.pt") == network_digest(model)
    state["critic"]["net.0.bias"] = state["critic"]["net.0.bias"] + 1e-3
    torch.save(state, tmp_path / "changed.pt")
    assert network_digest(tmp_path / "changed.pt") != network_digest(model)


def test_run_folder_names_its_first_worker_to_solve(pretrained: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    (run / "models").mkdir(parents=True)
    for wid in ("w0", "w1", "w2"):
        shutil.copy(pretrained / "models" / "w0.pt", run / "models" / f"{wid}.pt")
    workers = [WorkerSummary(id=wid, index=i, solved=solved, episodes=episodes, steps=0, state="finished")
               for i, (wid, solved, episodes) in enumerate((("w0", True, 40), ("w1", True, 31), ("w2", False, 12)))]
    summary = RunSummary(env="CartPole-v0", policy="weighted", tc=195.0, r_floor=0.0, max_episodes=50, workers=workers,
                         total_steps=0, rounds=0, end_reason="reached the maximum of 50 episodes")
    summary.write(run)
    assert resolve(run) == run / "models" / "w1.pt"
    assert InitModel.open(run).given == str(run)
    summary.model_copy(update={"workers": workers[2:]}).write(run)
    with pytest.raises(ModelFileError, match=r"no worker of the run .* solved"):
        resolve(run)
    with pytest.raises(ModelFileError, match="not a finished run folder"):
        resolve(tmp_path)
    (tmp_path / "junk.pt").write_bytes(b"PK not a zip")
    with pytest.raises(ModelFileError, match="is not a saved model"):
        network_digest(tmp_path / "junk.pt")


def test_roster_admits_only_the_runs_model() -> None:
    spec = {"net.0.weight": (128, 4)}
    roster = Roster("CartPole-v0")  # no model given: the first worker's decides
    assert roster.offer("w0", "CartPole-v0", spec, init_model="a" * 64, init_model_path="m.pt") is None
    assert roster.offer("w1", "CartPole-v0", spec, init_model=None)[0] == "wrong_init_model"  # type: ignore[index]
    assert roster.offer("w2", "CartPole-v0", spec, init_model="b" * 64)[0] == "wrong_init_model"  # type: ignore[index]
    assert roster.offer("w3", "CartPole-v0", spec, init_model="a" * 64) is None
    scratch = Roster("CartPole-v0")
    assert scratch.offer("w0", "CartPole-v0", spec) is None
    assert scratch.offer("w1", "CartPole-v0", spec, init_model="a" * 64)[0] == "wrong_init_model"  # type: ignore[index]


def test_chief_refuses_a_worker_started_from_another_model(pretrained: Path, tmp_path: Path) -> None:
    """The chief told --init-model counts a hello from another model (or from scratch) as a refusal."""
    digest = network_digest(pretrained / "models" / "w0.pt")
    hub = Hub()
    chief = ChiefService(ChiefSettings.given(run_id="ws", workers=2, run_dir=tmp_path, init_model=pretrained),
                         connect=lambda cid, will, rejects: MemoryConnection(hub, cid, will, rejects),
                         outputs=Outputs(state=False, tensorboard=False, plot=False, progress=False))
    spec = {"net.0.weight": (128, 4)}

    def hello(wid: str, model: str | None) -> WorkerHello:
        return WorkerHello(worker_id=wid, env_id="CartPole-v0", actor_spec=spec, init_model=model)

    assert chief._register(hello("w0", digest))
    assert not chief._register(hello("w1", "0" * 64))
    assert not chief._register(hello("w2", None))
    assert chief.rejects.as_dict().get("wrong_init_model") == 2
    assert chief.roster.workers == ["w0"]


#: A broker given (a process with none says which it joins, first): these refusals come before it connects.
NO_BROKER = ["--broker", "mqtt://127.0.0.1:1"]


def test_model_for_another_task_is_one_line_and_exit_2(pretrained: Path, capsys: pytest.CaptureFixture[str]) -> None:
    model = pretrained / "models" / "w0.pt"
    assert worker_main(["--env", "Acrobot-v1", "--init-model", str(model), "--worker-id", "w0", *NO_BROKER]) == 2
    err = capsys.readouterr().err
    assert f"{model} was made for CartPole-v0, not Acrobot-v1" in err and len(err.strip().splitlines()) == 1, err
    state = torch.load(model, weights_only=True)
    del state["provenance"]  # an older model without a recorded task: its shapes tell
    bare = pretrained / "bare.pt"
    torch.save(state, bare)
    assert worker_main(["--env", "Pendulum-v1", "--init-model", str(bare), "--worker-id", "w0", *NO_BROKER]) == 2
    err = capsys.readouterr().err
    assert "does not fit Pendulum-v1: actor net.0.weight" in err and len(err.strip().splitlines()) == 1, err
    assert worker_main(["--init-model", str(pretrained / "missing.pt"), "--worker-id", "w0", *NO_BROKER]) == 2
    assert "no model file or run folder at" in capsys.readouterr().err


def test_evaluate_takes_the_task_from_the_model(pretrained: Path, capsys: pytest.CaptureFixture[str]) -> None:
    model = pretrained / "models" / "w0.pt"
    assert evaluate_main([str(model), "--episodes", "2"]) == 0
    out = capsys.readouterr().out
    assert "task: CartPole-v0 (from the model)" in out and "TC 195: reached" in out
    assert evaluate_main([str(model), "--env", "Acrobot-v1"]) == 2
    err = capsys.readouterr().err
    assert "was made for CartPole-v0, not Acrobot-v1" in err and len(err.strip().splitlines()) == 1, err


def test_warm_rates_are_gentle_unless_three_episodes_in_a_row_fall_short_of_tc() -> None:
    """``warm_lr``: every optimizer at 0.1x its rate, and at its own for the updates after 3 episodes in a row short
    of TC (set before that episode's update), gentle again after an episode that met TC."""
    from worker.episode import build_learner_and_env
    from worker.federated import WARM_PATIENCE, Algorithm2, warm_factor

    env, learner = build_learner_and_env("CartPole-v0", seed=1, device_noise=0.0)
    algo = Algorithm2("w0", env, learner, 20.0, 1, warm_lr=0.1)  # seed 1: 22, 14, 15, 15, 13, 69, 63, 20
    rates = []
    for _ in range(8):
        algo.play()
        rates.append((learner.actor_optimizer.param_groups[0]["lr"], learner.critic_optimizer.param_groups[0]["lr"]))
    config, tc = learner.config, 20.0
    factors = [1.0 if i >= 2 and all(r < tc for r in algo.returns[i - 2:i + 1]) else 0.1 for i in range(8)]
    assert set(factors) == {0.1, 1.0}, algo.returns  # both were played
    for factor, (actor, critic) in zip(factors, rates, strict=True):
        assert (actor, critic) == pytest.approx((factor * config.actor_lr, factor * config.critic_lr)), rates
    assert WARM_PATIENCE == 3 and warm_factor([10.0, 10.0], tc, 0.1) == 0.1 and warm_factor([], tc, 0.1) == 0.1
    assert warm_factor([30.0, 10.0, 10.0, 10.0], tc, 0.1) == 1.0 and warm_factor([10.0] * 3 + [30.0], tc, 0.1) == 0.1


def test_warm_rates_are_a_setting_of_a_warm_start(pretrained: Path, tmp_path: Path) -> None:
    from worker.settings import WorkerSettings

    given = {"env": "CartPole-v0", "run_dir": tmp_path}
    with pytest.raises(ValueError, match=r"--warm-lr .* is a setting of a warm start"):
        InprocessSettings.given(**given, warm_lr=0.1)
    with pytest.raises(ValueError, match=r"--warm-lr .* is a setting of a warm start"):
        WorkerSettings.given(env="CartPole-v0", warm_lr=0.1)
    for bad in (0.0, 1.5):
        with pytest.raises(ValueError):
            InprocessSettings.given(**given, init_model=pretrained, warm_lr=bad)
    worker = InprocessSettings.given(**given, init_model=pretrained, warm_lr=0.1).child(WorkerSettings)
    assert worker.warm_lr == 0.1  # what a launcher's workers are given


def test_a_warm_temperature_sharpens_the_policy_and_keeps_its_greedy_action(pretrained: Path) -> None:
    """``--warm-temperature T``: the loaded policy's logits divided by T (CartPole, Discrete), the same arg-max; a
    Gaussian's standard deviation times T (Pendulum, Box); a learner without a policy temperature refuses it."""
    from worker import model
    from worker.episode import build_learner_and_env

    state = model.load_state(pretrained / "models" / "w0.pt")
    obs = torch.randn(64, 4)
    logits = {}
    for temperature in (1.0, 0.25):
        env, learner = build_learner_and_env("CartPole-v0", seed=3, device_noise=0.0)
        model.warm_start(learner, state, "CartPole-v0", pretrained, temperature=temperature)
        logits[temperature] = learner.actor(learner._normalized(obs))
        env.close()
    assert torch.allclose(logits[0.25], logits[1.0] / 0.25, atol=1e-5)
    assert torch.equal(logits[0.25].argmax(-1), logits[1.0].argmax(-1))

    env, gaussian = build_learner_and_env("Pendulum-v1", seed=3, device_noise=0.0)
    before = gaussian.actor.log_std.detach().clone()
    gaussian.temper(0.5)
    assert torch.allclose(gaussian.actor.log_std.exp(), before.exp() * 0.5)
    with pytest.raises(ValueError, match="temperature must be in"):
        gaussian.temper(1.5)
    env.close()
    env, sac = build_learner_and_env("Pendulum-v1", seed=3, device_noise=0.0, algo="sac")
    with pytest.raises(ValueError, match="sac has no policy temperature"):
        sac.temper(0.5)
    env.close()


def test_a_warm_temperature_is_a_setting_of_a_ppo_warm_start(pretrained: Path, tmp_path: Path) -> None:
    from deploy.lab import LabSettings, finetune_command
    from worker.settings import WorkerSettings

    given = {"env": "CartPole-v0", "run_dir": tmp_path}
    with pytest.raises(ValueError, match=r"--warm-temperature .* is a setting of a warm start"):
        InprocessSettings.given(**given, warm_temperature=0.5)
    with pytest.raises(ValueError, match=r"--warm-temperature .* needs a learner with a policy temperature"):
        InprocessSettings.given(**given, init_model=pretrained, warm_temperature=0.5, algo="dqn")
    with pytest.raises(ValueError, match=r"needs a learner with a policy temperature \(ppo\), not sac"):
        LabSettings.given(algo="sac", warm_temperature=0.5)
    for bad in (0.0, 1.5):
        with pytest.raises(ValueError):
            WorkerSettings.given(env="CartPole-v0", init_model=pretrained, warm_temperature=bad)
    worker = InprocessSettings.given(**given, init_model=pretrained, warm_temperature=0.5).child(WorkerSettings)
    assert worker.warm_temperature == 0.5  # what a launcher's workers are given
    lab = LabSettings.given(warm_temperature=0.5, init_model=pretrained, run_dir=tmp_path / "lab")
    command = finetune_command(lab, tmp_path / "lab")
    assert command[command.index("--warm-temperature") + 1] == "0.5"


def test_a_launchers_warm_temperature_reaches_its_workers(pretrained: Path, tmp_path: Path) -> None:
    """The same warm-started run at T = 1 and T = 0.25: each worker's first update reports a policy entropy, lower
    at 0.25 (the launcher's setting reached every worker's learner)."""
    entropy = {}
    for temperature in (1.0, 0.25):
        run_dir = tmp_path / f"t{temperature}"
        run_federation(InprocessSettings.given(env="CartPole-v0", policy="weighted", seed=7, workers=2,
                                               max_episodes=2, run_dir=run_dir, init_model=pretrained,
                                               warm_temperature=temperature), plot=False, tensorboard_files=False)
        entropy[temperature] = {r["worker"]: r["stats"]["entropy"] for r in map(json.loads, (run_dir / "metrics.jsonl")
                                .open()) if r["type"] == "episode" and r["episode"] == 1 and r.get("stats")}
    assert set(entropy[1.0]) == set(entropy[0.25]) == {"w0", "w1"}, entropy
    assert all(entropy[0.25][w] < entropy[1.0][w] for w in ("w0", "w1")), entropy
