"""Which messages travel on which topic, who publishes and who subscribes, with which QoS: the table the codec checks a
message's ``kind`` against (a message on the wrong topic is refused), the services read their QoS from (``qos_of``),
and docs/wire-contract.md and docs/asyncapi.yaml are generated from."""

from __future__ import annotations

from dataclasses import dataclass

from protocol import qube, topics
from protocol.messages import MESSAGE_TYPES, Message

CHIEF, EDGE, WORKER, BRIDGE, DASHBOARD = "chief", "edge", "worker", "rpi_bridge", "dashboard"
#: The processes on the wire, by the package each runs from.
PROCESSES: dict[str, str] = {
    CHIEF: "`python -m chief`: mediates the federation (Algorithm 1); in a tiered run the root, fed by the edges",
    WORKER: "`python -m worker`: learns on its own environment (Algorithm 2), drives a rig for the QUBE tasks",
    EDGE: "`python -m chief --role edge --edge-id <edge>`: closes its workers' part of each round and forwards one "
    "partial aggregate to the root chief, then passes the root's answers on to its workers (a tiered run)",
    BRIDGE: "`python -m rpi_bridge` on a rig's Raspberry Pi, or the simulated rig `python -m services.qube_sim` "
    "(the same BridgeService)",
    DASHBOARD: "`python -m services.dashboard`: the live web view; it only listens",
}
#: The topic levels a route's pattern leaves open (``<name>``), and what goes there.
PARAMETERS: dict[str, str] = {"run": "the run id", "id": "the worker id", "rig": "the rig id", "edge": "the edge id"}
#: The levels that name whom a message is from or for, and the payload field that must say the same (the codec
#: refuses a message whose field contradicts its topic: a worker speaking for another, a rig for another).
SENDER_FIELDS: dict[str, str] = {"id": "worker_id", "rig": "rig_id", "edge": "edge_id"}


@dataclass(frozen=True)
class Route:
    """One topic: who publishes what on it, and how, and who subscribes to it."""

    topic: str
    publisher: str
    subscribers: tuple[str, ...]
    payloads: tuple[type[Message], ...]
    qos: int
    note: str = ""
    retain: bool = False
    will: bool = False  # the publisher's MQTT last will is a message on this topic

    @property
    def kinds(self) -> frozenset[str]:
        return frozenset(p.model_fields["kind"].default for p in self.payloads)

    @property
    def remarks(self) -> str:
        """The note, and whether the publisher's last will comes here."""
        will = "the publisher's MQTT last will (`offline`) comes here too" if self.will else ""
        return "; ".join(text for text in (self.note, will) if text)

    @property
    def parameters(self) -> tuple[str, ...]:
        """The names of the pattern's open levels, in order (``run``, ``id``, ``rig``)."""
        return tuple(level[1:-1] for level in self.topic.split("/") if level.startswith("<"))

    def matches(self, topic: str) -> bool:
        """Whether a concrete topic is an instance of this route's pattern (``<...>`` is one level), or a
        subscription filter (``+``, ``#``) takes in messages of this route."""
        pattern, levels = self.topic.split("/"), topic.split("/")
        for i, level in enumerate(levels):
            if level == "#":
                return True
            if i >= len(pattern) or not (level == "+" or pattern[i].startswith("<") or pattern[i] == level):
                return False
        return len(levels) == len(pattern)

    def named(self, topic: str) -> dict[str, str]:
        """The payload fields a message on ``topic`` (an instance of this route) must have, by SENDER_FIELDS."""
        return {SENDER_FIELDS[level[1:-1]]: value for level, value in zip(self.topic.split("/"), topic.split("/"),
                                                                            strict=True)
                if level[1:-1] in SENDER_FIELDS}

    def filter(self, **levels: str) -> str:
        """This route's topic with the given levels filled in (checked ids) and the other open levels as ``+``."""
        unknown = set(levels) - set(self.parameters)
        if unknown:
            raise ValueError(f"{self.topic} has no level {sorted(unknown)}")
        out = []
        for level in self.topic.split("/"):
            name = level[1:-1] if level.startswith("<") else None
            out.append(level if name is None else topics.check_id(levels[name], PARAMETERS[name]) if name in levels
                       else "+")
        return "/".join(out)


def _w(leaf: str) -> str:
    return f"{topics.FEDRL}/<run>/worker/<id>/{leaf}"


def _c(leaf: str) -> str:
    return f"{topics.FEDRL}/<run>/chief/{leaf}"


def _e(leaf: str) -> str:
    return f"{topics.FEDRL}/<run>/edge/<edge>/{leaf}"


def _r(leaf: str) -> str:
    return f"{topics.QUBE}/<rig>/{leaf}"


#: A worker says hello until a RunStart names it: HELLO_FIRST_S after its first hello, each wait doubled up to
#: HELLO_MAX_S. Every chief and edge of the run gets every hello; at 1,024 workers saying hello every second, the
#: broker, the root and 16 edges fell behind (bench.scale: the edges' heartbeats queued behind the hellos, the root
#: took them for dead).
HELLO_FIRST_S, HELLO_MAX_S = 1.0, 4.0


def hello_wait(sent: int) -> float:
    """Seconds from a worker's ``sent``-th hello (1 for the first) to its next one."""
    return min(HELLO_MAX_S, HELLO_FIRST_S * 2.0 ** (sent - 1))


