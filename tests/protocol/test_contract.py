"""The generated wire contract: docs/asyncapi.yaml is current and a well-formed AsyncAPI 3.0 document that has every
route of protocol/routes.py (publisher, subscribers, QoS, retain) and every message model; and the QoS the services use
come from that routes table."""

from __future__ import annotations

import re
from collections.abc import Iterator
from typing import Any

import pytest
import yaml
from paho.mqtt.client import topic_matches_sub

from protocol import asyncapi, contract
from protocol.messages import MESSAGE_TYPES, Played
from protocol.routes import DASHBOARD, PROCESSES, ROUTES, Route, qos_of, route_of
from protocol.tensors import ALLOWED_DTYPES

#: The top-level fields an AsyncAPI 3.0 document may have.
TOP_LEVEL = {"asyncapi", "id", "info", "servers", "defaultContentType", "channels", "operations", "components"}


@pytest.fixture(scope="module")
def doc() -> dict[str, Any]:
    return yaml.safe_load(asyncapi.DOC.read_text(encoding="utf-8"))


def resolve(doc: dict[str, Any], ref: str) -> Any:
    """The node a local ``$ref`` (a JSON pointer) points at; fails the test when there is none."""
    assert ref.startswith("#/"), f"{ref} is not a reference inside the document"
    node: Any = doc
    for part in ref[2:].split("/"):
        part = part.replace("~1", "/").replace("~0", "~")
        assert isinstance(node, dict) and part in node, f"{ref} does not resolve"
        node = node[part]
    return node


def refs(node: Any) -> Iterator[str]:
    """Every ``$ref`` below a node."""
    if isinstance(node, dict):
        if "$ref" in node:
            yield node["$ref"]
        for value in node.values():
            yield from refs(value)
    elif isinstance(node, list):
        for value in node:
            yield from refs(value)


def concrete(route: Route) -> str:
    """An instance of the route's topic."""
    return route.filter(**{name: f"{name}1" for name in route.parameters})


def test_the_asyncapi_document_is_up_to_date() -> None:
    assert asyncapi.DOC.read_text(encoding="utf-8") == asyncapi.render(), (
        "docs/asyncapi.yaml is out of date: python -m protocol.asyncapi --write")


def test_it_is_a_well_formed_asyncapi_3_document(doc: dict[str, Any]) -> None:
    assert doc["asyncapi"] == "3.0.0"
    assert set(doc) <= TOP_LEVEL
    assert isinstance(doc["info"]["title"], str) and isinstance(doc["info"]["version"], str)
    for server in doc["servers"].values():
        assert server["host"] and server["protocol"] in ("mqtt", "secure-mqtt")
    for cid, channel in doc["channels"].items():
        assert re.fullmatch(r"[\w.-]+", cid)
        assert set(re.findall(r"\{(\w+)\}", channel["address"])) == set(channel.get("parameters", {})), cid
        assert channel["messages"], cid
    for oid, op in doc["operations"].items():
        assert re.fullmatch(r"[\w.-]+", oid)
        assert op["action"] in ("send", "receive"), oid
        channel = op["channel"]["$ref"]
        assert all(m["$ref"].startswith(f"{channel}/messages/") for m in op["messages"]), oid
    for message in doc["components"]["messages"].values():
        assert "payload" in message
    found = list(refs(doc))
    assert len(found) > 100
    for ref in found:
        resolve(doc, ref)


def test_every_route_is_a_channel_with_its_publisher_subscribers_and_qos(doc: dict[str, Any]) -> None:
    channels = {channel["address"]: cid for cid, channel in doc["channels"].items()}
    assert len(channels) == len(doc["channels"]) == len(ROUTES)
    for route in ROUTES:
        cid = channels[re.sub(r"<(\w+)>", r"{\1}", route.topic)]
        kinds = {resolve(doc, resolve(doc, m["$ref"])["payload"]["$ref"])["properties"]["kind"]["const"]
                 for m in doc["channels"][cid]["messages"].values()}
        assert kinds == {*route.kinds, "chunk"}, route.topic
        ops = [op for op in doc["operations"].values() if op["channel"]["$ref"] == f"#/channels/{cid}"]
        by_action: dict[str, list[str]] = {"send": [], "receive": []}
        for op in ops:
            [tag] = op["tags"]
            by_action[op["action"]].append(resolve(doc, tag["$ref"])["name"])
            assert op["bindings"]["mqtt"]["qos"] == route.qos, route.topic
            if op["action"] == "send":
                assert op["bindings"]["mqtt"]["retain"] is route.retain
        assert by_action == {"send": [route.publisher], "receive": list(route.subscribers)}, route.topic
    processes = {resolve(doc, op["tags"][0]["$ref"])["name"] for op in doc["operations"].values()}
    assert processes == set(PROCESSES)


def test_every_message_model_appears_with_its_fields(doc: dict[str, Any]) -> None:
    schemas = doc["components"]["schemas"]
    assert Played in contract.MODELS
    for model in contract.MODELS:
        assert set(schemas[model.__name__]["properties"]) == set(model.model_fields), model.__name__
    assert set(doc["components"]["messages"]) == {m.__name__ for m in MESSAGE_TYPES.values()}
    for kind, model in MESSAGE_TYPES.items():
        message = doc["components"]["messages"][model.__name__]
        assert message["contentType"] == "application/msgpack"
        assert resolve(doc, message["payload"]["$ref"])["properties"]["kind"]["const"] == kind
    blob = schemas["TensorBlob"]["properties"]
    assert blob["dtype"]["enum"] == sorted(ALLOWED_DTYPES) and blob["data"]["format"] == "binary"


def test_qos_comes_from_the_routes_table() -> None:
    for route in ROUTES:
        assert route_of(concrete(route)) is route
        assert qos_of(concrete(route)) == route.qos
    assert qos_of("fedrl/r1/#") == 1 and qos_of("qube/+/telemetry") == 0 and qos_of("qube/+/#") == 1
    with pytest.raises(ValueError, match="no topic of the contract"):
        qos_of("fedrl/r1/other")
    with pytest.raises(ValueError, match="no level"):
        ROUTES[0].filter(rig="g")


def test_the_dashboard_subscribes_to_the_routes_that_name_it() -> None:
    from services.dashboard.feed import subscriptions

    for rigs in (None, ["rig1"]):
        subs = subscriptions("run1", rigs)
        for route in ROUTES:
            matching = [qos for f, qos in subs if topic_matches_sub(f, concrete(route))]
            assert bool(matching) == (DASHBOARD in route.subscribers), route.topic
            assert all(qos == route.qos for qos in matching), route.topic
