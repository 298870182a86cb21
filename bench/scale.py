"""``python -m bench.scale``: a flat chief against a root fed by edge chiefs (docs/explanation/tiered.md), with up
to 1,024 simulated devices (``make scale``; ``make scale-quick`` for the reduced set).

Each point is one federation over a Mosquitto started here on a free loopback port: a real root chief
(``python -m chief``, policy ``weighted``; ``--edges E`` in a tiered point), E real edge chiefs (``python -m chief
--role edge``), and N simulated devices (bench.fleets.SpreadFleet: one MQTT connection each, real-size CartPole-v0
actor gradients, no learning; device i behind edge ``e<i mod E>``; up to 128 devices per process). Every round each
device publishes its update at once and waits for the answer. Per point, over the rounds after the first
(connections warming up):

- ``root_ms_per_round``: the median of the root's own time per round, from its records (metrics.jsonl): first
  submission (a tiered root: its first edge's partial) counted to the round's record (receiving, decoding, the
  round state machine, Eq. 9, the record);
- ``root_cpu_ms_per_round``: the root process's CPU time per round (/proc, user + system);
- ``root_bytes_per_round``: the bytes the root's connection received per round (the kernel's TCP counters);
- ``round_ms``: round latency, from the first device's publish until the last device has the answer (median);
- ``broker_msgs_per_s``: the broker's messages received and sent per second over the measured rounds (its $SYS
  counters); ``update_bytes``: one device's update message;
- with ``--rigs R`` (default 1): R simulated QUBE rigs in real time on the same broker during the rounds, from their
  first answered state until the last round, each answered from its own process as a worker does (bench.rigs: the
  bridge's 7 ms loop in one process, its answering worker in another, neither sharing the benchmark's interpreter):
  what the rigs saw, from their telemetry: ``rig_state_to_action_p99_ms`` (the worst rig's p99 of state-publish ->
  action-arrival), ``rig_deadline_misses`` of ``rig_deadline_ticks`` (summed over the rigs: the ticks whose action
  came in time or missed its deadline) and ``rig_miss_rate``; ``rig_ticks``: the states their workers answered.

The audit (python -m chief.audit) checks every point's run folder. Hosts: one machine and one broker; the devices
and the root chief on 127.0.0.1, each edge chief in its own network namespace acting as a host (a veth pair to this
one, 10.201.k.0/30; needs root and ``ip``), or on 127.0.0.1 with ``--no-netns`` or where namespaces cannot be made
(one line says so; each row's ``edge_hosts`` and the report's ``hosts`` too). Writes bench/results/scale.json
(``--out``), one row per point.
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench import output
from bench.cost import RUN, actor_arrays
from bench.fleets import PER_PROCESS, SpreadFleet
from bench.rigs import RigProcess
from chief.audit import audit
from protocol.codec import encode
from protocol.messages import WorkerUpdate
from protocol.mqtt import BrokerAddress
from protocol.tasks import PI_WINDOW
from protocol.tensors import pack_arrays
from protocol.transport import connector
from runtime.records import EdgeRecord, EpisodeRecord, RoundRecord, read_metrics
from services.broker import mosquitto
from services.broker.embedded import free_port, stop_process

OUT = Path("bench/results/scale.json")
HOST = "127.0.0.1"
#: (devices, topology, edges) of ``make scale`` and ``make scale-quick``.
FULL = [(4, "flat", 0), (16, "flat", 0), (64, "flat", 0), (256, "flat", 0), (16, "tiered", 4), (64, "tiered", 4),
        (256, "tiered", 16), (1024, "tiered", 16), (1024, "flat", 0)]
QUICK = [(4, "flat", 0), (16, "flat", 0), (64, "flat", 0), (256, "tiered", 4)]
ROUNDS = 6
#: The root's and the edges' round and start timeouts (s): a safety net, never reached by a healthy point at any
#: speed. The devices wait longer (ANSWER_WAIT_S), and fail at once when a process of the federation dies.
ROUND_TIMEOUT_S = 600
#: How long the devices wait for an answer: past the chiefs' own timeout, so that a round the root gave up on shows
#: as a round that did not count every device (a clear error), not as a device's timeout racing the root's.
ANSWER_WAIT_S = ROUND_TIMEOUT_S + 60
#: The broker's configuration for every point. ``max_queued_messages 0``: no limit on the QoS 1 messages Mosquitto
#: holds for one client beyond its 20 in flight (default 1,000). A flat root gets N updates at once; where the
#: devices publish faster than it reads (a quiet machine with fast cores), more than 1,000 waited for it, Mosquitto
#: dropped the rest ("Outgoing messages are being dropped"), and the round waited for them until the timeout. The
#: devices wait for each answer before they publish again, so what it holds is bounded by one round (N updates).
BROKER_CONF = "sys_interval 1\nmax_queued_messages 0\n"
#: The flat chief's round at 64 workers over Mosquitto (bench/results/cost.json, round_s median): the target.
FLAT_64_MS = 82.0


def proc_stats(pid: int, port: int) -> tuple[float, int]:
    """A process's CPU seconds (user + system, /proc) and the bytes its TCP connections to the broker on ``port``
    have received (the kernel's ``bytes_received``, from ``ss``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    cpu = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    lines = subprocess.run(["ss", "-tinpH", "state", "established", f"dport = :{port}"], capture_output=True,
                           text=True, check=True).stdout.splitlines()
    received = 0
    for head, info in zip(lines[::2], lines[1::2], strict=False):
        if f"pid={pid}," in head:
            received += next((int(f.split(":")[1]) for f in info.split() if f.startswith("bytes_received:")), 0)
    return cpu, received


