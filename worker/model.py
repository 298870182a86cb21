"""A worker's model file: the provenance it records, and a warm start from one (``--init-model PATH``).

The file (the learner's ``state_dict`` saved with ``torch.save``) names its learner (``algo``, worker/learners.py; a
file without one is PPO's) and holds the actor, the critic, the optimizers' state, the sampling RNG's state and the
learner's configuration (``config``), and, since
models record where they come from, a ``provenance`` dict: the task, the rig profile and randomisation where the task
has them, the worker's seed, its episodes and env steps, the code version and the model it was warm-started from.

A warm start checks the model against the task first (its recorded task, the observation and action spaces through
the networks' shapes, and the architecture), so that a model made for another task or shape is one line, exit 2
(``ModelFileError``); so is a model of another learner. It then takes what the learner's ``warm_start`` takes:
networks, observation statistics and Adam moments, never the RNG (runtime/model_file.py reads the file's digest
without torch, for the chief).
"""

from __future__ import annotations

import datetime as dt
import functools
import subprocess
from importlib import metadata
from pathlib import Path
from typing import Any

from protocol import qube
from protocol.tasks import TASKS
from runtime.model_file import InitModel, ModelFileError
from worker import learners
from worker.learners import Learner

#: Configuration fields that shape the networks or their inputs: a warm start needs them equal.
ARCHITECTURE = ("hidden_sizes", "activation", "obs_scale", "normalize_obs")  # those the learner's config has
#: Tasks whose models fit each other (one QUBE-Servo 2, over MQTT or simulated in process).
FAMILIES = ({"qube", "qube-local"},)


def same_task(a: str, b: str) -> bool:
    """Whether a model made for task ``a`` is one for task ``b``."""
    return a == b or any(a in family and b in family for family in FAMILIES)


@functools.cache
def code_version() -> str:
    """``git describe --always --dirty`` of the source tree when it is a git checkout, else the package version."""
    root = Path(__file__).resolve().parent.parent
    try:
        out = subprocess.run(["git", "describe", "--always", "--dirty"], cwd=root, capture_output=True, text=True,
                             timeout=10, check=False)
        if out.returncode == 0 and out.stdout.strip():
            return out.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        pass
    try:
        return f"fedrl {metadata.version('fedrl')}"
    except metadata.PackageNotFoundError:
        return "unknown"


def provenance(task: str, env_options: dict[str, Any], seed: int, run_seed: int | None, episodes: int,
               env_steps: int, init_model: InitModel | None, worker_id: str = "", run_id: str = "") -> dict[str, Any]:
    """What a saved model records about where it comes from (plain data: ``torch.load(weights_only=True)`` reads
    it). ``env_options``: the task's options (worker/settings.py ``env_options``); a rig profile is recorded whole,
    as the JSON data of its parameters and ranges, so the record does not depend on a file that may move."""
    profile = env_options.get("rig_profile")
    rig: dict[str, Any] | None = None
    if profile is not None or task == "qube-local":
        from services.qube_sim.profile import load_profile

        loaded = load_profile(profile or "ideal", seed)
        rig = {"given": str(profile or "ideal"), "profile": loaded.model_dump(mode="json")}
    return {
        "task": task, "rig": rig, "randomize": env_options.get("randomize"),
        "qube_actions": actions_of(task, env_options), "seed": seed, "run_seed": run_seed,
        "episodes": episodes, "env_steps": env_steps, "worker_id": worker_id, "run_id": run_id,
        "code_version": code_version(),
        "init_model": None if init_model is None else {"path": init_model.given, "digest": init_model.digest},
        "saved_at": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
    }


