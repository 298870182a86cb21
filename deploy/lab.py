"""``python -m deploy.lab``: a lab's pipeline in one command. Identify every rig, pretrain in process around the rigs
as identified, then warm-start and fine-tune the rigs federated.

1. **identify**: every rig runs the identification protocol (rpi_bridge/identify.py) and its profile is fitted on
   this host (services/qube_sim/identify.py) into ``identified/rig<i>.json``. ``--env qube-local``: each rig is
   simulated by ``python -m services.qube_sim --identify`` with the bridge's own control code; ``--env qube``: each
   rig is asked over MQTT (``python -m worker.identify``), a real bridge or a simulated one.
2. **pretrain**: a federation in process on simulated rigs randomised around the identified ones
   (services/qube_sim/pretrain.py) until every worker meets TC, into ``pretrain/``. Each worker that met TC plays one
   greedy episode on each identified rig, simulated (``validated``). When none of its workers met TC, or none of
   those balanced every identified rig, again with another seed into ``pretrain-2/`` and so on
   (``--pretrain-attempts``). When no attempt met TC, the workers' last controllers (``models/<id>.last.pt``) play
   the same episodes; the stage fails only when none of them balanced an identified rig either.
3. **finetune**: the rigs themselves, every worker warm-started from the pretrain, federated by
   ``python -m deploy.run_local`` into ``finetune/``; each rig's resets use its identified model. The warm start is
   the controller of the pretrains' workers that met TC (or, when none did, of their last controllers) that balanced
   the most identified rigs in simulation (``warm_start``, kept in ``warm-start.json``).

Simulated rigs take their true physics from ``FEDRL_RIG_PROFILE`` (a profile, or a folder with one per rig). The
pipeline never reads it: it passes the environment on to the simulators of stages 1 and 3 and learns the rigs only by
identifying them; the pretrain's simulator is told the identified profile instead. An interrupted pipeline resumes
at the stage it stopped in (``lab.json`` records what is done): a finished rig's identification is kept, an
interrupted fine-tune resumes from its saved state, and an interrupted pretrain starts again.

At the end it reports for every rig its identification, balance, reset and idle seconds, and writes them into the
fine-tune's summary.json (``workers[].rig.identify_s`` beside ``rig_s``) and into ``lab.json``.
"""

from __future__ import annotations

import datetime as dt
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

from pydantic import field_validator, model_validator
from pydantic_settings import CliSuppress

from chief.settings import PolicyName
from protocol import learners
from protocol.messages import IDENTIFY_ATTEMPTS_LIMIT
from protocol.mqtt import BrokerAddress
from protocol.qube import ACTION_SETS, MAX_RETURN, action_set
from protocol.tasks import worker_seed
from rpi_bridge.identify import IDENTIFY_ATTEMPTS
from runtime.records import SUMMARY, AnyRecord, EpisodeRecord, RunSummary, read_metrics
from runtime.settings import (
    Assignments,
    LearnerName,
    LearnerTaskSettings,
    QubeActions,
    qube_actions_setting,
    returns_code,
    setting,
    temperature_problem,
    warm_lr_setting,
    warm_temperature_setting,
)
from services.qube_sim.pretrain import AUTHORITY, EASE_IN
from worker.settings import LearnerSetSettings, parse_overrides

#: The stages, in order.
STAGES = ("identify", "pretrain", "finetune")
#: The learner preset's fields the pretrain replaces (``--pretrain-set``).
PRETRAIN_SET: tuple[str, ...] = ()
#: Pretrains tried (each with its own seed) until one has a controller that meets TC, by default.
PRETRAIN_ATTEMPTS = 2
#: The most pretrain attempts (--pretrain-attempts).
MAX_ATTEMPTS = 10
#: Variables that carry the true physics of simulated rigs: the pretrain's simulator must not see them.
TRUTH = ("FEDRL_RIG_PROFILE", "FEDRL_RANDOMIZE")
#: Variables the pipeline reads itself and hands each stage on its command line: a stage must not read them again.
HANDED = ("FEDRL_LEARNER_SET",)


