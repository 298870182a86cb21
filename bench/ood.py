"""``python -m bench.sim2real ood`` (or ``python -m bench.ood``): the out-of-distribution sweep, in RealAIGym's style.

The rigs' true physics leaves ``lab`` one parameter at a time (services/qube_sim/families.py: arm dry friction
0.5-3x, Dp 0.1-10x, Dr 0.2-6x, arm inertia 1-4x, motor gain 0.8-1.2x, the loop's delay 0-1 period), and in the
combined family and Quanser's course-file damping, while the controller keeps what it was trained on: the
``lab``-randomised pretrain (+-20 %, as bench.sim2real's ``randomised``), one per action set. Each report seed is a lab
of RIGS rigs, rig i of seed S simulated with seed S*1000 + i (as deploy.run_local and deploy.lab). Per setting:

- ``selftest``: the bridge's start-up (calibration and self-test) on every rig passed;
- ``reset``: ``--resets`` swing-up resets per seed (rig k mod RIGS, varied start S*100 + k) as the worker makes them
  (up to 5 requests, the bridge changing strategy), that reached ready;
- ``zeroshot``: the pretrained controller's greedy episode on every rig before any fine-tuning balanced to the end;
- ``finetune``: the rigs of a seed fine-tuned federated in process from the pretrained controller; the last rig's
  episodes and rig minutes (the rig that needed the most rig time; identification included where identified).

Each measure comes in variants. ``nominal``: the bridge computes the swing-up, hold and self-test from its
nominal model (no identification). ``identified``: every rig is identified first (rpi_bridge/identify.py's protocol
on the simulated rig, services/qube_sim/identify.py's fit over ``lab``: the pipeline of deploy.lab), and the bridge's
model is the rig's identified profile; the controller is still the nominal pretrain. ``around`` (opt-in): as
``identified``, with the controller pretrained around each lab's identified rigs (deploy.lab's pipeline, a pretrain
per setting, seed and action set, and deploy.lab's choice among its workers that met TC); the self-test and resets do
not depend on the controller and are ``identified``'s. A rig the identification refuses counts as failed in every
identified measure, as deploy.lab stops there.

The zero-shot and fine-tune episodes run on the ``delayed`` clock (the loop's delay and lost actions of the rig's
profile: what the loop-delay sweep varies) unless ``--clock lockstep``; the self-test and resets run inside the bridge,
where the loop's delay does not reach. Every measure is a stage that runs alone (``--measures``), on ``--settings``
and ``--seeds``, ``--jobs`` at a time; each finished unit (a setting, seed, action set and variant) goes into
``--out`` at once, and an invocation skips the units already there with the same parameters, so an interrupted sweep
resumes. ``--report`` writes the tables into README.md (a summary) and docs/how-to/ood.md.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import time
from collections.abc import Callable, Iterable
from concurrent.futures import Executor, Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bench.lab import family_profile, seeds_of, truth_file
from bench.output import command, write_block
from bench.runs import process_pool
from bench.stats import spread_censored
from runtime.records import SUMMARY, RunSummary

OUT = Path("bench/results/ood.json")
RUNS = Path("runs/bench-ood")
MEASURES = ("selftest", "reset", "zeroshot", "finetune")
VARIANTS = ("nominal", "identified", "around")
#: The bridge-side measures do not depend on the controller: ``around`` is ``identified`` for them.
RIG_VARIANTS = ("nominal", "identified")
SHORT = {"nominal": "nominal (`lab` pretrain)", "identified": "identified (`lab` pretrain)",
         "around": "identified (pretrain around it)"}
ACTIONS = ("paper", "levels")
RIGS = 3
SEEDS = "601-610"  # never used for tuning (sim2real 101-110, bench.lab and bench.identify 501-510)
RESETS = 5  # per seed: 50 over the 10 report seeds
PRETRAIN_SEED = 1
RANDOMIZE = 0.2
PRETRAIN_M = 600
FINETUNE_M = 150
TASK = "qube-local"
POLICY = "plain"
#: The issue's targets that this sweep measures.
TARGETS = {"reset_sweep": 0.99, "reset_course": 0.95, "zero_shot_combined": 0.9}


def settings() -> list[str]:
    """Every setting: ``lab``, each sweep factor off 1 (``<parameter>-x<factor>``; every loop delay, as ``lab``'s
    is a spread of 0-7 ms, not one value), ``combined`` and ``course``."""
    from services.qube_sim.families import SWEEPS

    sweep = [f"{p}-x{k:g}" for p, factors in SWEEPS.items() for k in factors if k != 1.0 or p == "loop_delay"]
    return ["lab", *sweep, "combined", "course"]


def extremes() -> list[str]:
    """``lab``, each parameter's lowest and highest factor, ``combined`` and ``course``: the settings that decide
    whether the bridge and the controller hold (a subset for the costly stages)."""
    from services.qube_sim.families import SWEEPS

    ends = [f"{p}-x{k:g}" for p, factors in SWEEPS.items() for k in (min(factors), max(factors))]
    return ["lab", *[e for e in ends if e in settings()], "combined", "course"]


def group_of(setting: str) -> str:
    return setting if setting in ("lab", "combined", "course") else "sweep"


def rig_seed(seed: int, i: int) -> int:
    from protocol.tasks import worker_seed

    return worker_seed(seed, i)


# -- the results file ---------------------------------------------------------------------------------------------


@dataclass
class Unit:
    """One unit of work: its key in the results, the function that measures it and its arguments; ``params`` are
    what makes a stored result the same measurement (a result with other params is measured again)."""

    key: str
    run: Callable[..., dict[str, Any]]
    kwargs: dict[str, Any]
    params: dict[str, Any] = field(default_factory=dict)


class Store:
    """``--out``: ``{"command", "config", "entries": {key: result}}``, rewritten (atomically) after every unit."""

    def __init__(self, path: Path) -> None:
        self.path = path
        data = json.loads(path.read_text()) if path.exists() else {}
        self.entries: dict[str, dict[str, Any]] = data.get("entries", {})
        self.config: dict[str, Any] = data.get("config", {})

    def done(self, unit: Unit) -> bool:
        """Measured with the same params, and the file it wrote (an identified profile) still there."""
        entry = self.entries.get(unit.key)
        return (entry is not None and entry.get("params") == unit.params
                and ("file" not in entry or Path(entry["file"]).exists()))

    def put(self, unit: Unit, result: dict[str, Any]) -> None:
        self.entries[unit.key] = {**result, "params": unit.params}
        self.save()

    def save(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps({"config": self.config, "entries": dict(sorted(self.entries.items()))}, indent=1)
                       + "\n")
        tmp.replace(self.path)


# -- the measures (each runs in a worker process) -----------------------------------------------------------------


def _control(model_file: str | None) -> Any:
    """The bridge's configuration: nominal, or computed from an identified profile."""
    from rpi_bridge.control import ControlConfig, with_model
    from services.qube_sim.profile import load_profile
    from services.qube_sim.trials import PERIOD_S

    config = ControlConfig(period_s=PERIOD_S)
    return config if model_file is None else with_model(config, load_profile(model_file).plant_model())


