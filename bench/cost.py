"""``python -m bench.cost``: what federation costs: bytes per round, and the chief's time per round for 4, 16 and 64
workers over Mosquitto and over the embedded amqtt broker (plus, from bench.paper's runs, env steps per second per
worker and the share of a worker's time spent waiting for the chief).

- **Bytes**: the real messages, encoded with protocol.codec.encode, for each task's actor (built by
  worker.episode.build_learner_and_env): a WorkerUpdate (actor gradient, 10 recent returns, receipt), the
  ChiefAggregate and ChiefTransfer for N workers, a MatureParams. Per aggregate round with N workers, N updates go
  to the chief and the broker delivers the aggregate to each of the N workers. Bytes on the wire add each MQTT
  PUBLISH packet's header (fixed header, topic, packet id); QoS 1 acknowledgements (4 bytes each) are left out.
- **Chief time per round**: a real ``python -m chief`` process (policy ``weighted`` unless told) on a broker started
  here on a free loopback port, and N scripted workers, each its own MQTT connection, that speak the wire format
  with real-size CartPole-v0 actor gradients and PIs below TC (so every round is an aggregate round). Each round
  every worker publishes its update (encoded beforehand), and the clock runs from the first publish until the last
  worker has the round's ChiefAggregate: the round's service time when workers answer instantly. From the chief's
  own records (metrics.jsonl) also: the time from the round's first to its last accepted update (receiving and
  decoding) and from the last update to the aggregate (aggregating and recording). The first round is left out
  (connections warming up). Growth with the worker count: the exponent b of t ~ N^b between the smallest and largest N.
- **Workers against N**: in-process federations of CartPole-v0 (``weighted``, seed 101) with 4, 16 and 64 workers for
  a fixed number of rounds: each worker's env steps per second and its waiting share, modelled as if every worker
  had its own core (bench/runs.py), and the chief side's seconds per round without a broker.
"""

from __future__ import annotations

import argparse
import json
import math
import queue
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from contextlib import suppress
from pathlib import Path
from typing import Any

import numpy as np

from chief import strategies
from protocol import topics
from protocol.codec import decode, encode
from protocol.messages import (
    ChiefAggregate,
    ChiefTransfer,
    MatureParams,
    Receipt,
    WorkerHello,
    WorkerUpdate,
)
from protocol.mqtt import BrokerAddress
from protocol.routes import hello_wait
from protocol.tasks import PI_WINDOW
from protocol.tensors import digest, pack_arrays
from protocol.transport import Transport, connector
from runtime.records import EpisodeRecord, RoundRecord, StepRecord, read_metrics
from services.broker import mosquitto

WORKER_COUNTS = (4, 16, 64)
ROUNDS = 20
HOST = "127.0.0.1"
RUN = "costbench"
SIZE_TASKS = ("CartPole-v0", "Acrobot-v1", "MountainCarContinuous-v0", "Pendulum-v1", "qube-local")


# -- bytes ------------------------------------------------------------------------------------------------------


def actor_arrays(env_id: str) -> dict[str, np.ndarray]:
    """The default actor of a task's worker, as float32 arrays (real shapes)."""
    from worker.episode import build_learner_and_env

    env, learner = build_learner_and_env(env_id, seed=1, device_noise=1.0, spec_only=env_id.startswith("qube"))
    close = getattr(env, "close", None)
    if close is not None:
        close()
    return {k: np.asarray(v, np.float32) for k, v in learner.actor_parameters().items()}


def publish_packet_bytes(topic: str, payload: int, qos: int = 1) -> int:
    """Size of an MQTT 3.1.1 PUBLISH packet: fixed header (1 byte + remaining length), topic, packet id, payload."""
    remaining = 2 + len(topic.encode()) + (2 if qos else 0) + payload
    length_bytes = 1 if remaining < 128 else 2 if remaining < 16_384 else 3 if remaining < 2_097_152 else 4
    return 1 + length_bytes + remaining


