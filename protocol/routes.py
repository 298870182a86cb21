"""Which messages travel on which topic, with which QoS: the table the codec checks a message's ``kind`` against
(a message on the wrong topic is refused) and docs/wire-contract.md is generated from."""

from __future__ import annotations

from dataclasses import dataclass

from protocol import topics
from protocol.messages import MESSAGE_TYPES, Message


@dataclass(frozen=True)
class Route:
    """One topic: who publishes what on it, and how."""

    topic: str
    publisher: str
    payloads: tuple[type[Message], ...]
    qos: int
    note: str = ""
    retain: bool = False

    @property
    def kinds(self) -> frozenset[str]:
        return frozenset(p.model_fields["kind"].default for p in self.payloads)

    def matches(self, topic: str) -> bool:
        """Whether a concrete topic is an instance of this route's pattern (``<...>`` is one level)."""
        pattern, levels = self.topic.split("/"), topic.split("/")
        return len(pattern) == len(levels) and all(p.startswith("<") or p == x for p, x in zip(pattern, levels,
                                                                                                strict=True))


def _w(leaf: str) -> str:
    return f"{topics.FEDRL}/<run>/worker/<id>/{leaf}"


def _c(leaf: str) -> str:
    return f"{topics.FEDRL}/<run>/chief/{leaf}"


def _r(leaf: str) -> str:
    return f"{topics.QUBE}/<rig>/{leaf}"


M = MESSAGE_TYPES
ROUTES: tuple[Route, ...] = (
    Route(_w(topics.HELLO), "worker", (M["hello"],), 1, "every second until a RunStart names the worker"),
    Route(_w(topics.STATUS), "worker", (M["status"],), 1, "its MQTT last will is `offline`"),
    Route(_w(topics.UPDATE), "worker", (M["update"], M["mature"]), 1,
          "one per episode; sent again after a reconnect or a chief restart until answered; MatureParams until a "
          "ChiefAck for its episode arrives"),
    Route(_c(topics.START), "chief", (M["run_start"],), 1, "again whenever a worker of the run says hello"),
    Route(_c(topics.AGGREGATE), "chief", (M["aggregate"],), 1, "the answer to a round without a finisher"),
    Route(_c(topics.TRANSFER), "chief", (M["transfer"],), 1, "the answer to a round in which a worker finished"),
    Route(_c(topics.ACK), "chief", (M["ack"],), 1, "the answer to every MatureParams"),
    Route(_c(topics.STOP), "chief", (M["run_stop"],), 1, "the run is over"),
    Route(_r(topics.STATE), "bridge / qube-sim", (M["qube_state"],), 0, "every control tick (7 ms)"),
    Route(_r(topics.ACTION), "worker", (M["qube_action"],), 0, "applied only within the deadline of its state"),
    Route(_r(topics.RESET), "worker", (M["qube_reset"],), 1, "start an episode: swing up and hold"),
    Route(_r(topics.STATUS), "bridge / qube-sim", (M["qube_status"],), 1, "its MQTT last will is `offline`"),
    Route(_r(topics.TELEMETRY), "bridge / qube-sim", (M["qube_telemetry"],), 0, "every second"),
)


def route_of(topic: str) -> Route | None:
    """The route a concrete topic belongs to (None: not a topic of the contract)."""
    return next((r for r in ROUTES if r.matches(topic)), None)
