"""The paper's QUBE-Servo 2 balance task (Section V-B-2) as gymnasium environments.

Observation (pendulum angle, pendulum velocity, arm angle, arm velocity) in rad and rad/s, alpha = 0 upright.
Actions {-60, 0, +60} SPI motor counts (the paper's; ``qube_actions`` picks a set with more authority,
protocol/qube.py ``ACTION_SETS``: nine levels, or a continuous command). Reward +1 per 7 ms step while |alpha| <= 7.5
deg; the episode ends when the pendulum leaves that band (or the rig faults) and is cut off at 2450 reward; learning
is complete when the mean of the last 10 episodes reaches 2450 (protocol.tasks, "qube").

- ``QubeMqttEnv`` drives a rig over MQTT: a real QUBE behind ``python -m rpi_bridge`` or a simulated one behind
  ``python -m services.qube_sim``. ``reset`` asks the rig to swing the pendulum up and hold it, ``step`` answers
  one state with one action. Nothing but the actor's forward pass happens between a state and its action.
- ``QubeLocalEnv`` is the same task on the same physics and the same bridge control code, in process (no MQTT),
  for fast experiments.
"""

from __future__ import annotations

import itertools
import logging
import queue
import threading
import time
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from protocol import topics
from protocol.codec import DecodeError, RejectCounter, decode, encode
from protocol.messages import QubeAction, QubeReset, QubeState, QubeStatus
from protocol.qube import BALANCE_BAND, MAX_RETURN, PERIOD_S, ActionSet, action_set
from protocol.rigtime import MEASURED_CLOCKS, EpisodeTime, ticks_to_s
from protocol.routes import qos_of
from rpi_bridge.control import ControlConfig, ControlCore, Sensed, with_model
from rpi_bridge.runner import InjectedTiming

log = logging.getLogger("worker.qube")

#: The paper's actions in SPI motor counts (turn left, stop, turn right): the default action set's levels.
ACTIONS: tuple[int, ...] = action_set(None).levels or ()
#: Swing-ups tried (the pendulum let settle 3 s between them) before a reset counts as failed.
RESET_ATTEMPTS = 5
#: The clocks of ``qube-local`` (simulated time; protocol/rigtime.py): the rig time is never measured there.
LOCAL_CLOCKS = ("lockstep", "delayed")
#: A domain-randomised simulated plant that cannot be swung up is replaced by a fresh draw this many times at most.
MAX_REDRAWS = 3


def observation(alpha: float, alpha_dot: float, theta: float, theta_dot: float) -> np.ndarray:
    return np.array([alpha, alpha_dot, theta, theta_dot], dtype=np.float32)


def balance_reward(alpha: float) -> float:
    """+1 while the pendulum is within the balance band, else 0 (and the episode ends)."""
    return 1.0 if abs(alpha) <= BALANCE_BAND else 0.0


class ResetFailed(RuntimeError):
    """The rig reported that one swing-up attempt did not succeed."""


class Halted(Exception):
    """The worker was told to stop (SIGTERM, SIGINT, SIGHUP) while the env waited for its rig: a reset, a state."""


#: How often a wait for the rig looks at the worker's halt event (s): a stop ends any wait within this.
HALT_POLL_S = 0.1


class _QubeTask(gym.Env):
    """Spaces and bookkeeping shared by the two envs, with the rig time of the episode (protocol/rigtime.py)."""

    observation_space = spaces.Box(-np.inf, np.inf, shape=(4,), dtype=np.float32)
    #: Whether this env's rig time is measured in wall seconds (else it comes from the simulated clock).
    measured = False

    def __init__(self, actions: ActionSet | None = None) -> None:
        self.actions = actions or action_set(None)
        self.action_space: spaces.Space[Any] = (
            spaces.Discrete(len(self.actions.levels)) if self.actions.levels is not None
            else spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32))
        self.episode_return = 0.0
        self.balance_steps = 0
        self.reset_s = 0.0
        self._balance_from = 0.0  # wall time of the episode's first state (measured clocks)
        self._balance_wall = 0.0

    @property
    def episode_time(self) -> EpisodeTime:
        """The rig time of the episode played last (or being played): its swing-up and its steps so far."""
        balance_s = self._balance_wall if self.measured else ticks_to_s(self.balance_steps)
        return EpisodeTime(self.balance_steps, balance_s, self.reset_s)

    def _started(self, reset_s: float) -> None:
        self.episode_return, self.balance_steps, self.reset_s = 0.0, 0, reset_s
        self._balance_from, self._balance_wall = time.perf_counter(), 0.0

    def _outcome(self, alpha: float, ended: bool) -> tuple[float, bool, bool]:
        reward = 0.0 if ended else balance_reward(alpha)
        terminated = ended or reward == 0.0
        self.episode_return += reward
        self.balance_steps += 1
        self._balance_wall = time.perf_counter() - self._balance_from
        truncated = not terminated and self.episode_return >= MAX_RETURN
        return reward, terminated, truncated