def sample_messages(arrays: dict[str, np.ndarray], workers: int) -> dict[str, bytes]:
    """Encoded messages of one round, as the system sends them (values random, sizes real)."""
    rng = np.random.default_rng(0)
    grad = pack_arrays({k: rng.normal(0, 1e-3, v.shape).astype(np.float32) for k, v in arrays.items()})
    params = pack_arrays(arrays)
    ids = [f"w{i}" for i in range(workers)]
    returns = [float(rng.normal(100, 10)) for _ in range(PI_WINDOW)]
    receipt = Receipt(round=99, applied="aggregate", digest=digest(grad))
    update = WorkerUpdate(worker_id="w0", episode=100, episode_return=returns[-1], pi=sum(returns) / len(returns),
                          recent_returns=returns, steps=200, gradient=grad, receipt=receipt, actor_loss=-0.01,
                          critic_loss=0.5, entropy=0.6)
    aggregate = ChiefAggregate(round=100, episode=100, gradient=grad, weights={w: 1.0 / workers for w in ids},
                               contributors=ids)
    transfer = ChiefTransfer(round=100, episode=100, source_worker="w0", source_pi=200.0, params=params,
                             keep_weights={w: 0.5 for w in ids[1:]}, finished=["w0"])
    mature = MatureParams(worker_id="w0", episode=100, episode_return=returns[-1], pi=sum(returns) / len(returns),
                          recent_returns=returns, steps=200, params=params, receipt=receipt)
    return {"update": encode(update), "aggregate": encode(aggregate), "transfer": encode(transfer),
            "mature": encode(mature)}


def bytes_per_round(env_id: str, worker_counts: tuple[int, ...] = WORKER_COUNTS,
                    arrays: dict[str, np.ndarray] | None = None) -> dict[str, Any]:
    """Message sizes and the bytes of one aggregate round for each worker count."""
    arrays = actor_arrays(env_id) if arrays is None else arrays
    params = int(sum(v.size for v in arrays.values()))
    per_n = {}
    sizes: dict[str, int] = {}
    for n in worker_counts:
        msgs = sample_messages(arrays, n)
        sizes = {k: len(v) for k, v in msgs.items()}
        up_topic, agg_topic = topics.worker(RUN, f"w{n - 1}", topics.UPDATE), topics.chief(RUN, "aggregate")
        up_wire = publish_packet_bytes(up_topic, sizes["update"])
        agg_wire = publish_packet_bytes(agg_topic, sizes["aggregate"])
        per_n[str(n)] = {"message_bytes": sizes,
                         "payload_bytes": n * sizes["update"] + n * sizes["aggregate"],
                         "wire_bytes": n * up_wire + n * agg_wire,
                         "per_worker_wire_bytes": up_wire + agg_wire}
    return {"task": env_id, "actor_parameters": params, "actor_float32_bytes": params * 4, "per_workers": per_n}


# -- chief time per round ----------------------------------------------------------------------------------------


