"""A QUBE-Servo 2 episode end to end: simulated rig process <-> broker <-> the worker's gymnasium env."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from protocol.codec import encode
from protocol.messages import QubeState, QubeStatus
from protocol.mqtt import BrokerAddress, MqttConnection
from protocol.qube import MAX_RETURN, PERIOD_S
from protocol.transport import connector
from worker.qube_env import ACTIONS, QubeLocalEnv, QubeMqttEnv


def bang_bang(obs: np.ndarray) -> int:
    """Index into ACTIONS from a crude LQR-signed rule on (alpha, alpha_dot, theta, theta_dot)."""
    alpha, alpha_dot, theta, theta_dot = (float(x) for x in obs)
    u = -(12.7 * theta - 563.3 * alpha + 13.3 * theta_dot - 39.0 * alpha_dot)
    return 2 if u > 20 else (0 if u < -20 else 1)


def start_rig(broker: str, rig: str, clock: str, tmp_path: Path) -> subprocess.Popen:
    log = (tmp_path / f"{rig}.log").open("wb")
    return subprocess.Popen([sys.executable, "-m", "services.qube_sim", "--broker", broker, "--rig-id", rig,
                             "--clock", clock, "--seed", "4"], stdout=log, stderr=subprocess.STDOUT)


def play(env, steps: int | None = None) -> tuple[float, bool, bool, int]:
    obs, _ = env.reset()
    ret, n = 0.0, 0
    while True:
        obs, reward, terminated, truncated, _ = env.step(bang_bang(obs))
        ret += reward
        n += 1
        if terminated or truncated or (steps is not None and n >= steps):
            return ret, terminated, truncated, n


def test_lockstep_episode_over_the_broker_reaches_the_cap(any_broker: str, tmp_path: Path) -> None:
    rig = start_rig(any_broker, "rigE", "lockstep", tmp_path)
    conn = MqttConnection(BrokerAddress.parse(any_broker), client_id="qube-e2e").start()
    try:
        env = QubeMqttEnv(conn, "rigE", reset_timeout_s=30, qube_clock="lockstep")
        ret, terminated, truncated, n = play(env)
        assert (ret, truncated, terminated, n) == (MAX_RETURN, True, False, MAX_RETURN)
        # A second episode: the rig swings up again on request. Its rig time is read from the simulated clock: the
        # ticks from the end of the first episode to the ready state of the second, and 7 ms per step.
        ret2, *_ = play(env, steps=100)
        assert ret2 == 100.0
        spent = env.episode_time
        assert spent.balance_steps == 100 and spent.balance_s == pytest.approx(0.7) and 0 < spent.reset_s < 60
        assert env.rejected == 0 and env.timeouts == 0
    finally:
        conn.stop()
        rig.terminate()
        rig.wait(10)


STOPPED = re.compile(r"(\d+) ticks, (\d+) deadline misses, (\d+) late actions, (\d+) late at the motor, .*"
                     r"read to motor write (\{.*\}) ms")


def test_real_time_episode_meets_the_deadline(any_broker: str, tmp_path: Path) -> None:
    """The rig's own clock runs the episode: every action that reached the motor was written within 7 ms of its
    state's read, and a state whose action came late got the safe action and was counted. How many states miss
    depends on the machine's load (bench/latency.py measures it), so the episode may end early, but only by a fall
    that the counted misses allow: with every action in time, the stabiliser balances all 700 steps."""
    rig = start_rig(any_broker, "rigR", "realtime", tmp_path)
    conn = MqttConnection(BrokerAddress.parse(any_broker), client_id="qube-rt").start()
    try:
        env = QubeMqttEnv(conn, "rigR", reset_timeout_s=30)
        ret, terminated, _, n = play(env, steps=700)  # about 5 s at 7 ms
    finally:
        conn.stop()
        rig.terminate()
        rig.wait(10)
    found = STOPPED.search((tmp_path / "rigR.log").read_text())
    assert found, "the rig logs its counters when it stops"
    ticks, misses = int(found[1]), int(found[2])
    motor_ms = ast.literal_eval(found[5])
    assert ticks >= n > 0 and ret == float(n - int(terminated))  # +1 a balanced step, 0 the step that fell
    assert motor_ms["n"] > 0 and motor_ms["max"] <= PERIOD_S * 1e3 + 1e-9  # never a write past the deadline
    if n < 700 or terminated:
        assert misses > 0, f"the episode ended at step {n} with every action in time"


def test_local_env_is_the_same_task() -> None:
    env = QubeLocalEnv(seed=4)
    ret, terminated, truncated, n = play(env)
    assert (ret, truncated, n) == (MAX_RETURN, True, MAX_RETURN)
    assert env.action_space.n == len(ACTIONS) == 3 and env.observation_space.shape == (4,)
    # Doing nothing lets the pendulum fall: reward stops and the episode terminates.
    env.reset()
    total = 0.0
    for _ in range(2000):
        _, r, terminated, _, _ = env.step(1)
        total += r
        if terminated:
            break
    assert terminated and 0 < total < 2000


SPOOF = QubeState(rig_id="rigX", seq=1, t=0.0, theta=0.0, alpha=0.0, theta_dot=0.0, alpha_dot=0.0)


@pytest.mark.parametrize(("bad", "reason"), [
    (b"\x00junk", "malformed"),
    (b"", "malformed"),
    (encode(QubeStatus(rig_id="rigG", state="ready")), "wrong_topic"),  # a status on the state topic
    (encode(SPOOF), "spoofed"),  # another rig's state on this rig's topic
])
def test_env_ignores_garbage_on_its_topics(amqtt_broker: str, tmp_path: Path, bad: bytes, reason: str) -> None:
    rig = start_rig(amqtt_broker, "rigG", "lockstep", tmp_path)
    conn = MqttConnection(BrokerAddress.parse(amqtt_broker), client_id="qube-garbage").start()
    try:
        env = QubeMqttEnv(conn, "rigG", reset_timeout_s=30)
        conn.publish("qube/rigG/state", bad, qos=1).wait_for_publish(5)
        ret, *_ = play(env, steps=50)
        assert ret == 50.0 and env.rejects.as_dict().get(reason) == 1
    finally:
        conn.stop()
        rig.terminate()
        rig.wait(10)


def test_local_env_retries_a_failed_swing_up_then_gives_up() -> None:
    from rpi_bridge.control import ControlConfig, ControlCore
    from rpi_bridge.reset import ResetConfig

    env = QubeLocalEnv(seed=4)
    env.core = ControlCore(env.device, ControlConfig(reset=ResetConfig(timeout_s=0.05)),  # no swing-up can succeed
                           clock=env.clock)
    with pytest.raises(RuntimeError, match="could not reset"):
        env.reset()
    assert env.failed_resets == 5


def test_the_first_action_of_every_episode_over_mqtt_is_applied(amqtt_broker: str) -> None:
    """The rig's first ``ready`` state opens an action slot, so the env's first answer of an episode is applied as
    in process (it used to be dropped as late, every episode)."""
    import threading

    from rpi_bridge.service import BridgeService
    from services.qube_sim.clock import VirtualClock
    from services.qube_sim.spi_peer import SimulatedQube

    clock = VirtualClock()
    device = SimulatedQube(seed=4, period_s=0, clock=clock)
    service = BridgeService(device, "rigF", connector(BrokerAddress.parse(amqtt_broker)), lockstep=True,
                            advance=clock.advance, clock=clock, client_prefix="qube-first")
    loop = threading.Thread(target=service.run, daemon=True)
    loop.start()
    conn = MqttConnection(BrokerAddress.parse(amqtt_broker), client_id="qube-first-env").start()
    try:
        env = QubeMqttEnv(conn, "rigF", reset_timeout_s=30)
        for _ in range(3):
            ret, *_ = play(env, steps=20)
            assert ret == 20.0
        counters = service.core.counters  # (the lockstep rig now waits for the next answer)
        assert service.runner.slot.late == 0 and counters.misses == 0
        assert counters.applied == 60  # every answer of every episode, the first ones included
    finally:
        conn.stop()
        service.stop_event.set()
        loop.join(10)


def test_the_env_retries_a_reset_that_ends_in_a_fault() -> None:
    """A rig that faults during the reset (e.g. its arm limit) answers with a ``fault`` status for that request:
    the env treats it as a failed swing-up and retries, instead of waiting for the reset timeout."""
    from protocol.codec import decode, encode
    from protocol.messages import QubeReset, QubeStatus

    class FaultingRig:
        def __init__(self) -> None:
            self.callbacks: dict[str, object] = {}
            self.resets = 0

        def subscribe(self, topic: str, callback, qos: int = 0) -> None:
            self.callbacks[topic] = callback

        def publish(self, topic: str, payload: bytes, qos: int = 0) -> None:
            request = decode(payload, QubeReset)
            self.resets += 1
            status = QubeStatus(rig_id="rigX", state="fault", request_id=request.request_id,
                                detail="arm at 114 deg, past the 110 deg limit")
            self.callbacks["qube/rigX/status"]("qube/rigX/status", encode(status))

    rig = FaultingRig()
    env = QubeMqttEnv(rig, "rigX", reset_timeout_s=1.0, reset_attempts=3, settle_s=0.0)
    with pytest.raises(RuntimeError, match="reset fault: arm at 114 deg"):
        env.reset()
    assert rig.resets == 3 and env.failed_resets == 3


def test_the_rig_refuses_actions_on_the_wrong_topic_or_for_another_rig(amqtt_broker: str, tmp_path: Path) -> None:
    from protocol.messages import QubeAction

    rig = start_rig(amqtt_broker, "rigH", "lockstep", tmp_path)
    conn = MqttConnection(BrokerAddress.parse(amqtt_broker), client_id="qube-spoof").start()
    try:
        env = QubeMqttEnv(conn, "rigH", reset_timeout_s=30)
        play(env, steps=5)  # the rig is up and subscribed
        conn.publish("qube/rigH/action", encode(QubeAction(rig_id="rigZ", seq=1, command=999))).wait_for_publish(5)
        conn.publish("qube/rigH/action", encode(QubeStatus(rig_id="rigH", state="fault"))).wait_for_publish(5)
        ret, *_ = play(env, steps=20)
        assert ret == 20.0
    finally:
        conn.stop()
        rig.terminate()
        rig.wait(10)
    log = (tmp_path / "rigH.log").read_text()
    assert "(spoofed): payload says rig 'rigZ'" in log and "(unexpected_kind)" in log
