"""``python -m worker.evaluate MODEL [--env ENV]``: run a saved controller greedily (or sampled) and report its returns.

    python -m worker.evaluate runs/<run>/models/w0.pt --episodes 10 --json eval.json   # on the model's own task
    python -m worker.evaluate runs/<run>/models/w0.pt --env CartPole-v0 --video videos/
    python -m worker.evaluate model.pt --env qube-local
    python -m worker.evaluate model.pt --env qube --rig-id rig0 --broker mqtt://lab:1883   # a rig over MQTT
    python -m worker.evaluate model.pt --env qube-local --rig-profile lab --rigs 10 --json robust.json

MODEL is a ``models/<worker>.pt`` that a worker saved when it solved its task (worker/ppo.py ``save``). The task is
the one the model records (worker/model.py provenance; a rig model over MQTT runs on the simulated qube-local unless
``--rig-id`` is given); ``--env`` names it explicitly, and one that disagrees with the model is an error. Each episode
takes the deterministic action (arg-max for discrete actions, the Gaussian mean for continuous ones), episode i is
seeded with ``seed + i``, and nothing is learned. ``--sampled T`` (PPO) plays the policy's sampled actions at
temperature T instead, as a fine-tune from ``--warm-temperature T`` does (its sampling seeded with ``seed + i`` too):
a warm start that balances greedily may still fall when it samples, and each fall costs a fine-tune up to the stop
rule's 10 episodes. The report: every return, mean +- standard deviation, and whether
the mean reaches the task's TC (protocol/tasks.py). ``--video DIR`` writes an animated GIF per recorded episode
(gymnasium tasks; needs the ``video`` extra: pygame renders, Pillow writes).

``--rigs N`` (qube-local) tests robustness instead (worker/robustness.py, as RealAIGym does): N rigs drawn from
``--rig-profile``, each with torque pulses of growing size on the arm at random times and extra encoder noise: the
trial (pulses within the controller's authority) and the sweep (on to twice it); for each rig it reports whether it
balanced to the end of the trial, for how many seconds, and the largest pulse it survived in the sweep.

Exit codes: 0 evaluated (whether or not TC was reached: see the report), 2 a bad option or a model that does not
fit (one line on stderr), 1 the broker or rig could not be reached.
"""

from __future__ import annotations

import importlib.util
import json
import os
import sys
import uuid
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from protocol import qube
from runtime.cli import setup_logging
from runtime.model_file import ModelFileError, provenance
from runtime.settings import returns_code
from worker import learners, model
from worker.envs import DeviceNoise, env_spec, make_env
from worker.learners import Learner
from worker.settings import EvaluateSettings


class EvalError(ValueError):
    """A problem with the inputs (missing or foreign model, unsupported option): one line, exit 2."""


@dataclass
class Evaluation:
    """What ``evaluate`` found; ``asdict`` is the ``--json`` file."""

    model: str
    env: str
    episodes: int
    seed: int
    device_noise: float | None  # None: the rig tasks, whose variation is the rig's own
    returns: list[float]
    steps: list[int]
    mean: float
    std: float
    min: float
    max: float
    tc: float
    reached_tc: bool
    greedy: bool = True
    temperature: float | None = None  # --sampled: the policy's temperature (None: greedy)
    rig_id: str | None = None
    videos: list[str] = field(default_factory=list)
    rig_profile: str | None = None
    #: Each episode's first observation (the QUBE's: alpha, alpha_dot, theta, theta_dot, as the reset handed over)
    starts: list[list[float]] = field(default_factory=list)


@dataclass
class Robustness:
    """What ``robustness`` found; ``asdict`` is the ``--json`` file."""

    model: str
    env: str
    rig_profile: str
    seed: int
    disturbances: dict[str, Any]
    stall_torque_nm: float
    summary: dict[str, Any]
    rigs: list[dict[str, Any]]


# -- the model -------------------------------------------------------------------------------------------------