class ScriptedFleet:
    """N fake workers, one MQTT connection each, speaking the wire format with real-size gradients; with ``edges``
    E > 0, worker i is behind edge chief ``e<i mod E>`` (a tiered run, bench/scale.py)."""

    def __init__(self, broker: str, workers: int, arrays: dict[str, np.ndarray], edges: int = 0, first: int = 0,
                 connect_timeout: float = 10.0) -> None:
        """``workers`` devices ``w<first>``, ``w<first + 1>``, ... (bench/fleets.py spreads a larger fleet over
        processes, each holding one such slice)."""
        self.ids = [f"w{first + i}" for i in range(workers)]
        self.edge = {w: f"e{(first + i) % edges}" for i, w in enumerate(self.ids)} if edges else {}
        self.spec = {k: tuple(v.shape) for k, v in arrays.items()}
        rng = np.random.default_rng(1 + first)
        self.grads = {w: pack_arrays({k: rng.normal(0, 1e-3, v.shape).astype(np.float32) for k, v in arrays.items()})
                      for w in self.ids}
        self.arrivals: dict[int, dict[str, float]] = {}
        self.started: set[str] = set()  # the workers that have read the RunStart (from their edge, when behind one)
        self.answers: queue.Queue[Any] = queue.Queue()
        self.lock = threading.Lock()
        self.conns: list[Transport] = []
        connect = connector(BrokerAddress.parse(broker))
        for w in self.ids:
            conn = connect(f"{RUN}-fake-{w}")
            conn.subscribe(topics.relayed(RUN, self.edge[w], "+") if w in self.edge else topics.chief(RUN, "+"),
                           self._handler(w))
            self.conns.append(conn.start(connect_timeout))

    def _handler(self, wid: str) -> Any:
        def on_message(topic: str, payload: bytes) -> None:
            now = time.monotonic()  # CLOCK_MONOTONIC: one clock for every process of a spread fleet
            leaf = topic.rsplit("/", 1)[-1]
            if leaf == "aggregate":
                if wid == self.ids[0]:  # one worker decodes (for the receipts); the rest just note the arrival
                    msg = decode(payload, ChiefAggregate)
                    self.answers.put(msg)
                    episode = msg.episode
                else:
                    episode = -1
                with self.lock:
                    self.arrivals.setdefault(episode, {})[wid] = now
            elif leaf == "start":
                with self.lock:
                    self.started.add(wid)
                self.answers.put(topics.START)  # wakes join up
        return on_message

    def join(self, timeout: float = 60.0) -> None:
        """Hellos, as a worker says them (protocol.routes.hello_wait apart), until every worker has read a RunStart:
        a worker behind an edge reads it from its edge, which may start after the root did (and so after the
        workers of another edge could start); an update sent before its edge serves it would be lost."""
        deadline = time.monotonic() + timeout
        sent = 0
        while time.monotonic() < deadline:
            with self.lock:
                waiting = [(w, conn) for w, conn in zip(self.ids, self.conns, strict=True) if w not in self.started]
            if not waiting:
                return
            for w, conn in waiting:
                hello = WorkerHello(worker_id=w, env_id="CartPole-v0", actor_spec=self.spec, edge=self.edge.get(w))
                conn.publish(topics.worker(RUN, w, topics.HELLO), encode(hello))
            sent += 1
            with suppress(queue.Empty):
                while len(self.started) < len(self.ids):
                    self.answers.get(timeout=hello_wait(sent))
        with self.lock:
            missing = sorted(set(self.ids) - self.started)
        raise TimeoutError(f"the chief never started the run for {', '.join(missing)}")

    def round(self, episode: int, previous: ChiefAggregate | None, timeout: float = 120.0) -> dict[str, float]:
        """One round: every worker publishes its update; returns the seconds until the first and the last worker
        had the aggregate (``first_s``, ``last_s``) and the clock (time.monotonic) at the first publish, the first
        and the last arrival (``start``, ``first``, ``last``)."""
        receipt = None
        if previous is not None:
            receipt = Receipt(round=previous.episode, applied="aggregate",
                              digest=digest(previous.gradient) if previous.gradient is not None else "")
        payloads = []
        for w in self.ids:
            ret = 20.0  # PI 20 < TC 195: nobody finishes
            msg = WorkerUpdate(worker_id=w, episode=episode, episode_return=ret, pi=ret,
                               recent_returns=[ret] * min(episode, PI_WINDOW), steps=20, gradient=self.grads[w],
                               receipt=receipt)
            payloads.append(encode(msg))
        with self.lock:
            self.arrivals.pop(-1, None)
        start = time.monotonic()
        for w, conn, payload in zip(self.ids, self.conns, payloads, strict=True):
            conn.publish(topics.worker(RUN, w, topics.UPDATE), payload)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self.lock:
                got = {**self.arrivals.get(episode, {}), **self.arrivals.get(-1, {})}
            if len(got) == len(self.ids):
                first, last = min(got.values()), max(got.values())
                return {"first_s": first - start, "last_s": last - start, "start": start, "first": first,
                        "last": last}
            time.sleep(0.0005)
        raise TimeoutError(f"round {episode}: only {len(got)} of {len(self.ids)} workers got the aggregate")

    def latest(self, episode: int, timeout: float = 30.0) -> ChiefAggregate:
        while True:
            msg = self.answers.get(timeout=timeout)
            if isinstance(msg, ChiefAggregate) and msg.episode == episode:
                return msg

    def stop(self) -> None:
        for conn in self.conns:
            conn.stop()


def chief_load(broker_kind: str, workers: int, rounds: int, strategy: str = strategies.DEFAULT,
               arrays: dict[str, np.ndarray] | None = None) -> dict[str, Any]:
    """Rounds of a real chief process with ``workers`` scripted workers on a fresh broker (mosquitto | amqtt)."""
    from services.broker.embedded import start_broker_process, stop_process

    arrays = actor_arrays("CartPole-v0") if arrays is None else arrays
    with tempfile.TemporaryDirectory(prefix="fedrl-cost-") as tmp:
        folder = Path(tmp)
        if broker_kind == "mosquitto":
            broker_proc, port = mosquitto.start(folder, max_packet_size=8 * 1024 * 1024)
        else:
            with (folder / "amqtt.log").open("wb") as log:
                broker_proc, port = start_broker_process(HOST, stdout=log, stderr=subprocess.STDOUT)
        broker = f"mqtt://{HOST}:{port}"
        run_dir = folder / "run"
        chief_log = (folder / "chief.log").open("wb")
        chief = subprocess.Popen(
            [sys.executable, "-m", "chief", "--broker", broker, "--run-id", RUN, "--workers", str(workers),
             "--env", "CartPole-v0", "--policy", strategy, "--max-episodes", str(rounds), "--round-timeout", "120",
             "--start-timeout", "120", "--run-dir", str(run_dir), "--log-level", "WARNING"],
            stdout=chief_log, stderr=subprocess.STDOUT)
        fleet = None
        try:
            fleet = ScriptedFleet(broker, workers, arrays)
            fleet.join()
            times, previous = [], None
            for episode in range(1, rounds + 1):
                times.append(fleet.round(episode, previous))
                previous = fleet.latest(episode)
            chief.wait(60)
            inside = _chief_side(run_dir)
        finally:
            if fleet is not None:
                fleet.stop()
            stop_process(chief)
            chief_log.close()
            stop_process(broker_proc)
    steady = times[1:] if len(times) > 1 else times
    last = [t["last_s"] for t in steady]
    return {"broker": broker_kind, "workers": workers, "strategy": strategy, "rounds": rounds,
            "round_s": _summary(last), "first_answer_s": _summary([t["first_s"] for t in steady]),
            "chief_receive_s": _summary(inside["receive"][1:]), "chief_aggregate_s": _summary(inside["aggregate"][1:])}


