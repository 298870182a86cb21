"""``python -m bench.savetime``: how long a tiered root takes to save its state (chief/checkpoint.py) as its run goes
on, at round ~10 and at round ~R (issue 34's target: a 256-device run's save at round 500 within 1.5x of round 10's).

It drives a root's RoundKeeper (tier ``root``, policy ``weighted``, CartPole-v0's real actor shapes) in process, as
the root's service does: each round, each of E edges' partials (one real-size float32 sum) and its workers'
submissions without tensors (each update's PI the mean of its recent returns, so the same driver runs at a commit
whose root still checks them), the round closed, then ``checkpoint.save`` into a temporary folder, timed (wall,
``time.perf_counter``). No MQTT and no learning: only the state's size decides the save time. Reports the median
save time (wall, with the file's fsync; and the process's CPU time) over the rounds around round 10 (``--early``) and
around the last round, their ratios (and the ratio of the least CPU time of each: the least disturbed by other
processes on a shared machine), the same for building the state's bytes alone (``checkpoint.encoded``: no file,
no fsync), and the state file's size at both.
``--quick``: 64 devices, 4 edges, 60 rounds (seconds).

    python -m bench.savetime --devices 256 --edges 16 --rounds 500 --out bench/results/savetime.json
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench import output
from bench.cost import actor_arrays
from chief import checkpoint, tiers
from chief.rounds import RoundKeeper, Submission
from protocol.tasks import PI_WINDOW, task

ENV = "CartPole-v0"
#: Rounds either side of a measured round whose save times are taken (the median of 2 * SPAN + 1).
SPAN = 5


def _service(edges: dict[str, str]) -> dict[str, Any]:
    """The service's part of the state, as a root of these edges saves it (chief/service.py ``_save``)."""
    return {"run_id": "savetime", "session": "s" * 16, "epoch": 1, "duplicates": 0,
            "hosts": {w: "127.0.0.1" for w in edges}, "update_steps": 10, "rejects": {}, "metrics_bytes": 0,
            "elapsed_s": 0.0, "init_model": None, "init_model_known": True, "claimed_since": 0.0, "algo": "ppo",
            "edges": edges}


def measure(devices: int, edges: int, rounds: int, early: int) -> dict[str, Any]:
    """Save times (seconds) of every round of a ``devices``-worker root of ``edges`` edges, and the summary."""
    workers = [f"w{i}" for i in range(devices)]
    edge_of = {w: f"e{i % edges}" for i, w in enumerate(workers)}
    spec = task(ENV)
    actor = actor_arrays(ENV)
    keeper = RoundKeeper(workers, "weighted", spec, rounds + 1, 60.0,
                         actor_spec={k: v.shape for k, v in actor.items()}, tier="root")
    returns: dict[str, list[float]] = {w: [] for w in workers}
    times: list[float] = []
    cpu: list[float] = []
    encode: list[float] = []  # the state's bytes only (checkpoint.encoded): no file, no fsync
    sizes: dict[int, int] = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for r in range(1, rounds + 1):
            for e in range(edges):
                mine = [w for w in workers if edge_of[w] == f"e{e}"]
                keeper.add_partial(r, f"e{e}", tiers.Partial(actor, 1.0, len(mine)), mine, {})
            for i, w in enumerate(workers):
                returns[w].append(float(10 + (i + r) % 50))  # below CartPole-v0's TC: nobody finishes
                recent = tuple(returns[w][-PI_WINDOW:])
                sub = Submission(w, r, float(np.mean(recent)), recent[-1], recent_returns=recent, steps=20,
                                 gradient={})
                verdict = keeper.submit(sub, float(r))
                assert verdict.status == "accepted", (verdict.reason, verdict.detail)
            assert keeper.round == r + 1, f"round {r} did not close"
            start_cpu = time.process_time()
            if hasattr(checkpoint, "encoded"):  # an earlier commit's checkpoint has none: its column is its save's
                checkpoint.encoded(keeper, _service(edge_of))
            encode.append(time.process_time() - start_cpu)
            start, start_cpu = time.perf_counter(), time.process_time()
            path = checkpoint.save(folder, keeper, _service(edge_of))
            times.append(time.perf_counter() - start)
            cpu.append(time.process_time() - start_cpu)
            sizes[r] = path.stat().st_size
    def around(values: list[float]) -> tuple[float, float]:
        return (statistics.median(values[max(0, early - 1 - SPAN):early + SPAN]),
                statistics.median(values[-(2 * SPAN + 1):]))

    def least(values: list[float]) -> tuple[float, float]:  # the least disturbed by other processes
        return min(values[max(0, early - 1 - SPAN):early + SPAN]), min(values[-(2 * SPAN + 1):])

    (wall_early, wall_last), (cpu_early, cpu_last) = around(times), around(cpu)
    (min_early, min_last) = least(cpu)
    (enc_early, enc_last), (enc_min_early, enc_min_last) = around(encode), least(encode)
    return {"devices": devices, "edges": edges, "rounds": rounds, "early_round": early,
            "save_ms_early": round(wall_early * 1e3, 3), "save_ms_last": round(wall_last * 1e3, 3),
            "ratio": round(wall_last / wall_early, 3),
            "save_cpu_ms_early": round(cpu_early * 1e3, 3), "save_cpu_ms_last": round(cpu_last * 1e3, 3),
            "cpu_ratio": round(cpu_last / cpu_early, 3), "min_cpu_ms_early": round(min_early * 1e3, 3),
            "min_cpu_ms_last": round(min_last * 1e3, 3), "min_cpu_ratio": round(min_last / min_early, 3),
            "encode_cpu_ms_early": round(enc_early * 1e3, 3), "encode_cpu_ms_last": round(enc_last * 1e3, 3),
            "encode_cpu_ratio": round(enc_last / enc_early, 3) if enc_early else None,
            "encode_min_cpu_ratio": round(enc_min_last / enc_min_early, 3) if enc_min_early else None,
            "state_bytes_early": sizes[early],
            "state_bytes_last": sizes[rounds], "save_ms": [round(t * 1e3, 3) for t in times],
            "save_cpu_ms": [round(t * 1e3, 3) for t in cpu]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.savetime", description=__doc__.splitlines()[0])
    parser.add_argument("--devices", type=int, default=256)
    parser.add_argument("--edges", type=int, default=16)
    parser.add_argument("--rounds", type=int, default=500)
    parser.add_argument("--early", type=int, default=10, help="the early round measured (default 10)")
    parser.add_argument("--quick", action="store_true", help="64 devices, 4 edges, 60 rounds")
    parser.add_argument("--out", type=Path, default=Path("bench/results/savetime.json"))
    args = parser.parse_args(argv)
    if args.quick:
        args.devices, args.edges, args.rounds = 64, 4, 60
    result = measure(args.devices, args.edges, args.rounds, args.early)
    print(f"save time at round {args.early}: {result['save_ms_early']} ms wall, {result['save_cpu_ms_early']} ms CPU "
          f"({result['state_bytes_early']} B); at round {args.rounds}: {result['save_ms_last']} ms wall, "
          f"{result['save_cpu_ms_last']} ms CPU ({result['state_bytes_last']} B); ratio {result['ratio']} wall, "
          f"{result['cpu_ratio']} CPU (medians), {result['min_cpu_ratio']} CPU (least of each); the state's bytes "
          f"alone (no file): {result['encode_cpu_ms_early']} -> {result['encode_cpu_ms_last']} ms CPU, ratio "
          f"{result['encode_cpu_ratio']} (medians), {result['encode_min_cpu_ratio']} (least)")
    output.write_report(args.out, "bench.savetime", argv, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
