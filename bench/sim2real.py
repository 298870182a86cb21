"""``python -m bench.sim2real``: what a simulator pretrain saves a lab in rig time (the sim-to-real table).

The setting: 3 rigs drawn from the ``lab`` rig profile (services/qube_sim/profile.py), on report seeds never used
for tuning, learning the QUBE-Servo 2 balance task in process (``qube-local``: the same services, physics and bridge
code as over MQTT, lockstep clock, rig time from the simulated clock). Compared, per report seed:

- ``scratch``: the rigs learn from nothing;
- ``ideal``: warm-started (``--init-model``) from a federation pretrained on ``ideal`` rigs;
- ``randomised``: warm-started from a federation pretrained on ``lab`` rigs whose parameters are drawn afresh at each
  reset (``--randomize``);
- and each pretrained model zero-shot, before any fine-tuning: balanced to the end or not on held-out ``lab`` rigs
  (worker/evaluate.py's robustness test without disturbances), and the fine-tuned controllers under the disturbances.

Each pretrain runs once, on a tuning seed (PRETRAIN_SEED). Reported for the last rig (runtime.records.LastRig):
episodes, balance steps, rig minutes (balance + reset), idle minutes and wall minutes, as median [IQR] with unfinished
runs counted as worse (bench.stats.spread_censored), against the targets of the rig-time issue. A rig whose swing-up
reset fails five times in a row stops its worker, as a real rig's would (worker/qube_env.py); its run then ends
unfinished, and the report names it with its end reason. Results:
``<out>/sim2real.json``; run folders under ``<runs-dir>``. ``--quick`` is a smoke-sized variant (one seed, small caps)
that checks the pipeline, not the figures.

``python -m bench.sim2real ood ...``: the out-of-distribution sweep, rigs off ``lab`` one parameter at a time, with
and without identification (bench/ood.py).
"""

from __future__ import annotations

import argparse
import datetime as dt
import functools
import json
import os
import platform
import re
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench import stats
from bench.runs import process_pool
from protocol.qube import ACTION_SETS, DEFAULT_ACTIONS
from runtime.records import SUMMARY, EpisodeRecord, RoundRecord, RunSummary, read_metrics

TASK = "qube-local"
POLICY = "plain"  # the QUBE's best strategy in bench/results/paper.json (plain 108 episodes, weighted 128, sync 131)
ALGO = "ppo"
#: The simulated clocks the fine-tuning runs on: lockstep, and delayed (the real loop's delays and lost actions).
CLOCKS = ("lockstep", "delayed")
RIGS = 3
#: Report seeds (never used for tuning) and the pretrain's tuning seed.
REPORT_SEEDS = tuple(range(101, 111))
PRETRAIN_SEED = 1
#: Domain randomisation of the ``randomised`` pretrain: each parameter drawn within +-this fraction at each reset.
RANDOMIZE = 0.2
HELD_OUT_SEED = 900_000  # held-out zero-shot rigs: seeds 900000.. (the report runs' rigs are seed*1000 + i)
HELD_OUT_RIGS = 10
DISTURBED_TRIALS = 10
DEFAULT_M = 600
PRETRAIN_M = 600
#: The rig-time issue's targets, for the last of 3 rigs, median over the report seeds.
TARGETS: dict[str, dict[str, float]] = {
    "randomised": {"episodes": 12, "balance_steps": 30_000, "rig_min": 4.0, "rig_wall_ratio": 1.25},
    "scratch": {"balance_steps": 34_000},
}
PRETRAINS: dict[str, dict[str, Any]] = {
    "ideal": {"rig_profile": "ideal"},
    "randomised": {"rig_profile": "lab", "randomize": RANDOMIZE},
}
QUICK: dict[str, Any] = {"seeds": (101,), "max_episodes": 6, "pretrain_episodes": 6, "held_out": 2, "trials": 1}


#: The settings compared, in the table's order: from scratch, then each pretrain's warm start.
SETTINGS = ("scratch", *PRETRAINS)