def identify(setting: str, seed: int, out: str) -> dict[str, Any]:
    """Identify rig ``seed`` of ``setting`` as deploy.lab does (record through the bridge's core, fit over ``lab``,
    a refused fit recorded again); the profile is written to ``out`` only if a fit is trusted."""
    from rpi_bridge.identify import IdentifyFailed, Recording
    from services.qube_sim.identify import IdentifyRefused, identify_and_write, record_simulated
    from services.qube_sim.profile import LAB

    t0 = time.process_time()
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    truth, control, tried = family_profile(setting), _control(None), []

    def record(attempt: int) -> Recording:
        tried.append(attempt)
        return record_simulated(truth, seed, control, attempt=attempt)

    try:
        _, profile, _ = identify_and_write(record, LAB, Path(out), f"bench.ood rig {seed} of {setting}")
    except (IdentifyRefused, IdentifyFailed) as err:
        spent = {"rig_s": round(err.rig_seconds, 1)} if isinstance(err, IdentifyRefused) else {}
        return {"ok": False, "detail": str(err), **spent, "attempts": len(tried),
                "cpu_s": round(time.process_time() - t0, 1)}
    assert profile.identified is not None
    return {"ok": True, "rig_s": round(profile.identified.rig_seconds, 1), "attempts": len(tried), "file": out,
            "cpu_s": round(time.process_time() - t0, 1)}


def selftest(setting: str, seeds: list[int], models: list[str | None]) -> dict[str, Any]:
    """The bridge's start-up on each rig (seed i with bridge model i; ``"missing"``: not identified, failed)."""
    from services.qube_sim.trials import start_up

    t0 = time.process_time()
    profile = family_profile(setting)
    failures = []
    for seed, model in zip(seeds, models, strict=True):
        if model == "missing":
            failures.append(f"rig {seed}: not identified")
            continue
        refused = start_up(profile.rig_params(seed), _control(model), profile.device_options())[3]
        if refused is not None:
            failures.append(f"rig {seed}: {refused}")
    return {"rigs": len(seeds), "passed": len(seeds) - len(failures), "failures": failures,
            "cpu_s": round(time.process_time() - t0, 1)}


def reset(setting: str, seeds: list[int], models: list[str | None], starts: list[int]) -> dict[str, Any]:
    """Reset k on rig seeds[k] with bridge model models[k] from varied start starts[k], as bench.reset makes them."""
    from bench.reset import WINDOW_S
    from services.qube_sim.trials import run_trial, summary, varied_start
    from worker.qube_env import RESET_ATTEMPTS

    t0 = time.process_time()
    profile = family_profile(setting)
    results, failures = [], []
    for seed, model, start in zip(seeds, models, starts, strict=True):
        if model == "missing":
            failures.append(f"rig {seed} start {start}: not identified")
            continue
        r = run_trial(profile.rig_params(seed), varied_start(start), _control(model), max_seconds=WINDOW_S,
                      device_options=profile.device_options(), attempts=RESET_ATTEMPTS)
        results.append(r)
        if not r.ready:
            failures.append(f"rig {seed} start {start}: {r.outcome}")
    s = summary(results)
    return {"resets": len(seeds), "ready": s["ready"], "first_attempt": s["first_attempt"],
            "median_s": s["median_s"], "failures": failures, "cpu_s": round(time.process_time() - t0, 1)}


def zeroshot(model: str, truth: str, seeds: list[int], models: list[str | None], clock: str) -> dict[str, Any]:
    """The pretrained controller, greedily, one episode on each rig (its true physics, the bridge's model given);
    balanced to the end: the task's most return. A reset that fails ends the rig's episode unbalanced."""
    from protocol.qube import MAX_RETURN
    from runtime.model_file import InitModel
    from worker.envs import make_env
    from worker.evaluate import actions_of_model, load_learner, play
    from worker.qube_env import ResetFailed

    t0 = time.process_time()
    file = InitModel.open(model).file
    options = actions_of_model(file)
    returns: list[float | None] = []
    failures = []
    for seed, bridge_model in zip(seeds, models, strict=True):
        if bridge_model == "missing":
            returns.append(None)
            failures.append(f"rig {seed}: not identified")
            continue
        env = make_env(TASK, seed, rig_profile=truth, rig_model=bridge_model, qube_clock=clock, **options)
        try:
            learner = load_learner(file, TASK, env.observation_space, env.action_space)
            returns.append(play(env, learner, seed)[0])
        except ResetFailed as err:
            returns.append(None)
            failures.append(f"rig {seed}: {err}")
        finally:
            env.close()
    return {"rigs": len(seeds), "balanced": sum(r is not None and r >= MAX_RETURN for r in returns),
            "returns": returns, "failures": failures, "cpu_s": round(time.process_time() - t0, 1)}


