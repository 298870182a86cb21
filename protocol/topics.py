"""Every MQTT topic name, in one place.

Federation topics live under ``fedrl/<run>/``; rig topics under ``qube/<rig>/``:

| topic | publisher | payload |
| --- | --- | --- |
| ``fedrl/<run>/worker/<id>/hello`` | worker | WorkerHello |
| ``fedrl/<run>/worker/<id>/status`` | worker (last will: offline) | WorkerStatus |
| ``fedrl/<run>/worker/<id>/update`` | worker | WorkerUpdate or MatureParams |
| ``fedrl/<run>/chief/start`` | chief | RunStart |
| ``fedrl/<run>/chief/aggregate`` | chief | ChiefAggregate |
| ``fedrl/<run>/chief/transfer`` | chief | ChiefTransfer |
| ``fedrl/<run>/chief/ack`` | chief | ChiefAck |
| ``fedrl/<run>/chief/stop`` | chief | RunStop |
| ``qube/<rig>/state`` | bridge / qube-sim | QubeState |
| ``qube/<rig>/action`` | worker | QubeAction |
| ``qube/<rig>/reset`` | worker | QubeReset |
| ``qube/<rig>/status`` | bridge / qube-sim (last will: offline) | QubeStatus |
| ``qube/<rig>/telemetry`` | bridge / qube-sim | QubeTelemetry |
"""

from __future__ import annotations

import re

FEDRL = "fedrl"
QUBE = "qube"
_ID = re.compile(r"^[A-Za-z0-9_.:-]{1,64}$")


def check_id(value: str, what: str = "id") -> str:
    """Ids become topic levels: reject empty ones, wildcards and separators."""
    if not _ID.match(value):
        raise ValueError(f"{what} {value!r} must be 1-64 characters of letters, digits, '_', '.', ':' or '-'")
    return value


def worker(run: str, worker_id: str, leaf: str) -> str:
    return f"{FEDRL}/{check_id(run, 'run id')}/worker/{check_id(worker_id, 'worker id')}/{leaf}"


def all_workers(run: str, leaf: str) -> str:
    """Subscription filter for one leaf of every worker."""
    return f"{FEDRL}/{check_id(run, 'run id')}/worker/+/{leaf}"


def worker_id_of(topic: str) -> str:
    """The worker id level of a ``fedrl/<run>/worker/<id>/<leaf>`` topic."""
    parts = topic.split("/")
    if len(parts) != 5 or parts[2] != "worker":
        raise ValueError(f"not a worker topic: {topic!r}")
    return parts[3]


def chief(run: str, leaf: str) -> str:
    return f"{FEDRL}/{check_id(run, 'run id')}/chief/{leaf}"


def rig(rig_id: str, leaf: str) -> str:
    return f"{QUBE}/{check_id(rig_id, 'rig id')}/{leaf}"


HELLO, STATUS, UPDATE = "hello", "status", "update"
START, AGGREGATE, TRANSFER, ACK, STOP = "start", "aggregate", "transfer", "ack", "stop"
STATE, ACTION, RESET, TELEMETRY = "state", "action", "reset", "telemetry"
