"""Chief messages workers can verify on any broker: an HMAC-SHA256 under the run's key (``FEDRL_RUN_KEY``).

The tag of a message is HMAC-SHA256(key, canonical(message)), hex, where ``canonical`` is the msgpack encoding of the
message's fields without ``tag``, every map's keys sorted. The launcher (deploy/run_local.py) makes one key per run
and hands it to the chief and the workers; whoever knows it can speak for the chief, so it is a secret like the MQTT
password. Without a key the chief sends empty tags and workers check nothing: on an anonymous broker any publisher is
then trusted. A worker with a key refuses (and counts) an untagged message (``unsigned``) and one whose tag is not
the message's (``forged``): a forger without the key cannot make one, and a changed field breaks the tag. A tag does
not make a message fresh: a replayed message keeps its valid tag, and the workers' round and session checks refuse it.
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
    """``payload`` decoded as one of ``types`` (protocol/codec.py) and checked against the run's key: the message, or
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


def refusal(message: Message, key: bytes | None) -> tuple[str, str] | None:
    """Why a message is not the keyholder's: (reason, detail), or None when it is, or when there is no key to check
    it with (without a key every message is trusted)."""
    if key is None:
        return None
    tag, kind = getattr(message, TAG_FIELD, ""), type(message).model_fields["kind"].default
    if not tag:
        return "unsigned", f"a {kind} without a tag, and this run has a key"
    if not hmac.compare_digest(tag, tag_of(message, key)):
        return "forged", f"a {kind} whose tag is not its HMAC under the run's key"
    return None