def federation(seed: int, rigs: int, max_episodes: int, folder: Path, options: dict[str, Any], algo: str,
               init_model: str | None = None) -> RunSummary:
    """One in-process federation of the sweep's task and strategy on ``rigs`` rigs with the rig ``options``
    (rig_profile, rig_model, randomize, qube_actions, qube_clock); its summary."""
    from deploy.inprocess import run_federation
    from deploy.settings import InprocessSettings

    s = InprocessSettings.given(env=TASK, policy=POLICY, seed=seed, workers=rigs, max_episodes=max_episodes,
                                run_dir=folder, algo=algo, init_model=init_model, **options)
    return run_federation(s, plot=False, tensorboard_files=False, tolerate_failures=True)


def finetune(seed: int, run_dir: str, options: dict[str, Any], model: str, max_episodes: int, algo: str,
             identify_s: list[float]) -> dict[str, Any]:
    """The lab of ``seed`` fine-tuned in process from ``model`` (a finished run is reused; an unfinished folder is
    started again); its last rig: the rig with the most rig minutes (identification + balance + reset)."""
    t0 = time.process_time()
    summary = reused(Path(run_dir), lambda folder: federation(seed, len(identify_s), max_episodes, folder, options,
                                                              algo, init_model=model))
    return {**last_rig(summary, identify_s), "run_dir": run_dir, "cpu_s": round(time.process_time() - t0, 1)}


def last_rig(summary: RunSummary, identify_s: list[float]) -> dict[str, Any]:
    """From a fine-tune's summary: finished (every rig solved), the last rig's episodes and rig minutes, the workers
    stopped on their rig."""
    rigs = []
    for w in summary.workers:
        extra = identify_s[w.index] if w.index < len(identify_s) else 0.0
        rigs.append({"solved": w.solved, "episodes": w.episodes,
                     "rig_min": round(((w.rig.rig_s if w.rig else 0.0) + extra) / 60, 3),
                     "stopped": w.state == "stopped"})
    finished = bool(rigs) and all(r["solved"] for r in rigs)
    last = max(rigs, key=lambda r: r["rig_min"]) if rigs else {}
    return {"finished": finished, "episodes": last.get("episodes") if finished else None,
            "rig_min": last.get("rig_min") if finished else None, "stopped": sum(r["stopped"] for r in rigs),
            "end_reason": summary.end_reason}


def pretrain(actions: str, run_dir: str, max_episodes: int, algo: str, seed: int = PRETRAIN_SEED,
             identified: list[str] | None = None, attempts: int = 1) -> dict[str, Any]:
    """A pretrain of ``actions``: a federation of RIGS rigs on lockstep, reused when finished. Without
    ``identified``, the ``lab``-randomised one (bench.sim2real's ``randomised``: each rig's physics drawn afresh within
    +-RANDOMIZE at every reset); with the identified profiles of a lab's rigs, deploy.lab's, randomised around them
    (services/qube_sim/pretrain.py), each simulated rig's reset from that profile's model, tried as deploy.lab does
    again with its next seed (up to ``attempts``, into ``<run_dir>-<k>``) while no worker met TC, and its controller
    chosen among the workers of that attempt as deploy.lab chooses (:func:`warm_start`; deploy.lab's further attempt
    when no controller holds every identified rig is not made here)."""
    from deploy.lab import attempt_seed

    t0 = time.process_time()
    for attempt in range(1, attempts + 1):
        folder = Path(run_dir if attempt == 1 else f"{run_dir}-{attempt}")
        def run(into: Path, its_seed: int = attempt_seed(seed, attempt)) -> RunSummary:
            return _pretrain(into, its_seed, actions, max_episodes, algo, identified)

        summary = reused(folder, run)
        solved = any(w.solved for w in summary.workers)
        if solved:
            break
    out = {"finished": solved, "model": str(folder) if solved else None, "end_reason": summary.end_reason,
           "episodes": summary.episodes_to_all_solved, "attempt": attempt}
    if solved and identified is not None:  # as deploy.lab: the worker the identified rigs balance best
        out.update(warm_start(folder, identified, seed))
    return {**out, "cpu_s": round(time.process_time() - t0, 1)}


def warm_start(run: Path, identified: list[str], seed: int) -> dict[str, Any]:
    """deploy.lab's choice of warm start for the lab of ``seed`` from its pretrain ``run`` (every worker that met TC,
    played greedily on each rig's identified simulation): the chosen model, and each candidate's returns."""
    from deploy.lab import candidates, choose, played

    pool = played(candidates(run), [Path(f) for f in identified], seed)
    if not pool:  # no worker's model kept: the run folder's own answer (its first worker to meet TC)
        return {}
    best = choose([c["returns"] for c in pool])
    return {"model": pool[best]["model"], "chosen": best, "candidates": pool}


def _pretrain(folder: Path, seed: int, actions: str, max_episodes: int, algo: str,
              identified: list[str] | None) -> RunSummary:
    """Run the pretrain :func:`pretrain` describes into ``folder``; its summary."""
    options: dict[str, Any] = {"rig_profile": "lab", "randomize": RANDOMIZE, "qube_actions": actions}
    if identified is not None:
        from services.qube_sim.pretrain import for_lab
        from services.qube_sim.profile import DRAWN_MODEL, load_profile

        profile = folder.parent / f"{folder.name}-profile.json"
        profile.write_text(for_lab([load_profile(f) for f in identified], actions, name="around-identified").to_json())
        options = {"rig_profile": str(profile), "rig_model": DRAWN_MODEL, "qube_actions": actions}  # as deploy.lab
    return federation(seed, RIGS, max_episodes, folder, options, algo)