@dataclass(frozen=True)
class Setup:
    """What every federation of one invocation shares: the learner, the federation strategy and the QUBE's action
    set (protocol/qube.py ACTION_SETS)."""

    algo: str = ALGO
    policy: str = POLICY
    qube_actions: str = DEFAULT_ACTIONS

    @property
    def paper_actions(self) -> bool:
        """Whether the rigs act with the paper's three actions, the only set the robustness trials test
        (worker/evaluate.py)."""
        return self.qube_actions == DEFAULT_ACTIONS

    def results_name(self, quick: bool) -> str:
        """The results file of this setup: sim2real.json for the default (PPO, plain, the paper's actions), else
        named by what differs, so that a run with another learner or action set never overwrites the table's."""
        parts = [] if self == Setup() else [self.algo, self.policy, self.qube_actions]
        return "-".join(["sim2real", *parts] + (["quick"] if quick else [])) + ".json"


def federate(run_dir: Path, seed: int, max_episodes: int, env_options: dict[str, Any],
             init_model: Path | None = None, setup: Setup = Setup()) -> RunSummary:
    """One in-process federation of RIGS rigs in ``run_dir``; its summary (reuses a finished run)."""
    if (run_dir / SUMMARY).exists():
        return RunSummary.read(run_dir)
    from deploy.inprocess import run_federation
    from deploy.settings import InprocessSettings

    run_dir.mkdir(parents=True, exist_ok=True)
    return run_federation(InprocessSettings.given(env=TASK, policy=setup.policy, seed=seed, workers=RIGS,
                          max_episodes=max_episodes, run_dir=run_dir, **env_options, init_model=init_model,
                          algo=setup.algo, qube_actions=setup.qube_actions), plot=False, tensorboard_files=False,
                          tolerate_failures=True)


def last_rig(summary: RunSummary, run_dir: Path) -> dict[str, Any]:
    """The figures the table reports for a run's last rig (None where the run did not finish)."""
    rig = summary.last_rig
    solved = summary.episodes_to_all_solved is not None
    done = rig if solved else None
    return {"finished": solved, "episodes": summary.episodes_to_all_solved,
            "balance_steps": done.balance_steps if done else None,
            "rig_min": round(done.rig_s / 60, 3) if done else None,
            "balance_min": round(done.balance_s / 60, 3) if done else None,
            "reset_min": round(done.reset_s / 60, 3) if done else None,
            "idle_min": round(rig.idle_s / 60, 3) if rig else None,
            "wall_min": round((summary.wall_s or 0.0) / 60, 3), "run_dir": str(run_dir),
            "rig_wall_ratio": rig_wall_ratio(summary) if solved else None,
            "end_reason": summary.end_reason,
            "unsolved": {w.id: w.state + (f": {w.detail}" if w.detail else "") for w in summary.workers
                         if not w.solved}}


def rig_wall_ratio(summary: RunSummary) -> float | None:
    """Wall-clock on real rigs over the slowest rig's rig time: the run lasts until its last rig is done, which is
    its rig time plus the idle time it waited for the federation (summary.json ``last_rig``), against the most rig
    time any rig spent. Under a simulated clock the idle time is modelled (protocol/rigtime.py); the learners'
    compute between episodes is not in it."""
    rigs = [w.rig.rig_s for w in summary.workers if w.rig]
    last = summary.last_rig
    if not rigs or not last or not max(rigs) > 0:
        return None
    return round((last.rig_s + last.idle_s) / max(rigs), 3)


def zero_shot(model: Path, rigs: int, disturbed: bool, seed: int = HELD_OUT_SEED) -> dict[str, Any]:
    """Balanced to the end on ``rigs`` held-out lab rigs from ``seed`` on: undisturbed (zero-shot) or in the
    robustness trial (worker/robustness.py: pulses within the controller's authority, then the sweep)."""
    from worker import robustness as rb
    from worker.evaluate import robustness

    d = rb.Disturbances() if disturbed else rb.Disturbances(pulse_ms=0, sensor_noise_counts=0)
    result = robustness(model, TASK, "lab", rigs, seed=seed, disturbances=d)
    return {"model": str(model), "rigs": rigs, "seed": seed, "balanced_to_end": result.summary["balanced_to_end"],
            "median_balance_s": result.summary["median_balance_s"],
            "largest_pulse_of_stall": result.summary["median_largest_pulse_of_stall"]}