class LabSettings(LearnerSetSettings, LearnerTaskSettings):
    """A lab's rigs from identification to a fine-tuned controller (docs/how-to/lab.md)."""

    env: Literal["qube", "qube-local"] = setting("qube-local", "qube: rigs over MQTT (real bridges, or the simulated "
                                                 "rigs deploy.run_local starts); qube-local: simulated rigs in each "
                                                 "worker's process")
    workers: int = setting(3, "rigs, one worker each", ge=1, le=32)
    seed: int = setting(1, "base seed: rig i is simulated with seed*1000 + i, as in deploy.run_local")
    run_dir: Path | None = setting(None, "the pipeline's folder (unset: runs/<time>-lab-<env>-s<seed>); give the same "
                                   "one again to resume")
    max_episodes: int = setting(150, "M of the fine-tune: the most episodes per rig", ge=1)
    identify_attempts: int = setting(IDENTIFY_ATTEMPTS, "recordings of a rig before its identification gives up (a "
                                     "refused fit is recorded again with the next PRBS sequence; each costs about "
                                     "80 s of rig time)", ge=1, le=IDENTIFY_ATTEMPTS_LIMIT)
    pretrain_episodes: int = setting(600, "M of the pretrain", ge=1)
    pretrain_workers: int = setting(3, "workers of the pretrain (simulated rigs)", ge=1, le=32)
    pretrain_authority: float = setting(
        AUTHORITY, "the largest share of the actions' standstill torque (on the median identified rig) that a "
        "pretrain rig's arm breakaway may take: drawn arm friction above it is cut there (a rig whose arm the actions "
        "barely move teaches nothing and keeps the pretrain from meeting TC); 10 leaves the ranges as identified",
        gt=0, le=10)
    pretrain_attempts: int = setting(PRETRAIN_ATTEMPTS, "pretrains to try until one has a controller that meets "
                                     "TC and balances every identified rig in simulation, each with its own seed (a "
                                     "pretrain costs this host's time, no rig time)",
                                     ge=1, le=MAX_ATTEMPTS)
    pretrain_ease_in: int = setting(EASE_IN, "episodes over which each pretrain worker's drawn arm friction rises "
                                    "from the bottom of its range to all of it (0: the whole range from the first)",
                                    ge=0, le=100_000)
    pretrain_set: CliSuppress[Assignments] = setting(
        list(PRETRAIN_SET), "override a field of the learner's preset in the pretrain only, after --set's (given, "
        f"they replace the default: {', '.join(PRETRAIN_SET) or 'none'}; docs/how-to/lab.md)",
        aliases=["--pretrain-set"], metavar="KEY=VALUE")
    policy: PolicyName = setting("plain", "federation strategy of the pretrain and the fine-tune")
    algo: LearnerName = setting(learners.DEFAULT, "learner")
    qube_actions: QubeActions = qube_actions_setting()
    qube_clock: Literal["lockstep", "delayed", "realtime"] = setting(
        "lockstep", "clock of the simulated rigs of the fine-tune (--env qube: the simulator's; qube-local: lockstep "
        "or delayed)")
    broker: str | None = setting(None, "--env qube: the broker of real rigs (unset: the pipeline starts an embedded "
                                 "broker and simulated rigs)")
    warm_lr: float = warm_lr_setting(0.1)
    warm_temperature: float = warm_temperature_setting()
    init_model: Path | None = setting(None, "skip the pretrain: fine-tune from this model (a models/<id>.pt, or a run "
                                      "folder: its first worker to solve), e.g. an earlier pipeline's pretrain/",
                                      metavar="PATH")

    @field_validator("broker")
    @classmethod
    def _broker(cls, value: str | None) -> str | None:
        if value is not None:
            BrokerAddress.parse(value)
        return value

    @model_validator(mode="after")
    def _fits(self) -> LabSettings:
        if self.env == "qube-local" and self.qube_clock == "realtime":
            raise ValueError("--env qube-local runs on a simulated clock: --qube-clock lockstep or delayed")
        if self.env == "qube-local" and self.broker is not None:
            raise ValueError("--broker is for --env qube (rigs over MQTT)")
        if (problem := temperature_problem(self.warm_temperature, self.algo)):  # it always warm-starts
            raise ValueError(problem)
        parse_overrides(self.pretrain_set, self.algo)
        return self

    def folder(self) -> Path:
        stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
        return self.run_dir or Path("runs") / f"{stamp}-lab-{self.env}-s{self.seed}"


