"""The bridge's loop: runs the ControlCore tick by tick, publishes each state, waits for the worker's action
until the deadline, and reports loop timing.

- Real time (the rig, or the simulator with ``lockstep=False``): ticks every ``period_s``; the action for state
  ``seq`` is applied only if it arrives within ``deadline_s`` of that state's read and its write to the motor
  starts within that deadline too (the core checks the clock right before the SPI transfer). A late action is
  counted and dropped, never applied to a later state; a miss applies the safe action.
- Lockstep (simulator only): simulated time advances one period per tick and the next state waits for the
  action, so training runs as fast as the worker answers. Nothing in it depends on wall time or on when a message
  arrives, only on which messages arrive: a state awaiting an action waits for it (or for a reset request, or
  stop) however long it takes, the rig's own phases (start-up checks, reset) tick freely, and an idle, fallen or
  faulted rig does not tick at all until the next reset request: its simulated time stands still, as in process
  (worker/qube_env.py's ``QubeLocalEnv``). So one rig's trajectory is a function of its seed and the actions
  only. With an :class:`InjectedTiming`, each action reaches the motor a random delay after its state's read
  (simulated time) and a fraction of them is lost, as on a real loop (drawn once per answered state, so
  deterministic too).
"""

from __future__ import annotations

import gzip
import logging
import random
import threading
import time
from collections import deque
from collections.abc import Callable

from protocol import qube, topics
from protocol.codec import encode
from protocol.messages import MAX_RECORDING_BYTES, QubeAction, QubeRecording, QubeState, QubeStatus, QubeTelemetry
from protocol.routes import qos_of
from rpi_bridge.control import ControlCore
from rpi_bridge.identify import Identification

log = logging.getLogger("rpi_bridge")

Publish = Callable[[str, bytes, int], object]

POLL_S = 0.1  # how often a lockstep wait without a timeout looks at the stop event (s of wall time)

#: Phases in which nothing awaits the rig: a lockstep rig does not tick in them until a reset request comes.
WAITING = ("idle", "fallen", "fault")


class InjectedTiming:
    """The real loop's timing for a lockstep rig: each action reaches the motor ``delay_s`` (uniform in [lo, hi]
    seconds) after its state's read, and with probability ``miss_rate`` not at all (the safe action instead).
    Deterministic in ``seed``."""

    def __init__(self, delay_s: tuple[float, float] = (0.0, qube.PERIOD_S), miss_rate: float = 0.003,
                 seed: int = 0) -> None:
        lo, hi = delay_s
        if not 0 <= lo <= hi:
            raise ValueError(f"delays must satisfy 0 <= lo <= hi, got {delay_s}")
        if not 0 <= miss_rate < 1:
            raise ValueError(f"miss_rate must be in [0, 1), got {miss_rate}")
        self.delay_s = (lo, hi)
        self.miss_rate = miss_rate
        self._rng = random.Random(seed)
        self.injected_misses = 0

    def draw(self) -> float | None:
        """The delay of the next action (s), or None when it is lost."""
        if self.miss_rate and self._rng.random() < self.miss_rate:
            self.injected_misses += 1
            return None
        return self._rng.uniform(*self.delay_s)

    @classmethod
    def parse(cls, delay_ms: str, miss_rate: float, seed: int = 0) -> InjectedTiming:
        """From ``"LO:HI"`` milliseconds (or a single number) and a miss rate; ValueError on bad input."""
        parts = delay_ms.split(":")
        if len(parts) not in (1, 2):
            raise ValueError(f"delay must be LO:HI in ms (e.g. 0:7), got {delay_ms!r}")
        try:
            values = [float(p) for p in parts]
        except ValueError:
            raise ValueError(f"delay must be LO:HI in ms (e.g. 0:7), got {delay_ms!r}") from None
        lo, hi = values[0], values[-1]
        return cls((lo / 1e3, hi / 1e3), miss_rate, seed)


