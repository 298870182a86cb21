"""The 4-worker CartPole-v0 federations of the end-to-end tests, as ``make run`` starts them (``deploy.run_local``:
separate processes over a real broker). One run per strategy is shared by every test that needs it (the ``runs``
fixture in conftest.py); those tests share the xdist group ``e2e``, so that one test process makes the runs."""

from __future__ import annotations

import json
import multiprocessing
import multiprocessing.synchronize
import os
import shlex
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

import psutil  # a dependency of amqtt (the broker extra)

SEED = 3
WORKERS = 4
ENV = "CartPole-v0"
MAX_EPISODES = 600


def federate(tmp_path: Path, name: str, policy: str, broker: str | None = None, max_episodes: int = MAX_EPISODES
             ) -> Path:
    """One federation through the launcher, to the end; its run folder (asserted: exit 0, all workers solved, or
    ended by ``max_episodes`` when that is given)."""
    run_dir = tmp_path / name
    argv = ["--workers", str(WORKERS), "--env", ENV, "--policy", policy, "--seed", str(SEED), "--max-episodes",
            str(max_episodes), "--run-dir", str(run_dir), "--run-id", name]
    if broker:
        argv += ["--broker", broker]
    log = tmp_path / f"{name}-launcher.log"
    with launched(argv, log) as launcher:
        code = launcher.wait(timeout=600)
    out = log.read_text()
    assert code == 0, out[-3000:]
    assert ("all workers solved" if max_episodes == MAX_EPISODES else
            f"reached the maximum of {max_episodes} episodes") in out, out[-3000:]
    return run_dir


@contextmanager
def launched(argv: Sequence[str], log: Path, env: dict[str, str] | None = None) -> Iterator[subprocess.Popen]:
    """``python -m deploy.run_local`` with ``argv``, its output (stdout and stderr) into ``log``; on the way out (the
    test failed, a wait timed out) whatever is left of it is stopped (``stop_launcher``)."""
    with log.open("wb") as out:
        launcher = subprocess.Popen([sys.executable, "-m", "deploy.run_local", *argv], stdout=out,
                                    stderr=subprocess.STDOUT, env={**os.environ, **(env or {})})
    try:
        yield launcher
    finally:
        stop_launcher(launcher)


def stop_launcher(launcher: subprocess.Popen, grace: float = 30.0) -> None:
    """End a launcher that is still running, and every process it started: SIGTERM, which it takes as a Ctrl-C (it
    stops its broker, chief and workers), then SIGKILL to whatever of its process tree is left after ``grace``
    seconds. Its children each lead a process group of their own (deploy.run_local.Fleet.start), so neither a
    SIGKILL to the launcher alone nor one to its process group would reach them: they are found in the tree."""
    if launcher.poll() is not None:
        return
    tree = _children(launcher.pid)
    launcher.terminate()
    try:
        launcher.wait(grace)
    except subprocess.TimeoutExpired:
        tree += _children(launcher.pid)  # and those started since (an edge started again)
        launcher.kill()
        launcher.wait()
    for proc in tree:  # psutil.Process knows its start time: a pid used again since is not killed
        with suppress(psutil.NoSuchProcess):
            proc.kill()
    psutil.wait_procs(tree, timeout=10)


def _children(pid: int) -> list[psutil.Process]:
    """Every descendant of process ``pid``, none if it has ended."""
    try:
        return list(psutil.Process(pid).children(recursive=True))
    except psutil.NoSuchProcess:
        return []


def warnings_of(run_dir: Path, limit: int = 40) -> str:
    """The warnings and errors of a run's processes (logs/*.log), for a failed assertion to show why."""
    lines = [f"{log.stem}: {line}" for log in sorted((run_dir / "logs").glob("*.log"))
             for line in log.read_text(errors="replace").splitlines() if " WARNING " in line or " ERROR " in line]
    return "\n".join(lines[:limit]) or "no warnings in the logs"