class StageFailed(RuntimeError):
    """A stage that could not finish: one line saying why (the pipeline exits 1 and resumes there)."""


# -- the record of what is done ---------------------------------------------------------------------------------


def load_progress(folder: Path) -> dict[str, Any]:
    path = folder / "lab.json"
    if not path.exists():
        return {"done": []}
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise StageFailed(f"{path}: not readable ({err}); move it away to start the pipeline again") from None
    return data if isinstance(data, dict) and isinstance(data.get("done"), list) else {"done": []}


def save_progress(folder: Path, progress: dict[str, Any]) -> None:
    path = folder / "lab.json"
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(progress, indent=2) + "\n")
    tmp.replace(path)


def child_env(hidden: Sequence[str] = ()) -> dict[str, str]:
    """A stage's environment: this one without what the pipeline hands its stages itself (:data:`HANDED`) and without
    ``hidden``, output unbuffered."""
    return {**{k: v for k, v in os.environ.items() if k not in (*HANDED, *hidden)}, "PYTHONUNBUFFERED": "1"}


def set_flags(texts: Sequence[str]) -> list[str]:
    """``--set KEY=VALUE`` for each of ``texts``: a stage's learner overrides on its command line."""
    return [word for text in texts for word in ("--set", text)]


def say(stage: str, text: str) -> None:
    print(f"[lab {stage}] {text}", flush=True)


def run_child(stage: str, command: Sequence[str], env: dict[str, str]) -> int:
    """A stage's command, its output passed on line by line under the stage's name."""
    say(stage, "$ " + " ".join(command))
    with subprocess.Popen(list(command), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
                          bufsize=1) as proc:
        assert proc.stdout is not None
        for line in proc.stdout:
            print(f"[lab {stage}]   {line.rstrip()}", flush=True)
        return proc.wait()


# -- stage 1: identify ------------------------------------------------------------------------------------------


def identified_files(s: LabSettings, folder: Path) -> list[Path]:
    return [folder / "identified" / f"rig{i}.json" for i in range(s.workers)]


def identify(s: LabSettings, folder: Path) -> None:
    """Every rig's identified profile, those already on file kept."""
    from services.qube_sim.profile import ProfileError, load_profile

    out = folder / "identified"
    out.mkdir(parents=True, exist_ok=True)
    env = child_env()
    todo = []
    for i, path in enumerate(identified_files(s, folder)):
        try:
            if load_profile(path).identified is not None:
                say("identify", f"rig{i}: kept {path}")
                continue
        except ProfileError:
            pass
        todo.append(i)
    if s.env == "qube":
        from deploy.lab_mqtt import identify_over_mqtt

        identify_over_mqtt(s, out, todo, env)
    else:
        for i in todo:
            command = [sys.executable, "-m", "services.qube_sim", "--rig-id", f"rig{i}", "--seed",
                       str(worker_seed(s.seed, i)), "--identify", str(out / f"rig{i}.json"), "--identify-attempts",
                       str(s.identify_attempts)]
            code = run_child("identify", command, env)
            if code != 0:
                raise StageFailed(f"rig{i} could not be identified (exit code {code}); see the lines above")
    from services.qube_sim.pretrain import breakaway_share

    for i, path in enumerate(identified_files(s, folder)):
        share, torque = breakaway_share(load_profile(path), s.qube_actions)
        say("identify", f"rig{i}: arm breakaway {share * torque * 1e3:.1f} mN m, {share:.0%} of the "
            f"{torque * 1e3:.1f} mN m the `{s.qube_actions}` actions give at standstill")