def load_learner(path: Path, env_id: str, observation_space: gym.Space, action_space: gym.Space,
                 algo: str | None = None) -> Learner:
    """A learner of the kind the model records (worker/learners.py) with its saved networks, checked against the env's
    spaces (and against ``algo`` when given); EvalError with the reason otherwise."""
    try:
        state = model.load_state(path)
        made_by = learners.recorded(state)
        kind = learners.get(algo or made_by)
        learner = kind.learner_class(observation_space, action_space, kind.config_class.from_dict(state["config"]),
                                     seed=0)
        model.check_fits(state, learner, env_id, path, kind.name, model.recorded_actions(state))
    except (TypeError, ValueError) as exc:
        raise EvalError(str(exc) if isinstance(exc, ModelFileError) else f"{path}: {exc}") from None
    try:
        learner.load_state_dict(state)
    except (KeyError, RuntimeError, ValueError) as exc:
        first = (str(exc).splitlines() or [""])[0][:300]
        raise EvalError(f"{path} could not be loaded for {env_id}: {first}") from None
    return learner


def task_of(path: Path, given: str | None, rig_id: str | None = None) -> str:
    """The task to evaluate on: ``given`` (``--env``), which must be the model's recorded task, or else the model's
    (a model made on rigs over MQTT runs on the in-process simulated rig unless a ``rig_id`` is given)."""
    try:
        recorded = (provenance(path) or {}).get("task")
    except ModelFileError as err:
        raise EvalError(str(err)) from None
    if given is not None:
        if isinstance(recorded, str) and not model.same_task(recorded, given):
            raise EvalError(f"{path} was made for {recorded}, not {given} (leave --env out to use the model's task)")
        return given
    if not isinstance(recorded, str):
        raise EvalError(f"{path} records no task (saved before models recorded their provenance): give --env")
    if recorded == "qube" and rig_id is None:
        return "qube-local"
    return recorded


def actions_of_model(path: Path) -> dict[str, Any]:
    """The env option that gives a QUBE model's env the action set it was made with (empty for other tasks)."""
    try:
        actions = model.recorded_actions(model.load_state(path))
    except ModelFileError as err:
        raise EvalError(str(err)) from None
    return {"qube_actions": actions} if actions is not None else {}


# -- episodes ----------------------------------------------------------------------------------------------------


def play(env: gym.Env, learner: Learner, seed: int, frames: list[np.ndarray] | None = None,
         starts: list[list[float]] | None = None, sampled: bool = False) -> tuple[float, int]:
    """One greedy episode (``sampled``: the learner's sampled actions, its generator seeded with ``seed``); returns
    (return, steps). ``frames`` collects ``env.render()`` images, ``starts`` the first observation (rounded), when
    given."""
    act = learner.act if sampled else learner.act_greedy
    if sampled:
        learner.generator.manual_seed(seed)
    obs, _ = env.reset(seed=seed)
    if starts is not None:
        starts.append([round(float(v), 4) for v in np.ravel(obs)])
    if frames is not None:
        frames.append(np.asarray(env.render()))
    ret, steps = 0.0, 0
    while True:
        obs, reward, terminated, truncated, _ = env.step(act(obs))
        ret += float(reward)
        steps += 1
        if frames is not None:
            frames.append(np.asarray(env.render()))
        if terminated or truncated:
            return ret, steps


def write_gif(frames: list[np.ndarray], path: Path, fps: float) -> Path:
    """Frames (H x W x 3 uint8) as an animated GIF that loops."""
    from PIL import Image

    images = [Image.fromarray(np.asarray(f, dtype=np.uint8)) for f in frames if f is not None]
    if not images:
        raise EvalError("the environment rendered no frames")
    path.parent.mkdir(parents=True, exist_ok=True)
    images[0].save(path, save_all=True, append_images=images[1:], duration=max(20, round(1000 / fps)), loop=0)
    return path


