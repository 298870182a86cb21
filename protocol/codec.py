"""msgpack codec for the pydantic messages, with validation that turns any bad payload into a DecodeError.

Decoding is strict: no coercion ("100" is not a number, ``true`` not an integer, 1.0 not a schema version), msgpack
arrays stay tuples, tensors must be finite (protocol/tensors.py), a message must be of a kind its topic carries and
its worker or rig id must be the one its topic names (protocol/routes.py). Every check of a message on its own is
here, so the services only ever see valid messages."""

from __future__ import annotations

import logging
import threading
from collections import Counter
from typing import TypeVar, overload

import msgpack
from pydantic import ValidationError

from protocol.messages import MESSAGE_TYPES, SCHEMA_VERSION, Message
from protocol.routes import route_of

#: Default cap on one payload. A 3x128 actor's gradient is ~140 KB; a QUBE state ~100 B.
MAX_PAYLOAD_BYTES = 4 * 1024 * 1024

M = TypeVar("M", bound=Message)
A = TypeVar("A", bound=Message)
B = TypeVar("B", bound=Message)
C = TypeVar("C", bound=Message)
D = TypeVar("D", bound=Message)
E = TypeVar("E", bound=Message)
F = TypeVar("F", bound=Message)


class DecodeError(ValueError):
    """A payload that is not a valid message; ``reason`` is a short category for counters."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


def encode(message: Message) -> bytes:
    """Message -> msgpack bytes (tensors stay raw bytes)."""
    return msgpack.packb(message.model_dump(mode="python"), use_bin_type=True)


@overload
def decode(payload: bytes, *, max_bytes: int = ..., topic: str | None = ...) -> Message: ...
@overload
def decode(payload: bytes, a: type[A], /, *, max_bytes: int = ..., topic: str | None = ...) -> A: ...
@overload
def decode(payload: bytes, a: type[A], b: type[B], /, *, max_bytes: int = ..., topic: str | None = ...) -> A | B: ...
@overload
def decode(payload: bytes, a: type[A], b: type[B], c: type[C], /, *, max_bytes: int = ...,
           topic: str | None = ...) -> A | B | C: ...
@overload
def decode(payload: bytes, a: type[A], b: type[B], c: type[C], d: type[D], /, *, max_bytes: int = ...,
           topic: str | None = ...) -> A | B | C | D: ...
@overload
def decode(payload: bytes, a: type[A], b: type[B], c: type[C], d: type[D], e: type[E], /, *, max_bytes: int = ...,
           topic: str | None = ...) -> A | B | C | D | E: ...
@overload
def decode(payload: bytes, a: type[A], b: type[B], c: type[C], d: type[D], e: type[E], f: type[F], /, *,
           max_bytes: int = ..., topic: str | None = ...) -> A | B | C | D | E | F: ...
def decode(payload: bytes, *expected: type[Message], max_bytes: int = MAX_PAYLOAD_BYTES,
           topic: str | None = None) -> Message:
    """msgpack bytes -> validated message of one of the ``expected`` types (any type when none given).

    With ``topic``, the message must also be of a kind that topic carries (``wrong_topic`` otherwise), and the
    worker or rig id it carries must be the one the topic names (``spoofed`` otherwise).
    """
    if len(payload) > max_bytes:
        raise DecodeError("oversized", f"{len(payload)} bytes exceeds the limit of {max_bytes}")
    try:
        obj = msgpack.unpackb(payload, raw=False, strict_map_key=True, use_list=False, max_bin_len=max_bytes)
    except Exception as exc:  # msgpack raises several unrelated types on garbage
        raise DecodeError("malformed", f"not msgpack ({type(exc).__name__}: {exc})") from None
    if not isinstance(obj, dict):
        raise DecodeError("malformed", f"expected a map, got {type(obj).__name__}")
    version = obj.get("schema_version")
    if type(version) is not int or version != SCHEMA_VERSION:
        raise DecodeError("version", f"schema version {version!r} not supported (this build speaks the integer "
                          f"{SCHEMA_VERSION})")
    kind = obj.get("kind")
    cls = MESSAGE_TYPES.get(kind) if isinstance(kind, str) else None
    if cls is None:
        raise DecodeError("unknown_kind", f"unknown message kind {kind!r}")
    if expected and cls not in expected:
        names = ", ".join(t.model_fields["kind"].default for t in expected)
        raise DecodeError("unexpected_kind", f"got {kind!r}, expected one of: {names}")
    route = None
    if topic is not None:
        route = route_of(topic)
        if route is None or kind not in route.kinds:
            carries = ", ".join(sorted(route.kinds)) if route else "nothing (not a topic of the contract)"
            raise DecodeError("wrong_topic", f"a {kind!r} message on {topic}, which carries {carries}")
    try:
        message = cls.model_validate(obj, strict=True)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first.get("loc", ()))
        raise DecodeError("invalid", f"{kind}: {where}: {first.get('msg')} ({exc.error_count()} error(s))") from None
    if route is not None and topic is not None:
        for field, named in route.named(topic).items():
            claimed = getattr(message, field, named)
            if claimed != named:
                who = field.removesuffix("_id")
                raise DecodeError("spoofed", f"payload says {who} {claimed!r}, topic says {named!r}")
    return message


class RejectCounter:
    """Counts rejected messages by reason and logs each one; thread-safe."""

    def __init__(self, logger: logging.Logger) -> None:
        self._logger = logger
        self._lock = threading.Lock()
        self._counts: Counter[str] = Counter()

    def reject(self, topic: str, reason: str, detail: str) -> None:
        with self._lock:
            self._counts[reason] += 1
            total = sum(self._counts.values())
        self._logger.warning("rejected message on %s (%s): %s [rejects so far: %d]", topic, reason, detail, total)

    def reject_error(self, topic: str, error: DecodeError) -> None:
        self.reject(topic, error.reason, error.detail)

    def restore(self, counts: dict[str, int]) -> None:
        """Carry on from saved counts (a resumed chief)."""
        with self._lock:
            self._counts.update(counts)

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self._counts.values())

    def as_dict(self) -> dict[str, int]:
        with self._lock:
            return dict(self._counts)