def authority_hint(s: LabSettings, folder: Path) -> str:
    """For a failed pretrain: the rig with the least authority left under ``--qube-actions``, and what the action
    set with the largest commands would give it (empty when that is the set in use)."""
    from services.qube_sim.pretrain import breakaway_share
    from services.qube_sim.profile import load_profile

    strongest = max(ACTION_SETS.values(), key=lambda a: a.limit).name
    if action_set(s.qube_actions).limit >= action_set(strongest).limit:
        return ""
    shares = [breakaway_share(load_profile(path), s.qube_actions)[0] for path in identified_files(s, folder)]
    worst = max(range(len(shares)), key=shares.__getitem__)
    stronger = breakaway_share(load_profile(identified_files(s, folder)[worst]), strongest)[0]
    return (f"; rig{worst}'s arm breakaway takes {shares[worst]:.0%} of the `{s.qube_actions}` actions' torque "
            f"(`--qube-actions {strongest}`: {stronger:.0%})")


# -- stage 2: pretrain --------------------------------------------------------------------------------------------


#: Attempt k > 1 of the pretrain runs with seed ``seed + PRETRAIN_SEED_STEP * (k - 1)``, into ``pretrain-<k>/``.
PRETRAIN_SEED_STEP = 10_000


def profile_file(folder: Path) -> Path:
    """The profile the pretrain's simulated rigs are randomised around (the identified rigs')."""
    return folder / "pretrain-profile.json"


def attempt_dir(folder: Path, attempt: int) -> Path:
    """The run folder of pretrain attempt ``attempt`` (1: ``pretrain/``)."""
    return folder / ("pretrain" if attempt == 1 else f"pretrain-{attempt}")


def attempt_seed(seed: int, attempt: int) -> int:
    """The seed of pretrain attempt ``attempt`` of the lab of ``seed``."""
    return seed + PRETRAIN_SEED_STEP * (attempt - 1)


def met_tc(summary: RunSummary | None) -> bool:
    """Whether a pretrain's summary has a worker whose controller met TC."""
    return summary is not None and any(w.solved for w in summary.workers)


def pretrain(s: LabSettings, folder: Path) -> None:
    """A federation in process on rigs randomised around the identified ones, until every worker meets TC; again
    with another seed (``--pretrain-attempts``) when none of its workers did, or none of those that did balanced every
    identified rig in simulation (:func:`validated`): the next attempt's controllers join the choice
    (:func:`warm_start`). Attempts that ended are kept: a resumed pipeline goes on at the first attempt that did not."""
    from services.qube_sim.pretrain import breakaway_share, for_lab
    from services.qube_sim.profile import load_profile

    rigs = [load_profile(path) for path in identified_files(s, folder)]
    profile = for_lab(rigs, s.qube_actions, name=f"around-{len(rigs)}-identified", authority=s.pretrain_authority,
                      ease_in=s.pretrain_ease_in)
    profile_path = profile_file(folder)
    profile_path.write_text(profile.to_json())
    ranges = ", ".join(f"{k} {lo:.3g}-{hi:.3g}" for k, (lo, hi) in profile.ranges.items())
    ceiling, torque = profile.ranges["static_arm"][1], breakaway_share(profile, s.qube_actions)[1]
    say("pretrain", f"randomised around {len(rigs)} identified rigs: {ranges}; the rest +-{profile.randomize:.0%}; "
        f"arm friction at most {ceiling * 1e3:.2f} mN m ({ceiling / torque:.0%} of what the `{s.qube_actions}` "
        f"actions give the median rig at standstill; --pretrain-authority {s.pretrain_authority:g})"
        + (f"; the arm's dry friction eased in over each worker's first {s.pretrain_ease_in} episodes "
           "(--pretrain-ease-in)" if s.pretrain_ease_in else ""))
    env = child_env(TRUTH)
    why, met = "", False
    for attempt in range(1, s.pretrain_attempts + 1):
        run_dir = attempt_dir(folder, attempt)
        summary, code = read_summary(run_dir), None
        if summary is None or summary.end_reason == "interrupted":  # not run yet, or to run again
            if attempt > 1:
                say("pretrain", f"attempt {attempt} of {s.pretrain_attempts}, seed {attempt_seed(s.seed, attempt)}")
            code = run_child("pretrain", pretrain_command(s, folder, attempt), env)
            summary = read_summary(run_dir)
        if summary is not None and met_tc(summary):
            met = True
            solved = sum(w.solved for w in summary.workers)
            if solved < len(summary.workers):  # a controller that met TC exists: the fine-tune starts from it
                say("pretrain", f"{solved} of {len(summary.workers)} workers met TC ({summary.end_reason}); the "
                    "fine-tune starts from one of them")
            pool = validated(s, folder, attempt)
            if not pool or any(holds(c["returns"]) for c in pool):
                return
            say("pretrain", f"attempt {attempt}: no controller that met TC balanced every identified rig"
                + (f"; attempt {attempt + 1} adds its own to the choice" if attempt < s.pretrain_attempts else ""))
            continue
        why = f"attempt {attempt}: {summary.end_reason if summary is not None else f'exit code {code}'}"
        say("pretrain", f"no controller met TC ({why}){how_far(read_metrics(run_dir))}")
    if met:  # the fine-tune starts from the best controller of the attempts that met TC
        return
    last = [c for attempt in range(1, s.pretrain_attempts + 1) for c in validated(s, folder, attempt)]
    most = max((balanced(c["returns"]) for c in last), default=0)
    if most:  # the fine-tune starts from the best last controller (warm_start)
        say("pretrain", f"no controller met TC in {s.pretrain_attempts} attempt{'s' * (s.pretrain_attempts > 1)}; "
            f"the best of the workers' last controllers balanced {most} of {len(identified_files(s, folder))} "
            "identified rigs to the end: the fine-tune starts from it")
        return
    raise StageFailed(f"no pretrain ended with a controller that meets TC ({s.pretrain_attempts} attempts, last "
                      f"{why}), and no worker's last controller balanced an identified rig; try more "
                      "--pretrain-episodes or --pretrain-attempts, or another --seed" + authority_hint(s, folder))