def reused(folder: Path, run: Callable[[Path], RunSummary]) -> RunSummary:
    """The summary of the finished run in ``folder``, else of ``run(folder)`` in the folder made empty (an
    unfinished run is started again)."""
    if (folder / SUMMARY).exists():
        return RunSummary.read(folder)
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    return run(folder)


# -- the plan -----------------------------------------------------------------------------------------------------


def identified_file(runs: Path, setting: str, seed: int, i: int) -> Path:
    """Rig i of lab ``seed``'s identified profile: one folder per lab, rig<i>.json (--rig-model's folder)."""
    return runs / "identified" / setting / f"s{seed}" / f"rig{i}.json"


def prerequisites(args: argparse.Namespace, store: Store) -> list[Unit]:
    """The pretrains (one per action set without ``--model``) and identifications the measures need."""
    units = []
    if {"zeroshot", "finetune"} & set(args.measures) and {"nominal", "identified"} & set(args.variants):
        for actions in args.actions:
            if actions not in args.model:
                units.append(Unit(f"pretrain/{actions}", pretrain,
                                  {"actions": actions, "run_dir": str(args.runs_dir / f"pretrain-{actions}"),
                                   "max_episodes": args.pretrain_episodes, "algo": args.algo},
                                  {"max_episodes": args.pretrain_episodes, "algo": args.algo}))
    if {"identified", "around"} & set(args.variants):
        for setting in args.settings:
            for seed in args.seeds:
                for i in range(RIGS):
                    out = identified_file(args.runs_dir, setting, seed, i)
                    units.append(Unit(f"identify/{setting}/s{seed}/rig{i}", identify,
                                      {"setting": setting, "seed": rig_seed(seed, i), "out": str(out)},
                                      {"out": str(out)}))  # another --runs-dir identifies again
    return [u for u in units if not store.done(u) or _refused_before_retries(store.entries[u.key])]


def _refused_before_retries(entry: dict[str, Any]) -> bool:
    """An identification that failed before a refused fit was recorded again (no ``attempts``): identified again."""
    return not entry.get("ok") and "attempts" not in entry


def around_pretrains(args: argparse.Namespace, store: Store) -> list[Unit]:
    """Variant ``around``: a pretrain per setting, lab and action set around the lab's identified rigs (once every
    rig of the lab is identified)."""
    if "around" not in args.variants or not {"zeroshot", "finetune"} & set(args.measures):
        return []
    from deploy.lab import PRETRAIN_ATTEMPTS  # tried as often as deploy.lab does by default

    units = []
    for setting in args.settings:
        for seed in args.seeds:
            files = bridge_models(store, args, setting, seed, "around")
            if "missing" in files:
                continue
            for actions in args.actions:
                units.append(Unit(f"pretrain/{actions}/around/{setting}/s{seed}", pretrain,
                                  {"actions": actions, "run_dir": str(args.runs_dir / "pretrain-around" / setting
                                                                      / actions / f"s{seed}"),
                                   "max_episodes": args.pretrain_episodes, "algo": args.algo, "seed": seed,
                                   "identified": files, "attempts": PRETRAIN_ATTEMPTS},
                                  {"max_episodes": args.pretrain_episodes, "algo": args.algo,
                                   "attempts": PRETRAIN_ATTEMPTS, "warm_start": "chosen"}))
    return [u for u in units if not store.done(u)]


def bridge_models(store: Store, args: argparse.Namespace, setting: str, seed: int, variant: str) -> list[str | None]:
    """The bridge's model of each rig of lab ``seed``: None (nominal), a profile file, or "missing"."""
    if variant == "nominal":
        return [None] * RIGS
    out: list[str | None] = []
    for i in range(RIGS):
        entry = store.entries.get(f"identify/{setting}/s{seed}/rig{i}", {})
        out.append(entry["file"] if entry.get("ok") and Path(entry["file"]).exists() else "missing")
    return out


def model_of(store: Store, args: argparse.Namespace, actions: str, around: str | None = None) -> str | None:
    """The controller of ``actions``: ``--model``, else its pretrain's run folder; ``around``: "<setting>/s<seed>",
    the pretrain around that lab's identified rigs (None: none finished)."""
    if around is not None:
        return store.entries.get(f"pretrain/{actions}/around/{around}", {}).get("model")
    if actions in args.model:
        return str(args.model[actions])
    return store.entries.get(f"pretrain/{actions}", {}).get("model")


def measures(args: argparse.Namespace, store: Store) -> list[Unit]:
    """Every measure unit not yet in ``store`` (or all of them: ``--again``) whose prerequisites are there."""
    units: list[Unit] = []
    for setting in args.settings:
        truth = str(truth_file(setting, args.runs_dir / "truth"))
        for variant in args.variants:
            for seed in args.seeds:
                units += _rig_units(args, store, setting, variant, seed)
                units += _controller_units(args, store, setting, variant, seed, truth)
    return [u for u in units if args.again or not store.done(u)]