class QubeMqttEnv(_QubeTask):
    """One rig reached through the broker (topics qube/<rig>/...)."""

    def __init__(self, conn: Any, rig_id: str, reset_timeout_s: float = 60.0, step_timeout_s: float = 10.0,
                 reset_attempts: int = RESET_ATTEMPTS, settle_s: float = 3.0, qube_clock: str = "realtime",
                 actions: ActionSet | None = None, halt: threading.Event | None = None) -> None:
        """``step_timeout_s``: a state that does not come within this many seconds of wall time ends the episode
        (a dead rig or link; a live rig reports a fault or goes offline long before). It must be long enough for a
        lockstep rig on a loaded machine, whose episodes would otherwise depend on wall time. ``qube_clock``: the
        rig's clock, which says whether rig time is measured or read from the simulated clock (the ticks between
        the last state of an episode and the ``ready`` state of the next: a lockstep rig does not tick meanwhile).
        ``actions``: the action set (default the paper's). ``halt``: once set, any wait for the rig raises
        :class:`Halted` within HALT_POLL_S (the worker's stop)."""
        super().__init__(actions)
        self.halt = halt
        self.measured = qube_clock in MEASURED_CLOCKS
        self._end_seq: int | None = None  # seq of the last state of the episode before
        self.reset_attempts = reset_attempts
        self.settle_s = settle_s
        self.failed_resets = 0
        self.rig_id = topics.check_id(rig_id, "rig id")
        self.conn = conn
        self.reset_timeout_s = reset_timeout_s
        self.step_timeout_s = step_timeout_s
        self.inbox: queue.Queue[QubeState | QubeStatus] = queue.Queue()
        self.rejects = RejectCounter(log)
        self.timeouts = 0
        self._request_ids = itertools.count(int(time.time() * 1000) % 1_000_000_000)
        self._request = -1
        self._last: QubeState | None = None
        self._action_topic, self._reset_topic = topics.rig(rig_id, topics.ACTION), topics.rig(rig_id, topics.RESET)
        self._action_qos = qos_of(self._action_topic)  # looked up once: an action goes out every step
        for topic in (topics.rig(rig_id, topics.STATE), topics.rig(rig_id, topics.STATUS)):
            conn.subscribe(topic, self._on_message, qos=qos_of(topic))

    @property
    def rejected(self) -> int:
        """Messages from the rig's topics that were refused (counted by reason in ``rejects``)."""
        return self.rejects.total

    def _on_message(self, topic: str, payload: bytes) -> None:
        try:
            msg = decode(payload, QubeState, QubeStatus, topic=topic)
        except DecodeError as err:
            self.rejects.reject_error(topic, err)
            return
        self.inbox.put(msg)

    def _next(self, deadline: float) -> QubeState | QubeStatus | None:
        """The rig's next message, or None at ``deadline``; Halted once ``halt`` is set."""
        while True:
            if self.halt is not None and self.halt.is_set():
                raise Halted(f"stopped while waiting for rig {self.rig_id}")
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            try:
                return self.inbox.get(timeout=min(remaining, HALT_POLL_S))
            except queue.Empty:
                continue

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        """Ask the rig for a new episode. A swing-up that fails (it happens, from a messy fall) is retried after
        the pendulum has had time to settle; ``reset_attempts`` failures in a row raise RuntimeError."""
        super().reset(seed=seed)
        began, settled = time.perf_counter(), 0.0
        for attempt in range(1, self.reset_attempts + 1):
            try:
                obs, info = self._reset_once()
            except ResetFailed as err:
                self.failed_resets += 1
                if attempt == self.reset_attempts:
                    raise RuntimeError(f"{err} ({attempt} attempts in a row)") from None
                if self.halt is not None and self.halt.wait(self.settle_s):
                    raise Halted(f"stopped while the pendulum of rig {self.rig_id} settled") from None
                if self.halt is None:
                    time.sleep(self.settle_s)
                settled += self.settle_s
                continue
            ticks = info.pop("reset_ticks")
            self._started(time.perf_counter() - began if self.measured else ticks_to_s(ticks) + settled)
            return obs, info
        raise AssertionError("unreachable")

    def _reset_once(self) -> tuple[np.ndarray, dict]:
        """One swing-up; its info's ``reset_ticks``: rig ticks from the end of the last episode (or from the first
        state this request brought) to the ``ready`` state."""
        self.episode_return = 0.0
        first_seq: int | None = None
        self._request = next(self._request_ids)
        request = encode(QubeReset(rig_id=self.rig_id, request_id=self._request))
        deadline = time.monotonic() + self.reset_timeout_s
        acknowledged, next_send = False, 0.0
        while True:
            if not acknowledged and time.monotonic() >= next_send:  # the rig may not be listening yet: repeat
                self.conn.publish(self._reset_topic, request, qos=qos_of(self._reset_topic))
                next_send = time.monotonic() + 1.0
            msg = self._next(min(deadline, next_send) if not acknowledged else deadline)
            if msg is None:
                if time.monotonic() >= deadline:
                    break
                continue
            if isinstance(msg, QubeStatus) and msg.request_id == self._request:
                acknowledged = True
                if msg.state in ("reset_failed", "fault"):  # a fault during the reset (e.g. the arm limit)
                    raise ResetFailed(f"rig {self.rig_id}: reset {msg.state.replace('_', ' ')}: {msg.detail}")
            if isinstance(msg, QubeState) and first_seq is None and (self._end_seq is None or msg.seq > self._end_seq):
                first_seq = msg.seq
            if isinstance(msg, QubeState) and msg.episode == self._request and msg.phase == "ready":
                self._last = msg
                since = self._end_seq if self._end_seq is not None else (first_seq or msg.seq) - 1
                self._end_seq = None
                return (observation(msg.alpha, msg.alpha_dot, msg.theta, msg.theta_dot),
                        {"seq": msg.seq, "reset_ticks": max(0, msg.seq - since)})
        raise TimeoutError(f"rig {self.rig_id} did not finish reset {self._request} within {self.reset_timeout_s} s "
                           "(is the bridge or qube-sim running? FEDRL_RIG_ID must match)")

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        last = self._last
        if last is None:
            raise RuntimeError("call reset() first")
        command = self.actions.command(action)
        self.conn.publish(self._action_topic, encode(QubeAction(rig_id=self.rig_id, seq=last.seq, command=command)),
                          qos=self._action_qos)
        deadline = time.monotonic() + self.step_timeout_s
        while (msg := self._next(deadline)) is not None:
            if isinstance(msg, QubeStatus):
                if msg.state in ("fault", "offline") and msg.episode == self._request:
                    obs = observation(last.alpha, last.alpha_dot, last.theta, last.theta_dot)
                    return obs, 0.0, True, False, {"ended": msg.state, "detail": msg.detail}
                continue
            if msg.episode != self._request or msg.seq <= last.seq:
                continue  # a state of an earlier episode, or one already answered
            self._last = msg
            ended = msg.phase not in ("ready", "running")
            reward, terminated, truncated = self._outcome(msg.alpha, ended)
            if terminated or truncated:
                self._end_seq = msg.seq
            obs = observation(msg.alpha, msg.alpha_dot, msg.theta, msg.theta_dot)
            return obs, reward, terminated, truncated, {"seq": msg.seq, "phase": msg.phase}
        self.timeouts += 1
        log.warning("rig %s: no state within %.0f s of the action for state %d: the episode ends (%d timeouts)",
                    self.rig_id, self.step_timeout_s, last.seq, self.timeouts)
        obs = observation(last.alpha, last.alpha_dot, last.theta, last.theta_dot)
        return obs, 0.0, True, False, {"ended": "timeout"}