#: A policy entropy (nats) below which a pretrain worker's policy has stopped exploring: pretrains that met TC kept
#: 0.17-0.82 at their 80th episode; at the end of the six attempts of 2026-12-06 that met none (tuning labs 527 and
#: 532, report labs 506 and 508), 14 of their 18 workers were below it (docs/how-to/lab.md).
COLLAPSED = 0.1


def how_far(records: Sequence[AnyRecord]) -> str:
    """What a pretrain that met no TC got to, for its failure line: each worker's best PI and its policy's entropy at
    its last update, naming the workers whose policy collapsed (below COLLAPSED); '' without episodes."""
    best: dict[str, float] = {}
    entropy: dict[str, float] = {}
    for r in records:
        if isinstance(r, EpisodeRecord):
            best[r.worker] = max(best.get(r.worker, -math.inf), r.pi)
            value = (r.stats or {}).get("entropy")
            if value is not None and math.isfinite(value):
                entropy[r.worker] = value
    if not best:
        return ""
    text = "; best PI " + ", ".join(f"{w} {pi:.0f}" for w, pi in sorted(best.items()))
    if entropy:
        last = sorted(entropy.items())
        text += "; policy entropy at the end " + ", ".join(f"{w} {h:.2f}" for w, h in last) + " nats"
        collapsed = [w for w, h in last if h < COLLAPSED]
        if collapsed:
            text += (f" ({', '.join(collapsed)} below {COLLAPSED:g}: a policy that no longer explores, see "
                     "docs/how-to/lab.md, 'When a pretrain misses TC')")
    return text


def pretrain_command(s: LabSettings, folder: Path, attempt: int) -> list[str]:
    """The pretrain's launcher: simulated rigs randomised around the identified ones, each reset computed from the
    drawn plant (as every rig's bridge from its identified profile in the fine-tune)."""
    from services.qube_sim.profile import DRAWN_MODEL

    profile_path = profile_file(folder)
    return [sys.executable, "-m", "deploy.inprocess", "--env", "qube-local", "--workers", str(s.pretrain_workers),
            "--seed", str(attempt_seed(s.seed, attempt)), "--policy", s.policy, "--algo", s.algo, "--max-episodes",
            str(s.pretrain_episodes), "--run-dir", str(attempt_dir(folder, attempt)),
            "--rig-profile", str(profile_path), "--rig-model", DRAWN_MODEL, "--qube-actions", s.qube_actions,
            *set_flags([*s.learner_set, *s.pretrain_set])]


# -- stage 3: fine-tune -------------------------------------------------------------------------------------------


