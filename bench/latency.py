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
import queue
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bench.output import write_report
from protocol import learners as names
from protocol import topics
from protocol.codec import decode
from protocol.messages import QubeTelemetry
from protocol.mqtt import BrokerAddress
from protocol.transport import connector
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


class AnsweredRig:
    """A simulated rig in real time (``python -m services.qube_sim --clock realtime``, its own process) on ``url``,
    its states answered from a thread of this process the way a worker does: the learner's forward pass (timed)
    then a balancing rule's action, until ``ticks`` states are answered or ``stop``. Also what bench.scale attaches
    to a federation under load."""

    def __init__(self, url: str, rig_id: str, algo: str = names.DEFAULT, ticks: int | None = None) -> None:
        self.rig_id, self.ticks = rig_id, ticks
        self.rig = subprocess.Popen([sys.executable, "-m", "services.qube_sim", "--broker", url, "--rig-id", rig_id,
                                     "--clock", "realtime", "--log-level", "WARNING"])
        self.conn = connector(BrokerAddress.parse(url))(f"bench-worker-{rig_id}").start()
        self.telemetry: queue.Queue[QubeTelemetry] = queue.Queue()
        self.conn.subscribe(topics.rig(rig_id, topics.TELEMETRY),
                            lambda t, p: self.telemetry.put(decode(p, QubeTelemetry)), qos=0)
        self.env = QubeMqttEnv(self.conn, rig_id, reset_timeout_s=60)
        self.learner = learners.get(algo).learner_class(self.env.observation_space, self.env.action_space,
                                                        learners_config(algo), seed=0)
        self.compute: list[float] = []
        self.answered = self.episodes = 0
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self.t0 = time.monotonic()
        self.thread = threading.Thread(target=self._answer, name=f"answer-{rig_id}", daemon=True)
        self.thread.start()

    def _done(self) -> bool:
        return self._stop.is_set() or (self.ticks is not None and self.answered >= self.ticks)

    def _answer(self) -> None:
        try:
            while not self._done():
                obs, _ = self.env.reset()
                self.episodes += 1
                while not self._done():
                    c0 = time.perf_counter()
                    self.learner.act(obs)  # the worker's forward pass, timed
                    action = balance_action(obs)
                    self.compute.append(time.perf_counter() - c0)
                    obs, _, terminated, truncated, _ = self.env.step(action)
                    self.answered += 1
                    if terminated or truncated:
                        break
        except BaseException as exc:  # reported by finish()
            self.error = exc

    def answering(self, timeout: float = 120.0) -> None:
        """Until the first state is answered (the rig's first reset done); TimeoutError after ``timeout`` s."""
        deadline = time.monotonic() + timeout
        while self.answered == 0:
            if self.error is not None or time.monotonic() > deadline:
                raise TimeoutError(f"rig {self.rig_id}: no state answered within {timeout:.0f} s ({self.error!r})")
            time.sleep(0.05)

    def wait(self) -> None:
        """Until ``ticks`` states are answered."""
        self.thread.join()

    def finish(self) -> dict[str, Any]:
        """Stop answering, read the rig's last telemetry report, stop the rig: the measurement."""
        self._stop.set()
        self.thread.join(120)
        wall = time.monotonic() - self.t0
        time.sleep(1.5)  # one more telemetry report from the rig
        last = None
        while not self.telemetry.empty():
            last = self.telemetry.get()
        self.conn.stop()
        self.rig.terminate()
        self.rig.wait(10)
        if self.error is not None:
            raise RuntimeError(f"answering rig {self.rig_id} failed: {self.error!r}") from self.error
        if last is None:
            raise RuntimeError(f"no telemetry from rig {self.rig_id}")
        answered_ticks = last.latency_ms["n"] + last.deadline_misses
        return {
            "ticks_answered": self.answered,
            "episodes": self.episodes,
            "wall_s": round(wall, 1),
            "latency_ms": last.latency_ms,
            "tick_jitter_ms": last.jitter_ms,
            "read_to_motor_ms": last.motor_ms,
            "tick_period_ms": last.period_ms,
            "deadline_misses": last.deadline_misses,
            "late_actions": last.late_actions,
            "late_at_motor": last.late_at_motor,
            "miss_rate": round(last.deadline_misses / answered_ticks, 6) if answered_ticks else None,
            "env_timeouts": self.env.timeouts,
            "worker_forward_pass_ms": percentiles(self.compute),
        }

    def kill(self) -> None:
        """Stop everything without measuring (a failed run)."""
        self._stop.set()
        self.conn.stop()
        if self.rig.poll() is None:
            self.rig.kill()
            self.rig.wait()


def measure(broker_name: str, ticks: int, workdir: Path, stress: int = 0, algo: str = names.DEFAULT) -> dict:
    if broker_name == "mosquitto":
        broker, port = mosquitto.start(workdir, max_packet_size=None)
    else:
        broker, port = start_broker_process(stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    url = f"mqtt://127.0.0.1:{port}"
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(stress)]
    rig = None
    try:
        rig = AnsweredRig(url, f"bench-{broker_name}", algo, ticks)
        rig.wait()
        result = rig.finish()
    except BaseException:
        if rig is not None:
            rig.kill()
        raise
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()
        stop_process(broker)
    return {"broker": broker_name, "algo": algo, "stress_processes": stress, **result}


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
    write_report(args.out, "bench.latency", argv, {"period_ms": 7.0, "deadline_ms": 7.0,
                                                     "ticks_per_broker": args.ticks, "results": results}, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
