"""Rig profiles (services/qube_sim/profile.py): loading and validating, ``--show-profile`` and its round trip, the
one-line errors with exit code 2, the per-rig spread and per-episode randomisation being deterministic, ``ideal``
being the rigs of before, and each non-ideal effect doing what it says on the simulated rig."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from rpi_bridge.frame import build_command, parse_reply
from services.qube_sim.__main__ import main as sim_main
from services.qube_sim.dynamics import QubeDynamics, QubeParams
from services.qube_sim.profile import BUILTIN, IDEAL, LAB, ProfileError, RigProfile, load_profile
from services.qube_sim.spi_peer import SimulatedQube
from worker.envs import make_env
from worker.qube_env import RESET_ATTEMPTS, QubeLocalEnv, ResetFailed


def test_show_profile_round_trips_through_a_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert sim_main(["--show-profile", "lab"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["name"] == "lab" and data["coulomb_arm"] == LAB.coulomb_arm
    data["coulomb_arm"] = 0.001
    path = tmp_path / "mine.json"
    path.write_text(json.dumps(data))
    edited = load_profile(str(path))
    assert edited.coulomb_arm == 0.001 and edited.model_copy(update={"coulomb_arm": LAB.coulomb_arm}) == LAB


@pytest.mark.parametrize("content, expected", [
    ({"Rm": 8.4, "frictoin": 0.1}, "frictoin: unknown key"),
    ({"mp": 5.0}, "mp: Input should be less than or equal to 0.5"),
    ({"coulomb_arm": 0.002, "static_arm": 0.001}, "static_arm must be 0 or at least coulomb_arm"),
    ({"ranges": {"mass": [0.01, 0.02]}}, "unknown parameter 'mass'"),
    ({"curriculum": {"coulomb_arm": 100}}, "a parameter of ranges and at least 1 episode, got 100"),
    ({"ranges": {"coulomb_arm": [0.001, 0.002]}, "curriculum": {"coulomb_arm": 0}}, "at least 1 episode, got 0"),
    ([1, 2], "expected a JSON object"),
])
def test_bad_profiles_get_one_line_and_exit_2(content: object, expected: str, tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(content))
    with pytest.raises(ProfileError, match=expected):
        load_profile(str(path))
    for flag in ("--rig-profile", "--show-profile"):
        assert sim_main([flag, str(path)]) == 2
        out, err = capsys.readouterr()
        assert err.count("\n") == 1 and expected.split(":")[0] in err and out == ""


def test_the_command_line_exits_2_with_one_line(tmp_path: Path) -> None:
    path = tmp_path / "bad.json"
    path.write_text(json.dumps({"bogus": 1}))
    proc = subprocess.run([sys.executable, "-m", "services.qube_sim", "--rig-profile", str(path)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "bogus: unknown key" in proc.stderr


def test_an_unknown_name_is_refused() -> None:
    with pytest.raises(ProfileError, match="neither a built-in"):
        load_profile("moon")
    assert set(BUILTIN) == {"ideal", "lab"}


def test_ideal_is_the_rigs_of_before() -> None:
    for seed in (0, 1000, 1002):
        assert IDEAL.rig_params(seed) == QubeParams.varied(seed, scale=0.05)
    assert IDEAL.device_options() == {"sensing_latency_s": 0.0, "encoder_noise_counts": 0.0,
                                      "action_delay_s": (0.0, 0.0), "missed_actions": 0.0}
    assert IDEAL.episode_params(1, 1) is None


def test_spread_and_randomisation_are_deterministic_and_bounded() -> None:
    assert LAB.rig_params(7) == LAB.rig_params(7) != LAB.rig_params(8)
    rand = LAB.model_copy(update={"randomize": 0.2, "ranges": {"voltage_offset_v": (-0.1, 0.1)}})
    draws = [rand.episode_params(3, k) for k in range(1, 30)]
    assert draws[0] == rand.episode_params(3, 1) and draws[0] != draws[1] and draws[0] != rand.episode_params(4, 1)
    for p in draws:
        assert p is not None
        assert 0.8 * LAB.mp <= p.mp <= 1.2 * LAB.mp and 0.8 * LAB.km <= p.km == p.kt <= 1.2 * LAB.km
        assert -0.1 <= p.voltage_offset <= 0.1
    assert min(p.voltage_offset for p in draws if p) < 0 < max(p.voltage_offset for p in draws if p)


def test_a_curriculum_eases_a_range_in_and_leaves_the_draws_of_the_rest_alone() -> None:
    lo, hi, n = 0.001, 0.005, 100
    plain = LAB.model_copy(update={"randomize": 0.2, "ranges": {"coulomb_arm": (lo, hi)}})
    eased = RigProfile.model_validate({**plain.model_dump(), "curriculum": {"coulomb_arm": n}})
    for seed in (3, 4):
        for episode in (1, 10, 50, 99, 100, 101, 400):
            a, b = plain.episode_params(seed, episode), eased.episode_params(seed, episode)
            assert a is not None and b is not None
            if episode >= n:  # the full range: the same draw as without a curriculum
                assert a == b
            else:  # the same quantile of the range's bottom part; every other parameter as without one
                assert lo <= b.Cr <= lo + (hi - lo) * episode / n and b.Cr < a.Cr
                assert (b.Cr - lo) / (episode / n) == pytest.approx(a.Cr - lo)
                assert replace(b, Cr=a.Cr) == a


def test_qube_local_randomises_each_episode_and_is_reproducible() -> None:
    def physics(seed: int) -> list[QubeParams]:
        env = make_env("qube-local", seed, rig_profile=LAB.model_copy(update={"randomize": 0.2}))
        out = []
        for _ in range(2):
            env.reset()
            out.append(env.device.params)  # type: ignore[attr-defined]
        return out

    first = physics(5)
    assert first == physics(5) and first[0] != first[1]


def test_rig_model_drawn_gives_the_bridge_each_drawn_plant_as_its_model() -> None:
    """``--rig-model drawn``: the bridge's resets are computed from the rig's own plant, and under randomisation from
    each drawn one (as every real rig's bridge from its identified profile); the draws themselves are unchanged."""
    from rpi_bridge.plant import PlantModel
    from services.qube_sim.profile import DRAWN_MODEL, params_model

    randomised = LAB.model_copy(update={"randomize": 0.2})
    env = make_env("qube-local", 5, rig_profile=randomised, rig_model=DRAWN_MODEL)
    plain = make_env("qube-local", 5, rig_profile=randomised)
    models = []
    for _ in range(2):
        env.reset()
        plain.reset()
        assert env.device.params == plain.device.params  # type: ignore[attr-defined]
        models.append(env.core.cfg.reset.model)  # type: ignore[attr-defined]
        assert models[-1] == params_model(env.device.params)  # type: ignore[attr-defined]
    assert models[0] != models[1] and plain.core.cfg.reset.model == PlantModel()  # type: ignore[attr-defined]
    fixed = make_env("qube-local", 5, rig_profile=LAB, rig_model=DRAWN_MODEL)
    assert fixed.core.cfg.reset.model == params_model(LAB.rig_params(5))  # type: ignore[attr-defined]


def test_rig_model_drawn_is_a_setting_of_simulated_rigs_only() -> None:
    from deploy.settings import InprocessSettings, LocalRunSettings
    from worker.settings import WorkerSettings

    assert WorkerSettings.given(env="qube-local", rig_model="drawn").rig_model == "drawn"
    assert InprocessSettings.given(env="qube-local", rig_model="drawn", run_dir=Path("x")).rig_model == "drawn"
    with pytest.raises(ValueError, match="--rig-model drawn is for the simulated rigs"):
        LocalRunSettings.given(env="qube", rig_model="drawn")
    with pytest.raises(ValueError, match="neither a built-in"):
        WorkerSettings.given(env="qube-local", rig_model="drawnn")


def test_ideal_qube_local_trajectories_match_the_nominal_construction() -> None:
    """The profile path builds exactly the rig the old code built: same trajectory, bit for bit."""
    from worker.qube_env import QubeLocalEnv

    for env_a, env_b in ((QubeLocalEnv(seed=1000), QubeLocalEnv(seed=1000, profile=IDEAL)),):
        a, _ = env_a.reset()
        b, _ = env_b.reset()
        assert (a == b).all()
        for i in range(100):
            sa, sb = env_a.step(i % 3), env_b.step(i % 3)
            assert (sa[0] == sb[0]).all() and sa[1:3] == sb[1:3]


def test_qube_local_on_the_delayed_clock_applies_the_profiles_loop_timing() -> None:
    """``delayed`` (the real loop's timing): every action reaches the motor U(loop_delay_ms) after its state's read,
    a share loop_miss_rate is lost to the safe action; deterministic in the seed; lockstep draws nothing; and
    qube-local refuses a clock it cannot simulate."""
    profile = LAB.model_copy(update={"loop_miss_rate": 0.05, "loop_delay_ms": (6.0, 7.0)})

    def play(**options: Any) -> tuple[list[float], Any]:
        env = make_env("qube-local", 7, rig_profile=profile, **options)
        obs, _ = env.reset(seed=7)
        trace = []
        for i in range(300):
            obs, _, terminated, truncated, _ = env.step(i % 3)
            trace.append(float(obs[0]))
            if terminated or truncated:
                break
        return trace, env.timing  # type: ignore[attr-defined]

    lockstep, none = play()
    delayed, timing = play(qube_clock="delayed")
    again, _ = play(qube_clock="delayed")
    assert none is None and timing.delay_s == (0.006, 0.007)
    assert delayed == again and delayed != lockstep
    assert 0 < timing.injected_misses < len(delayed)
    with pytest.raises(ValueError, match="simulated clock"):
        make_env("qube-local", 7, qube_clock="realtime")


# -- the non-ideal effects on the plant ----------------------------------------------------------------------------


def settle_arm(params: QubeParams, voltage: float, seconds: float = 1.0) -> float:
    d = QubeDynamics(params)
    d.set_state(0.0, math.pi)
    for _ in range(round(seconds / 0.007)):
        d.step(voltage, 0.007)
    return d.theta


def test_static_friction_holds_what_coulomb_friction_alone_lets_slide() -> None:
    coulomb = replace(QubeParams(), Cr=1.0e-3)
    sticky = replace(coulomb, Sr=3.0e-3)  # breakaway 3 mN m: 0.6 V at stall
    v = -0.4  # 2 mN m: above Coulomb, below static
    assert abs(settle_arm(sticky, v)) < 0.1 * abs(settle_arm(coulomb, v))


def test_deadzone_and_offset() -> None:
    dead = replace(QubeParams(), deadzone=0.3)
    assert abs(settle_arm(dead, 0.25)) < 1e-12  # inside the deadzone: no torque at all
    assert abs(settle_arm(dead, 0.6)) == pytest.approx(abs(settle_arm(QubeParams(), 0.3)), rel=1e-6)
    offset = replace(QubeParams(), voltage_offset=0.2)
    assert settle_arm(offset, 0.0) == pytest.approx(settle_arm(QubeParams(), 0.2), rel=1e-9)


def test_cable_pulls_the_arm_towards_its_rest() -> None:
    d = QubeDynamics(replace(QubeParams(), cable_stiffness=1e-3, cable_rest=0.3))
    d.set_state(0.0, math.pi)
    for _ in range(2000):
        d.step(0.0, 0.007, amplifier_on=False)
    assert d.theta == pytest.approx(0.3, abs=0.02)


def reading(q: SimulatedQube, command: int = 0) -> tuple[int, int, int]:
    r = parse_reply(q.transfer(build_command(command, enable=True)))
    return r.encoder0, r.encoder1, r.tach_raw


def test_sensing_latency_reports_the_state_of_that_long_ago() -> None:
    late = SimulatedQube(seed=1, period_s=0.001, sensing_latency_s=0.005)
    now = SimulatedQube(seed=1, period_s=0.001)
    for q in (late, now):
        q.reset_state(alpha=math.pi - 0.5)  # released from 0.5 rad: swings down
    history = [reading(now)[1] for _ in range(40)]
    delayed = [reading(late)[1] for _ in range(40)]
    assert delayed[10:] == history[5:35]  # 5 ms later, one transfer per ms


def test_encoder_noise_is_seeded_and_centred() -> None:
    def counts(seed: int) -> list[int]:
        q = SimulatedQube(seed=seed, period_s=0.001, encoder_noise_counts=2.0)
        return [reading(q)[0] for _ in range(400)]

    a = counts(1)
    assert a == counts(1) != counts(2)
    assert abs(sum(a) / len(a)) < 0.5 and len(set(a)) > 3


def test_action_delay_and_missed_actions() -> None:
    def arm_after(**options: object) -> float:
        q = SimulatedQube(seed=3, period_s=0.007, **options)  # type: ignore[arg-type]
        for _ in range(30):
            q.transfer(build_command(-200, enable=True))
        return q.state[0]

    prompt, delayed = arm_after(), arm_after(action_delay_s=(0.005, 0.005))
    assert 0 < delayed < prompt  # -200 counts drives theta positive, 5 ms later
    q = SimulatedQube(seed=3, period_s=0.007, missed_actions=0.3)
    for _ in range(1000):
        q.transfer(build_command(10, enable=True))
    assert 200 < q.lost_actions < 400


def test_lab_rigs_differ_from_ideal_ones() -> None:
    a, b = make_env("qube-local", 1000), make_env("qube-local", 1000, rig_profile="lab")
    assert a.device.params != b.device.params and b.device.params.Cr > 0  # type: ignore[attr-defined]
    assert RigProfile().model_dump() == IDEAL.model_copy(update={"name": "custom", "description": ""}).model_dump()


def test_a_sim_rig_over_mqtt_redraws_its_physics_at_each_reset_request() -> None:
    from services.qube_sim.__main__ import build_sim_service
    from services.qube_sim.settings import SimRigSettings

    def draws(seed: int) -> list[QubeParams]:
        service = build_sim_service(SimRigSettings(rig_profile="lab", randomize=0.2, seed=seed))
        device = service.core.device
        out = []
        for request in (1, 2):
            service.runner.on_reset(request)
            out.append(device._next_params)  # type: ignore[attr-defined]
        return out

    first = draws(3)
    assert first == draws(3) and first[0] != first[1]
    assert first == [LAB.episode_params(3, k, 0.2) for k in (1, 2)]
    plain = build_sim_service(SimRigSettings(rig_profile="lab", seed=3))
    assert plain.core.device.params == LAB.rig_params(3)  # type: ignore[attr-defined]


class _UndampableSecondDraw:
    """The lab profile, randomised, except that episode 2's first draw has a motor 50 times weaker: a plant the reset
    controller cannot swing up (nor hold: the episode before ends with the pendulum held upright)."""

    def __getattr__(self, name: str) -> Any:
        return getattr(LAB, name)

    def episode_params(self, seed: int, episode: int, randomize: float | None = None, draw: int = 0) -> Any:
        p = LAB.episode_params(seed, episode, 0.05, draw=draw)
        assert p is not None
        return replace(p, km=p.km / 50, kt=p.kt / 50) if (episode, draw) == (2, 0) else p


@pytest.mark.parametrize("drawn_model", [False, True])
def test_a_randomised_plant_that_cannot_be_swung_up_is_drawn_again(drawn_model: bool) -> None:
    env = QubeLocalEnv(seed=3, profile=_UndampableSecondDraw(), randomize=0.05, drawn_model=drawn_model)
    env.reset()
    assert (env.redrawn, env.failed_resets) == (0, 0)
    env.reset()  # five failed swing-ups of the bad draw, then a fresh draw that resets
    assert (env.redrawn, env.failed_resets) == (1, RESET_ATTEMPTS)
    assert LAB.episode_params(3, 2, 0.05, draw=1) != LAB.episode_params(3, 2, 0.05)  # deterministic, and another


def test_a_fixed_plant_that_cannot_be_swung_up_fails_after_its_attempts() -> None:
    env = QubeLocalEnv(seed=3, profile=LAB)
    env.reset()
    env.device.set_params(replace(env.device.params, Dp=env.device.params.Dp * 400))
    with pytest.raises(ResetFailed):
        env.reset()
    assert env.redrawn == 0 and env.failed_resets == RESET_ATTEMPTS


def test_a_folder_gives_each_rig_its_own_profile(tmp_path: Path) -> None:
    """Rig i of a run (seed worker_seed(base, i)) takes the folder's i-th file in name order, in every entry point
    that builds a simulated rig: the qube_sim rig over MQTT and the qube-local env."""
    from protocol.tasks import worker_seed
    from services.qube_sim import families
    from services.qube_sim.settings import SimRigSettings

    rigs = [families.combined(), families.course(), families.family("Dp", 10)]
    for i, profile in enumerate(rigs):
        (tmp_path / f"rig{i}.json").write_text(profile.to_json())
    for i, profile in enumerate(rigs):
        seed = worker_seed(7, i)
        assert load_profile(tmp_path, seed) == profile
        sim = SimRigSettings.load(["--rig-profile", str(tmp_path), "--seed", str(seed)], prog="qube_sim")
        assert sim.profile() == profile
        env = make_env("qube-local", seed, rig_profile=str(tmp_path))
        assert env.unwrapped.profile == profile  # type: ignore[attr-defined]
    assert load_profile(tmp_path) == rigs[0]  # no seed: every file checked, the first one returned
    with pytest.raises(ProfileError, match=r"rig 3 \(seed 7003\) has no file; the folder holds 3"):
        load_profile(tmp_path, worker_seed(7, 3))
    (tmp_path / "rig9.json").write_text("{")
    with pytest.raises(ProfileError, match=r"rig9\.json: not readable JSON"):
        load_profile(tmp_path, worker_seed(7, 0))  # a bad file anywhere in the folder is refused
    (tmp_path / "empty").mkdir()
    with pytest.raises(ProfileError, match=r"no \*\.json file"):
        load_profile(tmp_path / "empty")