M = MESSAGE_TYPES
_FEDERATION = (CHIEF, EDGE, DASHBOARD)
_WORKERS = (WORKER, EDGE, DASHBOARD)
#: What an edge passes on from the root to its workers, verbatim (the root's tag stays valid).
_RELAYED = ((topics.START, "run_start"), (topics.AGGREGATE, "aggregate"), (topics.TRANSFER, "transfer"),
            (topics.ACK, "ack"), (topics.STOP, "run_stop"))
ROUTES: tuple[Route, ...] = (
    Route(_w(topics.HELLO), WORKER, _FEDERATION, (M["hello"],), 1,
          "1 s after the first, then doubling to every 4 s (hello_wait), until a RunStart names the worker"),
    Route(_w(topics.STATUS), WORKER, _FEDERATION, (M["status"],), 1, "every change of its state", will=True),
    Route(_w(topics.UPDATE), WORKER, _FEDERATION, (M["update"], M["mature"]), 1,
          "one per episode; sent again after a reconnect or a chief restart until answered; MatureParams until a "
          "ChiefAck for its episode arrives"),
    Route(_c(topics.START), CHIEF, _WORKERS, (M["run_start"],), 1,
          "again whenever a worker of the run says hello, an edge says it has none, or the edges change (a worker "
          "behind an edge reads it here too: it learns of a dead edge's stand-in while its edge says nothing)"),
    Route(_c(topics.AGGREGATE), CHIEF, _WORKERS, (M["aggregate"],), 1, "the answer to a round without a finisher"),
    Route(_c(topics.TRANSFER), CHIEF, _WORKERS, (M["transfer"],), 1,
          "the answer to a round in which a worker finished"),
    Route(_c(topics.ACK), CHIEF, _WORKERS, (M["ack"],), 1, "the answer to every MatureParams"),
    Route(_c(topics.STOP), CHIEF, _WORKERS, (M["run_stop"],), 1, "the run is over"),
    Route(_e(topics.PARTIAL), EDGE, (CHIEF, DASHBOARD), (M["partial"],), 1,
          "an edge's part of a round: its counted submissions as contributions (who, PI, return, their record's "
          "digest), a finisher's actor, one unnormalised Eq. 9 sum"),
    Route(_e(topics.STATUS), EDGE, (CHIEF,), (M["edge_status"],), 1,
          "every second while it runs (online); the root moves a dead edge's workers to another edge "
          "(chief/failover.py)", will=True),
    *(Route(_e(f"{topics.CHIEF}/{leaf}"), EDGE, (WORKER, DASHBOARD), (M[kind],), 1,
            f"the root chief's {kind} message on fedrl/<run>/chief/{leaf}, passed on verbatim to the edge's workers")
      for leaf, kind in _RELAYED),
    Route(f"{topics.FEDRL}/<run>/{topics.CLAIM}", CHIEF, (CHIEF, DASHBOARD), (M["claim"],), 1,
          "the one retained message: the chief that holds the run (so a second chief sees it and does not start); "
          "cleared by an empty retained message when the run ends", retain=True),
    Route(_r(topics.STATE), BRIDGE, (WORKER,), (M["qube_state"],), 0,
          f"every control tick ({qube.PERIOD_S * 1e3:g} ms)"),
    Route(_r(topics.ACTION), WORKER, (BRIDGE,), (M["qube_action"],), 0,
          "applied only within the deadline of its state"),
    Route(_r(topics.RESET), WORKER, (BRIDGE,), (M["qube_reset"],), 1, "start an episode: swing up and hold"),
    Route(_r(topics.IDENTIFY), WORKER, (BRIDGE,), (M["qube_identify"],), 1,
          "run the identification protocol (python -m worker.identify, deploy.lab)"),
    Route(_r(topics.RECORDING), BRIDGE, (WORKER,), (M["qube_recording"],), 1,
          "what the identification protocol recorded (gzip JSON), or why it has nothing"),
    Route(_r(topics.STATUS), BRIDGE, _WORKERS, (M["qube_status"],), 1, "every change of its state",
          will=True),
    Route(_r(topics.TELEMETRY), BRIDGE, (DASHBOARD,), (M["qube_telemetry"],), 0, "every second"),
)


def route_of(topic: str) -> Route | None:
    """The route a concrete topic belongs to (None: not a topic of the contract)."""
    return next((r for r in ROUTES if r.matches(topic)), None)


def route_for(publisher: str, kind: str) -> Route:
    """The route ``publisher`` sends messages of ``kind`` on (a KeyError for a kind it does not send)."""
    found = [r for r in ROUTES if r.publisher == publisher and kind in r.kinds]
    if not found:
        raise KeyError(f"the {publisher} sends no {kind!r} message")
    return found[0]


def chief_route(kind: str) -> Route:
    """The route the chief publishes messages of ``kind`` on (a KeyError for a kind it does not send)."""
    return route_for(CHIEF, kind)


def qos_of(topic_filter: str) -> int:
    """The QoS to publish on a topic, or to subscribe with to a filter: the highest of the routes it takes in."""
    matched = [r.qos for r in ROUTES if r.matches(topic_filter)]
    if not matched:
        raise ValueError(f"{topic_filter!r} is no topic of the contract (protocol/routes.py)")
    return max(matched)


def received_by(process: str) -> tuple[Route, ...]:
    """The routes a process subscribes to."""
    return tuple(r for r in ROUTES if process in r.subscribers)