def load_state(path: Path) -> dict[str, Any]:
    """The saved dict of a model file (torch tensors); ModelFileError when it is not a worker's model."""
    import torch

    if not path.is_file():
        raise ModelFileError(f"no model file at {path}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for a file that is not a checkpoint
        first = (str(exc).splitlines() or [""])[0][:200]
        raise ModelFileError(f"{path} is not a saved model ({type(exc).__name__}: {first})") from None
    if not isinstance(state, dict) or not {"config", "actor", "critic"} <= set(state):
        raise ModelFileError(f"{path} is not a model saved by a fedrl worker (no actor/critic/config in it)")
    return state


def actions_of(task: str, env_options: dict[str, Any]) -> str | None:
    """The action set of a QUBE task's options (protocol/qube.py; None for another task)."""
    spec = TASKS.get(task)
    return (env_options.get("qube_actions") or qube.DEFAULT_ACTIONS) if spec is not None and spec.qube else None


def recorded_actions(state: dict[str, Any]) -> str | None:
    """The QUBE action set a model was made with (the paper's for a QUBE model saved before models recorded one;
    None for another task)."""
    prov = state.get("provenance")
    actions = prov.get("qube_actions") if isinstance(prov, dict) else None
    task = recorded_task(state)
    if isinstance(actions, str):
        return actions
    spec = TASKS.get(task or "")
    return qube.DEFAULT_ACTIONS if spec is not None and spec.qube else None


def recorded_task(state: dict[str, Any]) -> str | None:
    """The task a model's provenance names (None for a model saved before models recorded one)."""
    prov = state.get("provenance")
    task = prov.get("task") if isinstance(prov, dict) else None
    return task if isinstance(task, str) else None


def check_fits(state: dict[str, Any], learner: Learner, env_id: str, path: Path, algo: str = "ppo",
               qube_actions: str | None = None) -> None:
    """A ModelFileError naming the first difference when the model was made for another task, with another QUBE
    action set than ``qube_actions`` (default the paper's) or by another learner than ``algo``, or its networks do
    not have ``learner``'s shapes (the observation and action spaces) or architecture."""
    task = recorded_task(state)
    if task is not None and not same_task(task, env_id):
        raise ModelFileError(f"{path} was made for {task}, not {env_id}")
    made_with, wanted = recorded_actions(state), actions_of(env_id, {"qube_actions": qube_actions})
    if made_with is not None and wanted is not None and made_with != wanted:
        raise ModelFileError(f"{path} was made with the QUBE action set {made_with}, not {wanted} (give "
                             f"--qube-actions {made_with})")
    made_by = learners.recorded(state)
    if made_by != algo:
        raise ModelFileError(f"{path} was made by learner {made_by}, not {algo} (give --algo {made_by})")
    try:
        config = learners.get(algo).config_class.from_dict(state["config"])
    except (TypeError, ValueError) as exc:
        raise ModelFileError(f"{path}: {exc}") from None
    for net in ("actor", "critic"):
        expected = {k: tuple(v.shape) for k, v in getattr(learner, net).state_dict().items()}
        saved = {k: tuple(getattr(v, "shape", ())) for k, v in state[net].items()}
        names = [*expected, *(k for k in saved if k not in expected)]
        for name in sorted(names, key=lambda k: "." not in k):  # layers (the input layer first), then the rest
            if expected.get(name) != saved.get(name):
                raise ModelFileError(f"{path} does not fit {env_id}: {net} {name} is {saved.get(name)} in the model "
                                     f"but {expected.get(name)} for {env_id} (was it made for another task?)")
    for key in (k for k in ARCHITECTURE if hasattr(config, k)):
        if getattr(config, key) != getattr(learner.config, key):
            raise ModelFileError(f"{path} does not fit {env_id}'s learner: its {key} is {getattr(config, key)!r}, "
                                 f"{env_id}'s is {getattr(learner.config, key)!r}")


def warm_start(learner: Learner, state: dict[str, Any], env_id: str, path: Path, algo: str = "ppo",
               qube_actions: str | None = None, temperature: float = 1.0) -> None:
    """Check the model against the task and learner (``check_fits``), then start ``learner`` from it, its policy at
    ``temperature`` (``Learner.temper``; 1: as the model was trained)."""
    check_fits(state, learner, env_id, path, algo, qube_actions)
    try:
        learner.warm_start(state)
    except (KeyError, RuntimeError, ValueError) as exc:
        first = (str(exc).splitlines() or [""])[0][:300]
        raise ModelFileError(f"{path} could not be loaded for {env_id}: {first}") from None
    if temperature != 1.0:
        learner.temper(temperature)


def open_init_model(path: Path, env_id: str, rig_id: str | None = None, algo: str = "ppo",
                    qube_actions: str | None = None) -> tuple[InitModel, dict[str, Any]]:
    """``--init-model PATH`` for task ``env_id``, learner ``algo`` and QUBE action set ``qube_actions``: the model
    (resolved, digested) and its saved dict, checked against the task's spaces and the learner; ModelFileError (one
    line, exit 2) otherwise."""
    from worker.episode import build_learner_and_env

    init = InitModel.open(path)
    state = load_state(init.file)
    _, probe = build_learner_and_env(env_id, seed=0, device_noise=0.0, rig_id=rig_id, spec_only=True, algo=algo,
                                     env_options={"qube_actions": qube_actions} if qube_actions else None)
    check_fits(state, probe, env_id, init.file, algo, qube_actions)
    return init, state
