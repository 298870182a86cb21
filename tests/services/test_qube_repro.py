"""A lockstep rig over MQTT is reproducible: the same seed and the same actions give the same trajectory bit for bit,
on each broker, however long the worker takes between episodes or steps and under extra CPU load."""

from __future__ import annotations

import hashlib
import random
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from protocol.mqtt import BrokerAddress, MqttConnection
from worker.qube_env import QubeMqttEnv

EPISODES = 4
MAX_STEPS = 300  # per episode (a longer one is cut by the next reset, which the rig serves as any other)


def policy(obs: np.ndarray, rng: random.Random) -> int:
    """A crude stabiliser (signed LQR gains) with 60 % random actions, so that most episodes end in a fall: a
    function of the observation and ``rng`` only."""
    alpha, alpha_dot, theta, theta_dot = (float(x) for x in obs)
    u = -(12.7 * theta - 563.3 * alpha + 13.3 * theta_dot - 39.0 * alpha_dot)
    lqr = 2 if u > 20 else (0 if u < -20 else 1)
    return rng.randrange(3) if rng.random() < 0.6 else lqr


@contextmanager
def rig(broker: str, rig_id: str, tmp_path: Path) -> Iterator[None]:
    log = (tmp_path / f"{rig_id}.log").open("wb")
    proc = subprocess.Popen([sys.executable, "-m", "services.qube_sim", "--broker", broker, "--rig-id", rig_id,
                             "--clock", "lockstep", "--seed", "4"], stdout=log, stderr=subprocess.STDOUT)
    try:
        yield
    finally:
        proc.terminate()
        proc.wait(10)
        log.close()


@contextmanager
def busy_loop(on: bool) -> Iterator[None]:
    """One process spinning on a core meanwhile (extra load on top of whatever else the machine runs)."""
    proc = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if on else None
    try:
        yield
    finally:
        if proc is not None:
            proc.kill()
            proc.wait()


def play(broker: str, rig_id: str, tmp_path: Path, pauses: random.Random | None) -> list[tuple[float, int, str]]:
    """(return, steps, digest of every observation) per episode; ``pauses`` draws wall-clock pauses after each
    episode (as a worker waits for its round) and now and then between a state and its action."""
    conn = MqttConnection(BrokerAddress.parse(broker), client_id=f"repro-{rig_id}").start()
    episodes = []
    try:
        env = QubeMqttEnv(conn, rig_id, reset_timeout_s=60)
        if pauses is not None:
            time.sleep(pauses.uniform(0.5, 1.5))  # the rig finished its start-up checks long ago
        actions = random.Random(7)
        for _ in range(EPISODES):
            obs, _ = env.reset()
            digest, ret, steps = hashlib.sha256(obs.tobytes()), 0.0, 0
            while steps < MAX_STEPS:
                if pauses is not None and pauses.random() < 0.01:
                    time.sleep(pauses.uniform(0.05, 0.3))
                obs, reward, terminated, truncated, _ = env.step(policy(obs, actions))
                digest.update(obs.tobytes())
                ret, steps = ret + float(reward), steps + 1
                if terminated or truncated:
                    break
            episodes.append((ret, steps, digest.hexdigest()))
            if pauses is not None:
                time.sleep(pauses.uniform(0.2, 1.0))
        assert env.timeouts == 0 and env.rejected == 0
    finally:
        conn.stop()
    return episodes


def test_a_lockstep_rig_gives_the_same_trajectory_whatever_the_wall_clock(any_broker: str, tmp_path: Path) -> None:
    with rig(any_broker, "rigA", tmp_path):
        quiet = play(any_broker, "rigA", tmp_path, pauses=None)
    with rig(any_broker, "rigB", tmp_path), busy_loop(on=True):
        loaded = play(any_broker, "rigB", tmp_path, pauses=random.Random(3))
    assert sum(steps < MAX_STEPS for _, steps, _ in quiet) >= 2, quiet  # falls, and the resets after them, happened
    assert loaded == quiet