def records_up_to(run_dir: Path, episodes: int) -> tuple[dict[str, list[tuple[Any, ...]]], list[tuple[Any, ...]]]:
    """Each worker's accepted episodes (episode, return, steps, PI) and the chief's rounds (round, kind, contributors,
    PIs, weights, digest of the answer's tensors, source, keep-weights, finished) up to ``episodes`` (a strategy of
    one round per episode), without times: a run capped there is the uncapped one's beginning record by record."""
    subs: dict[str, list[tuple[Any, ...]]] = {}
    rounds: list[tuple[Any, ...]] = []
    for r in map(json.loads, (run_dir / "metrics.jsonl").read_text().splitlines()):
        if r["type"] == "episode" and r["episode"] <= episodes:
            subs.setdefault(r["worker"], []).append((r["episode"], r["return"], r["steps"], r["pi"]))
        elif r["type"] == "round" and r["round"] <= episodes:
            rounds.append((r["round"], r["kind"], r["contributors"], r["pis"], r["weights"], r["digest"], r["source"],
                           r["keep_weights"], r["finished"]))
    return {w: sorted(eps) for w, eps in sorted(subs.items())}, rounds


def per_worker_up_to(run_dir: Path, episodes: int) -> list[tuple[str, int, int]]:
    """Each worker's (id, episodes, steps) in a run capped at ``episodes``, from an uncapped run's records."""
    return [(w, len(eps), sum(e[2] for e in eps)) for w, eps in records_up_to(run_dir, episodes)[0].items()]


def per_worker(run_dir: Path) -> list[tuple[str, int, int]]:
    """Each worker's (id, episodes, steps) from summary.json: what a disturbed run must reproduce."""
    return [(w["id"], w["episodes"], w["steps"]) for w in json.loads((run_dir / "summary.json").read_text())["workers"]]


def federate_through(tmp_path: Path, fault: Callable[[], None], argv: Sequence[str], env: dict[str, str],
                     after_rounds: int = 10, name: str = "run") -> Path:
    """A federation through the launcher (``python -m deploy.run_local`` with ``argv``), disturbed by ``fault`` once
    ``after_rounds`` rounds have closed, to its end (asserted: exit 0, and rounds closed after the fault); its run
    folder."""
    run_dir = tmp_path / name
    log = tmp_path / f"{name}-launcher.log"
    with launched([*argv, "--run-dir", str(run_dir), "--run-id", name], log, env) as launcher:
        metrics = run_dir / "metrics.jsonl"
        deadline = time.monotonic() + 300
        while not metrics.exists() or metrics.read_text().count('"type":"round"') < after_rounds:
            assert time.monotonic() < deadline and launcher.poll() is None, log.read_text()
            time.sleep(0.05)
        fault()
        at_fault = metrics.read_text().count('"type":"round"')
        assert launcher.wait(timeout=400) == 0, log.read_text()[-3000:]
    # the fault's premise: it struck a running federation (not one that had ended meanwhile on a busy machine)
    assert metrics.read_text().count('"type":"round"') > at_fault, f"the run had ended by round {at_fault}"
    return run_dir


class Runs:
    """Run folders by strategy, each federation made the first time it is asked for."""

    def __init__(self, base: Path) -> None:
        self.base = base
        self._made: dict[str, Path] = {}

    def __getitem__(self, policy: str) -> Path:
        if policy not in self._made:
            self._made[policy] = federate(self.base, f"amqtt-{policy}", policy)
        return self._made[policy]


