"""``python -m bench.latency``: state-to-action latency through the bridge loop and a worker, per broker.

For each broker (the embedded amqtt, and Mosquitto with ``set_tcp_nodelay true`` where installed) it starts the broker
and a simulated rig in real time (``python -m services.qube_sim --clock realtime``: the bridge's own control loop, 7 ms
period and deadline) as separate processes, and answers the rig's states from this process the way a worker does:
observation -> the learner's actor forward pass (``--algo``: each learner in turn) -> action. The answers follow a
balancing rule so that episodes last; the actor's sampled action is computed (and timed) but not sent. After ``--ticks``
answered states it reads the rig's own telemetry: p50/p99/max of state-publish -> action-arrival, of state-read ->
motor-write (the deadline held at the motor: an action whose write would start after the read + 7 ms is not written),
deadline misses, late actions and actions dropped at the motor. ``--stress N`` runs N busy processes meanwhile (a loaded
machine). Writes ``bench/results/latency.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import queue
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from protocol import learners as names
from protocol import topics
from protocol.codec import decode
from protocol.messages import QubeTelemetry
from protocol.mqtt import BrokerAddress, MqttConnection
from rpi_bridge.runner import percentiles
from services.broker import mosquitto
from services.broker.embedded import start_broker_process, stop_process
from worker import learners
from worker.qube_env import QubeMqttEnv

RESULTS = Path("bench/results")


def learners_config(algo: str) -> object:
    """The QUBE's preset of learner ``algo`` (worker/envs.py)."""
    from worker.envs import env_spec

    return env_spec("qube").learner_config(algo)


def balance_action(obs: np.ndarray) -> int:
    alpha, alpha_dot, theta, theta_dot = (float(x) for x in obs)
    u = -(12.7 * theta - 563.3 * alpha + 13.3 * theta_dot - 39.0 * alpha_dot)
    return 2 if u > 20 else (0 if u < -20 else 1)


def measure(broker_name: str, ticks: int, workdir: Path, stress: int = 0, algo: str = names.DEFAULT) -> dict:
    if broker_name == "mosquitto":
        broker, port = mosquitto.start(workdir, max_packet_size=None)
    else:
        broker, port = start_broker_process(stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    url = f"mqtt://127.0.0.1:{port}"
    rig_id = f"bench-{broker_name}"
    rig = subprocess.Popen([sys.executable, "-m", "services.qube_sim", "--broker", url, "--rig-id", rig_id,
                            "--clock", "realtime", "--log-level", "WARNING"])
    conn = MqttConnection(BrokerAddress.parse(url), client_id="bench-worker").start()
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(stress)]
    telemetry: queue.Queue[QubeTelemetry] = queue.Queue()
    conn.subscribe(topics.rig(rig_id, topics.TELEMETRY), lambda t, p: telemetry.put(decode(p, QubeTelemetry)), qos=0)
    try:
        env = QubeMqttEnv(conn, rig_id, reset_timeout_s=60)
        learner = learners.get(algo).build(env.observation_space, env.action_space,
                                           learners_config(algo), seed=0)
        compute: list[float] = []
        answered, episodes, t0 = 0, 0, time.monotonic()
        while answered < ticks:
            obs, _ = env.reset()
            episodes += 1
            while answered < ticks:
                c0 = time.perf_counter()
                learner.act(obs)  # the worker's forward pass, timed
                action = balance_action(obs)
                compute.append(time.perf_counter() - c0)
                obs, _, terminated, truncated, _ = env.step(action)
                answered += 1
                if terminated or truncated:
                    break
        wall = time.monotonic() - t0
        time.sleep(1.5)  # one more telemetry report from the rig
        last = None
        while not telemetry.empty():
            last = telemetry.get()
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()
        conn.stop()
        rig.terminate()
        rig.wait(10)
        stop_process(broker)
    if last is None:
        raise RuntimeError(f"no telemetry from the rig over {broker_name}")
    answered_ticks = last.latency_ms["n"] + last.deadline_misses
    return {
        "broker": broker_name,
        "algo": algo,
        "stress_processes": stress,
        "ticks_answered": answered,
        "episodes": episodes,
        "wall_s": round(wall, 1),
        "latency_ms": last.latency_ms,
        "tick_jitter_ms": last.jitter_ms,
        "read_to_motor_ms": last.motor_ms,
        "tick_period_ms": last.period_ms,
        "deadline_misses": last.deadline_misses,
        "late_actions": last.late_actions,
        "late_at_motor": last.late_at_motor,
        "miss_rate": round(last.deadline_misses / answered_ticks, 6) if answered_ticks else None,
        "env_timeouts": env.timeouts,
        "worker_forward_pass_ms": percentiles(compute),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.latency", description=__doc__.splitlines()[0])
    parser.add_argument("--ticks", type=int, default=10_000, help="answered states per broker (default 10000)")
    parser.add_argument("--brokers", nargs="+", default=["amqtt", "mosquitto"], choices=("amqtt", "mosquitto"))
    parser.add_argument("--stress", type=int, nargs="+", default=[0],
                        help="busy processes running during a measurement; one measurement per value (default 0)")
    parser.add_argument("--algo", nargs="+", default=names.names(), choices=names.names(),
                        help="learners whose actor answers; one measurement each (default: all)")
    parser.add_argument("--out", type=Path, default=RESULTS / "latency.json")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    results = []
    if any(n < 0 for n in args.stress):
        parser.error("--stress values must be >= 0")
    for name in args.brokers:
        if name == "mosquitto" and subprocess.run(["which", "mosquitto"], capture_output=True).returncode != 0:
            print("mosquitto not installed; skipping it", file=sys.stderr)
            continue
        for stress in args.stress:
            for algo in args.algo:
                with tempfile.TemporaryDirectory() as workdir:  # the Mosquitto config lives only as long as the run
                    result = measure(name, args.ticks, Path(workdir), stress, algo)
                print(json.dumps(result), flush=True)
                results.append(result)
    report = {"command": " ".join(["python -m bench.latency", *(argv if argv is not None else sys.argv[1:])]),
              "period_ms": 7.0, "deadline_ms": 7.0, "ticks_per_broker": args.ticks, "machine": platform.platform(),
              "cpus": __import__("os").cpu_count(), "results": results}
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