class QubeLocalEnv(_QubeTask):
    """The same task, rig and bridge code in process: ControlCore over a SimulatedQube on a virtual clock."""

    def __init__(self, seed: int = 0, variation: float = 0.05, reset_ticks: int = 20_000, profile: Any = None,
                 randomize: float | None = None, timing: InjectedTiming | None = None,
                 actions: ActionSet | None = None, control: ControlConfig | None = None,
                 drawn_model: bool = False) -> None:
        """``profile`` (a services.qube_sim.profile.RigProfile) gives the rig's physics and non-ideal effects, spread
        by ``seed``; without one, the nominal plant spread by ``variation``. ``randomize`` (or the profile's) draws
        the physics again at every reset. ``timing``: the real loop's timing (the ``delayed`` clock): each action
        reaches the motor a random delay after its state's read, or is lost to the safe action; None: at the read
        (``lockstep``). ``actions``: the action set (default the paper's); ``control``: the bridge's configuration
        (default: the nominal rig's, at the task's period); ``drawn_model``: its reset and self-test computed from the
        rig's own plant, and from each drawn one (``--rig-model drawn``: services/qube_sim/profile.py DRAWN_MODEL)."""
        super().__init__(actions)
        from services.qube_sim.clock import VirtualClock
        from services.qube_sim.dynamics import QubeParams
        from services.qube_sim.spi_peer import SimulatedQube

        self.seed, self.profile, self.randomize = seed, profile, randomize
        if profile is not None:
            params, options = profile.rig_params(seed), profile.device_options()
        else:
            params, options = QubeParams.varied(seed, scale=variation) if variation > 0 else QubeParams(), {}
        self.clock = VirtualClock()
        self.device = SimulatedQube(params, seed=seed, period_s=0, clock=self.clock, **options)
        self.core = ControlCore(self.device, control or ControlConfig(period_s=PERIOD_S), clock=self.clock)
        self.drawn_model = drawn_model
        if drawn_model:
            self._use_plant(params)
        self.reset_ticks = reset_ticks
        self.timing = timing
        self.failed_resets = 0
        self.redrawn = 0  # randomised plants replaced because they could not be swung up
        self._requests = itertools.count(1)
        self._episodes = itertools.count(1)

    def _use_plant(self, params: Any) -> None:
        """The bridge's model is this plant (``drawn_model``)."""
        from services.qube_sim.profile import params_model

        self.core.use_model(params_model(params))

    def _sense(self) -> Sensed:
        self.clock.advance(PERIOD_S)
        return self.core.sense()

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        """A swing-up on the simulated clock (its seconds, failed attempts and settling included, are the episode's
        reset seconds)."""
        super().reset(seed=seed)
        began = self.clock()
        obs, info = self._swing_up()
        self._started(self.clock() - began)
        return obs, info

    def _swing_up(self) -> tuple[np.ndarray, dict]:
        """Under domain randomisation a drawn plant that the reset controller cannot swing up (RESET_ATTEMPTS
        failures) is no rig to learn on: it is replaced by a fresh draw (counted in ``redrawn``), at most
        MAX_REDRAWS times. A rig of fixed physics, as a real one, fails after its attempts."""
        episode = next(self._episodes)
        for draw in range(MAX_REDRAWS + 1):
            params = None if self.profile is None else self.profile.episode_params(self.seed, episode,
                                                                                  self.randomize, draw=draw)
            if params is not None:  # domain randomisation: this episode's physics
                self.device.set_params(params)
                if self.drawn_model:
                    self._use_plant(params)
            try:
                return self._attempts()
            except ResetFailed:
                if params is None or draw == MAX_REDRAWS:
                    raise
                self.redrawn += 1
        raise AssertionError("unreachable")

    def _attempts(self) -> tuple[np.ndarray, dict]:
        for attempt in range(1, RESET_ATTEMPTS + 1):  # as over MQTT: retried after the pendulum settles
            try:
                return self._reset_once()
            except ResetFailed:
                self.failed_resets += 1
                if attempt == RESET_ATTEMPTS:
                    raise
                for _ in range(round(3.0 / PERIOD_S)):
                    self._sense()
                    self.core.act(None)
        raise AssertionError("unreachable")

    def _reset_once(self) -> tuple[np.ndarray, dict]:
        """As over MQTT: the episode starts with the first state of the rig's ``ready`` phase (actionable)."""
        self.episode_return = 0.0
        request = next(self._requests)
        self.core.events.clear()
        self.core.request_reset(request)
        for _ in range(self.reset_ticks):
            s = self.core.sense()
            if s.awaits_action:
                self.core.events.clear()
                return observation(s.alpha, s.alpha_dot, s.theta, s.theta_dot), {"seq": s.seq}
            failed = [e for e in self.core.events if (e[0] == "reset_failed" and e[1] == request) or e[0] == "fault"]
            if failed:
                raise ResetFailed(f"simulated rig could not reset: {failed[-1][0]}: {failed[-1][2]}")
            self.core.act(None)
            self.clock.advance(PERIOD_S)
        raise ResetFailed("simulated rig did not reset in time")

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        command: int | None = self.actions.command(action)
        delay = self.timing.draw() if self.timing is not None else None
        if self.timing is None or delay is None:  # lockstep: written at the read; delayed and lost: the safe action
            self.core.act(command if self.timing is None else None)
            s = self._sense()
        else:  # as the bridge's lockstep runner with injected timing (rpi_bridge/runner.py)
            self.clock.advance(delay)
            self.core.act(command)
            self.clock.advance(PERIOD_S - delay)
            s = self.core.sense()
        ended = s.phase not in ("ready", "running")
        reward, terminated, truncated = self._outcome(s.alpha, ended)
        self.core.events.clear()
        obs = observation(s.alpha, s.alpha_dot, s.theta, s.theta_dot)
        return obs, reward, terminated, truncated, {"phase": s.phase}