def over_mqtt(url: str, run_id: str, run_dir: Path, env: str, policy: str, seed: int, workers: int,
              max_episodes: int, algo: str = "ppo") -> None:
    """A federation whose chief and workers each have their own connection to the broker at ``url`` (MQTT; or the
    in-memory hub ``memory://<name>``), in threads of this process (the services deploy.inprocess runs on its
    in-memory hub), to its end: each service's connection is its settings' ``connector()``."""
    from chief.service import ChiefService, Outputs
    from chief.settings import ChiefSettings
    from worker.service import WorkerService
    from worker.settings import WorkerSettings

    chief = ChiefService(ChiefSettings.given(broker=url, run_id=run_id, workers=workers, env=env, policy=policy,
                                             seed=seed, max_episodes=max_episodes, round_timeout=600.0,
                                             run_dir=run_dir, algo=algo),
                         outputs=Outputs(tensorboard=False, plot=False, progress=False))
    services = [chief] + [WorkerService(WorkerSettings.given(broker=url, run_id=run_id, worker_id=f"w{i}", env=env,
                                                             algo=algo))
                          for i in range(workers)]
    run_in_threads([s.run for s in services], timeout=900)


def all_records(run_dir: Path) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The submissions' records per worker and round, and the round records in order; without their times and
    the workers' life tokens."""
    lines = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines() if line.strip()]
    for line in lines:
        line.pop("t")
        if isinstance(line.get("played"), dict):
            line["played"].pop("life")  # a random token per worker process (protocol.messages.Played)
    subs = sorted((r for r in lines if r["type"] != "round"), key=lambda r: (r["worker"], r["round"]))
    return subs, [r for r in lines if r["type"] == "round"]


def per_worker_final(run_dir: Path) -> list[tuple[Any, ...]]:
    """Each worker's (id, episodes, steps, final PI, state) from summary.json."""
    summary = json.loads((run_dir / "summary.json").read_text())
    return [(w["id"], w["episodes"], w["steps"], w["final_pi"], w["state"]) for w in summary["workers"]]


def run_in_threads(services: Sequence[Callable[[], int]], timeout: float) -> None:
    """Run each service (a chief's or a worker's ``run``) in a thread of this process; assert each returned 0."""
    codes: dict[int, int] = {}
    threads = [threading.Thread(target=lambda i=i, run=run: codes.__setitem__(i, run()), daemon=True)
               for i, run in enumerate(services)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=timeout)
    assert codes == dict.fromkeys(range(len(services)), 0)


def _spin(stop: multiprocessing.synchronize.Event) -> None:
    x = 0
    while not stop.is_set():
        x += 1


def busy_loops_wanted(cores: int | None = None, load: float | None = None) -> int:
    """Busy loops that, with the machine's own load (1-minute average), keep every core busy: one at least, and one per
    core left idle (both cores of a quiet 2-core machine; one under ``make test``, whose other test processes already
    load the cores: a second loop there only takes CPU from them)."""
    cores = (os.cpu_count() or 2) if cores is None else cores
    load = os.getloadavg()[0] if load is None else load
    return max(1, cores - int(load))  # a load is never negative: at most one loop per core


@contextmanager
def cpu_load(processes: int | None = None) -> Iterator[None]:
    """Busy processes competing with the federation for the cores (default :func:`busy_loops_wanted`)."""
    processes = busy_loops_wanted() if processes is None else processes
    stop = multiprocessing.Event()
    procs = [multiprocessing.Process(target=_spin, args=(stop,), daemon=True) for _ in range(processes)]
    for p in procs:
        p.start()
    try:
        yield
    finally:
        stop.set()
        for p in procs:
            p.join(5)


def as_started(line: str) -> tuple[list[str], dict[str, str]]:
    """A printed command as a shell runs it: its leading VAR=value words as the environment (over this one's, without
    its FEDRL_* variables, so that only the printed ones count), ``make run`` as what it runs (the Makefile's
    ``python -m deploy.run_local``), and the interpreter it names as this one."""
    words = shlex.split(line)
    env = {k: v for k, v in os.environ.items() if not k.startswith("FEDRL_")}
    while "=" in words[0] and words[0].split("=", 1)[0].isidentifier():
        var, value = words.pop(0).split("=", 1)
        env[var] = value
    if words[:2] == ["make", "run"]:
        return [sys.executable, "-m", "deploy.run_local", *words[2:]], env
    assert words[1:3] == ["-m", "deploy.run_local"], line
    return [sys.executable, *words[1:]], env