def _chief_side(run_dir: Path) -> dict[str, list[float]]:
    """Per round, from the chief's records: first to last accepted update, and last update to the round's record."""
    accepted: dict[int, list[float]] = {}
    closed: dict[int, float] = {}
    for rec in read_metrics(run_dir):
        if isinstance(rec, RoundRecord):
            closed[rec.round] = rec.t
        elif isinstance(rec, (EpisodeRecord, StepRecord)):
            accepted.setdefault(rec.round, []).append(rec.t)
    receive, aggregate = [], []
    for r in sorted(closed):
        ts = accepted.get(r, [])
        if ts:
            receive.append(max(ts) - min(ts))
            aggregate.append(closed[r] - max(ts))
    return {"receive": receive, "aggregate": aggregate}


def _summary(values: list[float]) -> dict[str, float | None]:
    if not values:
        return {"median": None, "p90": None, "max": None}
    return {"median": round(statistics.median(values), 5), "p90": round(float(np.percentile(values, 90)), 5),
            "max": round(max(values), 5)}


def growth(points: dict[int, float]) -> dict[str, float | None]:
    """Exponent b of t ~ N^b between the smallest and largest N, and t per worker at each N."""
    ns = sorted(n for n, t in points.items() if t)
    out: dict[str, Any] = {"per_worker_s": {str(n): round(points[n] / n, 6) for n in ns}}
    if len(ns) >= 2:
        lo, hi = ns[0], ns[-1]
        out["exponent"] = round(math.log(points[hi] / points[lo]) / math.log(hi / lo), 3)
        out["ratio"] = round(points[hi] / points[lo], 2)
        out["between"] = [lo, hi]
    return out


# -- workers: env steps per second and waiting, against the worker count ------------------------------------------


def worker_scaling(runs_dir: Path, worker_counts: tuple[int, ...] = WORKER_COUNTS, rounds: int = 30,
                   task: str = "CartPole-v0", strategy: str = strategies.DEFAULT, seed: int = 101) -> dict[str, Any]:
    """In-process federations of N workers for ``rounds`` rounds (one seed): each worker's env steps per second and
    modelled waiting share (bench.runs), and the chief's CPU seconds per round (decoding the submissions, the round
    state machine, the records, encoding its answer; no broker), for each N."""
    from bench.runs import Job, collect
    from bench.stats import spread
    from deploy.inprocess import run_federation
    from deploy.settings import InprocessSettings

    points = []
    for n in worker_counts:
        print(f"cost: {n} workers in process, {rounds} rounds of {task}", flush=True)
        job = Job("federation", task, strategy, seed, n, rounds)
        run_dir = runs_dir / f"scaling-{job.name}"
        run_federation(InprocessSettings.given(env=task, policy=strategy, seed=seed, workers=n, max_episodes=rounds,
                       run_dir=run_dir), plot=False, tensorboard_files=False)
        result = collect(run_dir, job)
        chief_s = json.loads((run_dir / "timing.json").read_text())["chief_s"]
        workers = result["per_worker"]
        points.append({"workers": n, "rounds": result["rounds"], "audit_passed": result["audit"]["passed"],
                       "steps_per_s": spread([w["steps_per_s"] for w in workers if w["steps_per_s"]]),
                       "wait_share": spread([w["wait_share"] for w in workers if w["wait_share"] is not None]),
                       "chief_s_per_round": _summary(chief_s[1:])})
    return {"task": task, "strategy": strategy, "seed": seed, "rounds": rounds, "time_basis": "modelled",
            "points": points,
            "growth": {"steps_per_s": growth({p["workers"]: p["steps_per_s"]["median"] for p in points}),
                       "wait_share": growth({p["workers"]: p["wait_share"]["median"] for p in points}),
                       "chief_s_per_round": growth({p["workers"]: p["chief_s_per_round"]["median"]
                                                    for p in points})}}


