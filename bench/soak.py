"""``python -m bench.soak`` (``make soak``): a long federation of many workers over Mosquitto, watched for leaks.

Starts Mosquitto on a free loopback port, runs ``deploy.run_local`` with 16 CartPole-v0 workers (by default) against
it, and samples every second the resident memory of the broker and of the chief (from /proc), while the chief's
records give each round's latency (time between consecutive round closes). Writes ``bench/results/soak.json`` and
``soak.png``. "No growth" is judged on the second half of the rounds (not the start, nor the summary and plot at
the end): the memory slope there, in MiB per minute.
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from chief import strategies
from chief.audit import audit
from runtime.records import RoundRecord, RunSummary, read_metrics
from services.broker import mosquitto

RESULTS = Path("bench/results")


def rss_mib(pid: int) -> float | None:
    """Resident memory of a process in MiB (None when it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def chief_pids(run_id: str) -> list[int]:
    """The running ``python -m chief`` processes of a run (found by their FEDRL_RUN_ID), from /proc."""
    pids = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            cmdline = (proc / "cmdline").read_bytes().split(b"\0")
            environ = (proc / "environ").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"chief" in cmdline and b"-m" in cmdline and f"FEDRL_RUN_ID={run_id}".encode() in environ:
            pids.append(int(proc.name))
    return pids


def slope_per_minute(samples: list[tuple[float, float]]) -> float | None:
    """Least-squares slope (MiB per minute) of (seconds, MiB) samples."""
    if len(samples) < 3:
        return None
    xs, ys = [s[0] / 60 for s in samples], [s[1] for s in samples]
    mx, my = statistics.fmean(xs), statistics.fmean(ys)
    den = sum((x - mx) ** 2 for x in xs)
    return sum((x - mx) * (y - my) for x, y in zip(xs, ys, strict=True)) / den if den else None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.soak", description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, default=16)
    parser.add_argument("--env", default="CartPole-v0")
    parser.add_argument("--policy", default=strategies.DEFAULT)
    parser.add_argument("--seed", type=int, default=101)
    parser.add_argument("--max-episodes", type=int, default=600)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if not mosquitto.available():
        parser.error("mosquitto is not installed (apt-get install mosquitto)")
    work = Path(tempfile.mkdtemp(prefix="fedrl-soak-"))
    broker, port = mosquitto.start(work)
    run_id, run_dir = f"soak{port}", work / "run"
    memory: dict[str, list[tuple[float, float]]] = {"broker": [], "chief": []}
    stop = threading.Event()
    t0 = time.monotonic()
    chief_seen: list[float] = []  # when the sampler first found the chief (its records count from its start)

    def sample() -> None:
        chief = None
        while not stop.wait(1.0):
            if chief is None and (chief := next(iter(chief_pids(run_id)), None)) is not None:
                chief_seen.append(time.monotonic() - t0)
            for name, pid in (("broker", broker.pid), ("chief", chief)):
                value = rss_mib(pid) if pid else None
                if value is not None:
                    memory[name].append((round(time.monotonic() - t0, 1), round(value, 2)))

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    try:
        launcher = subprocess.run(
            [sys.executable, "-m", "deploy.run_local", "--workers", str(args.workers), "--env", args.env,
             "--policy", args.policy, "--seed", str(args.seed), "--max-episodes", str(args.max_episodes),
             "--broker", f"mqtt://127.0.0.1:{port}", "--run-dir", str(run_dir), "--run-id", run_id,
             "--dashboard-port", "off"],
            capture_output=True, text=True)
    finally:
        stop.set()
        sampler.join(5)
        broker.terminate()
        broker.wait(10)
    wall = time.monotonic() - t0
    report = measure(args, run_dir, launcher.returncode, wall, memory, chief_seen[0] if chief_seen else 0.0)
    try:
        report["audit"] = f"passed: {audit(run_dir)}"
    except Exception as err:  # the report says what failed; the soak's job is to measure
        report["audit"] = f"FAILED: {err}"
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "soak.json").write_text(json.dumps(report, indent=1) + "\n")
    plot(report, args.out / "soak.png")
    print(json.dumps({k: v for k, v in report.items() if k not in ("samples", "round_t")}, indent=1))
    return 0 if launcher.returncode == 0 else 1


def measure(args: argparse.Namespace, run_dir: Path, launcher_exit: int, wall: float,
            memory: dict[str, list[tuple[float, float]]], offset: float) -> dict[str, Any]:
    """The soak's report from the run folder's records and the memory samples (``offset``: when the sampler first
    saw the chief, on its clock)."""
    summary = RunSummary.read(run_dir)
    rounds = [r for r in read_metrics(run_dir) if isinstance(r, RoundRecord)]
    latency = [b.t - a.t for a, b in itertools.pairwise(rounds)]
    # Steady state: the second half of the rounds (on the sampler's clock), not the start (imports, the workers'
    # hellos) nor the end (the chief's summary and plot).
    round_t = [offset + r.t for r in rounds]
    window = (round_t[len(round_t) // 2], round_t[-1]) if len(round_t) >= 4 else (wall / 2, wall)
    half = {name: [s for s in xs if window[0] <= s[0] <= window[1]] for name, xs in memory.items()}
    return {
        "workers": args.workers, "env": args.env, "policy": args.policy, "seed": args.seed, "broker": "mosquitto",
        "launcher_exit": launcher_exit, "wall_s": round(wall, 1), "rounds": summary.rounds,
        "episodes_to_all_solved": summary.episodes_to_all_solved, "end_reason": summary.end_reason,
        "rejected_messages": summary.rejected_messages, "duplicates": summary.duplicates,
        "round_latency_s": {"median": statistics.median(latency), "p95": sorted(latency)[int(0.95 * len(latency))],
                            "max": max(latency)} if latency else None,
        "memory_mib": {name: {"first": xs[0][1] if xs else None, "last": xs[-1][1] if xs else None,
                              "max": max(v for _, v in xs) if xs else None,
                              "steady_first": half[name][0][1] if half[name] else None,
                              "steady_last": half[name][-1][1] if half[name] else None,
                              "slope_second_half_mib_per_min": slope_per_minute(half[name])}
                       for name, xs in memory.items()},
        "steady_window_s": [round(window[0], 1), round(window[1], 1)],
        "samples": memory, "round_t": [round(t, 3) for t in round_t],
    }


def plot(report: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (mem, lat) = plt.subplots(2, 1, figsize=(8, 6), dpi=110)
    for name, xs in report["samples"].items():
        mem.plot([s[0] for s in xs], [s[1] for s in xs], label=name)
    mem.axvspan(*report["steady_window_s"], color="0.9", label="second half of the rounds")
    mem.set_ylabel("resident memory (MiB)")
    mem.legend()
    mem.set_title(f"soak: {report['workers']} workers, {report['env']}, {report['policy']}, Mosquitto")
    ts = report["round_t"]
    lat.plot(ts[1:], [b - a for a, b in itertools.pairwise(ts)], linewidth=0.8)
    lat.set_xlabel("seconds since the soak started")
    lat.set_xlim(mem.get_xlim())
    lat.set_ylabel("round latency (s)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