class BrokerCounters:
    """Mosquitto's $SYS message counters (received, sent), published every second."""

    def __init__(self, broker: str) -> None:
        self.values: dict[str, int] = {}
        self.updates: queue.Queue[str] = queue.Queue()
        self.conn = connector(BrokerAddress.parse(broker))(f"{RUN}-sys")
        for leaf in ("received", "sent"):
            self.conn.subscribe(f"$SYS/broker/messages/{leaf}", self._note, qos=0)
        self.conn.start()

    def _note(self, topic: str, payload: bytes) -> None:
        self.values[topic.rsplit("/", 1)[-1]] = int(payload)

    def total(self) -> int:
        return sum(self.values.values())

    def stop(self) -> None:
        self.conn.stop()


class EdgeHosts:
    """Network namespaces acting as the edges' hosts: edge k runs in namespace ``fedrl-scale-e<k>``, joined to this
    host by a veth pair (10.201.k.1 on this side, 10.201.k.2 on its side), and reaches the broker over it."""

    def __init__(self, count: int) -> None:
        self.names = [f"fedrl-scale-e{k}" for k in range(count)]

    @classmethod
    def make(cls, count: int) -> EdgeHosts | None:
        """The namespaces, or None (after one line saying why) where they cannot be made (not root, no ``ip``)."""
        hosts = cls(count)
        try:
            for k, ns in enumerate(hosts.names):
                here, there = f"fe{k}h", f"fe{k}n"
                for cmd in (["netns", "add", ns], ["link", "add", here, "type", "veth", "peer", "name", there],
                            ["link", "set", there, "netns", ns], ["addr", "add", f"10.201.{k}.1/30", "dev", here],
                            ["link", "set", here, "up"],
                            ["netns", "exec", ns, "ip", "addr", "add", f"10.201.{k}.2/30", "dev", there],
                            ["netns", "exec", ns, "ip", "link", "set", there, "up"],
                            ["netns", "exec", ns, "ip", "link", "set", "lo", "up"]):
                    subprocess.run(["ip", *cmd], check=True, capture_output=True, text=True)
        except (OSError, subprocess.CalledProcessError) as err:
            hosts.close()
            print(f"scale: no network namespaces ({getattr(err, 'stderr', '') or err}): every edge on 127.0.0.1",
                  flush=True)
            return None
        return hosts

    def command(self, k: int, argv: list[str]) -> list[str]:
        return ["ip", "netns", "exec", self.names[k], *argv]

    @staticmethod
    def broker(k: int, port: int) -> str:
        return f"mqtt://10.201.{k}.1:{port}"

    def close(self) -> None:
        for ns in self.names:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)  # its end of the veth pair goes with it