def lqr_action(obs: Any) -> int:
    """The reference controller: the bridge's balance LQR (rpi_bridge/reset.py, what holds the pendulum after a
    swing-up) restricted to the task's actions as bang-bang, the sign of its command (worker/qube_env.py ACTIONS).
    The nearest action instead leaves a dead band of +-30 counts in which it does nothing: on the trials' rigs it
    balanced to the end on none of 10, a median of 1.1 s (the first pulse comes at 1 s)."""
    from worker.qube_env import ACTIONS

    alpha, alpha_dot, theta, theta_dot = (float(v) for v in obs)
    u = _bridge_lqr().hold_command(theta, alpha, theta_dot, alpha_dot)
    return ACTIONS.index(60 if u > 0 else -60 if u < 0 else 0)


@functools.cache
def _bridge_lqr() -> Any:
    """The bridge's reset controller with its default configuration, made once (its hold command keeps no state)."""
    from rpi_bridge.reset import ResetController

    return ResetController()


def reference_trials(rigs: int) -> dict[str, Any]:
    """The robustness trial of the reference controller on the disturbed trials' held-out rigs (one each): what a
    hand-designed controller with the same three actions survives."""
    from services.qube_sim.profile import load_profile
    from worker import robustness as rb

    results = [rb.run_rig(lqr_action, load_profile("lab"), i, HELD_OUT_SEED + HELD_OUT_RIGS + i, rb.Disturbances())
               for i in range(rigs)]
    return {"controller": "bridge LQR, sign of its command", **rb.summary(results)}


def pretrain(name: str, runs_dir: Path, max_episodes: int, setup: Setup) -> dict[str, Any]:
    """The ``name`` pretrain's federation (lockstep); its model is that of the first rig to solve
    (runtime.model_file)."""
    folder = runs_dir / f"pretrain-{name}"
    summary = federate(folder, PRETRAIN_SEED, max_episodes, PRETRAINS[name], setup=setup)
    return {"name": name, **last_rig(summary, folder), "options": PRETRAINS[name], "seed": PRETRAIN_SEED}


def _job(setting: str, seed: int, clock: str, runs_dir: Path, max_episodes: int, model: str | None,
         setup: Setup) -> dict[str, Any]:
    import torch

    torch.set_num_threads(1)
    options = {"rig_profile": "lab", **({"qube_clock": clock} if clock != "lockstep" else {})}
    folder = runs_dir / clock / f"{setting}-s{seed}"
    summary = federate(folder, seed, max_episodes, options, Path(model) if model else None, setup)
    return {"setting": setting, "seed": seed, "clock": clock, **last_rig(summary, folder)}


def fine_tune(models: dict[str, str | None], seeds: list[int], clocks: list[str], runs_dir: Path,
              max_episodes: int, jobs: int, setup: Setup) -> list[dict[str, Any]]:
    """Every setting on every report seed and clock, ``jobs`` at a time (each single-threaded)."""
    work = [(clock, setting, seed) for clock in clocks for seed in seeds for setting in models]
    with process_pool(jobs) as pool:
        futures = [pool.submit(_job, setting, seed, clock, runs_dir, max_episodes, models[setting], setup)
                   for clock, setting, seed in work]
        out = []
        for (clock, setting, seed), fut in zip(work, futures, strict=True):
            out.append(fut.result())
            r = out[-1]
            print(f"{clock:8s} {setting:10s} seed {seed}: " + (
                f"last rig at episode {r['episodes']}, {r['balance_steps']} balance steps, {r['rig_min']} rig min"
                if r["finished"] else "not finished"), flush=True)
    return out