def robustness(model: Path, env_id: str, rig_profile: str | None, rigs: int, seed: int = 0,
               disturbances: Any = None, algo: str | None = None) -> Robustness:
    """The robustness test of ``--rigs`` (see the module docstring and worker/robustness.py)."""
    from services.qube_sim.profile import ProfileError, load_profile
    from worker import robustness as rb

    if env_id != "qube-local":
        raise EvalError("--rigs tests the simulated rigs of --env qube-local")
    try:
        profile = load_profile(rig_profile or "ideal")
    except ProfileError as err:
        raise EvalError(str(err)) from None
    if actions_of_model(model).get("qube_actions", qube.DEFAULT_ACTIONS) != qube.DEFAULT_ACTIONS:
        raise EvalError("--rigs tests controllers of the paper's three actions; this model has another action set")
    probe = make_env(env_id, seed, probe=True)
    learner = load_learner(model, env_id, probe.observation_space, probe.action_space, algo)
    d = disturbances or rb.Disturbances()
    print(f"robustness of {model} on {rigs} {profile.name} rigs (seeds {seed}-{seed + rigs - 1}): pulses of "
          f"{d.pulse_ms:g} ms up to {max(d.ladder, default=0):.0%} of stall in the trial"
          + (f", up to {max(d.sweep):.0%} in the sweep" if d.sweep else "")
          + f", extra encoder noise {d.sensor_noise_counts:g} counts", flush=True)
    results = []
    for i in range(rigs):
        r = rb.run_rig(learner.act_greedy, profile, i, seed + i, d)
        results.append(r)
        verdict = "balanced to the end" if r.balanced_to_end else "fell"
        print(f"rig {i + 1:3d}: {verdict:19s} after {r.balance_s:6.2f} s; largest pulse survived "
              + ("in the sweep " if d.sweep else "") +
              f"{r.largest_pulse_nm * 1e3:5.1f} mN m ({r.largest_pulse_of_stall:.0%} of stall)",
              flush=True)
    return Robustness(model=str(model), env=env_id, rig_profile=profile.name, seed=seed, disturbances=asdict(d),
                      stall_torque_nm=round(rb.stall_torque(), 6), summary=rb.summary(results),
                      rigs=[asdict(r) for r in results])


def evaluate(model: Path, env_id: str, episodes: int = 10, seed: int = 0, device_noise: float = 1.0,
             video_dir: Path | None = None, video_episodes: int = 1, rig_id: str | None = None,
             conn: Any = None, rig_profile: str | None = None, algo: str | None = None,
             rig_model: str | None = None, temperature: float | None = None) -> Evaluation:
    """Run ``model`` greedily (or sampled at ``temperature``) for ``episodes`` episodes of ``env_id``; see the module
    docstring."""
    spec = env_spec(env_id)
    if video_dir is not None:
        check_video_support(env_id)
    extra: dict[str, Any] = {"rig_id": rig_id, "conn": conn} if spec.factory is not None else {}
    if rig_profile is not None:
        extra["rig_profile"] = rig_profile
    if rig_model is not None:
        extra["rig_model"] = rig_model
    if spec.factory is not None:
        extra.update(actions_of_model(model))
    environment = make_env(env_id, seed, DeviceNoise(scale=device_noise),
                           render_mode="rgb_array" if video_dir is not None else None, **extra)
    videos: list[str] = []
    returns: list[float] = []
    steps: list[int] = []
    starts: list[list[float]] = []
    try:
        learner = load_learner(model, env_id, environment.observation_space, environment.action_space, algo)
        if temperature is not None:
            try:
                learner.temper(temperature)
            except ValueError as err:
                raise EvalError(f"--sampled: {err}") from None
        where = f" (rig {rig_id})" if rig_id else ""
        noise = f", device noise {device_noise:g}" if spec.factory is None else ""
        kind = "greedy" if temperature is None else f"sampled (temperature {temperature:g})"
        print(f"evaluating {model} on {env_id}{where}: {episodes} {kind} episodes, seeds {seed}-{seed + episodes - 1}"
              f"{noise}", flush=True)
        fps = float(environment.metadata.get("render_fps") or 30)
        for i in range(episodes):
            frames: list[np.ndarray] | None = [] if video_dir is not None and i < video_episodes else None
            ret, n = play(environment, learner, seed + i, frames, starts, sampled=temperature is not None)
            returns.append(ret)
            steps.append(n)
            print(f"episode {i + 1:3d}: return {ret:9.2f} ({n} steps)", flush=True)
            if frames is not None and video_dir is not None:
                out = write_gif(frames, video_dir / f"{model.stem}-{env_id}-episode{i + 1}.gif", fps)
                videos.append(str(out))
                print(f"             video: {out}", flush=True)
    finally:
        environment.close()
    arr = np.asarray(returns, dtype=np.float64)
    mean = float(arr.mean())
    return Evaluation(model=str(model), env=env_id, episodes=episodes, seed=seed,
                      device_noise=device_noise if spec.factory is None else None,
                      returns=returns, steps=steps, mean=mean, std=float(arr.std()), min=float(arr.min()),
                      max=float(arr.max()), tc=spec.tc, reached_tc=bool(mean >= spec.tc), rig_id=rig_id,
                      videos=videos, rig_profile=rig_profile, starts=starts, greedy=temperature is None,
                      temperature=temperature)