def _rig_units(args: argparse.Namespace, store: Store, setting: str, variant: str, seed: int) -> list[Unit]:
    models = bridge_models(store, args, setting, seed, variant)
    rigs = [rig_seed(seed, i) for i in range(RIGS)]
    units = []
    if variant not in RIG_VARIANTS:
        return []
    if "selftest" in args.measures:
        units.append(Unit(f"selftest/{setting}/{variant}/s{seed}", selftest,
                          {"setting": setting, "seeds": rigs, "models": models}, {"models": models}))
    if "reset" in args.measures:
        picks = [k % RIGS for k in range(args.resets)]
        units.append(Unit(f"reset/{setting}/{variant}/s{seed}", reset,
                          {"setting": setting, "seeds": [rigs[k] for k in picks], "models": [models[k] for k in picks],
                           "starts": [seed * 100 + k for k in range(args.resets)]},
                          {"resets": args.resets, "models": models}))
    return units


def _controller_units(args: argparse.Namespace, store: Store, setting: str, variant: str, seed: int,
                      truth: str) -> list[Unit]:
    models = bridge_models(store, args, setting, seed, variant)
    rigs = [rig_seed(seed, i) for i in range(RIGS)]
    units = []
    for actions in args.actions:
        around = f"{setting}/s{seed}" if variant == "around" else None
        model = model_of(store, args, actions, around)
        if model is None and around is not None and f"pretrain/{actions}/around/{around}" in store.entries:
            units += _without_controller(args, setting, actions, seed, rigs)  # the lab stops there, as deploy.lab
            continue
        if model is None or not {"zeroshot", "finetune"} & set(args.measures):
            continue
        params = {"model": model, "clock": args.clock, "models": models}
        if "zeroshot" in args.measures:
            units.append(Unit(f"zeroshot/{setting}/{actions}/{variant}/s{seed}", zeroshot,
                              {"model": model, "truth": truth, "seeds": rigs, "models": models, "clock": args.clock},
                              params))
        if "finetune" in args.measures and "missing" not in models:
            options = {"rig_profile": truth, "qube_actions": actions,
                       **({"qube_clock": "delayed"} if args.clock == "delayed" else {}),
                       **({"rig_model": str(Path(models[0] or "").parent)} if variant != "nominal" else {})}
            ident = [store.entries.get(f"identify/{setting}/s{seed}/rig{i}", {}).get("rig_s", 0.0)
                     if variant != "nominal" else 0.0 for i in range(RIGS)]
            units.append(Unit(f"finetune/{setting}/{actions}/{variant}/s{seed}", finetune,
                              {"seed": seed, "run_dir": str(args.runs_dir / "finetune" / setting / actions / variant
                                                            / f"s{seed}"), "options": options, "model": model,
                               "max_episodes": args.max_episodes, "algo": args.algo, "identify_s": ident},
                              {**params, "max_episodes": args.max_episodes, "algo": args.algo}))
        elif "finetune" in args.measures:  # a rig the identification refused: the lab stops there
            units.append(Unit(f"finetune/{setting}/{actions}/{variant}/s{seed}", _not_identified, {}, params))
    return units


def _not_identified(why: str = "a rig was not identified") -> dict[str, Any]:
    return {"finished": False, "episodes": None, "rig_min": None, "stopped": 0, "end_reason": why, "cpu_s": 0.0}


#: What deploy.lab does when no pretrain met TC, for variant ``around``'s zero-shot and fine-tune.
NO_CONTROLLER = "no pretrain around the lab's identified rigs met TC"


def _without_controller(args: argparse.Namespace, setting: str, actions: str, seed: int,
                        rigs: list[int]) -> list[Unit]:
    """A lab of variant ``around`` whose pretrains met no TC: none of its rigs balanced zero-shot, its fine-tune
    unfinished (deploy.lab stops before it)."""
    params = {"no_controller": True}
    units = []
    if "zeroshot" in args.measures:
        units.append(Unit(f"zeroshot/{setting}/{actions}/around/s{seed}", _no_zeroshot, {"rigs": rigs}, params))
    if "finetune" in args.measures:
        units.append(Unit(f"finetune/{setting}/{actions}/around/s{seed}", _not_identified, {"why": NO_CONTROLLER},
                          params))
    return units


def _no_zeroshot(rigs: list[int]) -> dict[str, Any]:
    return {"rigs": len(rigs), "balanced": 0, "returns": [None] * len(rigs),
            "failures": [f"rig {r}: {NO_CONTROLLER}" for r in rigs], "cpu_s": 0.0}


def run_units(units: list[Unit], store: Store, jobs: int,
              executor: Callable[[int], Executor] = process_pool) -> int:
    """Run ``units`` ``jobs`` at a time (in ``executor``'s workers: processes, one torch thread each); each result goes
    into the store as it comes. A unit that raises is reported in one line and left out (the next invocation tries it
    again); returns how many did."""
    if not units:
        return 0
    failed = 0
    with executor(jobs) as pool:
        futures: dict[Future[dict[str, Any]], Unit] = {pool.submit(u.run, **u.kwargs): u for u in units}
        for fut in _as_completed(futures):
            unit = futures[fut]
            try:
                result = fut.result()
            except Exception as err:  # one unit's error is a line, not the end of the sweep
                failed += 1
                print(f"{unit.key}: failed, not stored: {type(err).__name__}: {str(err).splitlines()[0][:300]}",
                      flush=True)
                continue
            store.put(unit, result)
            brief = {k: v for k, v in result.items() if k not in ("failures", "returns", "run_dir", "file")}
            print(f"{unit.key}: {json.dumps(brief)}", flush=True)
    return failed


def _as_completed(futures: Iterable[Future[dict[str, Any]]]) -> Iterable[Future[dict[str, Any]]]:
    from concurrent.futures import as_completed

    return as_completed(list(futures))


# -- the tables ---------------------------------------------------------------------------------------------------


def _entries(entries: dict[str, dict[str, Any]], prefix: str) -> list[dict[str, Any]]:
    return [e for k, e in entries.items() if k.startswith(prefix + "/s")]


