"""Every task x learner x strategy, over MQTT and in process: does each federation run, do what its strategy says, and
pass its audit? (``--algo`` works for every task and strategy.)

    python -m bench.matrix                      # the whole matrix, 2 workers, M = 2, both modes
    python -m bench.matrix --tasks Acrobot-v1 --algos sac --modes mqtt --broker mqtt://127.0.0.1:1884

A cell is one short federation, started as a user starts one: ``deploy.run_local`` (embedded broker, or ``--broker``;
the QUBE task over MQTT is ``qube`` with simulated rigs) or ``deploy.inprocess`` (the QUBE as ``qube-local``). A cell
passes when the launcher exits 0 and its run folder says the run was this task, learner and strategy, every worker
played its M episodes, the chief closed M x rounds_per_episode rounds (every update of ``sync``), refused no message,
and ``chief.audit`` passes. A learner that cannot act in a task (protocol/learners.py misfit) is a cell too: each
launcher must refuse it with that one line and exit code 2.

Writes bench/results/matrix.json (``--out``); exit code 1 when a cell failed. This checks behaviour, not speed: the
wall seconds it records are of this host under this run's load.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from bench.output import write_report
from chief import strategies
from chief.audit import AuditFailure, audit
from protocol import learners
from runtime.records import RunSummary

TASKS = ("CartPole-v0", "Acrobot-v1", "MountainCarContinuous-v0", "Pendulum-v1", "qube-local")
MODES = ("mqtt", "inprocess")
LAUNCHER = {"mqtt": "deploy.run_local", "inprocess": "deploy.inprocess"}


@dataclass(frozen=True)
class Cell:
    task: str
    algo: str
    strategy: str
    mode: str

    @property
    def name(self) -> str:
        return f"{self.task}-{self.algo}-{self.strategy}-{self.mode}"

    @property
    def env(self) -> str:
        """The task as the launcher names it: over MQTT the QUBE is rigs reached through the broker."""
        return "qube" if self.mode == "mqtt" and self.task == "qube-local" else self.task


def cells(tasks: Iterable[str], algos: Iterable[str], strategy_names: Iterable[str],
          modes: Iterable[str]) -> list[Cell]:
    """The matrix: a misfit pair once per mode (its strategy is irrelevant: it must not start)."""
    out: list[Cell] = []
    for task in tasks:
        for algo in algos:
            for mode in modes:
                if learners.misfit(algo, task):
                    out.append(Cell(task, algo, "-", mode))
                else:
                    out += [Cell(task, algo, s, mode) for s in strategy_names]
    return out


def problems(cell: Cell, summary: RunSummary, audit_passed: bool, audit_detail: str, m: int) -> list[str]:
    """What a finished cell's run folder says went wrong (empty: nothing)."""
    found = []
    said = (summary.env, summary.algo, summary.policy)
    if said != (cell.env, cell.algo, cell.strategy):
        found.append(f"the run says env, learner, strategy = {said}")
    short = {w.id: w.episodes for w in summary.workers if w.episodes < m and not w.solved}
    if short:
        found.append(f"workers that played fewer than M = {m} episodes: {short}")
    played = max((w.episodes for w in summary.workers), default=0)
    if summary.rounds != played * summary.rounds_per_episode:
        found.append(f"{summary.rounds} rounds for {played} episodes of {summary.rounds_per_episode} rounds")
    if refused := {k: v for k, v in (summary.rejected_messages or {}).items() if v}:
        found.append(f"refused messages: {refused}")
    if not audit_passed:
        found.append(f"audit failed: {audit_detail}")
    return found