def pretrained(s: LabSettings, folder: Path) -> Path:
    """The model the fine-tune starts from: ``--init-model``, else the one :func:`warm_start` chose among the
    pretrain's workers that met TC."""
    return s.init_model if s.init_model is not None else warm_start(s, folder)


# -- between the pretrain and the fine-tune: which controller the rigs start from -------------------------------------


#: Identified rig i's validation episode runs with seed ``worker_seed(seed, i) + VALIDATION_SEED``: never the seed of a
#: rig of this lab (< 1000 of them) nor of another lab's.
VALIDATION_SEED = 500


def choose(returns: Sequence[Sequence[float]]) -> int:
    """The candidate to start from, given each one's greedy return on each identified rig (rows in the order the
    workers met TC): the one that balances the most rigs to the end, then the largest sum of returns, then the
    first to meet TC."""
    if not returns:
        raise ValueError("no candidate controllers to choose from")
    return min(range(len(returns)),
               key=lambda k: (-balanced(returns[k]), -sum(returns[k]), k))


def choice_file(folder: Path) -> Path:
    """Where the pipeline keeps the warm start it chose and why (``warm_start``)."""
    return folder / "warm-start.json"


def chosen(folder: Path) -> Path | None:
    """The model a pipeline chose to start its fine-tune from (None: it has not chosen, or started from a given
    model)."""
    path = choice_file(folder)
    return Path(json.loads(path.read_text())["model"]) if path.exists() else None


def candidates(run: Path) -> list[Path]:
    """The models of a finished pretrain's workers that met TC, in the order they met it (runtime.model_file.solvers):
    the warm starts to choose from."""
    from runtime.model_file import mature_model, solvers

    summary = read_summary(run)
    order = solvers(summary) if summary is not None else []
    return [m for name in order if (m := mature_model(run / "models", name)).is_file()]


def last_candidates(run: Path) -> list[Path]:
    """The last networks of a finished pretrain's workers that played their episodes without meeting TC, in worker
    order (runtime.model_file.last_model): the warm starts to choose from when no attempt met TC."""
    from runtime.model_file import last_model

    summary = read_summary(run)
    workers = sorted(summary.workers, key=lambda w: w.index) if summary is not None else []
    return [m for w in workers if not w.solved and (m := last_model(run / "models", w.id)).is_file()]


def validation_returns(model: Path, rigs: Sequence[Path], seed: int) -> list[float]:
    """``model``'s greedy return on each identified rig (profile files, in rig order) of the lab of ``seed``: one
    episode each, the rig simulated from its identified profile (never its truth) with its validation seed."""
    import torch

    from worker.evaluate import evaluate

    torch.set_num_threads(1)  # one thread, as every training process
    return [evaluate(model, "qube-local", episodes=1, seed=worker_seed(seed, i) + VALIDATION_SEED,
                     rig_profile=str(rig), rig_model=str(rig)).returns[0] for i, rig in enumerate(rigs)]


def balanced(returns: Sequence[float]) -> int:
    """How many identified rigs a controller balanced to the end, given its return on each."""
    return sum(r >= MAX_RETURN for r in returns)


def holds(returns: Sequence[float]) -> bool:
    """Whether a controller balanced every identified rig to the end."""
    return balanced(returns) == len(returns)


def played(models: Sequence[Path], rigs: Sequence[Path], seed: int, stage: str | None = None) -> list[dict[str, Any]]:
    """Each of ``models`` with its :func:`validation_returns` on ``rigs``: ``[{"model", "returns"}]``, in order, each
    said under ``stage`` as it comes (None: silently)."""
    out = []
    for model in models:
        returns = validation_returns(model, rigs, seed)
        if stage is not None:
            say(stage, f"{model.stem}: balanced {balanced(returns)} of {len(rigs)} identified rigs to the end "
                f"(returns {', '.join(f'{r:.0f}' for r in returns)})")
        out.append({"model": str(model), "returns": returns})
    return out


def validation_file(folder: Path, attempt: int) -> Path:
    """Where pretrain attempt ``attempt``'s candidates and their returns on the identified rigs are kept."""
    return folder / f"validation-{attempt}.json"


