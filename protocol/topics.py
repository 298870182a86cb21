"""Every MQTT topic name, in one place.

Federation topics live under ``fedrl/<run>/``; rig topics under ``qube/<rig>/``. Which messages travel on which topic,
who publishes and who subscribes, and with which QoS is protocol/routes.py (docs/wire-contract.md, docs/asyncapi.yaml).
"""

from __future__ import annotations

import re

FEDRL = "fedrl"
QUBE = "qube"
#: What a run, worker or rig id (a topic level) may be.
ID_PATTERN = r"^[A-Za-z0-9_.:-]{1,64}$"
_ID = re.compile(ID_PATTERN)


def check_id(value: str, what: str = "id") -> str:
    """Ids become topic levels: reject empty ones, wildcards and separators."""
    if not _ID.match(value):
        raise ValueError(f"{what} {value!r} must be 1-64 characters of letters, digits, '_', '.', ':' or '-'")
    return value


def worker(run: str, worker_id: str, leaf: str) -> str:
    return f"{FEDRL}/{check_id(run, 'run id')}/worker/{check_id(worker_id, 'worker id')}/{leaf}"


def chief(run: str, leaf: str) -> str:
    return f"{FEDRL}/{check_id(run, 'run id')}/{CHIEF}/{leaf}"


def edge(run: str, edge_id: str, leaf: str) -> str:
    """An edge chief's topics: its partials for the root, and the root's answers it passes on to its workers."""
    return f"{FEDRL}/{check_id(run, 'run id')}/edge/{check_id(edge_id, 'edge id')}/{leaf}"


def relayed(run: str, edge_id: str, leaf: str) -> str:
    """Where an edge chief passes the root chief's messages (``leaf``: start, aggregate...) on to its workers."""
    return edge(run, edge_id, f"{CHIEF}/{leaf}")


#: The edge id of the root chief itself, standing in for a dead edge whose site has no live edge left
#: (chief/failover.py): no edge chief or worker may take it. The workers it serves read the root's own topics.
ROOT_EDGE = "root"


def check_edge(value: str) -> str:
    """An edge id a worker or edge chief may be given: an id, and not ROOT_EDGE (the root's)."""
    if check_id(value, "edge id") == ROOT_EDGE:
        raise ValueError(f"edge id {ROOT_EDGE!r} is the root chief's own (it stands in for a dead edge): choose "
                         "another")
    return value


def answers(run: str, edge_id: str, leaf: str) -> str:
    """Where the workers an edge serves read the root chief's messages: the edge passes them on (``relayed``), or,
    when the root itself serves them (ROOT_EDGE), they read the root's own topics."""
    return chief(run, leaf) if edge_id == ROOT_EDGE else relayed(run, edge_id, leaf)


def claim(run: str) -> str:
    """The topic of the run's claim by its chief (retained)."""
    return f"{FEDRL}/{check_id(run, 'run id')}/{CLAIM}"


def rig(rig_id: str, leaf: str) -> str:
    return f"{QUBE}/{check_id(rig_id, 'rig id')}/{leaf}"


HELLO, STATUS, UPDATE = "hello", "status", "update"
CLAIM = "claim"
CHIEF = "chief"
START, AGGREGATE, TRANSFER, ACK, STOP = "start", "aggregate", "transfer", "ack", "stop"
PARTIAL = "partial"
STATE, ACTION, RESET, TELEMETRY = "state", "action", "reset", "telemetry"
IDENTIFY, RECORDING = "identify", "recording"
