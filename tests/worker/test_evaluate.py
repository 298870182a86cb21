"""``python -m worker.evaluate``: a saved controller run greedily on CartPole-v0, qube-local and a simulated rig over a
real broker; the video; and the one-line errors for missing, foreign or broken models and bad options."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from protocol.tasks import solved
from worker import learners
from worker.envs import env_spec, make_env
from worker.episode import run_episode
from worker.evaluate import evaluate, main
from worker.ppo import PPOLearner

pytestmark = pytest.mark.xdist_group("test_evaluate")  # its module fixture is made once, in one test process


def save_fresh(env_id: str, path: Path, seed: int = 1) -> Path:
    env = make_env(env_id, seed)
    PPOLearner(env.observation_space, env.action_space, env_spec(env_id).ppo_config(), seed=seed).save(path)
    env.close()
    return path


@pytest.fixture(scope="module")
def cartpole_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """CartPole-v0 learned alone until PI >= TC (seed 1000: about 30 episodes), saved as a worker saves it."""
    torch.set_num_threads(1)
    env = make_env("CartPole-v0", 1000)
    learner = PPOLearner(env.observation_space, env.action_space, env_spec("CartPole-v0").ppo_config(), seed=1000)
    returns: list[float] = []
    for episode in range(1, 301):
        returns.append(run_episode(env, learner, seed=1000 if episode == 1 else None)[0])
        if solved(returns, 195.0):
            break
        learner.update()
    assert solved(returns, 195.0), "the fixture's training did not solve CartPole-v0"
    path = tmp_path_factory.mktemp("models") / "w0.pt"
    learner.save(path)
    return path


def test_trained_cartpole_controller_reaches_tc(cartpole_model: Path, tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    out_json = tmp_path / "eval" / "result.json"
    assert main([str(cartpole_model), "--env", "CartPole-v0", "--episodes", "5", "--json", str(out_json)]) == 0
    out = capsys.readouterr().out
    result = json.loads(out_json.read_text())
    assert result["env"] == "CartPole-v0" and result["episodes"] == 5 and len(result["returns"]) == 5
    assert result["greedy"] and result["tc"] == 195.0 and result["reached_tc"] == (result["mean"] >= 195.0)
    assert result["reached_tc"], result["returns"]
    assert f"mean return {result['mean']:.2f} ± {result['std']:.2f}" in out and "TC 195: reached" in out
    assert out.count("episode ") >= 5


def test_greedy_evaluation_is_reproducible_and_tells_models_apart(cartpole_model: Path, tmp_path: Path) -> None:
    first = evaluate(cartpole_model, "CartPole-v0", episodes=3, seed=7)
    again = evaluate(cartpole_model, "CartPole-v0", episodes=3, seed=7)
    assert first.returns == again.returns
    fresh = evaluate(save_fresh("CartPole-v0", tmp_path / "fresh.pt"), "CartPole-v0", episodes=3, seed=7)
    assert not fresh.reached_tc and fresh.mean < first.mean


def test_sampled_evaluation_is_seeded_and_plays_the_tempered_policy(cartpole_model: Path, tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """``--sampled T``: the policy's sampled actions at temperature T, reproducible per seed; a colder policy plays
    nearer its greedy one (T -> 0 is greedy), and a learner without a temperature is a one-line error."""
    out_json = tmp_path / "sampled.json"
    assert main([str(cartpole_model), "--env", "CartPole-v0", "--episodes", "3", "--seed", "7", "--sampled", "1",
                 "--json", str(out_json)]) == 0
    assert "3 sampled (temperature 1) episodes" in capsys.readouterr().out
    result = json.loads(out_json.read_text())
    assert not result["greedy"] and result["temperature"] == 1.0
    again = evaluate(cartpole_model, "CartPole-v0", episodes=3, seed=7, temperature=1.0)
    assert again.returns == result["returns"]
    fresh = save_fresh("CartPole-v0", tmp_path / "fresh.pt")  # an untrained policy: near uniform when sampled
    greedy = evaluate(fresh, "CartPole-v0", episodes=5, seed=11)
    cold = evaluate(fresh, "CartPole-v0", episodes=5, seed=11, temperature=1e-4)
    warm = evaluate(fresh, "CartPole-v0", episodes=5, seed=11, temperature=1.0)
    assert cold.returns == greedy.returns and warm.returns != greedy.returns
    assert main([str(cartpole_model), "--env", "CartPole-v0", "--sampled", "0"]) == 2
    assert "--sampled" in capsys.readouterr().err
    kind = learners.get("dqn")  # epsilon-greedy: no policy temperature
    env = make_env("CartPole-v0", 1)
    kind.learner_class(env.observation_space, env.action_space, kind.config_class(), seed=1).save(tmp_path / "q.pt")
    assert main([str(tmp_path / "q.pt"), "--env", "CartPole-v0", "--sampled", "0.5"]) == 2
    assert "--sampled: dqn has no policy temperature to set" in capsys.readouterr().err


def test_qube_local(tmp_path: Path) -> None:
    model = save_fresh("qube-local", tmp_path / "q.pt")
    result = evaluate(model, "qube-local", episodes=2, seed=3)
    assert len(result.returns) == 2 and all(0 < r < 2450 for r in result.returns)
    assert result.steps == [int(r) + 1 for r in result.returns], "+1 per step until the fall"
    assert result.device_noise is None and not result.reached_tc
    assert evaluate(model, "qube-local", episodes=2, seed=3).returns == result.returns
    # each episode's first state, as the reset handed it over: the pendulum caught inside the balance band
    assert len(result.starts) == 2 and all(len(s) == 4 and abs(s[0]) <= math.radians(5.0) for s in result.starts)


def test_a_rig_over_mqtt(amqtt_broker: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    model = save_fresh("qube-local", tmp_path / "q.pt")  # same spaces and preset: a controller moves to a rig
    log = (tmp_path / "rig.log").open("wb")
    rig = subprocess.Popen([sys.executable, "-m", "services.qube_sim", "--broker", amqtt_broker, "--rig-id", "rigEv",
                            "--clock", "lockstep", "--seed", "4"], stdout=log, stderr=subprocess.STDOUT)
    try:
        code = main([str(model), "--env", "qube", "--rig-id", "rigEv", "--broker", amqtt_broker, "--episodes", "2",
                     "--json", str(tmp_path / "r.json")])
    finally:
        rig.terminate()
        rig.wait(10)
        log.close()
    assert code == 0, capsys.readouterr()
    result = json.loads((tmp_path / "r.json").read_text())
    assert result["rig_id"] == "rigEv" and len(result["returns"]) == 2 and all(r > 0 for r in result["returns"])
    assert "(rig rigEv)" in capsys.readouterr().out


def test_video_of_a_gymnasium_task(tmp_path: Path) -> None:
    from PIL import Image

    model = save_fresh("CartPole-v0", tmp_path / "m.pt")
    result = evaluate(model, "CartPole-v0", episodes=2, seed=1, video_dir=tmp_path / "videos", video_episodes=1)
    assert len(result.videos) == 1
    gif = Path(result.videos[0])
    assert gif.parent == tmp_path / "videos" and gif.suffix == ".gif"
    with Image.open(gif) as image:
        assert image.size == (600, 400) and 1 < image.n_frames <= result.steps[0] + 1


@pytest.mark.parametrize("case", ["missing", "foreign", "garbage", "not-a-model", "episodes", "qube-no-rig",
                                  "video-on-rig-task", "no-env"])
def test_errors_are_one_line_and_exit_2(case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    model = tmp_path / "model.pt"
    argv = [str(model), "--env", "CartPole-v0"]
    expect = ""
    if case == "missing":
        expect = "no model file"
    elif case == "foreign":
        save_fresh("Pendulum-v1", model)
        expect = "does not fit CartPole-v0: actor net.0.weight is (128, 3) in the model but (128, 4)"
    elif case == "garbage":
        model.write_bytes(b"\x00not a checkpoint")
        expect = "is not a saved model"
    elif case == "not-a-model":
        torch.save({"weights": torch.zeros(3)}, model)
        expect = "not a model saved by a fedrl worker"
    elif case == "episodes":
        argv += ["--episodes", "0"]
        expect = "bad setting --episodes '0' (command line): input should be greater than or equal to 1"
    elif case == "qube-no-rig":
        argv = [str(model), "--env", "qube"]
        expect = "give --rig-id"
    elif case == "video-on-rig-task":
        save_fresh("qube-local", model)
        argv = [str(model), "--env", "qube-local", "--video", str(tmp_path / "v")]
        expect = "gymnasium tasks only"
    elif case == "no-env":
        save_fresh("CartPole-v0", model)  # a model without provenance names no task
        argv = [str(model)]
        expect = "records no task"
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2
    assert expect in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