def realtime(seed: int, model: str, runs_dir: Path, max_episodes: int, setup: Setup) -> dict[str, Any]:
    """A warm-started federation of RIGS simulated ``lab`` rigs over MQTT in real time (``deploy.run_local --env qube
    --qube-clock realtime``: the bridge's 7 ms loop, the real swing-ups, the learners' updates between episodes, the
    rounds over the broker), where the wall-clock and every rig's time are measured: the wall-clock target's figure.
    Reuses a finished run."""
    run_dir = runs_dir / "realtime" / f"randomised-s{seed}"
    if not (run_dir / SUMMARY).exists():
        command = [sys.executable, "-m", "deploy.run_local", "--env", "qube", "--qube-clock", "realtime",
                   "--workers", str(RIGS), "--seed", str(seed), "--policy", setup.policy, "--algo", setup.algo,
                   "--qube-actions", setup.qube_actions,
                   "--max-episodes", str(max_episodes), "--init-model", model, "--run-dir", str(run_dir),
                   "--dashboard-port", "off"]
        print(" ".join(command), flush=True)
        subprocess.run(command, env={**os.environ, "FEDRL_RIG_PROFILE": "lab"}, check=False,
                       stdout=subprocess.DEVNULL)
    summary = RunSummary.read(run_dir)
    wall = measured_wall(run_dir)
    slowest = max((w.rig.rig_s for w in summary.workers if w.rig), default=0.0)
    return {"seed": seed, **last_rig(summary, run_dir), "measured_wall_min": wall,
            "slowest_rig_min": round(slowest / 60, 3), "missed_actions": missed_actions(run_dir),
            "measured_ratio": round(wall * 60 / slowest, 3) if wall and slowest > 0 else None}


def missed_actions(run_dir: Path) -> float | None:
    """The share of control periods whose action came too late over all rigs, from each simulated rig's last
    periodic report in its log (rpi_bridge/runner.py: "<ticks> ticks, <misses> misses"): the machine's load shows
    there, against the ``lab`` profile's loop_miss_rate."""
    ticks = misses = 0
    for log in sorted((run_dir / "logs").glob("qube-sim-*.log")):
        found = re.findall(r"(\d+) ticks, (\d+) misses", log.read_text())
        if found:
            ticks, misses = ticks + int(found[-1][0]), misses + int(found[-1][1])
    return round(misses / ticks, 4) if ticks else None


def measured_wall(run_dir: Path) -> float | None:
    """Minutes from the first rig's first swing-up to the run's last round (metrics.jsonl: each record's chief time
    ``t``; a worker's first episode began its reset and balance seconds before its record)."""
    starts, end = [], None
    seen: set[str] = set()
    for rec in read_metrics(run_dir):
        if isinstance(rec, EpisodeRecord) and rec.worker not in seen and rec.reset_s is not None:
            seen.add(rec.worker)
            starts.append(rec.t - rec.reset_s - (rec.balance_s or 0.0))
        if isinstance(rec, (EpisodeRecord, RoundRecord)):
            end = rec.t
    return round((end - min(starts)) / 60, 3) if starts and end is not None else None


