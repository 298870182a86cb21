"""``python -m bench.loop_cost``: what one tick of the bridge loop costs, part by part, on this machine.

The real loop (rpi_bridge.runner.BridgeRunner in real time, 7 ms period and deadline, the real ControlCore) runs
against the simulated SPI peer (services/qube_sim), instrumented without changing it:

- ``spi_read``: the SPI transfer that reads the rig (here: the simulated peer, i.e. its physics for one period
  and its frame codec; on a Raspberry Pi: spidev's ``xfer2`` of 17 bytes, 136 us of bus time at 1 MHz);
- ``sense``: the rest of ``ControlCore.sense`` (frame building and parsing, filters, safety checks, phases);
- ``publish``: from the end of ``sense`` to the end of the publish call (the state message, its msgpack encoding,
  opening the action slot, paho's ``publish``);
- ``wait``: from the end of the publish to the action's arrival (the worker's round trip through the broker);
- ``write``: ``ControlCore.act`` without its SPI transfer, and ``spi_write``: that transfer;
- ``busy``: the tick's own work (everything but ``wait``), the part a Raspberry Pi has to fit into the period.

Mode ``inproc`` answers each state inside the publish call (no broker: the bridge's CPU cost alone); modes
``amqtt`` and ``mosquitto`` start that broker and answer from a worker-like client in this process (QubeMqttEnv and
a balancing rule). Writes ``bench/results/loop_cost.json`` with p50 / p99 / max in microseconds per part.
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from bench.output import write_report
from protocol import qube
from protocol.codec import decode
from protocol.messages import QubeAction, QubeState, QubeStatus, QubeTelemetry
from protocol.mqtt import BrokerAddress
from protocol.transport import connector
from rpi_bridge.control import ControlConfig, ControlCore
from rpi_bridge.runner import BridgeRunner
from rpi_bridge.service import BridgeService
from services.broker import mosquitto
from services.broker.embedded import start_broker_process, stop_process
from services.qube_sim.spi_peer import SimulatedQube

RESULTS = Path("bench/results")
PARTS = ("spi_read", "sense", "publish", "wait", "write", "spi_write", "busy")


def balance_command(alpha: float, alpha_dot: float, theta: float, theta_dot: float) -> int:
    u = -(12.7 * theta - 563.3 * alpha + 13.3 * theta_dot - 39.0 * alpha_dot)
    return 60 if u > 20 else (-60 if u < -20 else 0)


class TimedQube(SimulatedQube):
    """The simulated peer, timing each transfer."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.last_s = 0.0

    def transfer(self, frame: bytes) -> bytes:
        t0 = time.perf_counter()
        reply = super().transfer(frame)
        self.last_s = time.perf_counter() - t0
        return reply


class TimedCore(ControlCore):
    """The real control core, timing sense and act and recording one row per answered tick."""

    def __init__(self, device: TimedQube, config: ControlConfig) -> None:
        super().__init__(device, config, clock=time.perf_counter)
        self.timed: TimedQube = device
        self.rows: list[dict[str, float]] = []
        self.publish_s = 0.0
        self.published_at = 0.0
        self.sensed_at = 0.0
        self._sense: tuple[float, float] = (0.0, 0.0)

    def sense(self):
        t0 = time.perf_counter()
        sensed = super().sense()
        self.sensed_at = time.perf_counter()
        self._sense = (self.timed.last_s, self.sensed_at - t0 - self.timed.last_s)
        return sensed

    def published(self) -> None:
        """Call at the end of the state's publish."""
        self.published_at = time.perf_counter()
        self.publish_s = self.published_at - self.sensed_at

    def act(self, command: int | None, deadline: float | None = None) -> int:
        t0 = time.perf_counter()
        wait = t0 - self.published_at
        self.timed.last_s = 0.0
        applied = super().act(command, deadline)
        total = time.perf_counter() - t0
        if command is not None and self.phase == "running":
            spi_read, sense = self._sense
            spi_write = self.timed.last_s
            self.rows.append({"spi_read": spi_read, "sense": sense, "publish": self.publish_s, "wait": wait,
                              "write": total - spi_write, "spi_write": spi_write,
                              "busy": spi_read + sense + self.publish_s + total})
        return applied


def stats_us(rows: list[dict[str, float]]) -> dict[str, dict[str, float]]:
    out = {}
    for part in PARTS:
        v = np.array([r[part] for r in rows]) * 1e6
        out[part] = {"p50": round(float(np.percentile(v, 50)), 1), "p99": round(float(np.percentile(v, 99)), 1),
                     "max": round(float(v.max()), 1), "mean": round(float(v.mean()), 1)}
    return out


