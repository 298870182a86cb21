"""The Stable-Baselines3 reference (our stop rule, the zoo's hyperparameters) and the cost benchmark's pieces."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench import cost, sb3_ref
from protocol.tasks import TASKS


def test_stop_rule_is_ours() -> None:
    rule = sb3_ref.StopRule(tc=195.0)
    for i in range(9):
        assert not rule.episode_done(200.0, steps_so_far=200 * (i + 1))  # 9 episodes: too few, whatever the mean
    assert rule.episode_done(200.0, steps_so_far=2000)
    assert (rule.solved_episode, rule.solved_steps) == (10, 2000)
    assert rule.episode_done(0.0, steps_so_far=5000) and rule.solved_steps == 2000  # stays at the first time


def test_stop_rule_uses_the_last_ten() -> None:
    rule = sb3_ref.StopRule(tc=-100.0)
    returns = [-500.0] * 5 + [-90.0] * 9 + [-95.0]  # the last 10: nine -90 and one -95 -> mean -90.5
    met = [rule.episode_done(r, i) for i, r in enumerate(returns, 1)]
    assert met.index(True) == 14 and rule.solved_episode == 15
    assert rule.pi == pytest.approx(-90.5)


def test_zoo_entries_and_linear_schedule() -> None:
    assert set(sb3_ref.ZOO) == {t for t in TASKS if not t.startswith("qube")}
    assert sb3_ref.ZOO["CartPole-v0"].zoo_key == "CartPole-v1"
    assert sb3_ref.ZOO["Pendulum-v1"].kwargs["gamma"] == 0.9 and sb3_ref.ZOO["Pendulum-v1"].kwargs["use_sde"]
    assert sb3_ref.linear(1e-3)(0.5) == pytest.approx(5e-4)


def test_sb3_model_builds_on_our_env() -> None:
    pytest.importorskip("stable_baselines3")
    model, entry = sb3_ref.build("MountainCarContinuous-v0", seed=101)
    assert entry.n_envs == 1 and model.n_steps == 8 and model.use_sde
    assert model.get_env().num_envs == 1
    from stable_baselines3.common.vec_env import VecNormalize

    assert isinstance(model.get_env(), VecNormalize)
    with pytest.raises(ValueError):
        sb3_ref.build("qube-local", seed=101)


@pytest.mark.slow
def test_sb3_cartpole_meets_the_stop_rule() -> None:
    pytest.importorskip("stable_baselines3")
    r = sb3_ref.run("CartPole-v0", seed=101)
    assert r["finished"] and 10 <= r["episodes"] <= 400 and r["steps"] <= r["budget_steps"]


def test_bytes_per_round_are_the_real_messages() -> None:
    b = cost.bytes_per_round("CartPole-v0", (4, 16))
    assert b["actor_parameters"] == 4 * 128 + 128 + 128 * 128 + 128 + 128 * 128 + 128 + 128 * 2 + 2
    four = b["per_workers"]["4"]
    assert four["message_bytes"]["update"] > b["actor_float32_bytes"]  # the raw float32 tensors plus the fields
    assert four["message_bytes"]["update"] < b["actor_float32_bytes"] * 1.01
    assert b["per_workers"]["16"]["wire_bytes"] > 3.9 * four["wire_bytes"]
    assert cost.publish_packet_bytes("a/b", 10) == 1 + 1 + 2 + 3 + 2 + 10
    assert cost.publish_packet_bytes("a/b", 200_000) == 1 + 3 + 2 + 3 + 2 + 200_000


def test_growth_exponent() -> None:
    g = cost.growth({4: 0.01, 16: 0.04, 64: 0.16})
    assert g["exponent"] == pytest.approx(1.0) and g["ratio"] == 16 and g["per_worker_s"]["64"] == 0.0025


def test_chief_load_over_the_embedded_broker(tmp_path: Path) -> None:
    p = cost.chief_load("amqtt", workers=2, rounds=3, arrays={"w": __import__("numpy").zeros((3, 2), "float32")})
    assert p["workers"] == 2 and p["rounds"] == 3
    assert p["round_s"]["median"] > 0 and p["chief_aggregate_s"]["median"] is not None


def test_worker_scaling_in_process(tmp_path: Path) -> None:
    s = cost.worker_scaling(tmp_path, worker_counts=(1, 2), rounds=3)
    assert [p["workers"] for p in s["points"]] == [1, 2]
    for p in s["points"]:
        assert p["rounds"] == 3 and p["audit_passed"] and p["steps_per_s"]["median"] > 0
        assert 0.0 <= p["wait_share"]["median"] < 1.0
    assert s["time_basis"] == "modelled"


def test_each_learner_has_its_sb3_reference() -> None:
    assert {t: sb3_ref.reference("sac", t) for t in sb3_ref.ZOO} == {
        "CartPole-v0": "dqn", "Acrobot-v1": "dqn", "Pendulum-v1": "sac", "MountainCarContinuous-v0": "sac"}
    assert sb3_ref.reference("ppo", "Acrobot-v1") == "ppo" and sb3_ref.reference("sac", "qube-local") is None
    assert {t: sb3_ref.reference("dqn", t) for t in sb3_ref.ZOO} == {
        "CartPole-v0": "dqn", "Acrobot-v1": "dqn", "Pendulum-v1": None, "MountainCarContinuous-v0": None}
    pytest.importorskip("stable_baselines3")
    sac, entry = sb3_ref.build("MountainCarContinuous-v0", seed=101, algo="sac")
    assert entry.kwargs["ent_coef"] == 0.1 and sac.use_sde and sac.batch_size == 512
    dqn, _ = sb3_ref.build("CartPole-v0", seed=101, algo="dqn")
    assert dqn.target_update_interval == 10 and dqn.gradient_steps == 128
    r = sb3_ref.run("Pendulum-v1", seed=101, max_steps=120, algo="sac")
    assert r["strategy"] == "sb3-zoo-sac" and not r["finished"] and r["steps"] == 120