def table(runs: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per setting: median [IQR] of the last rig's figures (unfinished runs count as worse) and the targets met."""
    out: dict[str, dict[str, Any]] = {}
    for setting in dict.fromkeys(r["setting"] for r in runs):
        rows = [r for r in runs if r["setting"] == setting]
        cells = {key: stats.spread_censored([r.get(key) for r in rows])
                 for key in ("episodes", "balance_steps", "rig_min", "rig_wall_ratio")}
        cells["wall_min"] = stats.spread([r["wall_min"] for r in rows])
        cells["idle_min"] = stats.spread([r["idle_min"] or 0.0 for r in rows])
        met = {k: _at_most(cells[k]["median"], v) for k, v in TARGETS.get(setting, {}).items()}
        out[setting] = {"runs": len(rows), "finished": sum(r["finished"] for r in rows), **cells, "targets_met": met}
    return out


def _at_most(value: float | int | None, target: float) -> bool:
    return value is not None and value <= target


BEGIN = "<!-- sim2real:begin (generated by python -m bench.sim2real --report; do not edit) -->"
END = "<!-- sim2real:end -->"
LABELS = {"scratch": "from scratch", "ideal": "warm start: `ideal` pretrain",
          "randomised": f"warm start: randomised pretrain (`lab`, +-{RANDOMIZE:.0%})"}


def _cell(s: dict[str, Any], digits: int = 0) -> str:
    """median [q1-q3] of a spread whose unfinished runs count as worse: a statistic that falls on one is 'unfinished',
    and a median that does says how many runs did not finish."""
    def num(v: float | None) -> str:
        if v is None:
            return "unfinished"
        return f"{v:,.{digits if digits or v == round(v) else 1}f}"  # a median between two counts keeps its .5
    if s["median"] is None:
        return f"not reached ({s.get('unfinished', 0)} of {s['n']} runs unfinished)"
    return f"{num(s['median'])} [{num(s['q1'])} to {num(s['q3'])}]"


def report(result: dict[str, Any], source: str) -> str:
    """The sim-to-real tables (markdown) of a sim2real.json: per clock and setting, the last of 3 lab rigs, median
    [IQR]."""
    cfg = result["config"]
    actions = cfg.get("qube_actions", DEFAULT_ACTIONS)
    named = "" if actions == DEFAULT_ACTIONS else f", action set `{actions}`"
    lines = [f"Last of {cfg['rigs']} `lab` rigs per run, learner `{cfg.get('algo', 'ppo')}`, `{cfg['policy']}`{named}, "
             f"report seeds {cfg['seeds'][0]}-{cfg['seeds'][-1]} ({len(cfg['seeds'])} runs per setting), median [IQR], "
             f"unfinished runs counted as worse; pretrains on tuning seed {cfg['pretrain_seed']}; rig time from the "
             f"simulated clock; generated from `{source}` ({cfg['date']}, {cfg['cores']} cores, load average "
             f"{cfg['load_average'][0]:.1f} at the start, {result['wall_s'] / 60:.0f} min for the runs this "
             "invocation made: it reuses finished runs' folders)."]
    for clock, rows in _tables(result).items():
        lines += ["", f"**Clock `{clock}`**" + (" (the real loop's delays and lost actions)" if clock == "delayed"
                                                 else ""), "", *_table_lines(rows)]
        saved = _saving(rows)
        if saved:
            lines += ["", saved]
    lines.append("")
    for name, p in result["pretrains"].items():
        shot = result["zero_shot"].get(name)
        split = (f": {p['balance_min']:.1f} balancing, {p['reset_min']:.1f} in swing-up resets"
                 if p.get("balance_min") is not None else "")
        made = (f"finished at episode {p['episodes']}, its last rig after {p['rig_min']:.1f} rig minutes{split} "
                f"({p['wall_min']:.1f} wall minutes here)" if p["finished"] else "did not finish: no model")
        zero = (f"zero-shot: balanced to the end on {shot['balanced_to_end']} of {shot['rigs']} unseen `lab` rigs "
                "(in distribution)"
                if shot else "no zero-shot test")
        lines.append(f"- `{name}` pretrain: {made}; {zero}.")
    for r in result.get("runs", []):
        if not r["finished"]:
            rigs = ", ".join(f"{w} {state}" for w, state in (r.get("unsolved") or {}).items())
            lines.append(f"- Unfinished: {LABELS.get(r['setting'], r['setting'])}, "
                         f"{r.get('clock', 'lockstep')} clock, seed {r['seed']}: "
                         f"{r.get('end_reason') or 'no end reason recorded'}" + (f" ({rigs})" if rigs else "") + ".")
    live = [r for r in result.get("realtime", []) if r["finished"] and r.get("measured_ratio")]
    if result.get("realtime"):
        ratios = sorted(r["measured_ratio"] for r in live)
        lines.append(f"- Measured in real time over MQTT (`deploy.run_local --env qube --qube-clock realtime`, the "
                     f"randomised warm start, seeds {', '.join(str(r['seed']) for r in result['realtime'])}): "
                     f"{len(live)} of {len(result['realtime'])} finished"
                     + (f"; wall-clock over the slowest rig's rig time {ratios[len(ratios) // 2]:.2f} (median; "
                        f"{ratios[0]:.2f} to {ratios[-1]:.2f})" if ratios else "") + "; last rig per seed: "
                     + "; ".join(_live(r) for r in result["realtime"]) + ".")
    trials = result["disturbed_trials"]
    if trials:
        pulses = sorted(t["largest_pulse_of_stall"] for t in trials if "largest_pulse_of_stall" in t)
        lines.append(f"- Fine-tuned controllers (randomised warm start, one per report seed, each on its own unseen "
                     f"rig) in the robustness trial (pulses up to the controller's authority, 15 % of stall): "
                     f"{sum(t['balanced_to_end'] for t in trials)} of {sum(t['rigs'] for t in trials)} balanced to "
                     "the end" + (f"; in the sweep on to 30 % of stall the median largest pulse survived was "
                                  f"{pulses[len(pulses) // 2]:.0%} of stall" if pulses else "") + ".")
    ref = result.get("reference_trials")
    if ref:
        lines.append(f"- For comparison, the bridge's balance LQR restricted to the same three actions on the same "
                     f"unseen rigs: {ref['balanced_to_end']} of {ref['rigs']} balanced to the end in the trial; "
                     f"median largest pulse survived in the sweep {ref['median_largest_pulse_of_stall']:.0%} of "
                     "stall.")
    return "\n".join(lines)


def _live(r: dict[str, Any]) -> str:
    """One real-time run's last rig, and the share of its rigs' actions that came too late."""
    rig = (f"episode {r['episodes']}, {r['balance_steps']:,} balance steps, {r['rig_min']:.1f} rig min"
           if r["finished"] else "unfinished")
    late = f", {r['missed_actions']:.1%} of actions late" if r.get("missed_actions") is not None else ""
    return f"{r['seed']}: {rig}{late}"


def _tables(result: dict[str, Any]) -> dict[str, dict[str, dict[str, Any]]]:
    """The tables by clock (a result of before clocks has one ``table``, lockstep)."""
    return result.get("tables") or {"lockstep": result["table"]}


def _table_lines(rows: dict[str, dict[str, Any]]) -> list[str]:
    out = ["| setting | finished | episodes | balance steps | rig minutes (balance + reset) | idle minutes | "
           "wall on real rigs / slowest rig time | wall minutes here | targets |",
           "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for setting, row in rows.items():
        met = ", ".join(f"{k} {'met' if ok else '**missed**'}" for k, ok in row["targets_met"].items()) or "-"
        ratio = _cell(row["rig_wall_ratio"], 2) if "rig_wall_ratio" in row else "-"
        out.append(f"| {LABELS.get(setting, setting)} | {row['finished']}/{row['runs']} | {_cell(row['episodes'])} | "
                   f"{_cell(row['balance_steps'])} | {_cell(row['rig_min'], 1)} | {_cell(row['idle_min'], 1)} | "
                   f"{ratio} | {_cell(row['wall_min'], 1)} | {met} |")
    return out


def _saving(table: dict[str, dict[str, Any]]) -> str | None:
    """What the randomised warm start saves against learning from scratch, in median rig minutes of the last rig."""
    scratch, warm = (table.get(k, {}).get("rig_min", {}).get("median") for k in ("scratch", "randomised"))
    if scratch is None or warm is None:
        return None
    return (f"- What the randomised pretrain saves: the last rig's median rig time falls from {scratch:.1f} minutes "
            f"from scratch to {warm:.1f} warm-started ({warm / scratch:.0%}).")


def write_report(json_path: Path, pages: list[Path]) -> None:
    """Replace the BEGIN..END block of each page with the table of ``json_path``."""
    block = report(json.loads(json_path.read_text()), str(json_path))
    for page in pages:
        text = page.read_text()
        if BEGIN not in text or END not in text:
            raise SystemExit(f"{page} has no {BEGIN!r} ... {END!r} block")
        head, rest = text.split(BEGIN, 1)
        page.write_text(head + BEGIN + "\n" + block + "\n" + END + rest.split(END, 1)[1])
        print(f"wrote the sim-to-real table into {page}")


def main(argv: list[str] | None = None) -> int:
    given = sys.argv[1:] if argv is None else argv
    if given[:1] == ["ood"]:  # the out-of-distribution sweep (bench/ood.py)
        from bench import ood

        return ood.main(given[1:])
    args = parse(argv)
    if args.report:
        write_report(args.out / "sim2real.json", [Path("docs/how-to/warm-start.md")])
        return 0
    start = time.monotonic()
    setup = Setup(args.algo, args.policy, args.qube_actions)
    pre = {name: pretrain(name, args.runs_dir, args.pretrain_episodes, setup)
           for name in PRETRAINS if name in args.settings}
    models: dict[str, str | None] = {"scratch": None} if "scratch" in args.settings else {}
    for name, p in pre.items():
        if p["finished"]:
            models[name] = p["run_dir"]  # a run folder: the model of its first rig to solve
        else:
            print(f"!! the {name} pretrain did not finish within {args.pretrain_episodes} episodes: no model",
                  flush=True)
    trials = setup.paper_actions  # the robustness trials test the paper's actions only
    if not trials:
        print(f"the zero-shot and disturbed trials test the paper's actions only: none with {setup.qube_actions}",
              flush=True)
    shots = {name: zero_shot(Path(p["run_dir"]) / "models" / _first(p), args.held_out, disturbed=False)
             for name, p in pre.items() if p["finished"] and trials}
    runs = fine_tune(models, args.seeds, args.clocks, args.runs_dir, args.max_episodes, args.jobs, setup)
    tuned = [r for r in runs if r["setting"] == "randomised" and r["clock"] == args.clocks[0] and r["finished"]]
    disturbed = [zero_shot(Path(r["run_dir"]) / "models" / _first_of(r["run_dir"]), 1, disturbed=True,
                           seed=HELD_OUT_SEED + HELD_OUT_RIGS + i)
                 for i, r in enumerate(tuned[:args.trials] if trials else [])]
    reference = reference_trials(len(disturbed) or args.trials) if trials else None
    tables = {clock: table([r for r in runs if r["clock"] == clock]) for clock in args.clocks}
    warm = models.get("randomised")
    live = [realtime(seed, warm, args.runs_dir, args.max_episodes, setup) for seed in args.realtime] if warm else []
    result = {"config": config(args), "pretrains": pre, "zero_shot": shots, "runs": runs, "tables": tables,
              "disturbed_trials": disturbed, "reference_trials": reference, "realtime": live,
              "wall_s": round(time.monotonic() - start, 1)}
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / setup.results_name(args.quick)
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(f"results in {path}")
    return 0


def _first(p: dict[str, Any]) -> str:
    return _first_of(p["run_dir"])


def _first_of(run_dir: str) -> str:
    """models/<id>.pt of the run's first worker to solve."""
    solved = [w for w in RunSummary.read(Path(run_dir)).workers if w.solved]
    return f"{min(solved, key=lambda w: (w.episodes, w.index)).id}.pt"


def config(args: argparse.Namespace) -> dict[str, Any]:
    return {"task": TASK, "policy": args.policy, "algo": args.algo, "qube_actions": args.qube_actions,
            "settings": args.settings, "clocks": args.clocks, "rigs": RIGS,
            "seeds": args.seeds, "max_episodes": args.max_episodes,
            "pretrain_seed": PRETRAIN_SEED, "pretrain_episodes": args.pretrain_episodes, "randomize": RANDOMIZE,
            "held_out_rigs": args.held_out, "quick": args.quick, "jobs": args.jobs,
            "date": dt.date.today().isoformat(), "python": platform.python_version(), "cores": os.cpu_count(),
            "load_average": os.getloadavg(), "targets": TARGETS, "realtime_seeds": args.realtime}


def parse(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m bench.sim2real", description=__doc__.splitlines()[0],
                                     epilog="python -m bench.sim2real ood --help: the out-of-distribution sweep "
                                     "(bench/ood.py)")
    parser.add_argument("--quick", action="store_true", help="one seed, small caps: checks the pipeline only")
    parser.add_argument("--report", action="store_true", help="write the table of <out>/sim2real.json into "
                        "docs/how-to/warm-start.md (runs nothing)")
    parser.add_argument("--seeds", nargs="+", type=int, help="report seeds (default 101-110)")
    parser.add_argument("--clocks", nargs="+", choices=CLOCKS, default=list(CLOCKS),
                        help="the fine-tuning runs' simulated clocks (default: both; the disturbed trials take the "
                        "first's controllers)")
    parser.add_argument("--realtime", nargs="*", type=int, default=[], metavar="SEED",
                        help="also run the randomised warm start over MQTT in real time on these report seeds, one at "
                        "a time, where the wall-clock is measured (minutes each; best on a quiet machine)")
    parser.add_argument("--algo", default=ALGO, help=f"the learner of every federation (default {ALGO})")
    parser.add_argument("--policy", default=POLICY, help=f"the federation strategy (default {POLICY})")
    parser.add_argument("--qube-actions", choices=list(ACTION_SETS), default=DEFAULT_ACTIONS,
                        help="the QUBE's action set of every federation (docs/explanation/qube-actions.md; default "
                        f"{DEFAULT_ACTIONS}); another set's results go to their own file, without robustness trials")
    parser.add_argument("--settings", nargs="+", choices=SETTINGS, default=list(SETTINGS),
                        help="the settings to run (default all; a warm start runs its pretrain)")
    parser.add_argument("--max-episodes", type=int, help=f"episode cap of a fine-tuning run (default {DEFAULT_M})")
    parser.add_argument("--pretrain-episodes", type=int, help=f"episode cap of a pretrain (default {PRETRAIN_M})")
    parser.add_argument("--held-out", type=int, help="unseen lab rigs (new seeds, in the pretrain's distribution) for "
                        f"zero-shot (default {HELD_OUT_RIGS})")
    parser.add_argument("--trials", type=int, help=f"disturbed trials (default {DISTURBED_TRIALS})")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="runs at a time (default: cores)")
    parser.add_argument("--out", type=Path, default=Path("bench/results"), help="results folder")
    parser.add_argument("--runs-dir", type=Path, help="run folders (default bench/results/runs/sim2real[-quick])")
    args = parser.parse_args(argv)
    q = args.quick
    args.seeds = args.seeds or list(QUICK["seeds"] if q else REPORT_SEEDS)
    args.max_episodes = args.max_episodes or (QUICK["max_episodes"] if q else DEFAULT_M)
    args.pretrain_episodes = args.pretrain_episodes or (QUICK["pretrain_episodes"] if q else PRETRAIN_M)
    args.held_out = args.held_out or (QUICK["held_out"] if q else HELD_OUT_RIGS)
    args.trials = args.trials or (QUICK["trials"] if q else DISTURBED_TRIALS)
    named = [] if args.qube_actions == DEFAULT_ACTIONS else [args.qube_actions]
    args.runs_dir = args.runs_dir or (Path("bench/results/runs") / ("sim2real-quick" if q else "sim2real")
                                      / "-".join([args.algo, args.policy, *named]))
    if any(v < 1 for v in (args.max_episodes, args.pretrain_episodes, args.held_out, args.trials, args.jobs)):
        parser.error("the caps, --held-out, --trials and --jobs must be at least 1")
    return args


if __name__ == "__main__":
    sys.exit(main())