def rig_row(entries: dict[str, dict[str, Any]], setting: str, variant: str) -> dict[str, Any]:
    """Self-test and reset of one setting and variant, summed over the seeds measured."""
    tests = _entries(entries, f"selftest/{setting}/{variant}")
    resets = _entries(entries, f"reset/{setting}/{variant}")
    return {"selftest": (sum(e["passed"] for e in tests), sum(e["rigs"] for e in tests)) if tests else None,
            "reset": (sum(e["ready"] for e in resets), sum(e["resets"] for e in resets)) if resets else None}


def controller_row(entries: dict[str, dict[str, Any]], setting: str, actions: str, variant: str) -> dict[str, Any]:
    """Zero-shot (rigs balanced to the end) and the fine-tune's last rig (median [IQR] over the seeds, unfinished
    counted as worse) of one setting, action set and variant."""
    shots = _entries(entries, f"zeroshot/{setting}/{actions}/{variant}")
    runs = _entries(entries, f"finetune/{setting}/{actions}/{variant}")
    return {"zeroshot": (sum(e["balanced"] for e in shots), sum(e["rigs"] for e in shots)) if shots else None,
            "finished": (sum(e["finished"] for e in runs), len(runs)) if runs else None,
            "episodes": spread_censored([e["episodes"] for e in runs]) if runs else None,
            "rig_min": spread_censored([e["rig_min"] for e in runs]) if runs else None}


def _frac(pair: tuple[int, int] | None) -> str:
    return "-" if pair is None else f"{pair[0]}/{pair[1]}"


def _med(s: dict[str, Any] | None, digits: int = 0) -> str:
    if s is None:
        return "-"
    if s["median"] is None:
        return f"unfinished ({s['unfinished']} of {s['n']})"
    fmt = (lambda v: "unfinished" if v is None else f"{v:.{digits}f}")  # noqa: E731
    return f"{fmt(s['median'])} [{fmt(s['q1'])}-{fmt(s['q3'])}]"


def _present(entries: dict[str, dict[str, Any]], index: int) -> list[str]:
    """The distinct values of part ``index`` of the keys, in first-seen order."""
    return list(dict.fromkeys(k.split("/")[index] for k in entries if len(k.split("/")) > index))


def settings_of(entries: dict[str, dict[str, Any]]) -> list[str]:
    measured = {k.split("/")[1] for k in entries if k.split("/")[0] in MEASURES}
    return [s for s in settings() if s in measured] + sorted(measured - set(settings()))


def render_docs(data: dict[str, Any], source: str) -> str:
    """The docs page's tables: the rig side per setting, then per action set the controller side."""
    entries = data["entries"]
    names = settings_of(entries)
    variants = [v for v in VARIANTS if any(f"/{v}/" in k for k in entries if k.split("/")[0] in MEASURES)]
    rig_variants = [v for v in variants if v in RIG_VARIANTS]
    cfg = data.get("config", {})
    made = "; ".join(f"`{c}`" for c in cfg.get("commands", [])) or "`python -m bench.sim2real ood`"
    lines = [f"Generated from `{source}`, made by {made}; {cfg.get('rigs', RIGS)} rigs per report seed, clock "
             f"`{cfg.get('clock', 'delayed')}` for the controller's episodes. `nominal`: the bridge's nominal model, "
             "no identification; `identified`: every rig identified first and the bridge's model is its identified "
             "profile (the controller is still the `lab`-randomised pretrain; rig minutes include identification); "
             "`around`: as `identified`, the controller pretrained around each lab's identified rigs.",
             "", *_head(["setting", *(f"self-test passed ({v})" for v in rig_variants),
                         *(f"resets ready ({v})" for v in rig_variants)])]
    for name in names:
        rows = [rig_row(entries, name, v) for v in rig_variants]
        lines.append(_cells([f"`{name}`", *(_frac(r["selftest"]) for r in rows), *(_frac(r["reset"]) for r in rows)]))
    for actions in [a for a in _present(entries, 2) if a in _action_sets()]:
        measured = [v for v in variants if any(k.split("/")[0] in ("zeroshot", "finetune")
                                               and k.split("/")[2:4] == [actions, v] for k in entries)]
        lines += ["", f"**Actions `{actions}`**: zero-shot (rigs balanced to the end), fine-tune runs finished, the "
                  "last rig's episodes and rig minutes, median [IQR] over the seeds (unfinished counted as worse).", "",
                  *_head(["setting", *(f"{m} ({v})" for m in ("zero-shot", "finished", "episodes", "rig min")
                                       for v in measured)])]
        for name in names:
            rows = [controller_row(entries, name, actions, v) for v in measured]
            lines.append(_cells([f"`{name}`", *(_frac(r["zeroshot"]) for r in rows),
                                 *(_frac(r["finished"]) for r in rows), *(_med(r["episodes"]) for r in rows),
                                 *(_med(r["rig_min"], 1) for r in rows)]))
    lines += ["", *pretrain_lines(entries), cost_line(entries)]
    return "\n".join(lines) + "\n"


def pretrain_lines(entries: dict[str, dict[str, Any]]) -> list[str]:
    """One line per `lab`-randomised pretrain, and one for the pretrains around identified rigs."""
    lines = []
    for key, e in entries.items():
        parts = key.split("/")
        if parts[0] == "pretrain" and len(parts) == 2:
            how = (f"every worker met TC by episode {e['episodes']}" if e.get("episodes") is not None else
                   f"not every worker met TC ({e.get('end_reason')})"
                   + ("; the controller is the first to meet it" if e.get("finished") else "; no controller"))
            lines.append(f"- The `{parts[1]}` pretrain (`lab`, +-{RANDOMIZE:.0%}): {how}.")
    around = [e for k, e in entries.items() if k.startswith("pretrain/") and "/around/" in k]
    if around:
        lines.append(f"- Pretrains around identified rigs: {sum(bool(e.get('finished')) for e in around)} of "
                     f"{len(around)} made a controller.")
    return lines + ([""] if lines else [])


