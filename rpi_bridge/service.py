"""The bridge's MQTT adapter: connects the BridgeRunner of one rig to the broker.

Subscribes ``qube/<rig>/action`` (QoS 0: a late retransmission is useless) and ``qube/<rig>/reset`` (QoS 1);
publishes ``state`` (QoS 0), ``status`` (QoS 1, last will ``offline``) and ``telemetry`` (QoS 0), each with the QoS
of its route in protocol/routes.py. Bad payloads are logged, counted and dropped.
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from collections.abc import Callable
from typing import TypeVar

from protocol import qube, topics
from protocol.codec import DecodeError, RejectCounter, decode, encode
from protocol.messages import Message, QubeAction, QubeIdentify, QubeReset, QubeStatus
from protocol.mqtt import Stopped
from protocol.routes import qos_of
from protocol.transport import Connect
from rpi_bridge.calibration import CalibrationStore
from rpi_bridge.control import ControlConfig, ControlCore
from rpi_bridge.device import QubeDevice
from rpi_bridge.runner import BridgeRunner, InjectedTiming
from runtime.cli import STOP_SIGNALS

M = TypeVar("M", bound=Message)

log = logging.getLogger("rpi_bridge")


class BridgeService:
    """One rig on the broker: runner + connection + subscriptions."""

    def __init__(
        self,
        device: QubeDevice,
        rig_id: str,
        connect: Connect,
        control: ControlConfig | None = None,
        deadline_s: float = qube.PERIOD_S,
        lockstep: bool = False,
        advance: Callable[[float], None] | None = None,
        client_prefix: str = "bridge",
        clock: Callable[[], float] = time.perf_counter,
        store: CalibrationStore | None = None,
        recalibrate: bool = False,
        timing: InjectedTiming | None = None,
    ) -> None:
        """``connect`` makes its connection (protocol.transport.Connect: its settings' ``connector()``, or a test's
        transport); ``clock`` is the core's clock (the device's time base: perf_counter on a rig, a virtual clock for a
        lockstep simulator); ``store`` keeps the calibration across restarts."""
        self.rig_id = topics.check_id(rig_id, "rig id")
        self.rejects = RejectCounter(log)
        will = encode(QubeStatus(rig_id=rig_id, state="offline", detail="connection lost"))
        self.conn = connect(f"{client_prefix}-{rig_id}", (topics.rig(rig_id, topics.STATUS), will), self.rejects)
        self.core = ControlCore(device, control, clock=clock, store=store, recalibrate=recalibrate)
        self.runner = BridgeRunner(self.core, rig_id, self._publish, deadline_s=deadline_s, lockstep=lockstep,
                                   advance=advance, timing=timing)
        self.stop_event = threading.Event()

    def _publish(self, topic: str, payload: bytes, qos: int) -> object:
        return self.conn.publish(topic, payload, qos=qos)

    def _decode(self, topic: str, payload: bytes, kind: type[M]) -> M | None:
        """The message, if it is a valid one of ``kind`` for this rig on its topic; else counted and None."""
        try:
            msg = decode(payload, kind, topic=topic)
        except DecodeError as err:
            self.rejects.reject_error(topic, err)
            return None
        return msg

    def _on_action(self, topic: str, payload: bytes) -> None:
        msg = self._decode(topic, payload, QubeAction)
        if msg is not None:
            self.runner.on_action(msg)

    def _on_identify(self, topic: str, payload: bytes) -> None:
        msg = self._decode(topic, payload, QubeIdentify)
        if msg is None:
            return
        log.info("rig %s: identification %d requested (attempt %d)", self.rig_id, msg.request_id, msg.attempt)
        self.runner.on_identify(msg.request_id, msg.attempt)

    def _on_reset(self, topic: str, payload: bytes) -> None:
        msg = self._decode(topic, payload, QubeReset)
        if msg is None:
            return
        log.info("rig %s: reset %d requested", self.rig_id, msg.request_id)
        self.runner.on_reset(msg.request_id)

    def run(self, max_ticks: int | None = None, connect_timeout_s: float = 60.0) -> None:
        """Connect (waiting up to ``connect_timeout_s`` for the broker: a rig starts with the broker, on a loaded
        machine too), then run the control loop in this thread until SIGINT/SIGTERM (or ``max_ticks``)."""
        try:
            self.conn.start(timeout=connect_timeout_s, stop=self.stop_event)
        except Stopped:
            return
        for leaf, handler in ((topics.ACTION, self._on_action), (topics.RESET, self._on_reset),
                              (topics.IDENTIFY, self._on_identify)):
            topic = topics.rig(self.rig_id, leaf)
            self.conn.subscribe(topic, handler, qos=qos_of(topic))
        status = topics.rig(self.rig_id, topics.STATUS)
        self.conn.publish(status, encode(QubeStatus(rig_id=self.rig_id, state="idle", detail="bridge up")),
                          qos=qos_of(status))
        timing = self.runner.timing
        mode = "real-time" if not self.runner.lockstep else (
            "lockstep" if timing is None else f"lockstep with delays of {timing.delay_s[0] * 1e3:g}-"
            f"{timing.delay_s[1] * 1e3:g} ms and {timing.miss_rate:.2%} misses")
        log.info("rig %s: control loop at %.1f ms, deadline %.1f ms, %s clock; calibration %s", self.rig_id,
                 self.core.cfg.period_s * 1e3, self.runner.deadline_s * 1e3, mode,
                 self.core.store.path if self.core.store is not None else "not stored")
        try:
            self.runner.run(self.stop_event, max_ticks=max_ticks)
        finally:
            t = self.runner.telemetry()
            log.info("rig %s stopped: %d ticks, %d deadline misses, %d late actions, %d late at the motor, %d faults, "
                     "latency %s ms, read to motor write %s ms", self.rig_id, t.ticks, t.deadline_misses,
                     t.late_actions, t.late_at_motor, t.faults, t.latency_ms, t.motor_ms)
            self.conn.stop()

    def install_signal_handlers(self) -> None:
        for sig in STOP_SIGNALS:
            signal.signal(sig, lambda *_: self.stop_event.set())
