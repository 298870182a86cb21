"""Messages their receivers can verify on any broker: an HMAC-SHA256 under a key derived from the run's key.

The tag of a message is HMAC-SHA256(key, canonical(message)), hex, where ``canonical`` is the msgpack encoding of the
message's fields without ``tag``, every map's keys sorted. The launcher (deploy/run_local.py) makes one run key
(``FEDRL_RUN_KEY``) per run and hands it to the chief, its edges and the dashboard; the other keys are derived from it
(each the hex HMAC-SHA256 of a purpose under the run key, so none reveals the run key or another):

- the **chief key** ``chief_key(K)`` tags what the chief (or an edge) says to the workers: RunStart, RunStop,
  aggregates, transfers, acknowledgements. Every worker holds it to check them (``FEDRL_CHIEF_KEY``);
- a **worker key** ``worker_key(K, id)`` tags everything worker ``id`` sends: hello, status (its last will too),
  update, mature actor. Only that worker holds it (``FEDRL_WORKER_KEY``); the chief and the edges derive it from K;
- the run key itself tags what only chiefs read: an edge's partial, a chief's claim of the run.

So a worker cannot speak for another worker, an edge or a claiming chief. HMAC keys are symmetric: whoever checks a
tag can make one, so a worker (it holds the chief key) can speak for the chief to the other workers; signatures
(a public key) would close that, at the price of a dependency. Whoever holds the run key can speak for everyone.
Without a key senders send empty tags and receivers check nothing: on an anonymous broker any publisher is then
trusted. A receiver with a key refuses (and counts) an untagged message (``unsigned``) and one whose tag is not the
message's (``forged``): a forger without the key cannot make one, and a changed field breaks the tag. A tag does not
make a message fresh: a replayed message keeps its valid tag, and the round and session checks refuse it.
"""

from __future__ import annotations

import hashlib
import hmac
from typing import Any, Final, TypeVar

import msgpack

from protocol.codec import DecodeError, RejectCounter, decode
from protocol.messages import Message

#: The field that carries the authenticator (left out of what it authenticates).
TAG_FIELD: Final = "tag"
#: The shortest key accepted (characters): a guessable key is no key.
MIN_KEY_LENGTH: Final = 16
#: What the derived keys are derived for (the message HMAC'd under the run key; a worker's id follows its prefix).
CHIEF_PURPOSE: Final = "chief"
WORKER_PURPOSE: Final = "worker:"

M = TypeVar("M", bound=Message)


def _sorted(value: Any) -> Any:
    """Maps with their keys sorted, at every depth; sequences as lists."""
    if isinstance(value, dict):
        return {k: _sorted(value[k]) for k in sorted(value)}
    if isinstance(value, (list, tuple)):
        return [_sorted(v) for v in value]
    return value


def canonical(message: Message) -> bytes:
    """The bytes a tag authenticates: the message without its tag, as msgpack with sorted keys."""
    return msgpack.packb(_sorted(message.model_dump(mode="python", exclude={TAG_FIELD})), use_bin_type=True)


def key_bytes(key: str) -> bytes:
    """A run key as the HMAC takes it (its UTF-8 bytes); a ValueError for one shorter than MIN_KEY_LENGTH."""
    if len(key) < MIN_KEY_LENGTH:
        raise ValueError(f"a run key must be at least {MIN_KEY_LENGTH} characters")
    return key.encode()


def derived_key(run_key: bytes, purpose: str) -> str:
    """The key for ``purpose`` derived from the run key: HMAC-SHA256(run key, purpose), hex (64 characters)."""
    return hmac.new(run_key, purpose.encode(), hashlib.sha256).hexdigest()


def chief_key(run_key: bytes) -> str:
    """The key of what the chief (or an edge) says to the workers, which every worker holds to check it."""
    return derived_key(run_key, CHIEF_PURPOSE)


def chief_key_of(run_key: bytes | None) -> bytes | None:
    """The chief key as the HMAC takes it, for whoever holds the run key (None: the run has no key)."""
    return None if run_key is None else chief_key(run_key).encode()


def worker_key(run_key: bytes, worker_id: str) -> str:
    """Worker ``worker_id``'s own key: it tags what that worker sends, and only that worker holds it."""
    return derived_key(run_key, WORKER_PURPOSE + worker_id)


class WorkerKeys:
    """A chief's (or an edge's) keys of the workers, derived from the run key once per worker id."""

    def __init__(self, run_key: bytes | None) -> None:
        self.run_key = run_key
        self._keys: dict[str, bytes] = {}

    def of(self, worker_id: str) -> bytes | None:
        """The key worker ``worker_id``'s messages must be tagged with (None: the run has no key)."""
        if self.run_key is None:
            return None
        key = self._keys.get(worker_id)
        if key is None:
            key = self._keys[worker_id] = worker_key(self.run_key, worker_id).encode()
        return key

    def refusal(self, message: Message) -> tuple[str, str] | None:
        """Why a worker's message (any with a ``worker_id``) is not its worker's, as :func:`refusal`."""
        return refusal(message, self.of(str(getattr(message, "worker_id", ""))), whose="its worker's key")


def tag_of(message: Message, key: bytes) -> str:
    """HMAC-SHA256 of the message's canonical encoding under ``key``, hex."""
    return hmac.new(key, canonical(message), hashlib.sha256).hexdigest()


def signed(message: M, key: bytes | None) -> M:
    """The message with its tag (unchanged without a key)."""
    if key is None:
        return message
    return message.model_copy(update={TAG_FIELD: tag_of(message, key)})


def admitted(payload: bytes, *types: type[Message], topic: str, key: bytes | None,
             rejects: RejectCounter) -> Message | None:
    """``payload`` decoded as one of ``types`` (protocol/codec.py) and checked against ``key``: the message, or
    None when it is malformed, forged or unsigned, which ``rejects`` counts and logs."""
    try:
        msg = decode(payload, *types, topic=topic)
    except DecodeError as err:
        rejects.reject_error(topic, err)
        return None
    refused = refusal(msg, key)
    if refused is not None:
        rejects.reject(topic, *refused)
        return None
    return msg


def refusal(message: Message, key: bytes | None, whose: str = "the sender's key") -> tuple[str, str] | None:
    """Why a message is not the keyholder's: (reason, detail), or None when it is, or when there is no key to check
    it with (without a key every message is trusted). ``whose`` names the key in the detail."""
    if key is None:
        return None
    tag, kind = getattr(message, TAG_FIELD, ""), type(message).model_fields["kind"].default
    if not tag:
        return "unsigned", f"a {kind} without a tag, and this run has a key"
    if not hmac.compare_digest(tag, tag_of(message, key)):
        return "forged", f"a {kind} whose tag is not its HMAC under {whose}"
    return None
