"""``python -m deploy.inprocess``: a whole federation in one process, for sweeps.

It runs the same chief logic (chief/rounds.py with the strategies, and the chief service's translation between
messages and rounds) and the same worker logic (worker/federated.py, Algorithm 2) as ``make run``, and every message
goes through the same msgpack encoding; only MQTT and the separate processes are left out. The workers play their
episodes one after another, so a run takes about as long as one worker's episodes times N, without brokers and
process start-up. It writes the same run folder (summary.json with ``"mode": "in-process"``, metrics.jsonl,
learning_curve.png), which ``python -m chief.audit`` checks like any other. For a given seed it gives the same
per-worker episodes as a federation over MQTT (a test checks this).

It also writes ``timing.json``: per worker, the seconds each of its episodes took in its own code (playing the
episode, its K PPO updates, applying the chief's answer), and per round the seconds the chief's side took (the
message encoding both ways and the round state machine). bench.paper derives each worker's env steps per second
and the time it would wait for the chief and the slower workers with a core of its own.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import torch

from chief import strategies
from chief.report import MetricsLog, plot_learning_curves, run_summary, write_summary
from chief.rounds import RoundKeeper
from chief.service import answer_of, submission_of
from protocol.cli import add_device_noise, add_run_options, parse_checked
from protocol.codec import decode, encode
from protocol.messages import ChiefAggregate, ChiefTransfer, MatureParams, WorkerUpdate
from protocol.tasks import task, worker_seed
from worker.episode import build_learner_and_env
from worker.federated import Algorithm2


def run_federation(env_id: str, policy: str, seed: int, workers: int, max_episodes: int, run_dir: Path,
                   device_noise: float = 1.0, plot: bool = True, progress: bool = False) -> dict[str, Any]:
    """Run one federation to its end; returns its summary (also written to ``run_dir``)."""
    torch.set_num_threads(1)
    spec = task(env_id)
    ids = [f"w{i}" for i in range(workers)]
    algos: dict[str, Algorithm2] = {}
    for i, wid in enumerate(ids):
        env, learner = build_learner_and_env(env_id, seed=worker_seed(seed, i), device_noise=device_noise,
                                             init_seed=seed)
        algos[wid] = Algorithm2(wid, env, learner, spec.tc, worker_seed(seed, i))
    keeper = RoundKeeper(ids, policy, spec, max_episodes, round_timeout=float("inf"),
                         actor_spec=next(iter(algos.values())).actor_spec)
    metrics = MetricsLog(run_dir)
    t0 = time.monotonic()
    learning = list(ids)
    worker_s: dict[str, list[float]] = {wid: [] for wid in ids}  # per episode: the worker's own seconds
    chief_s: list[float] = []  # per round: the chief side's seconds (encoding both ways, the state machine)
    try:
        while not keeper.done:
            answers: dict[int, ChiefAggregate | ChiefTransfer] = {}
            chief_round = 0.0
            for wid in list(learning):
                algo = algos[wid]
                start = time.perf_counter()
                played = algo.play()
                mid = time.perf_counter()
                worker_s[wid].append(mid - start)
                msg = _wire(played, WorkerUpdate, MatureParams)
                while True:
                    verdict = keeper.submit(submission_of(msg), time.monotonic() - t0)
                    if verdict.status == "accepted":
                        metrics.episode(verdict.record(time.monotonic() - t0))
                    for outcome in verdict.outcomes:
                        metrics.round({**outcome.record(), "t": round(time.monotonic() - t0, 3)})
                        answers[outcome.episode] = _wire(answer_of(outcome), ChiefAggregate, ChiefTransfer)
                    if isinstance(msg, MatureParams) and verdict.ack is not None and not verdict.ack.accepted:
                        refused_at = time.perf_counter()
                        again = algo.refused(msg)  # refused: it learns on
                        worker_s[wid][-1] += time.perf_counter() - refused_at
                        mid += time.perf_counter() - refused_at
                        msg = _wire(again, WorkerUpdate)
                        continue
                    break
                chief_round += time.perf_counter() - mid
                if isinstance(msg, MatureParams):
                    learning.remove(wid)
            chief_s.append(chief_round)
            for wid in learning:
                start = time.perf_counter()
                algos[wid].apply(answers.get(algos[wid].episode))
                worker_s[wid][-1] += time.perf_counter() - start
            if progress:
                cells = " | ".join(f"{w} PI {algos[w].pi:.1f}" for w in learning if algos[w].pi is not None)
                print(f"round {keeper.episode - 1:4d} | {cells}", flush=True)
    finally:
        metrics.close()
        for algo in algos.values():
            algo.close()
    summary = run_summary(keeper, keeper.done_reason or "stopped", run_id=run_dir.name, seed=seed, mode="in-process",
                          wall_s=round(time.monotonic() - t0, 2), rejected_messages={})
    write_summary(run_dir, summary)
    (run_dir / "timing.json").write_text(json.dumps(
        {"worker_s": {w: [round(x, 5) for x in v] for w, v in worker_s.items()},
         "chief_s": [round(x, 5) for x in chief_s]}) + "\n")
    if plot:
        plot_learning_curves(run_dir, metrics.curves, spec.tc,
                             f"{env_id}, {workers} workers, policy {policy}, seed {seed} (in-process)")
    return summary


def _wire(message: Any, *kinds: type) -> Any:
    """Through the same msgpack encoding as over MQTT (bit-exact tensors, the same validation)."""
    return decode(encode(message), *kinds)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m deploy.inprocess", description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, default=4, help="number of workers (default 4)")
    add_run_options(parser, strategies.names())
    add_device_noise(parser)
    parser.add_argument("--run-dir", type=Path, required=True, help="the run folder to write")
    args = parse_checked(parser, argv)
    if args.env in ("qube",):
        parser.error("the in-process mode has no MQTT for rigs: use --env qube-local")
    summary = run_federation(args.env, args.policy, args.seed, args.workers, args.max_episodes, args.run_dir,
                             device_noise=args.device_noise, progress=True)
    last = summary["episodes_to_all_solved"]
    reason = summary["end_reason"]
    outcome = f"all workers solved by episode {last}" if last is not None else f"not all solved ({reason})"
    print(f"{args.env} / {args.policy} / seed {args.seed}: {outcome}; {summary['wall_s']:.1f} s; "
          f"results in {args.run_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