# -- from bench.paper's runs ----------------------------------------------------------------------------------


def from_runs(paper_reports: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Per task: env steps/s per worker and waiting share, over all federation runs and for the single worker."""
    from bench.stats import spread

    out = {}
    for task, rep in paper_reports.items():
        row: dict[str, Any] = {}
        for kind in ("federation", "single"):
            workers = [w for r in rep["runs"] if r["kind"] == kind and "error" not in r for w in r["per_worker"]]
            if not workers:
                continue
            n = next(r["workers"] for r in rep["runs"] if r["kind"] == kind and "error" not in r)
            row[kind] = {"workers_per_run": n,
                         "steps_per_s": spread([w["steps_per_s"] for w in workers if w.get("steps_per_s")]),
                         "wait_share": spread([w["wait_share"] for w in workers if w.get("wait_share") is not None]),
                         "time_basis": sorted({w.get("time_basis", "?") for w in workers})}
        out[task] = row
    return out


def run_all(out: Path, rounds: int = ROUNDS, worker_counts: tuple[int, ...] = WORKER_COUNTS,
            brokers: tuple[str, ...] = ("mosquitto", "amqtt"), strategy: str = strategies.DEFAULT,
            paper_reports: dict[str, dict[str, Any]] | None = None, size_tasks: tuple[str, ...] = SIZE_TASKS,
            scaling_rounds: int = 0, runs_dir: Path | None = None, scaling_workers: tuple[int, ...] | None = None
            ) -> dict[str, Any]:
    """Everything; written to ``out/cost.json`` and returned (``scaling_rounds`` 0: no worker scaling runs)."""
    t0 = time.monotonic()
    cartpole = actor_arrays("CartPole-v0")
    result: dict[str, Any] = {"bytes": {t: bytes_per_round(t, worker_counts, cartpole if t == "CartPole-v0" else None)
                                        for t in size_tasks}}
    loads = []
    skipped = []
    for broker in brokers:
        if broker == "mosquitto" and not mosquitto.available():
            skipped.append("mosquitto (not installed)")
            continue
        for n in worker_counts:
            print(f"cost: chief with {n} workers over {broker}, {rounds} rounds", flush=True)
            loads.append(chief_load(broker, n, rounds, strategy, cartpole))
    result["chief"] = {"task": "CartPole-v0", "strategy": strategy, "rounds_per_point": rounds, "skipped": skipped,
                       "points": loads,
                       "growth": {b: growth({p["workers"]: p["round_s"]["median"] for p in loads if p["broker"] == b})
                                  for b in brokers}}
    if paper_reports:
        result["workers"] = from_runs(paper_reports)
    if scaling_rounds:
        result["scaling"] = worker_scaling(runs_dir or out / "runs", scaling_workers or worker_counts, scaling_rounds)
    result["wall_s"] = round(time.monotonic() - t0, 1)
    out.mkdir(parents=True, exist_ok=True)
    (out / "cost.json").write_text(json.dumps(result, indent=1) + "\n")
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.cost", description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=ROUNDS)
    parser.add_argument("--workers", type=int, nargs="+", default=list(WORKER_COUNTS))
    parser.add_argument("--brokers", nargs="+", default=["mosquitto", "amqtt"], choices=["mosquitto", "amqtt"])
    parser.add_argument("--strategy", default=strategies.DEFAULT)
    parser.add_argument("--scaling-rounds", type=int, default=30,
                        help="rounds of the in-process worker scaling runs (0: none)")
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    args = parser.parse_args(argv)
    result = run_all(args.out, args.rounds, tuple(args.workers), tuple(args.brokers), args.strategy,
                     scaling_rounds=args.scaling_rounds, runs_dir=Path("bench/results/runs/cost"))
    print(json.dumps(result["chief"]["growth"], indent=1))
    for p in result["chief"]["points"]:
        print(f"{p['broker']:>9} N={p['workers']:>3}: round {p['round_s']['median'] * 1000:.1f} ms median "
              f"(p90 {p['round_s']['p90'] * 1000:.1f}); chief receive {p['chief_receive_s']['median']} s, "
              f"aggregate {p['chief_aggregate_s']['median']} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