def _action_sets() -> tuple[str, ...]:
    from protocol.qube import ACTION_SETS

    return tuple(ACTION_SETS)


def cost_line(entries: dict[str, dict[str, Any]]) -> str:
    """Median CPU seconds of one unit of each stage (what the sweep costs)."""
    parts = []
    for stage in ("pretrain", "identify", *MEASURES):
        cpu = sorted(e.get("cpu_s", 0.0) for k, e in entries.items() if k.split("/")[0] == stage)
        if cpu:
            parts.append(f"{stage} {cpu[len(cpu) // 2]:.0f} s ({len(cpu)} units)")
    return "CPU per unit, median: " + ("; ".join(parts) if parts else "nothing measured yet") + "."


def summary_rows(entries: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per group (sweep, combined, course, lab) and variant: totals of self-test, reset and zero-shot per action
    set."""
    out: dict[str, dict[str, Any]] = {}
    for group in ("lab", "sweep", "combined", "course"):
        names = [s for s in settings_of(entries) if group_of(s) == group]
        for variant in VARIANTS:
            rows = [rig_row(entries, s, variant) for s in names]
            row: dict[str, Any] = {"settings": len(names)}
            for measure in ("selftest", "reset"):
                pairs = [r[measure] for r in rows if r[measure] is not None]
                row[measure] = (sum(p[0] for p in pairs), sum(p[1] for p in pairs)) if pairs else None
            for actions in _action_sets():
                pairs = [c["zeroshot"] for s in names
                         if (c := controller_row(entries, s, actions, variant))["zeroshot"] is not None]
                if pairs:
                    row[f"zeroshot-{actions}"] = (sum(p[0] for p in pairs), sum(p[1] for p in pairs))
                runs = [e for s in names for e in _entries(entries, f"finetune/{s}/{actions}/{variant}")]
                if runs:
                    row[f"finetune-{actions}"] = spread_censored([e["rig_min"] for e in runs])
            if any(v is not None for k, v in row.items() if k != "settings"):
                out[f"{group}/{variant}"] = row
    return out


def targets(rows: dict[str, dict[str, Any]]) -> list[str]:
    """The issue's targets this sweep measures, met or missed (with identification)."""
    out = []
    tests = [r["selftest"] for r in rows.values() if r.get("selftest")]
    if tests:
        out.append(f"self-test on every rig {'met' if all(p == q for p, q in tests) else '**missed**'}")
    for group, key in (("sweep", "reset_sweep"), ("course", "reset_course")):
        pair = rows.get(f"{group}/identified", {}).get("reset")
        if pair and pair[1]:
            ok = pair[0] / pair[1] >= TARGETS[key]
            out.append(f"reset success {group} >= {TARGETS[key]:.0%} {'met' if ok else '**missed**'}")
    for variant in ("identified", "around"):
        for k, pair in rows.get(f"combined/{variant}", {}).items():
            if k.startswith("zeroshot-") and pair[1]:
                ok = pair[0] / pair[1] >= TARGETS["zero_shot_combined"]
                out.append(f"zero-shot combined `{k[9:]}` ({variant}) >= {TARGETS['zero_shot_combined']:.0%} "
                           f"{'met' if ok else '**missed**'}")
    return out


def render_readme(data: dict[str, Any], source: str) -> str:
    """README's short block: totals per group of settings."""
    rows = summary_rows(data["entries"])
    shots = [a for a in _action_sets() if any(f"zeroshot-{a}" in r for r in rows.values())]
    tuned = [a for a in _action_sets() if any(f"finetune-{a}" in r for r in rows.values())]
    lines = ["Rigs outside `lab`, one parameter at a time (RealAIGym's style), the combined family and the course "
             "files' damping; totals over each group's settings and seeds (fine-tune: median [IQR] over its runs, "
             f"unfinished counted as worse), from `{source}` (every setting: "
             "[Out of distribution](docs/how-to/ood.md)).", "",
             *_head(["rigs", "bridge model (controller)", "self-test passed", "resets ready"]
                    + [f"zero-shot `{a}`" for a in shots]
                    + [f"fine-tune `{a}`: last rig's rig minutes" for a in tuned])]
    for key, row in rows.items():
        group, variant = key.split("/")
        label = f"sweep ({row['settings']} settings)" if group == "sweep" else group
        lines.append(_cells([label, SHORT[variant], _pct(row["selftest"]), _pct(row["reset"])]
                            + [_pct(row.get(f"zeroshot-{a}")) for a in shots]
                            + [_med(row.get(f"finetune-{a}"), 1) for a in tuned]))
    met = targets(rows)
    if met:
        lines += ["", "Targets: " + "; ".join(met) + "."]
    return "\n".join(lines) + "\n"


def _cells(cells: list[str]) -> str:
    """One markdown table row."""
    return "| " + " | ".join(cells) + " |"


def _head(names: list[str]) -> list[str]:
    """A markdown table's header row and its separator, one column per name."""
    return [_cells(names), _cells(["---"] * len(names))]


def _pct(pair: tuple[int, int] | None) -> str:
    if not pair or not pair[1]:
        return "-"
    return f"{pair[0]}/{pair[1]} ({pair[0] / pair[1]:.0%})"


BEGIN = "<!-- ood:begin (generated by python -m bench.sim2real ood --report; do not edit) -->"
END = "<!-- ood:end -->"
README = Path("README.md")
DOCS = Path("docs/how-to/ood.md")


def write_pages(source: Path, readme: Path = README, docs: Path = DOCS) -> None:
    data = json.loads(source.read_text())
    write_block([readme], BEGIN, END, render_readme(data, str(source)))
    write_block([docs], BEGIN, END, render_docs(data, str(source)))


# -- the command --------------------------------------------------------------------------------------------------


def parse(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m bench.sim2real ood", description=__doc__.splitlines()[0])
    p.add_argument("--measures", default=",".join(MEASURES), help=f"comma list of {', '.join(MEASURES)} (default all)")
    p.add_argument("--settings", default="all", help="comma list of settings, 'sweep', 'extremes' (each parameter's "
                   "lowest and highest factor, lab, combined, course) or 'all' (default): "
                   + ", ".join(settings()))
    p.add_argument("--seeds", default=SEEDS, help=f"report seeds LO-HI or a comma list (default {SEEDS}); each a lab "
                   f"of {RIGS} rigs")
    p.add_argument("--variants", default=",".join(RIG_VARIANTS),
                   help="nominal (the bridge's nominal model, the lab-randomised pretrain), identified (every rig "
                   "identified, the bridge's model from it, the same pretrain), around (as identified, with a "
                   "pretrain around each lab's identified rigs: a pretrain per setting, seed and action set); "
                   "default nominal,identified")
    p.add_argument("--actions", default=",".join(ACTIONS), help="QUBE action sets (default paper,levels)")
    p.add_argument("--model", action="append", default=[], metavar="ACTIONS=PATH",
                   help="the controller of an action set (a model file or a run folder) instead of its pretrain")
    p.add_argument("--resets", type=int, default=RESETS, help=f"resets per seed (default {RESETS})")
    p.add_argument("--clock", choices=("delayed", "lockstep"), default="delayed")
    p.add_argument("--algo", default="ppo")
    p.add_argument("--max-episodes", type=int, default=FINETUNE_M)
    p.add_argument("--pretrain-episodes", type=int, default=PRETRAIN_M)
    p.add_argument("--jobs", type=int, default=1, help="units at a time (processes)")
    p.add_argument("--runs-dir", type=Path, default=RUNS)
    p.add_argument("--out", type=Path, default=OUT)
    p.add_argument("--again", action="store_true", help="measure the selected units again even where --out holds "
                   "them with the same parameters (the code changed since); identifications are not made again")
    p.add_argument("--report", action="store_true", help="only write the tables of --out into README.md and "
                   f"{DOCS} (runs nothing)")
    args = p.parse_args(argv)
    args.measures = _choices(p, "--measures", args.measures, MEASURES)
    args.variants = _choices(p, "--variants", args.variants, VARIANTS)
    args.actions = _choices(p, "--actions", args.actions, _action_sets())
    every = settings()
    groups = {"all": every, "sweep": [s for s in every if group_of(s) == "sweep"], "extremes": extremes()}
    args.settings = _choices(p, "--settings", ",".join(groups.get(args.settings, [args.settings])), tuple(every))
    args.seeds = seeds_of(args.seeds) if "," not in args.seeds else [int(s) for s in args.seeds.split(",")]
    args.model = dict(_pair(p, m) for m in args.model)
    if min(args.resets, args.jobs, args.max_episodes, args.pretrain_episodes) < 1:
        p.error("--resets, --jobs and the caps must be at least 1")
    return args


def _choices(p: argparse.ArgumentParser, flag: str, text: str, allowed: tuple[str, ...]) -> list[str]:
    picked = [t for t in text.split(",") if t]
    bad = [t for t in picked if t not in allowed]
    if bad or not picked:
        p.error(f"{flag}: unknown {', '.join(bad) or '(empty)'}; choose from {', '.join(allowed)}")
    return picked


def _pair(p: argparse.ArgumentParser, text: str) -> tuple[str, Path]:
    actions, _, path = text.partition("=")
    if actions not in _action_sets() or not path:
        p.error(f"--model {text!r}: expected ACTIONS=PATH with ACTIONS one of {', '.join(_action_sets())}")
    return actions, Path(path)


def main(argv: list[str] | None = None) -> int:
    args = parse(argv)
    if args.report:
        write_pages(args.out)
        return 0
    try:
        store = Store(args.out)
    except (OSError, ValueError) as err:
        print(f"python -m bench.sim2real ood: {args.out} is not a results file ({err}); move it away", file=sys.stderr)
        return 2
    made = command("bench.sim2real ood", argv)
    store.config = {"commands": [*(c for c in store.config.get("commands", []) if c != made), made], "rigs": RIGS,
                    "clock": args.clock, "cpus": os.cpu_count(), "load_at_start": round(os.getloadavg()[0], 2)}
    began = time.monotonic()
    first = prerequisites(args, store)
    print(f"{len(first)} pretrains and identifications to make", flush=True)
    failed = run_units(first, store, args.jobs)
    second = around_pretrains(args, store)
    if second:
        print(f"{len(second)} pretrains around identified rigs to make", flush=True)
        failed += run_units(second, store, args.jobs)
    todo = measures(args, store)
    print(f"{len(todo)} measure units to make ({', '.join(args.measures)})", flush=True)
    failed += run_units(todo, store, args.jobs)
    store.config["wall_s"] = round(time.monotonic() - began, 1)
    store.save()
    missing = [a for a in args.actions if model_of(store, args, a) is None and {"zeroshot", "finetune"}
               & set(args.measures)]
    if missing:
        print(f"!! no controller for {', '.join(missing)}: its pretrain did not finish (give --model)", flush=True)
    print(f"results in {args.out}; {math.ceil(time.monotonic() - began)} s"
          + (f"; {failed} units failed (see above; the same command tries them again)" if failed else ""), flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
