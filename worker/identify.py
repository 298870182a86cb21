"""``python -m worker.identify``: ask a rig over MQTT to identify itself, fit its profile on this host, write it.

The rig (``python -m rpi_bridge`` on its Pi, or ``python -m services.qube_sim``) runs the identification protocol
(rpi_bridge/identify.py) when a QubeIdentify comes, as it swings up on a QubeReset, and answers with a QubeRecording:
the recording, or the one-line reason it has none. This side fits the rig's profile to it (services/qube_sim/
identify.py, scipy) and writes the profile only if the fit is trusted. The bridge stays light: it records, the host
fits. ``deploy.lab --env qube`` runs this for every rig.
"""

from __future__ import annotations

import gzip
import io
import logging
import queue
import sys
import time
from collections.abc import Callable
from pathlib import Path

from pydantic import ValidationError, field_validator

from protocol import topics
from protocol.codec import DecodeError, RejectCounter, decode, encode
from protocol.messages import (
    IDENTIFY_ATTEMPTS_LIMIT,
    MAX_RECORDING_BYTES,
    QubeIdentify,
    QubeRecording,
    QubeStatus,
)
from protocol.routes import qos_of
from protocol.transport import Transport
from rpi_bridge.identify import IDENTIFY_ATTEMPTS, IdentifyFailed, Recording
from runtime.cli import setup_logging
from runtime.settings import LogLevel, MqttSettings, returns_code, setting

log = logging.getLogger("worker.identify")

#: The most a recording may grow to when unzipped (a 3-minute protocol is about 1.5 MB of JSON).
MAX_UNZIPPED_BYTES = 64 * 1024 * 1024


class IdentifySettings(MqttSettings):
    """Identify one rig over MQTT and fit its profile."""

    rig_id: str = setting(help="the rig to identify (its bridge's FEDRL_RIG_ID)")
    out: Path = setting(help="the profile JSON to write (only a trusted fit is written)", env=False)
    base: str = setting("lab", "profile of every value the fit does not set (built-in name or file)",
                        metavar="NAME|FILE")
    recording_out: Path | None = setting(None, "also keep the rig's recording here (JSON)", env=False)
    identify_timeout: float = setting(900.0, "seconds to wait for each of the rig's recordings (the protocol takes "
                                      "about 80 s of rig time, after the rig's start-up checks)", gt=0)
    identify_attempts: int = setting(IDENTIFY_ATTEMPTS, "recordings before giving up (a refused fit is recorded "
                                     "again with the next PRBS sequence)", ge=1, le=IDENTIFY_ATTEMPTS_LIMIT)
    log_level: LogLevel = setting("INFO", "DEBUG, INFO, WARNING or ERROR")

    @field_validator("base")
    @classmethod
    def _base(cls, value: str) -> str:
        from services.qube_sim.profile import load_profile  # pydantic only

        load_profile(value)
        return value


def unpack(msg: QubeRecording) -> Recording:
    """The recording a rig sent (IdentifyFailed with its outcome when it has none, or for a payload that is no
    recording)."""
    if msg.outcome != "complete":
        raise IdentifyFailed(f"rig {msg.rig_id}: {msg.outcome}")
    try:
        with gzip.GzipFile(fileobj=io.BytesIO(msg.recording)) as fh:
            text = fh.read(MAX_UNZIPPED_BYTES + 1)
        if len(text) > MAX_UNZIPPED_BYTES:
            raise IdentifyFailed(f"rig {msg.rig_id}: the recording unzips to over {MAX_UNZIPPED_BYTES} bytes")
        return Recording.model_validate_json(text)
    except (OSError, EOFError, ValidationError) as err:
        first = str(err).splitlines()[0][:200]
        raise IdentifyFailed(f"rig {msg.rig_id}: its recording could not be read ({first})") from None


def request_recording(conn: Transport, rig_id: str, timeout_s: float,
                      progress: Callable[[str], None] = print, clock: Callable[[], float] = time.monotonic,
                      request_id: int | None = None, attempt: int = 0) -> Recording:
    """Ask rig ``rig_id`` to identify itself (repeated every second until it acknowledges; ``attempt``: its PRBS
    sequence, QubeIdentify's) and return its complete recording; IdentifyFailed with the rig's reason, or
    TimeoutError when nothing comes within ``timeout_s``."""
    inbox: queue.Queue[QubeRecording | QubeStatus] = queue.Queue()
    rejects = RejectCounter(log)

    def on_message(topic: str, payload: bytes) -> None:
        try:
            inbox.put(decode(payload, QubeRecording, QubeStatus, topic=topic, max_bytes=MAX_RECORDING_BYTES + 4096))
        except DecodeError as err:
            rejects.reject_error(topic, err)

    for leaf in (topics.RECORDING, topics.STATUS):
        topic = topics.rig(rig_id, leaf)
        conn.subscribe(topic, on_message, qos=qos_of(topic))
    request = request_id if request_id is not None else int(time.time() * 1000) % 1_000_000_000
    ask = encode(QubeIdentify(rig_id=rig_id, request_id=request, attempt=attempt))
    ask_topic = topics.rig(rig_id, topics.IDENTIFY)
    deadline, next_ask, acknowledged = clock() + timeout_s, 0.0, False
    while clock() < deadline:
        if not acknowledged and clock() >= next_ask:
            conn.publish(ask_topic, ask, qos=qos_of(ask_topic))
            next_ask = clock() + 1.0
        try:
            msg = inbox.get(timeout=0.2)
        except queue.Empty:
            continue
        if isinstance(msg, QubeStatus):
            if msg.request_id == request and not acknowledged:
                acknowledged = True
            if msg.request_id == request and msg.state in ("identifying", "calibrating", "self_test", "fault"):
                progress(f"rig {rig_id}: {msg.state}" + (f": {msg.detail}" if msg.detail else ""))
            continue
        if msg.request_id == request:
            return unpack(msg)
    raise TimeoutError(f"rig {rig_id} sent no recording within {timeout_s:g} s (is its bridge or qube_sim running, "
                       "with FEDRL_RIG_ID as given?)")


@returns_code
def main(argv: list[str] | None = None) -> int:
    s = IdentifySettings.load(argv, prog="python -m worker.identify", description=__doc__.splitlines()[0])
    setup_logging(s.log_level, f"identify[{s.rig_id}]")
    from services.qube_sim.identify import identify_to_file
    from services.qube_sim.profile import load_profile

    conn = s.connector()(f"identify-{s.rig_id}")

    def record(attempt: int) -> Recording:
        """One recording of the rig (the connection stays up while the host fits: a refusal asks again)."""
        print(f"rig {s.rig_id}: identification requested over {s.address()}"
              + (f" (attempt {attempt + 1} of {s.identify_attempts})" if attempt else ""), flush=True)
        try:
            recording = request_recording(conn, s.rig_id, s.identify_timeout, attempt=attempt)
        except (TimeoutError, ConnectionError) as err:
            raise IdentifyFailed(str(err)) from None
        if s.recording_out is not None:
            recording.save(s.recording_out)
        print(f"rig {s.rig_id}: {recording.rig_seconds:.0f} s recorded; fitting", flush=True)
        return recording

    try:
        conn.start(timeout=30.0)
    except ConnectionError as err:
        print(f"python -m worker.identify: {err}", file=sys.stderr)
        return 1
    try:
        return identify_to_file(record, load_profile(s.base), s.out, f"rig {s.rig_id} over MQTT",
                                "python -m worker.identify", s.identify_attempts)
    finally:
        conn.stop()


if __name__ == "__main__":
    sys.exit(main())