def gone(procs: list[tuple[str, subprocess.Popen[bytes]]]) -> str | None:
    """Why the federation cannot answer any more: the first of its processes that failed (None while none has; one
    that exited 0 has ended its run, and its last answers may still be on their way)."""
    for name, proc in procs:
        if proc.poll() not in (None, 0):
            return f"{name} exited with code {proc.returncode}"
    return None


def check_counted(run_dir: Path, devices: int) -> None:
    """Every round of the root counted every device (RuntimeError naming the first that did not: the root gave up
    on some, and the point did not measure what it says)."""
    for rec in read_metrics(run_dir):
        if isinstance(rec, RoundRecord) and len(rec.contributors) != devices:
            raise RuntimeError(f"round {rec.round} counted {len(rec.contributors)} of {devices} devices (timed out: "
                               f"{len(rec.timed_out)})")


def root_times(run_dir: Path) -> list[float]:
    """Per round, from the root's records: its first counted submission to the round's record (s)."""
    first: dict[int, float] = {}
    closed: dict[int, float] = {}
    for rec in read_metrics(run_dir):
        if isinstance(rec, RoundRecord):
            closed[rec.round] = rec.t
        elif isinstance(rec, (EpisodeRecord, EdgeRecord)):  # a tiered root records its edges' partials
            first[rec.round] = min(first.get(rec.round, rec.t), rec.t)
    return [closed[r] - first[r] for r in sorted(closed) if r in first]


def measured_rounds(fleet: SpreadFleet, root: subprocess.Popen[bytes], port: int, counters: BrokerCounters,
                    rounds: int) -> tuple[list[dict[str, float]], list[float], list[int], float]:
    """The rounds: each one's latencies, the root's CPU seconds and received bytes, and the broker's messages per
    second after the first round."""
    times, cpu, read = [], [], []
    stats = proc_stats(root.pid, port)
    msgs, began = counters.total(), time.monotonic()
    for episode in range(1, rounds + 1):
        times.append(fleet.round(episode, timeout=ANSWER_WAIT_S))
        now = proc_stats(root.pid, port) if root.poll() is None else stats
        cpu.append(now[0] - stats[0])
        read.append(now[1] - stats[1])
        stats = now
        if episode == 1:  # the measurement starts after the first round
            time.sleep(1.5)  # let the $SYS counters catch up
            msgs, began = counters.total(), time.monotonic()
    time.sleep(1.5)
    return times, cpu, read, (counters.total() - msgs) / (time.monotonic() - began)


