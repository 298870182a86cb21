"""The embedded broker's topic check: no NUL in any topic or filter, no wildcard in a published topic.

MQTT 3.1.1 forbids both ([MQTT-1.5.3-2], [MQTT-3.3.2-2]); Mosquitto refuses them itself, amqtt did not refuse NUL.
Loaded by amqtt from its dotted path (services/broker/embedded.py ``broker_config``): a refused PUBLISH is dropped
(delivered to no one), a refused SUBSCRIBE filter gets the failure return code, and each refusal logs one line.

amqtt 0.12 refuses a wildcard PUBLISH while parsing it, but then reads on from the middle of that packet, taking its
payload for further packets; :func:`install_wildcard_close` makes that refusal close the connection instead.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

from amqtt.contexts import Action
from amqtt.errors import MQTTError
from amqtt.plugins.base import BaseTopicPlugin
from amqtt.session import Session

log = logging.getLogger(__name__)


def topic_fault(topic: str | None, publish: bool) -> str | None:
    """Why a topic (``publish``) or a topic filter may not be used, or None when it may."""
    if not topic:
        return "empty topic"
    if "\x00" in topic:
        return "NUL character in topic"
    if publish and ("+" in topic or "#" in topic):
        return "wildcard in a published topic"
    return None


class TopicGuardPlugin(BaseTopicPlugin):
    """Refuses what :func:`topic_fault` names; lets every other topic through to the other plugins (the ACL)."""

    @dataclass
    class Config:
        """No options."""

    async def topic_filtering(self, *, session: Session | None = None, topic: str | None = None,
                              action: Action | None = None) -> bool:
        if action == Action.RECEIVE:
            return True  # only topics that passed on the way in are delivered
        fault = topic_fault(topic, publish=action == Action.PUBLISH)
        if fault is None:
            return True
        client = session.client_id if session is not None else "?"
        log.warning("refused %s of %r by client %r: %s", action, topic, client, fault)
        return False


class WildcardPublish(Exception):
    """A PUBLISH named a wildcard topic: its connection is closed (amqtt logs this exception in one line)."""


def install_wildcard_close() -> None:
    """Make amqtt close a connection whose PUBLISH topic has a wildcard, rather than parse on inside that packet."""
    from amqtt.mqtt.publish import PublishVariableHeader

    original = PublishVariableHeader.from_stream.__func__
    if getattr(original, "_fedrl_guard", False):
        return

    async def from_stream(cls: type, reader: Any, fixed_header: Any) -> Any:
        try:
            return await original(cls, reader, fixed_header)
        except MQTTError as e:
            raise WildcardPublish(f"closing a connection: {e}") from e

    from_stream._fedrl_guard = True  # type: ignore[attr-defined]
    PublishVariableHeader.from_stream = classmethod(from_stream)