class ActionSlot:
    """A one-action mailbox for the state being answered; offers for any other state are late."""

    def __init__(self, clock: Callable[[], float]) -> None:
        self._clock = clock
        self._cond = threading.Condition()
        self._seq: int | None = None
        self._deadline: float | None = None
        self._command: int | None = None
        self._arrived = 0.0
        self._cancelled = False
        self.late = 0

    def open(self, seq: int, deadline: float | None) -> None:
        """Await the action for state ``seq`` until clock time ``deadline`` (None: no deadline, lockstep)."""
        with self._cond:
            self._seq, self._deadline, self._command, self._cancelled = seq, deadline, None, False

    def offer(self, action: QubeAction) -> bool:
        """Network thread: accept the action if it answers the open state in time, else count it late.

        The arrival time is checked against the deadline here, so a loop thread that wakes up late (a loaded
        machine) still never applies a late action."""
        with self._cond:
            now = self._clock()
            if (self._seq is None or action.seq != self._seq or self._command is not None
                    or (self._deadline is not None and now > self._deadline)):
                self.late += 1
                return False
            self._command, self._arrived = action.command, now
            self._cond.notify()
            return True

    def cancel(self) -> None:
        """Wake a waiting tick without an action (a reset request arrived)."""
        with self._cond:
            self._cancelled = True
            self._cond.notify()

    def wait(self, timeout: float | None, stop: threading.Event | None = None) -> tuple[int | None, float]:
        """Block until the action arrives, the slot is cancelled, or ``timeout`` s pass (None: no timeout, until
        ``stop`` is set); then close the slot."""
        with self._cond:
            answered = lambda: self._command is not None or self._cancelled  # noqa: E731
            if timeout is not None:
                self._cond.wait_for(answered, timeout=max(0.0, timeout))
            else:
                while not answered() and not (stop is not None and stop.is_set()):
                    self._cond.wait(POLL_S)  # (stop does not notify this condition)
            command, arrived = self._command, self._arrived
            self._seq = None
            return command, arrived