def run_cell(cell: Cell, m: int, workers: int, seed: int, runs_dir: Path, round_timeout: float,
             broker: str | None) -> dict[str, Any]:
    """Start the cell's launcher, wait for it, and judge its run folder (or, for a misfit, its refusal)."""
    run_dir = runs_dir / cell.name
    argv = [sys.executable, "-m", LAUNCHER[cell.mode], "--env", cell.env, "--algo", cell.algo, "--seed", str(seed),
            "--workers", str(workers), "--max-episodes", str(m), "--run-dir", str(run_dir)]
    misfit = learners.misfit(cell.algo, cell.task)
    if not misfit:
        argv += ["--policy", cell.strategy, "--round-timeout", str(round_timeout)]
        if cell.mode == "mqtt":
            argv += ["--run-id", f"matrix-{cell.name}".replace(".", "-")]
            argv += ["--broker", broker] if broker else []
    t0 = time.monotonic()
    done = subprocess.run(argv, capture_output=True, text=True)
    row: dict[str, Any] = {**asdict(cell), "exit_code": done.returncode, "wall_s": round(time.monotonic() - t0, 1)}
    if misfit:
        lines = done.stderr.strip().splitlines()
        ok = done.returncode == 2 and len(lines) == 1 and lines[0].endswith(misfit)
        return {**row, "ok": ok, "problems": [] if ok else [f"expected one line ending {misfit!r}: {done.stderr}"]}
    if done.returncode != 0 or not (run_dir / "summary.json").exists():
        return {**row, "ok": False, "problems": [f"launcher exited {done.returncode}: {done.stderr[-1500:]}"]}
    try:
        passed, detail = True, str(audit(run_dir))
    except AuditFailure as failure:
        passed, detail = False, str(failure)
    summary = RunSummary.read(run_dir)
    found = problems(cell, summary, passed, detail, m)
    return {**row, "ok": not found, "problems": found, "rounds": summary.rounds,
            "rounds_per_episode": summary.rounds_per_episode, "episodes": {w.id: w.episodes for w in summary.workers}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.matrix", description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), choices=TASKS)
    parser.add_argument("--algos", nargs="+", default=learners.names(), choices=learners.names())
    parser.add_argument("--strategies", nargs="+", default=strategies.names(), choices=strategies.names())
    parser.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    parser.add_argument("--max-episodes", type=int, default=2, help="M of every cell (default 2)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=101)
    parser.add_argument("--round-timeout", type=float, default=120.0,
                        help="seconds a round waits for a silent worker (default 120: a SAC update on a loaded host "
                             "can outlast the run default of 30 s, and a late submission would be a refused message)")
    parser.add_argument("--broker", help="run the MQTT cells on this broker (mqtt://host:port; default: each "
                                         "launcher's embedded amqtt)")
    parser.add_argument("--jobs", type=int, default=1, help="cells at once")
    parser.add_argument("--runs-dir", type=Path, default=Path("bench/results/runs/matrix"))
    parser.add_argument("--out", type=Path, default=Path("bench/results/matrix.json"))
    args = parser.parse_args(argv)
    todo = cells(args.tasks, args.algos, args.strategies, args.modes)
    print(f"{len(todo)} cells, {args.jobs} at a time, M = {args.max_episodes}, {args.workers} workers", flush=True)
    started, rows = time.monotonic(), []

    def one(cell: Cell) -> dict[str, Any]:
        row = run_cell(cell, args.max_episodes, args.workers, args.seed, args.runs_dir, args.round_timeout,
                       args.broker)
        rows.append(row)
        verdict = "ok" if row["ok"] else "FAILED: " + "; ".join(row["problems"])
        print(f"[{len(rows)}/{len(todo)}] {cell.mode:<9} {cell.task} {cell.algo} {cell.strategy}: {verdict} "
              f"({row['wall_s']:.0f} s)", flush=True)
        return row

    with ThreadPoolExecutor(args.jobs) as pool:
        list(pool.map(one, todo))
    order = {cell: i for i, cell in enumerate(todo)}
    rows.sort(key=lambda r: order[Cell(r["task"], r["algo"], r["strategy"], r["mode"])])
    failed = [r for r in rows if not r["ok"]]
    write_report(args.out, "bench.matrix", argv, {
        "max_episodes": args.max_episodes, "workers": args.workers, "seed": args.seed,
        "round_timeout_s": args.round_timeout, "broker": args.broker or "embedded amqtt per launcher",
        "jobs": args.jobs, "wall_s": round(time.monotonic() - started, 1), "cells": len(rows),
        "passed": len(rows) - len(failed), "failed": [f"{r['mode']} {r['task']} {r['algo']} {r['strategy']}"
                                                      for r in failed], "rows": rows})
    print(f"{len(rows) - len(failed)}/{len(rows)} cells passed", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