def validated(s: LabSettings, folder: Path, attempt: int) -> list[dict[str, Any]]:
    """Pretrain attempt ``attempt``'s candidates (:func:`candidates`; for an attempt none of whose workers met TC,
    :func:`last_candidates`) :func:`played` on the identified rigs, once: kept in :func:`validation_file`."""
    run = attempt_dir(folder, attempt)
    models = candidates(run) or last_candidates(run)
    path = validation_file(folder, attempt)
    if path.exists():
        kept: list[dict[str, Any]] = json.loads(path.read_text())["candidates"]
        if [c["model"] for c in kept] == [str(m) for m in models]:
            return kept
    rigs = identified_files(s, folder)
    if models:
        kind = "that met TC" if met_tc(read_summary(run)) else "last of workers that did not meet TC"
        say("pretrain", f"attempt {attempt}: {len(models)} controller{'s' * (len(models) > 1)} {kind}, one "
            f"greedy episode each on the {len(rigs)} identified rigs (simulated)")
    out = played(models, rigs, s.seed, "pretrain")
    path.write_text(json.dumps({"rigs": [str(r) for r in rigs], "candidates": out}, indent=2) + "\n")
    return out


def warm_start(s: LabSettings, folder: Path) -> Path:
    """The pretrain's controller the rigs start from. Every worker of every pretrain attempt that met TC has one
    (:func:`candidates`); each played one greedy episode on each identified rig (:func:`validated`), and the one
    :func:`choose` takes wins. The first to meet TC (the run folder's model) may have met it on a lucky streak of
    draws. When no attempt met TC (and ``pretrain`` went on, because one of them balanced an identified rig), the
    candidates are the workers' last controllers (:func:`last_candidates`). Chosen once: ``warm-start.json`` keeps the
    candidates, their returns and the choice."""
    from runtime.model_file import ModelFileError, resolve

    kept = chosen(folder)
    if kept is not None:
        return kept
    attempts = range(1, s.pretrain_attempts + 1)
    met = [a for a in attempts if met_tc(read_summary(attempt_dir(folder, a)))]
    pool = [c for attempt in met or attempts for c in validated(s, folder, attempt)]  # none met TC: the last ones
    if not pool:
        try:
            return resolve(pretrain_dir(folder))  # no model to compare: the run folder's own answer (or its error)
        except ModelFileError as err:
            raise StageFailed(str(err)) from None
    best = choose([c["returns"] for c in pool])
    model = Path(pool[best]["model"])

    def name(m: str | Path) -> str:  # <attempt's run folder>/<worker>
        return f"{Path(m).parent.parent.name}/{Path(m).stem}"

    say("finetune", f"the rigs start from {name(model)}" + (
        " (the last controller of a worker that did not meet TC)" if not met
        else "" if best == 0 else f" (the first to meet TC was {name(pool[0]['model'])})"))
    choice_file(folder).write_text(json.dumps({
        "model": str(model), "chosen": best, "rigs": [str(r) for r in identified_files(s, folder)],
        "candidates": pool}, indent=2) + "\n")
    return model


def pretrain_dir(folder: Path) -> Path:
    """The run folder of a pipeline's pretrain: its first attempt with a worker that met TC (else ``pretrain/``)."""
    return attempt_dir(folder, pretrain_met(folder) or 1)


def pretrain_met(folder: Path) -> int | None:
    """The first pretrain attempt with a worker that met TC (None: none has one)."""
    for attempt in range(1, MAX_ATTEMPTS + 1):
        if met_tc(read_summary(attempt_dir(folder, attempt))):
            return attempt
    return None


def finetune_command(s: LabSettings, folder: Path) -> list[str]:
    command = [sys.executable, "-m", "deploy.run_local", "--env", s.env, "--workers", str(s.workers), "--seed",
               str(s.seed), "--policy", s.policy, "--algo", s.algo, "--max-episodes", str(s.max_episodes),
               "--run-id", f"lab-s{s.seed}", "--run-dir", str(folder / "finetune"), "--init-model",
               str(pretrained(s, folder)), "--warm-lr", str(s.warm_lr), "--warm-temperature",
               str(s.warm_temperature), "--rig-model", str(folder / "identified"),
               "--qube-actions", s.qube_actions, "--qube-clock", s.qube_clock, "--dashboard-port", "off",
               *set_flags(s.learner_set)]
    return command + (["--broker", s.broker, "--no-simulate-rigs"] if s.broker else [])