def make_qube_env(spec: Any, seed: int, noise: Any, rig_id: str | None = None, conn: Any = None,
                  probe: bool = False, qube_clock: str = "realtime", qube_actions: str | None = None,
                  halt: threading.Event | None = None,
                  **_: Any) -> gym.Env:
    """Factory for the ``qube`` task: the rig ``rig_id`` over the worker's MQTT connection.

    Per-device variation comes from the rig itself (each simulated rig draws its physics from its seed and its own
    rig profile; real rigs differ anyway), so the paper's simulated action noise is not added here.
    """
    actions = action_set(qube_actions)
    if probe:
        return _QubeTask(actions)
    if conn is None or not rig_id:
        raise ValueError("env 'qube' drives a rig over MQTT: give the worker --rig-id (FEDRL_RIG_ID)")
    return QubeMqttEnv(conn, rig_id, qube_clock=qube_clock, actions=actions, halt=halt)


def make_qube_local_env(spec: Any, seed: int, noise: Any, probe: bool = False, rig_profile: Any = None,
                        randomize: float | None = None, qube_clock: str = "lockstep", qube_actions: str | None = None,
                        rig_model: Any = None, **_: Any) -> gym.Env:
    """Factory for the ``qube-local`` task: a simulated rig inside the worker, its physics drawn from ``seed`` around
    ``rig_profile`` (a name, a JSON file or a RigProfile; default ``ideal``), on the simulated clock ``qube_clock``:
    ``lockstep``, or ``delayed`` (the profile's ``loop_delay_ms`` and ``loop_miss_rate``, as ``python -m
    services.qube_sim --clock delayed`` applies them). ``rig_model``: the bridge's model of the rig (an identified
    profile, a file or a folder with one per worker; as ``--rig-model`` of the bridge; ``drawn``: the rig's own plant,
    each drawn one under randomisation), else the nominal one."""
    actions = action_set(qube_actions)
    if probe:
        return _QubeTask(actions)
    from services.qube_sim.profile import DRAWN_MODEL, RigProfile, load_profile

    if qube_clock not in LOCAL_CLOCKS:
        raise ValueError(f"qube-local runs on a simulated clock ({' or '.join(LOCAL_CLOCKS)}), not {qube_clock!r}")
    profile = rig_profile if isinstance(rig_profile, RigProfile) else load_profile(rig_profile or "ideal", seed)
    timing = None
    if qube_clock == "delayed":
        lo, hi = profile.loop_delay_ms
        timing = InjectedTiming((lo / 1e3, hi / 1e3), profile.loop_miss_rate, seed=seed)
    control = None
    drawn = rig_model == DRAWN_MODEL
    if rig_model is not None and not drawn:
        model = (rig_model if isinstance(rig_model, RigProfile) else load_profile(rig_model, seed)).plant_model()
        control = with_model(ControlConfig(period_s=PERIOD_S), model)
    return QubeLocalEnv(seed=seed, profile=profile, randomize=randomize, timing=timing, actions=actions,
                        control=control, drawn_model=drawn)