def percentiles(samples: deque[float] | list[float]) -> dict[str, float]:
    """p50 / p99 / max in milliseconds (zeros when empty)."""
    if not samples:
        return {"p50": 0.0, "p99": 0.0, "max": 0.0, "n": 0.0}
    ordered = sorted(samples)
    n = len(ordered)
    return {"p50": round(ordered[n // 2] * 1e3, 3), "p99": round(ordered[min(n - 1, int(0.99 * n))] * 1e3, 3),
            "max": round(ordered[-1] * 1e3, 3), "n": float(n)}


class BridgeRunner:
    """Owns the clock of one rig's control loop."""

    def __init__(
        self,
        core: ControlCore,
        rig_id: str,
        publish: Publish,
        deadline_s: float = qube.PERIOD_S,
        lockstep: bool = False,
        advance: Callable[[float], None] | None = None,
        telemetry_interval_s: float = 1.0,
        clock: Callable[[], float] = time.perf_counter,
        window: int = 20_000,
        timing: InjectedTiming | None = None,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        """``clock`` measures wall time (latency, jitter); deadlines use the core's clock, which in real time must
        be the same clock. ``timing`` (lockstep only) injects the real loop's delays and misses. ``sleep`` waits
        out the rest of a real-time period (a test's stepped clock passes one that advances it)."""
        if deadline_s <= 0 or deadline_s > core.cfg.period_s:
            raise ValueError(f"deadline {deadline_s * 1e3:.2f} ms must be in (0, period {core.cfg.period_s * 1e3} ms]")
        if timing is not None and not lockstep:
            raise ValueError("injected timing is for a lockstep rig (a real-time loop has its own)")
        if timing is not None and timing.delay_s[1] > core.cfg.period_s:
            raise ValueError(f"injected delays must not exceed the period ({core.cfg.period_s * 1e3:.1f} ms)")
        topics.check_id(rig_id, "rig id")
        self.core = core
        self.rig_id = rig_id
        self.publish = publish
        self.deadline_s = deadline_s
        self.lockstep = lockstep
        self.advance = advance
        self.telemetry_interval_s = telemetry_interval_s
        self.clock = clock
        self.timing = timing
        self.sleep = sleep
        self.slot = ActionSlot(core.clock)
        self._stop = threading.Event()  # the stop event of run()
        self._requested = threading.Event()  # set on every reset request (wakes a lockstep rig that waits for one)
        self._advanced = 0.0
        self.latencies: deque[float] = deque(maxlen=window)
        self.jitters: deque[float] = deque(maxlen=window)
        self.overruns = 0
        self._state_topic = topics.rig(rig_id, topics.STATE)
        self._state_qos = qos_of(self._state_topic)  # looked up once: states go out every tick
        self._status_topic = topics.rig(rig_id, topics.STATUS)
        self._telemetry_topic = topics.rig(rig_id, topics.TELEMETRY)
        self._recording_topic = topics.rig(rig_id, topics.RECORDING)
        self._last_telemetry = clock()
        self._reports = 0

    # -- network thread --------------------------------------------------------------------------------------

    def on_action(self, action: QubeAction) -> None:
        if action.rig_id == self.rig_id:
            self.slot.offer(action)

    def on_reset(self, request_id: int) -> None:
        self.core.request_reset(request_id)
        self.slot.cancel()
        self._requested.set()

    def on_identify(self, request_id: int, attempt: int = 0) -> None:
        self.core.request_identify(request_id, attempt)
        self.slot.cancel()
        self._requested.set()

    # -- loop ------------------------------------------------------------------------------------------------

    def run(self, stop: threading.Event, max_ticks: int | None = None) -> None:
        """Tick until ``stop`` is set (or ``max_ticks``); the amplifier is disabled on the way out."""
        period = self.core.cfg.period_s
        next_tick = self.clock()
        ticks = 0
        self._stop = stop
        try:
            while not stop.is_set() and (max_ticks is None or ticks < max_ticks):
                start = self.clock()
                if not self.lockstep:
                    self.jitters.append(max(0.0, start - next_tick))
                phase = self.tick(start)
                ticks += 1
                if self.lockstep:
                    if self.advance is not None:
                        self.advance(period - self._advanced)
                    self._advanced = 0.0
                    if phase in WAITING:
                        self._await_request(stop)
                    continue
                next_tick += period
                delay = next_tick - self.clock()
                if delay > 0:
                    self.sleep(delay)
                elif delay < -period:
                    self.overruns += 1
                    next_tick = self.clock()
                self._maybe_telemetry()
        finally:
            self.core.disable()
            self._drain_events()
            self._publish_status("offline" if stop.is_set() else "idle", "bridge loop stopped")

    def _await_request(self, stop: threading.Event) -> None:
        """Lockstep: block until a reset request is pending (or ``stop``). No tick runs meanwhile, so the rig's
        simulated time stands still however long the worker takes (a round of the federation, a PPO update)."""
        while not stop.is_set():
            self._requested.clear()
            if self.core.reset_pending or self.core.identify_pending:
                return
            self._requested.wait(POLL_S)

    def tick(self, start: float) -> str:
        """One period: sense, publish the state, wait for the action (until the deadline), act."""
        core = self.core
        before = core.phase
        sensed = core.sense()
        self._drain_events()
        publish_state = sensed.awaits_action or not self.lockstep or sensed.phase != before
        deadline = sensed.t + self.deadline_s  # core clock: the state's read + the deadline
        if sensed.awaits_action:
            self.slot.open(sensed.seq, None if self.lockstep else deadline)
        if publish_state:
            state = QubeState(rig_id=self.rig_id, seq=sensed.seq, t=start, theta=sensed.theta, alpha=sensed.alpha,
                              theta_dot=sensed.theta_dot, alpha_dot=sensed.alpha_dot, episode=sensed.episode,
                              phase=sensed.phase)
            published_at = self.clock()
            self.publish(self._state_topic, encode(state), self._state_qos)
        if sensed.awaits_action:
            timeout = None if self.lockstep else start + self.deadline_s - self.clock()
            command, arrived = self.slot.wait(timeout, self._stop)
            if command is not None:
                self.latencies.append(arrived - published_at if not self.lockstep else self.clock() - published_at)
            if self.lockstep and self.timing is None:
                core.act(command)  # simulated time stands still: written at the instant of the read
            elif self.lockstep:
                delay = self.timing.draw() if command is not None else None  # type: ignore[union-attr]
                if delay is not None and self.advance is not None:
                    self.advance(delay)
                    self._advanced = delay
                core.act(command if delay is not None else None, deadline)
            else:
                core.act(command, deadline)
        return core.phase

    # -- reporting -------------------------------------------------------------------------------------------

    def _drain_events(self) -> None:
        while self.core.identify_answers:
            self._publish_recording(*self.core.identify_answers.pop(0))
        while self.core.events:
            state, request_id, detail = self.core.events.pop(0)
            if state == "fault":
                log.error("rig %s fault: %s (amplifier disabled)", self.rig_id, detail)
            elif state in ("calibrating", "self_test", "idle") and detail:
                log.info("rig %s %s: %s", self.rig_id, state, detail)
            elif state == "reset_failed":
                log.warning("rig %s reset %d failed: %s", self.rig_id, request_id, detail)
            self._publish_status(state, detail, request_id)

    def _publish_recording(self, request_id: int, ident: Identification | None, outcome: str) -> None:
        """The answer to an identification request: the recording (gzip JSON) when it is complete, else the reason
        there is none."""
        payload = b""
        if ident is not None and outcome == "complete":
            payload = gzip.compress(ident.recording(self.rig_id).model_dump_json().encode())
            if len(payload) > MAX_RECORDING_BYTES:
                outcome = f"the recording is {len(payload)} bytes compressed, over the {MAX_RECORDING_BYTES} allowed"
                payload = b""
        log.info("rig %s: identification %d: %s", self.rig_id, request_id, outcome)
        msg = QubeRecording(rig_id=self.rig_id, request_id=max(0, request_id), outcome=outcome[:2000],
                            recording=payload)
        self.publish(self._recording_topic, encode(msg), qos_of(self._recording_topic))

    def _publish_status(self, state: str, detail: str = "", request_id: int = -1) -> None:
        msg = QubeStatus(rig_id=self.rig_id, state=state, request_id=request_id, episode=self.core.episode,
                         detail=detail[:2000])
        self.publish(self._status_topic, encode(msg), qos_of(self._status_topic))

    def telemetry(self) -> QubeTelemetry:
        c = self.core.counters
        return QubeTelemetry(rig_id=self.rig_id, ticks=c.ticks, deadline_misses=c.misses, late_actions=self.slot.late,
                             faults=c.faults, jitter_ms=percentiles(self.jitters),
                             latency_ms=percentiles(self.latencies), late_at_motor=c.late_at_motor,
                             motor_ms=percentiles(self.core.write_latencies),
                             period_ms=percentiles(self.core.periods))

    def _maybe_telemetry(self) -> None:
        now = self.clock()
        if now - self._last_telemetry < self.telemetry_interval_s:
            return
        self._last_telemetry = now
        t = self.telemetry()
        self.publish(self._telemetry_topic, encode(t), qos_of(self._telemetry_topic))
        self._reports += 1
        level = logging.INFO if self._reports % 10 == 0 else logging.DEBUG  # the log gets one line per 10 reports
        log.log(level, "rig %s: %d ticks, %d misses, %d late, latency p50 %.2f p99 %.2f max %.2f ms, "
                "jitter p99 %.2f ms", self.rig_id, t.ticks, t.deadline_misses, t.late_actions, t.latency_ms["p50"],
                  t.latency_ms["p99"], t.latency_ms["max"], t.jitter_ms["p99"])
