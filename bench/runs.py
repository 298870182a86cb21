"""One benchmark run and what is measured from its run folder.

A run is a federation (``kind: federation``), one worker of ours alone (``kind: single``) or a Stable-Baselines3
reference (``kind: sb3``, bench/sb3_ref.py), each of one learner of ours (``algo``: the workers' learner, or the one
an SB3 run is the reference of); every result keeps it. Federations run either in process (``deploy.inprocess``,
the default for sweeps) or as ``make run`` does (``deploy.run_local``: embedded broker, chief and workers as
separate processes); each result names its mode. Every federation's run folder is audited (chief.audit).

Per worker, from the run folder:

- ``episodes`` and ``steps``: until it finished (its MatureParams), or so far when it did not;
- ``own_s``: seconds spent in its own code (in process: timing.json, the CPU seconds of its service's threads,
  playing episodes, PPO updates, decoding and applying the chief's answers; over MQTT: from the chief's accept
  times, each episode from the answer to the previous round to the next submission, i.e. including the answer's and
  the submission's trip through the broker);
- ``wall_s``: seconds until it finished. Over MQTT: the chief's accept time of its mature actor, counted from the
  run's first accepted submission. In process the workers' threads share the cores (and one interpreter), so wall
  time is modelled as if each had a core of its own: every round lasts as long as its slowest worker plus the
  chief's part;
- ``wait_share``: the share of its wall time spent waiting for the chief's answer (and so for the slower workers):
  1 - own_s / wall_s in process; over MQTT the time from its submission to the round's answer, over that plus own_s,
  for the rounds it took part in before finishing;
- ``steps_per_s``: env steps per second of its own time.

Every result carries ``code``, the fingerprint of the code that made it (``code_fingerprint``), so that reusing it
(``bench.paper --resume``) is refused once that code changed.
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import hashlib
import importlib.metadata
import json
import os
import shutil
import subprocess
import sys
import time
import traceback
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Any

from protocol import learners
from runtime.records import SUMMARY, EpisodeRecord, RoundRecord, RunSummary, read_metrics

#: The strategy every other is compared with (bench.paper, bench.report).
BASELINE = "independent"


def learner_blocks(rep: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """A task report's blocks per learner; a report from before learners were a dimension is PPO's alone."""
    if "learners" in rep:
        return dict(rep["learners"])
    keys = ("workers", "max_episodes", "seeds", "strategies", "summary", "significance", "references", "target")
    return {learners.DEFAULT: {"algo": learners.DEFAULT, **{k: rep[k] for k in keys if k in rep}}}


def process_pool(jobs: int) -> ProcessPoolExecutor:
    """The benchmarks' one process pool (bench.paper, bench.sim2real): ``jobs`` spawned processes, torch on one
    thread in each (the runs share the cores, not threads within a run)."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    return ProcessPoolExecutor(max_workers=jobs, mp_context=get_context("spawn"), initializer=_one_thread)


def _one_thread() -> None:
    import torch

    torch.set_num_threads(1)

#: Most points a run's learning curve keeps (evenly spaced, the last one always).
CURVE_POINTS = 250
#: The packages whose code decides what a run of ours does (the benchmark's own code only measures it).
RUN_CODE = ("chief", "deploy", "protocol", "runtime", "services", "worker")
ROOT = Path(__file__).resolve().parent.parent