def point(devices: int, topology: str, edges: int, rounds: int, arrays: dict[str, Any], folder: Path,
          netns: bool = True, rigs: int = 0, per_process: int = PER_PROCESS) -> dict[str, Any]:
    """One federation of ``devices`` simulated devices, flat or behind ``edges`` edge chiefs (each in its own
    network namespace with ``netns``, where they can be made), for ``rounds``; ``rigs`` simulated rigs answered
    meanwhile; at most ``per_process`` devices per process."""
    name = f"{topology}-{devices}" + (f"-{edges}e" if edges else "")
    work = folder / name
    work.mkdir()
    hosts = EdgeHosts.make(edges) if netns and edges else None
    outer = free_port()  # the listener the namespaces reach (every address), beside the loopback one
    broker_proc, port = mosquitto.start(work, max_packet_size=8 * 1024 * 1024,
                                        extra=BROKER_CONF + (f"listener {outer}\n" if hosts else ""))
    broker = f"mqtt://{HOST}:{port}"
    run_dir = work / "run"
    logs = [(work / f"{n}.log").open("wb") for n in ["root", *(f"e{k}" for k in range(edges))]]
    common = ["--broker", broker, "--run-id", RUN, "--env", "CartPole-v0", "--round-timeout", str(ROUND_TIMEOUT_S),
              "--start-timeout", str(ROUND_TIMEOUT_S), "--log-level", "WARNING"]
    root = subprocess.Popen([sys.executable, "-m", "chief", *common, "--workers", str(devices), "--edges", str(edges),
                             "--max-episodes", str(rounds), "--run-dir", str(run_dir)],
                            stdout=logs[0], stderr=subprocess.STDOUT)
    edge_procs = [subprocess.Popen(
        hosts.command(k, [sys.executable, "-m", "chief", *common, "--broker", hosts.broker(k, outer), "--role", "edge",
                          "--edge-id", f"e{k}", "--run-dir", str(run_dir)]) if hosts else
        [sys.executable, "-m", "chief", *common, "--role", "edge", "--edge-id", f"e{k}", "--run-dir", str(run_dir)],
        stdout=logs[k + 1], stderr=subprocess.STDOUT) for k in range(edges)]
    fleet = counters = None
    answered: list[RigProcess] = []
    rig_stats: list[dict[str, Any]] = []
    try:
        print(f"scale: {name}: connecting {devices} devices", flush=True)
        counters = BrokerCounters(broker)
        fleet = SpreadFleet(broker, devices, arrays, edges=edges, per_process=per_process,
                            watch=lambda: gone([("the broker", broker_proc), ("the root chief", root),
                                                *((f"edge chief e{k}", p) for k, p in enumerate(edge_procs))]))
        fleet.join(timeout=ANSWER_WAIT_S)
        answered = [RigProcess(broker, f"scale-rig{k}", timeout=ANSWER_WAIT_S) for k in range(rigs)]
        for r in answered:
            r.answering()  # the rounds start once every rig is balancing: its latencies are those of the rounds
        times, cpu, read, msgs_per_s = measured_rounds(fleet, root, port, counters, rounds)
        rig_stats = [r.finish() for r in answered]
        answered = []
        root.wait(ROUND_TIMEOUT_S)  # its RunStop to "run over" took 4-19 s under load: a safety net only
        for p in edge_procs:
            p.wait(ROUND_TIMEOUT_S)
        report = audit(run_dir)
        check_counted(run_dir, devices)
    finally:
        for r in answered:
            r.kill()
        if fleet is not None:
            fleet.stop()
        if counters is not None:
            counters.stop()
        for p in [root, *edge_procs]:
            stop_process(p)
        for log in logs:
            log.close()
        stop_process(broker_proc)
        if hosts is not None:
            hosts.close()
    steady = slice(1, None) if rounds > 1 else slice(None)
    rng = np.random.default_rng(0)
    update = WorkerUpdate(worker_id=f"w{devices - 1}", episode=rounds, episode_return=20.0, pi=20.0,
                          recent_returns=[20.0] * min(rounds, PI_WINDOW), steps=20,
                          gradient=pack_arrays({k: rng.normal(0, 1e-3, v.shape).astype(np.float32)
                                                for k, v in arrays.items()}))
    return {"n": devices, "topology": topology, "edges": edges, "rounds": rounds,
            "root_ms_per_round": round(1000 * statistics.median(root_times(run_dir)[steady]), 2),
            "root_cpu_ms_per_round": round(1000 * statistics.mean(cpu[steady]), 1),
            "root_bytes_per_round": int(statistics.median(read[steady])),
            "update_bytes": len(encode(update)),
            "round_ms": round(1000 * statistics.median(t["last_s"] for t in times[steady]), 1),
            "broker_msgs_per_s": {"core": round(msgs_per_s, 1)},
            "edge_hosts": "network namespaces" if hosts else ("127.0.0.1" if edges else None),
            **(rig_row(rig_stats) if rig_stats else {}),
            "audit": str(report)}