def run_inproc(ticks: int) -> dict:
    device = TimedQube(seed=1, period_s=0, clock=time.perf_counter)
    core = TimedCore(device, ControlConfig())
    runner: BridgeRunner

    def publish(topic: str, payload: bytes, qos: int) -> None:
        msg = decode(payload, QubeState, QubeStatus, QubeTelemetry)  # stands in for the network send
        if not isinstance(msg, QubeState):
            return
        core.published()
        if msg.phase in ("ready", "running"):
            runner.on_action(QubeAction(rig_id="bench", seq=msg.seq,
                                        command=balance_command(msg.alpha, msg.alpha_dot, msg.theta, msg.theta_dot)))
        elif msg.phase in ("fallen", "idle", "fault"):
            runner.on_reset(msg.seq)

    runner = BridgeRunner(core, "bench", publish, deadline_s=qube.PERIOD_S)
    runner.on_reset(1)
    stop = threading.Event()
    loop = threading.Thread(target=runner.run, args=(stop,), daemon=True)
    loop.start()
    deadline = time.monotonic() + ticks * qube.PERIOD_S * 3 + 30
    while len(core.rows) < ticks and time.monotonic() < deadline:
        time.sleep(0.2)
    stop.set()
    loop.join(5)
    return summarise("inproc (no broker: the state is decoded instead of sent, answered in place)", core, runner)


def run_broker(name: str, ticks: int, workdir: Path) -> dict:
    from worker.qube_env import QubeMqttEnv

    if name == "mosquitto":
        broker, port = mosquitto.start(workdir, max_packet_size=None)
    else:
        broker, port = start_broker_process(stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    address = BrokerAddress.parse(f"mqtt://127.0.0.1:{port}")
    device = TimedQube(seed=1, period_s=0, clock=time.perf_counter)
    service = BridgeService(device, "bench", connector(address), client_prefix="loop-cost")
    core = TimedCore(device, ControlConfig())
    service.core = core
    service.runner = BridgeRunner(core, "bench", service._publish, deadline_s=qube.PERIOD_S)
    original_publish = service.conn.publish

    def timed_publish(topic: str, payload: bytes, qos: int = 0):
        result = original_publish(topic, payload, qos=qos)
        if topic.endswith("/state"):
            core.published()
        return result

    service.conn.publish = timed_publish  # type: ignore[method-assign,assignment]
    loop = threading.Thread(target=service.run, daemon=True)
    loop.start()
    conn = connector(address)("loop-cost-worker").start()
    try:
        env = QubeMqttEnv(conn, "bench", reset_timeout_s=60)
        while len(core.rows) < ticks:
            obs, _ = env.reset()
            while len(core.rows) < ticks:
                alpha, alpha_dot, theta, theta_dot = (float(x) for x in obs)
                obs, _, terminated, truncated, _ = env.step(
                    {-60: 0, 0: 1, 60: 2}[balance_command(alpha, alpha_dot, theta, theta_dot)])
                if terminated or truncated:
                    break
    finally:
        conn.stop()
        service.stop_event.set()
        loop.join(10)
        stop_process(broker)
    return summarise(f"{name} broker, answered by a worker-like client in this process", core, service.runner)


def summarise(mode: str, core: TimedCore, runner: BridgeRunner) -> dict:
    t = runner.telemetry()
    rows = core.rows
    return {"mode": mode, "ticks": len(rows), "parts_us": stats_us(rows),
            "busy_over_period": round(float(np.mean([r["busy"] for r in rows])) / qube.PERIOD_S, 4),
            "deadline_misses": t.deadline_misses, "late_actions": t.late_actions, "late_at_motor": t.late_at_motor,
            "read_to_motor_ms": t.motor_ms, "period_ms": t.period_ms}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.loop_cost", description=__doc__.splitlines()[0])
    parser.add_argument("--ticks", type=int, default=5000, help="answered ticks per mode (default 5000)")
    parser.add_argument("--modes", nargs="+", default=["inproc", "amqtt", "mosquitto"],
                        choices=("inproc", "amqtt", "mosquitto"))
    parser.add_argument("--out", type=Path, default=RESULTS / "loop_cost.json")
    args = parser.parse_args(argv)
    if args.ticks < 100:
        parser.error("--ticks must be at least 100")
    results = []
    for mode in args.modes:
        if mode == "mosquitto" and shutil.which("mosquitto") is None:
            print("mosquitto not installed; skipping it", file=sys.stderr)
            continue
        if mode == "inproc":
            result = run_inproc(args.ticks)
        else:
            with tempfile.TemporaryDirectory() as workdir:
                result = run_broker(mode, args.ticks, Path(workdir))
        print(json.dumps(result), flush=True)
        results.append(result)
    write_report(args.out, "bench.loop_cost", argv, {"period_ms": 7.0, "deadline_ms": 7.0,
                                                       "python": platform.python_version(), "results": results})
    return 0


if __name__ == "__main__":
    sys.exit(main())