def finetune(s: LabSettings, folder: Path) -> None:
    code = run_child("finetune", finetune_command(s, folder), child_env())
    summary = read_summary(folder / "finetune")
    if summary is None or summary.end_reason == "interrupted":
        raise StageFailed(f"the fine-tune did not end (exit code {code}); the same command resumes it")


# -- the report ---------------------------------------------------------------------------------------------------


def read_summary(run_dir: Path) -> RunSummary | None:
    return RunSummary.read(run_dir) if (run_dir / SUMMARY).exists() else None


def report(s: LabSettings, folder: Path, progress: dict[str, Any]) -> list[dict[str, Any]]:
    """Per rig: identification, balance, reset and idle seconds and the fine-tune's episodes; identify_s goes into
    the fine-tune's summary.json beside rig_s."""
    from services.qube_sim.profile import load_profile

    summary = RunSummary.read(folder / "finetune")
    rows: list[dict[str, Any]] = []
    identified: dict[str, float] = {}
    for i, path in enumerate(identified_files(s, folder)):
        record = load_profile(path).identified
        identify_s = record.rig_seconds if record is not None else 0.0
        worker = next((w for w in summary.workers if w.id == f"w{i}"), None)
        rig = worker.rig if worker is not None else None
        rows.append({"rig": f"rig{i}", "worker": f"w{i}", "identify_s": round(identify_s, 1),
                     "balance_s": rig.balance_s if rig else None, "reset_s": rig.reset_s if rig else None,
                     "idle_s": rig.idle_s if rig else None, "rig_s": rig.rig_s if rig else None,
                     "episodes": worker.episodes if worker else None, "solved": worker.solved if worker else False})
        identified[f"w{i}"] = round(identify_s, 3)
    workers = [w.model_copy(update={"rig": w.rig.model_copy(update={"identify_s": identified[w.id]})})
               if w.rig is not None and w.id in identified else w for w in summary.workers]
    summary.model_copy(update={"workers": workers}).write(folder / "finetune")
    progress["rigs"] = rows
    print(f"\n{'rig':<6}{'solved':>7}{'episodes':>9}{'identify s':>11}{'balance s':>10}{'reset s':>9}{'idle s':>8}"
          f"{'rig min':>8}")
    for r in rows:
        minutes = ((r["rig_s"] or 0.0) + r["identify_s"]) / 60
        print(f"{r['rig']:<6}{'yes' if r['solved'] else 'no':>7}{r['episodes'] or '-':>9}{r['identify_s']:>11.1f}"
              f"{r['balance_s'] or 0:>10.1f}{r['reset_s'] or 0:>9.1f}{r['idle_s'] or 0:>8.1f}{minutes:>8.2f}")
    print(f"(rig min: identification + balance + reset; the fine-tune's run folder: {folder / 'finetune'})")
    return rows


@returns_code
def main(argv: list[str] | None = None) -> int:
    s = LabSettings.load(argv, prog="python -m deploy.lab", description=__doc__.splitlines()[0])
    folder = s.folder()
    folder.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    try:
        progress = load_progress(folder)
        progress["settings"] = s.model_dump(mode="json", exclude={"run_dir"})
        for name, stage in (("identify", identify), ("pretrain", pretrain), ("finetune", finetune)):
            if name in progress["done"]:
                say(name, "done before: skipped")
                continue
            if name == "pretrain" and s.init_model is not None:
                say(name, f"skipped: the fine-tune starts from {s.init_model} (--init-model)")
                continue
            say(name, f"stage {STAGES.index(name) + 1} of {len(STAGES)}")
            stage(s, folder)
            progress["done"].append(name)
            save_progress(folder, progress)
        report(s, folder, progress)
        progress["wall_s"] = round(progress.get("wall_s", 0.0) + time.monotonic() - t0, 1)
        save_progress(folder, progress)
    except StageFailed as err:
        print(f"python -m deploy.lab: {err}; the same command resumes at this stage (folder {folder})",
              file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"\ninterrupted; the same command with --run-dir {folder} resumes at the stage it stopped in",
              file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