def rig_row(rig_stats: list[dict[str, Any]]) -> dict[str, Any]:
    """A point's rig columns: what its rigs saw (their telemetry), summed over them; the worst rig's p99."""
    misses = sum(r["deadline_misses"] for r in rig_stats)
    ticks = int(sum(r["latency_ms"]["n"] + r["deadline_misses"] for r in rig_stats))
    return {"rigs": len(rig_stats), "rig_answered_from": "its own process",
            "rig_state_to_action_p99_ms": max(r["latency_ms"]["p99"] for r in rig_stats),
            "rig_deadline_misses": misses, "rig_deadline_ticks": ticks,
            "rig_miss_rate": round(misses / ticks, 4) if ticks else None,
            "rig_ticks": sum(r["ticks_answered"] for r in rig_stats)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.scale", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"the reduced set: {QUICK}")
    parser.add_argument("--point", action="append", default=[], metavar="N:TOPOLOGY[:EDGES]",
                        help="measure this point instead (repeatable), e.g. 1024:tiered:16 or 64:flat")
    parser.add_argument("--rounds", type=int, default=ROUNDS, help=f"rounds per point (default {ROUNDS})")
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--no-netns", action="store_true", help="every edge on 127.0.0.1 (no network namespaces)")
    parser.add_argument("--rigs", type=int, default=1,
                        help="simulated rigs in real time answered during each point's rounds (default 1; 0: none)")
    args = parser.parse_args(argv)
    points = [(int(n), topology, int(rest[0]) if rest else 0) for n, topology, *rest in
              (p.split(":") for p in args.point)] if args.point else (QUICK if args.quick else FULL)
    arrays = actor_arrays("CartPole-v0")
    began = time.monotonic()
    load = os.getloadavg()[0]
    rows = []
    failed = 0
    with tempfile.TemporaryDirectory(prefix="fedrl-scale-") as tmp:
        for n, topology, edges in points:
            try:
                r = point(n, topology, edges, args.rounds, arrays, Path(tmp), netns=not args.no_netns,
                          rigs=args.rigs)
            except Exception as exc:  # one failed point (a device's connection timed out, say) is a row saying so
                failed += 1
                rows.append({"n": n, "topology": topology, "edges": edges, "error": f"{type(exc).__name__}: {exc}"})
                print(f"scale: {n} devices {topology} ({edges} edges) FAILED: {rows[-1]['error']}", flush=True)
            else:
                rows.append(r)
                rig = (f", rigs' state-to-action p99 {r['rig_state_to_action_p99_ms']} ms" if "rigs" in r else "")
                print(f"scale: {r['n']} devices {r['topology']} ({r['edges']} edges): root {r['root_ms_per_round']} "
                      f"ms ({r['root_cpu_ms_per_round']} ms CPU) and {r['root_bytes_per_round']} B per round, round "
                      f"{r['round_ms']} ms, broker {r['broker_msgs_per_s']['core']} msg/s{rig}; audit {r['audit']}",
                      flush=True)
            write(args.out, rows, load, began, argv)  # after every point: a later failure keeps what was measured
    print(f"scale: {len(rows)} points in {args.out} ({round(time.monotonic() - began, 1)} s), {failed} failed")
    return 1 if failed else 0


def write(out: Path, rows: list[dict[str, Any]], load: float, began: float, argv: list[str] | None) -> None:
    """scale.json: the rows so far and how they were measured."""
    spread = {r.get("edge_hosts") for r in rows if r.get("edge_hosts")}
    result = {"points": rows, "hosts": "one machine, one Mosquitto; the devices and the root on 127.0.0.1, each edge "
              + ("in its own network namespace (a veth pair to this host)" if spread == {"network namespaces"}
                 else "on 127.0.0.1" if spread else "(no edges)"),
              "cores": os.cpu_count(), "load_average_at_start": load, "wall_s": round(time.monotonic() - began, 1),
              "flat_64_ms_cost_json": FLAT_64_MS,
              "command": output.command("bench.scale", argv)}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    sys.exit(main())
