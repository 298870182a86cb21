"""``python -m deploy.inprocess``: a whole federation in one process, for sweeps.

It runs the same chief logic (chief/rounds.py with the strategies, and the chief service's translation between
messages and rounds) and the same worker logic (worker/federated.py, Algorithm 2) as ``make run``, and every message
goes through the same msgpack encoding; only MQTT and the separate processes are left out. The workers play their
episodes one after another, so a run takes about as long as one worker's episodes times N, without brokers and
process start-up. It writes the same run folder (summary.json with ``"mode": "in-process"``, metrics.jsonl,
learning_curve.png), which ``python -m chief.audit`` checks like any other. For a given seed it gives the same
per-worker episodes as a federation over MQTT (a test checks this).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import torch

from chief import strategies, tensorboard
from chief.report import MetricsLog, plot_learning_curves, run_summary, write_summary
from chief.rounds import RoundKeeper
from chief.service import answer_of, submission_of
from deploy.settings import InprocessSettings
from protocol.codec import decode, encode
from protocol.messages import ChiefAggregate, ChiefTransfer, MatureParams, WorkerUpdate
from protocol.tasks import task, worker_seed
from runtime.settings import returns_code
from worker.episode import build_learner_and_env
from worker.federated import Algorithm2


def run_federation(env_id: str, policy: str, seed: int, workers: int, max_episodes: int, run_dir: Path,
                   device_noise: float = 1.0, plot: bool = True, progress: bool = False,
                   tensorboard_files: bool = True, env_options: dict[str, Any] | None = None) -> dict[str, Any]:
    """Run one federation to its end; returns its summary (also written to ``run_dir``). ``tensorboard_files``:
    write the TensorBoard event files live, as the chief does (the benchmarks leave them out of their timing).
    ``env_options`` go to the task's factory (qube-local: ``rig_profile``, ``randomize``)."""
    torch.set_num_threads(1)
    spec = task(env_id)
    ids = [f"w{i}" for i in range(workers)]
    algos: dict[str, Algorithm2] = {}
    keeper: RoundKeeper | None = None
    for i, wid in enumerate(ids):
        env, learner = build_learner_and_env(env_id, seed=worker_seed(seed, i), device_noise=device_noise,
                                             init_seed=seed, env_options=env_options)
        if keeper is None:
            keeper = RoundKeeper(ids, policy, spec, max_episodes, round_timeout=float("inf"),
                                 actor_spec=learner.actor_spec(), critic_spec=learner.critic_spec(),
                                 shape=strategies.get(policy).rounds(learner.config.update_epochs))
        algos[wid] = Algorithm2(wid, env, learner, spec.tc, worker_seed(seed, i), shape=keeper.shape)
    assert keeper is not None
    metrics = MetricsLog(run_dir)
    t0 = time.monotonic()
    if tensorboard_files:
        metrics.attach(tensorboard.open_board(run_dir, keeper.rounds_per_episode, wall_start=time.time()))
    open_: dict[str, WorkerUpdate | MatureParams] = {}  # each worker's submission for its open round
    sent: set[str] = set()  # workers whose open submission the chief has counted: they wait for its answer
    answers: dict[int, ChiefAggregate | ChiefTransfer] = {}  # closed rounds' answers, as the wire carries them
    worker_s: dict[str, list[float]] = {wid: [] for wid in ids}  # per episode: the worker's own seconds
    chief_s: list[float] = []  # per round: the chief side's seconds (encoding both ways, the state machine)
    chief_acc = 0.0
    catching_up: dict[str, range] = {}  # helpers that apply their finishing episode's answers before playing on
    try:
        while not keeper.done:
            for wid in [w for w in ids if keeper.workers[w].state != "finished" or keeper.workers[w].helping]:
                algo = algos[wid]
                if wid in catching_up:
                    if keeper.round <= catching_up[wid][-1]:
                        continue  # those rounds are still open: it waits for their answers, as over MQTT
                    skipped = catching_up.pop(wid)
                    algo.catch_up({r: a for r in skipped if isinstance(a := answers.get(r), ChiefAggregate)})
                if wid not in open_:
                    start = time.perf_counter()
                    played = algo.play()
                    worker_s[wid].append(time.perf_counter() - start)
                    open_[wid] = _wire(played, WorkerUpdate, MatureParams)
                if wid in sent:
                    continue
                while True:
                    msg = open_[wid]
                    start = time.perf_counter()
                    verdict = keeper.submit(submission_of(msg), time.monotonic() - t0)
                    if verdict.status == "accepted":
                        metrics.episode(verdict.record(time.monotonic() - t0))
                    for outcome in verdict.outcomes:
                        metrics.round({**outcome.record(), "t": round(time.monotonic() - t0, 3)})
                        answers[outcome.round] = _wire(answer_of(outcome), ChiefAggregate, ChiefTransfer)
                    chief_acc += time.perf_counter() - start
                    for _ in verdict.outcomes:
                        chief_s.append(chief_acc / len(verdict.outcomes))
                    chief_acc = 0.0 if verdict.outcomes else chief_acc
                    if isinstance(msg, MatureParams) and verdict.ack is not None and not verdict.ack.accepted:
                        start = time.perf_counter()
                        open_[wid] = _wire(algo.refused(msg), WorkerUpdate)  # refused: it learns on
                        worker_s[wid][-1] += time.perf_counter() - start
                        continue
                    break
                sent.add(wid)
                if keeper.done:
                    break
            for wid in list(open_):
                algo = algos[wid]
                if isinstance(open_[wid], MatureParams):
                    del open_[wid]  # finished (accepted); it plays on if its finish lets it help
                    sent.discard(wid)
                    algo.finished = True
                    if algo.per_step and keeper.workers[wid].helping:
                        catching_up[wid] = algo.skipped_rounds
                    continue
                if algo.round not in answers:
                    continue  # its round is still open (it went ahead of the others): it waits, as over MQTT
                sent.discard(wid)
                start = time.perf_counter()
                nxt = algo.apply(answers[algo.round])
                worker_s[wid][-1] += time.perf_counter() - start
                if nxt is None:
                    del open_[wid]  # its episode's rounds are done: it plays the next one
                else:
                    open_[wid] = _wire(nxt, WorkerUpdate)
            for old in [r for r in answers if r < keeper.round - AHEAD_ROUNDS_KEPT]:
                del answers[old]
            if progress and keeper.round > 1 and keeper.shape.ends_episode(keeper.round - 1):
                cells = " | ".join(f"{w} PI {algos[w].pi:.1f}" for w in ids if algos[w].pi is not None)
                print(f"episode {keeper.shape.episode_of(keeper.round - 1):4d} | {cells}", flush=True)
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


#: Closed rounds whose answers the runner keeps for workers that are behind.
AHEAD_ROUNDS_KEPT = 1000


def _wire(message: Any, *kinds: type) -> Any:
    """Through the same msgpack encoding as over MQTT (bit-exact tensors, the same validation)."""
    return decode(encode(message), *kinds)


@returns_code
def main(argv: list[str] | None = None) -> int:
    s = InprocessSettings.load(argv, prog="python -m deploy.inprocess", description=__doc__.splitlines()[0])
    summary = run_federation(s.env, s.policy, s.seed, s.workers, s.max_episodes, s.run_dir,
                             device_noise=s.device_noise, progress=True)
    last = summary["episodes_to_all_solved"]
    reason = summary["end_reason"]
    outcome = f"all workers solved by episode {last}" if last is not None else f"not all solved ({reason})"
    print(f"{s.env} / {s.policy} / seed {s.seed}: {outcome}; {summary['wall_s']:.1f} s; results in {s.run_dir}")
    return 0

if __name__ == "__main__":
    sys.exit(main())