@functools.cache
def code_fingerprint(kind: str) -> str:
    """16 hex digits of SHA-256 over what decides a run's result: for ours (``federation``, ``single``) every
    Python source of RUN_CODE, path and content; for an SB3 reference (``sb3``) bench/sb3_ref.py and the installed
    stable-baselines3's version. Any change to them, even one meant to keep behaviour, gives another."""
    digest = hashlib.sha256()
    if kind == "sb3":
        files = [ROOT / "bench" / "sb3_ref.py"]
        with contextlib.suppress(importlib.metadata.PackageNotFoundError):
            digest.update(importlib.metadata.version("stable-baselines3").encode())
    else:
        files = sorted(p for package in RUN_CODE for p in (ROOT / package).rglob("*.py"))
    for path in files:
        digest.update(path.relative_to(ROOT).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()[:16]


@dataclass(frozen=True)
class Job:
    """One run of the benchmark."""

    kind: str  # federation | single | sb3
    task: str
    strategy: str
    seed: int
    workers: int
    max_episodes: int
    mode: str = "inprocess"  # inprocess | mqtt (federations and single workers)
    algo: str = "ppo"  # the learner (protocol/learners.py); results from before learners had names are PPO's

    @property
    def key(self) -> tuple[Any, ...]:
        return (self.kind, self.task, self.strategy, self.seed, self.workers, self.max_episodes, self.mode, self.algo)

    @property
    def name(self) -> str:
        """The run folder's name (PPO's without the learner, as before learners had names)."""
        name = f"{self.task}-{self.kind}-{self.strategy}-s{self.seed}-n{self.workers}-m{self.max_episodes}-{self.mode}"
        return name if self.algo == "ppo" else f"{name}-{self.algo}"


class RunFolderBusy(RuntimeError):
    """Another process is running the same job into the same runs folder."""


@contextlib.contextmanager
def run_folder_lock(runs_dir: Path, name: str) -> Any:
    """Hold ``runs_dir/.locks/<name>.lock`` (an advisory ``flock``, released when this process ends, however it
    ends) while a run writes its folder, so two benchmark processes never write the same run folder at once (they
    would clobber each other's metrics.jsonl and fail its audit); RunFolderBusy names the holder."""
    path = runs_dir / ".locks" / f"{name}.lock"
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "unknown"
            raise RunFolderBusy(f"{runs_dir / name} is being written by another process (pid {holder}); "
                                f"give each benchmark process its own --runs-dir or its own seeds") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        yield
    finally:
        os.close(fd)


def execute(job: Job, runs_dir: Path) -> dict[str, Any]:
    """Run one job (in this process, or its launcher as a child process); never raises: errors are results."""
    t0, code = time.monotonic(), code_fingerprint(job.kind)  # of the code as the run starts
    try:
        if job.kind == "sb3":
            from bench import sb3_ref

            result = sb3_ref.run(job.task, job.seed, algo=job.strategy.removeprefix("sb3-zoo-"))
            result["mode"] = "in-process"
        else:
            run_dir = runs_dir / job.name
            with run_folder_lock(runs_dir, job.name):
                shutil.rmtree(run_dir, ignore_errors=True)
                if job.mode == "inprocess":
                    from deploy.inprocess import run_federation
                    from deploy.settings import InprocessSettings

                    run_federation(InprocessSettings.given(env=job.task, policy=job.strategy, seed=job.seed,
                                   workers=job.workers, max_episodes=job.max_episodes, run_dir=run_dir, algo=job.algo),
                                   plot=False, tensorboard_files=False)
                else:
                    _run_mqtt(job, run_dir)
                result = collect(run_dir, job)
    except Exception as err:  # a failed run is reported, never dropped
        result = {"kind": job.kind, "task": job.task, "strategy": job.strategy, "seed": job.seed,
                  "workers": job.workers, "max_episodes": job.max_episodes, "finished": False, "algo": job.algo,
                  "error": f"{type(err).__name__}: {err}", "traceback": traceback.format_exc()[-3000:]}
    result["job"] = asdict(job)
    result["algo"] = job.algo
    result["code"] = code
    result["run_wall_s"] = round(time.monotonic() - t0, 2)
    return result


def _run_mqtt(job: Job, run_dir: Path) -> None:
    env = "qube" if job.task == "qube-local" else job.task
    proc = subprocess.run(
        [sys.executable, "-m", "deploy.run_local", "--env", env, "--policy", job.strategy, "--seed", str(job.seed),
         "--workers", str(job.workers), "--max-episodes", str(job.max_episodes), "--run-dir", str(run_dir),
         "--algo", job.algo,
         "--run-id", f"bench-{job.strategy}-s{job.seed}-n{job.workers}"],
        capture_output=True, text=True)
    if not (run_dir / SUMMARY).exists():
        raise RuntimeError(f"deploy.run_local exited {proc.returncode} without a summary: "
                           f"{proc.stdout[-1500:]} {proc.stderr[-1500:]}")


def read_records(run_dir: Path) -> tuple[RunSummary, list[EpisodeRecord], list[RoundRecord]]:
    """summary.json, the episode records and the round records of metrics.jsonl (the later-step records of a
    per-step strategy are left out: the episode record has what the benchmark needs)."""
    records = read_metrics(run_dir)
    return (RunSummary.read(run_dir), [r for r in records if isinstance(r, EpisodeRecord)],
            [r for r in records if isinstance(r, RoundRecord)])


def collect(run_dir: Path, job: Job) -> dict[str, Any]:
    """A federation's result from its run folder (summary, records, timing), with its audit."""
    from chief.audit import AuditFailure, audit

    summary, episodes, rounds = read_records(run_dir)
    try:
        audited = {"passed": True, "detail": str(audit(run_dir))}
    except AuditFailure as failure:
        audited = {"passed": False, "detail": str(failure)}
    timing_path = run_dir / "timing.json"
    timing = json.loads(timing_path.read_text()) if timing_path.exists() else None
    mode = summary.mode or "mqtt"
    workers = per_worker(summary, episodes, rounds, timing, summary.rounds_per_episode)
    finished = summary.episodes_to_all_solved is not None
    last = max(workers, key=lambda w: (w["episodes"], w["steps"]))
    solved = [w for w in workers if w["solved"]]
    return {
        "kind": job.kind, "task": job.task, "strategy": job.strategy, "seed": job.seed, "workers": job.workers,
        "max_episodes": job.max_episodes, "mode": mode, "finished": finished, "end_reason": summary.end_reason,
        "rounds": summary.rounds,
        "last_worker": {"episodes": last["episodes"] if finished else None,
                        "steps": last["steps"] if finished else None,
                        "wall_s": max((w["wall_s"] for w in workers if w["wall_s"] is not None), default=None)
                        if finished else None,
                        "episodes_reached": last["episodes"], "steps_reached": last["steps"]},
        "first_worker_episodes": min((w["episodes"] for w in solved), default=None),
        "solved_workers": len(solved), "total_steps": summary.total_steps, "per_worker": workers,
        "audit": audited, "curve": learning_curve(episodes), "run_dir": str(run_dir),
    }


def algo_of(r: dict[str, Any]) -> str:
    """A result's learner (results from before learners had names are PPO's)."""
    return str(r.get("algo") or r.get("job", {}).get("algo") or "ppo")


def outcome(r: dict[str, Any]) -> tuple[int | None, int | None]:
    """(episodes, steps) of a run's last worker (the learner itself for sb3); (None, None) when unfinished."""
    if "error" in r or not r.get("finished"):
        return None, None
    if r["kind"] == "sb3":
        return r["episodes"], r["steps"]
    return r["last_worker"]["episodes"], r["last_worker"]["steps"]


def per_worker(summary: RunSummary, episodes: list[EpisodeRecord], rounds: list[RoundRecord],
               timing: dict[str, Any] | None, per_episode: int = 1) -> list[dict[str, Any]]:
    """Each worker's episodes, steps, own time, wall time, waiting share and env steps per second."""
    out = []
    for w in summary.workers:
        n, steps = w.episodes, w.steps
        row: dict[str, Any] = {"id": w.id, "solved": w.solved, "episodes": n, "steps": steps}
        if timing is not None:
            row.update(_modelled_times(w.id, n, timing, per_episode))
        else:
            row.update(_mqtt_times(w.id, n, episodes, rounds, per_episode))
        own = row.get("own_s")
        row["steps_per_s"] = round(row.pop("timed_steps", steps) / own, 1) if own else None
        if not w.solved:
            row["wall_s"] = None if timing is None else row["wall_s"]
        out.append(row)
    return out


def _modelled_times(wid: str, n: int, timing: dict[str, Any], per_episode: int = 1) -> dict[str, Any]:
    """In process: the worker's own seconds, and its wall time as if every worker had its own core (the chief's
    seconds per round summed per episode when an episode has several rounds)."""
    mine = timing["worker_s"][wid][:n]
    per_round = timing["chief_s"]
    chief = [sum(per_round[i:i + per_episode]) for i in range(0, len(per_round), per_episode)]
    everyone = timing["worker_s"].values()
    wall = 0.0
    for r in range(len(mine)):
        wall += max(s[r] for s in everyone if len(s) > r) + (chief[r] if r < len(chief) else 0.0)
    own = sum(mine)
    return {"own_s": round(own, 3), "wall_s": round(wall, 3),
            "wait_share": round(1.0 - own / wall, 4) if wall > 0 else None, "time_basis": "modelled"}


def _mqtt_times(wid: str, n: int, episodes: list[EpisodeRecord], rounds: list[RoundRecord],
                per_episode: int = 1) -> dict[str, Any]:
    """Over MQTT, from the chief's clock: accept times of the worker's episode submissions and of the answer to each
    episode's last round (an episode's later-step exchanges count as waiting)."""
    sent = {r.episode: r for r in episodes if r.worker == wid}
    answered = {r.episode: r.t for r in rounds if r.step == per_episode - 1}
    start = min((r.t for r in episodes), default=0.0)
    own = wait = 0.0
    steps = 0
    for e in range(1, n + 1):
        if e not in sent:
            continue
        t = sent[e].t
        if e >= 2 and (e - 1) in answered:  # from the previous answer to this submission: the worker's own time
            own += max(0.0, t - answered[e - 1])
            steps += sent[e].steps
        if e < n and e in answered:  # from this submission to the round's answer: waiting
            wait += max(0.0, answered[e] - t)
    end = sent[n].t if n in sent else None
    return {"own_s": round(own, 3), "wall_s": round(end - start, 3) if end is not None else None,
            "wait_share": round(wait / (wait + own), 4) if wait + own > 0 else None, "timed_steps": steps,
            "time_basis": "chief clock"}


def learning_curve(episodes: list[EpisodeRecord]) -> dict[str, list[float | None]]:
    """The run's mean over workers of PI (last-10 average return) and of env steps, per episode.

    A worker that finished keeps its last PI and step count (it keeps its mature actor). At most CURVE_POINTS
    points, evenly spaced, always the last.
    """
    by_worker: dict[str, dict[int, tuple[float, int]]] = {}
    for rec in sorted(episodes, key=lambda r: r.episode):
        by_worker.setdefault(rec.worker, {})[rec.episode] = (rec.pi, rec.steps)
    if not by_worker:
        return {"episode": [], "pi": [], "steps": []}
    last = max(max(v) for v in by_worker.values())
    pis, steps = [], []
    for records in by_worker.values():
        pi_row, step_row, pi, total = [], [], float("nan"), 0
        for e in range(1, last + 1):
            if e in records:
                pi, inc = records[e]
                total += inc
            pi_row.append(pi)
            step_row.append(total)
        pis.append(pi_row)
        steps.append(step_row)
    keep = _evenly(last, CURVE_POINTS)
    mean_pi = [_nanmean([row[i] for row in pis]) for i in keep]
    mean_steps = [sum(row[i] for row in steps) / len(steps) for i in keep]
    return {"episode": [i + 1 for i in keep], "pi": [None if v != v else round(v, 2) for v in mean_pi],
            "steps": [round(v, 1) for v in mean_steps]}


def _evenly(n: int, most: int) -> list[int]:
    if n <= most:
        return list(range(n))
    picks = {round(i * (n - 1) / (most - 1)) for i in range(most)}
    return sorted(picks)


def _nanmean(values: list[float]) -> float:
    finite = [v for v in values if v == v]
    return sum(finite) / len(finite) if finite else float("nan")