def check_video_support(env_id: str) -> None:
    if env_spec(env_id).gym_id is None:
        raise EvalError(f"--video records the gymnasium tasks only; {env_id} has no renderer")
    needed = (("pygame", "pygame"), ("Pillow", "PIL"))
    absent = [name for name, module in needed if importlib.util.find_spec(module) is None]
    if absent:
        raise EvalError(f"--video needs {' and '.join(absent)}: pip install -e '.[video]'")
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # rgb_array rendering needs no screen


# -- command line ------------------------------------------------------------------------------------------------


def report(result: Evaluation | Robustness) -> str:
    if isinstance(result, Robustness):
        s = result.summary
        return (f"{s['balanced_to_end']} of {s['rigs']} rigs balanced to the end of the trial; median "
                f"{s['median_balance_s']:.2f} s balanced; every rig survived pulses up to "
                f"{s['smallest_largest_pulse_nm'] * 1e3:.1f} mN m (median largest "
                f"{s['median_largest_pulse_of_stall']:.0%} of stall)")
    verdict = "reached" if result.reached_tc else "not reached"
    return (f"mean return {result.mean:.2f} ± {result.std:.2f} (min {result.min:.2f}, max {result.max:.2f}) over "
            f"{result.episodes} episodes; TC {result.tc:g}: {verdict}")


@returns_code
def main(argv: list[str] | None = None) -> int:
    s = EvaluateSettings.load(argv, prog="python -m worker.evaluate", description=__doc__.split("\n")[0],
                              epilog="Exit codes: 0 evaluated, 2 bad setting or model, 1 broker/rig unreachable.")
    setup_logging(s.log_level, "evaluate")
    import torch

    torch.set_num_threads(1)
    conn = None
    try:
        env = task_of(s.model, s.env, s.rig_id)
        if env != s.env:
            print(f"task: {env} (from the model)", flush=True)
        if (s.rigs or s.rig_profile or s.rig_model) and env != "qube-local":
            raise EvalError(f"--rig-profile and --rigs are for the simulated rigs of qube-local, not {env}")
        if s.eval_video is not None:
            check_video_support(env)
        if not s.model.is_file():
            raise EvalError(f"no model file at {s.model}")
        if env == "qube":
            conn = s.connector()(f"fedrl-eval-{s.rig_id}-{uuid.uuid4().hex[:6]}").start()
        if s.rigs:
            from worker.robustness import Disturbances

            result: Evaluation | Robustness = robustness(
                s.model, env, s.rig_profile, s.rigs, s.eval_seed,
                Disturbances(pulse_ms=s.pulse_ms, sensor_noise_counts=s.sensor_noise), s.algo)
        else:
            result = evaluate(s.model, env, s.eval_episodes, s.eval_seed, s.device_noise, s.eval_video,
                              s.eval_video_episodes, s.rig_id if conn else None, conn, s.rig_profile, s.algo,
                              s.rig_model, s.eval_temperature)
    except EvalError as err:
        print(f"evaluate: {err}", file=sys.stderr)
        return 2
    except (ConnectionError, TimeoutError, RuntimeError) as err:
        print(f"evaluate: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    finally:
        if conn is not None:
            conn.stop()
    print(report(result), flush=True)
    if s.eval_json is not None:
        s.eval_json.parent.mkdir(parents=True, exist_ok=True)
        s.eval_json.write_text(json.dumps(asdict(result), indent=2) + "\n")
        print(f"results: {s.eval_json}", flush=True)
    return 0

if __name__ == "__main__":
    sys.exit(main())
