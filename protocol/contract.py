"""The wire contract, generated from the code: every topic (publisher, payload, QoS, retain) and every message's
fields with their types and constraints, read off the pydantic models.

``python -m protocol.contract --markdown`` prints it; ``docs/wire-contract.md`` is that output, kept in the repository
(a test checks it is up to date: ``python -m protocol.contract --write`` refreshes it).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from protocol import topics
from protocol.codec import MAX_PAYLOAD_BYTES
from protocol.messages import MESSAGE_TYPES, Message, Receipt
from protocol.tensors import ALLOWED_DTYPES, MAX_ELEMENTS, MAX_NDIM, TensorBlob

DOC = Path(__file__).resolve().parents[1] / "docs" / "wire-contract.md"


@dataclass(frozen=True)
class Route:
    """One topic: who publishes what on it, and how."""

    topic: str
    publisher: str
    payloads: tuple[type[Message], ...]
    qos: int
    note: str = ""
    retain: bool = False


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
          "one per episode; MatureParams is sent again until a ChiefAck for its episode arrives"),
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


def _type_name(schema: dict[str, Any], defs: dict[str, Any]) -> str:
    """A short type name from a JSON-schema fragment."""
    if "$ref" in schema:
        name = schema["$ref"].rsplit("/", 1)[-1]
        return name
    if "anyOf" in schema:
        return " or ".join(_type_name(s, defs) for s in schema["anyOf"])
    if "const" in schema:
        return repr(schema["const"])
    if "enum" in schema:
        return " / ".join(repr(v) for v in schema["enum"])
    kind = schema.get("type")
    if kind == "array":
        inner = schema.get("items") or schema.get("prefixItems", [{}])[0]
        return f"list of {_type_name(inner, defs)}"
    if kind == "object":
        extra = schema.get("additionalProperties")
        return f"map of str to {_type_name(extra, defs)}" if isinstance(extra, dict) else "map"
    if kind == "string" and schema.get("format") == "binary":
        return "bytes"
    return str(kind or "any")


def _constraints(schema: dict[str, Any]) -> str:
    parts = []
    for key, text in (("minimum", ">= {}"), ("maximum", "<= {}"), ("exclusiveMinimum", "> {}"),
                      ("minLength", "length >= {}"), ("maxLength", "length <= {}"), ("minItems", ">= {} items"),
                      ("maxItems", "<= {} items"), ("pattern", "matches `{}`")):
        if key in schema:
            parts.append(text.format(schema[key]))
    for option in schema.get("anyOf", []):
        inner = _constraints(option)
        if inner:
            parts.append(inner)
    return ", ".join(parts)


def fields_table(model: type[BaseModel]) -> list[str]:
    """Markdown rows: field, type, required/default, constraints."""
    schema = model.model_json_schema(mode="serialization")
    defs = schema.get("$defs", {})
    required = set(schema.get("required", []))
    rows = ["| field | type | required | constraints |", "| --- | --- | --- | --- |"]
    for name, prop in schema["properties"].items():
        default = "yes" if name in required else f"no (default `{prop.get('default')!r}`)"
        rows.append(f"| `{name}` | {_type_name(prop, defs)} | {default} | {_constraints(prop)} |")
    return rows


def markdown() -> str:
    """The whole contract as markdown."""
    out = [
        "# Wire contract",
        "",
        "Generated by `python -m protocol.contract --write` from the pydantic models in `protocol/`; do not edit.",
        "",
        "MQTT 3.1.1. Every payload is the msgpack map of one message (below), with `schema_version` = 1 and its",
        f"`kind`; unknown fields are errors and floats must be finite. Payloads over {MAX_PAYLOAD_BYTES:,} bytes are "
        "refused.",
        "Nothing is retained. Topic levels `<run>`, `<id>` and `<rig>` are 1-64 of `A-Z a-z 0-9 _ . : -`.",
        "",
        "## Topics",
        "",
        "| topic | publisher | payload | QoS | retain | note |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for r in ROUTES:
        payloads = " or ".join(f"[{p.__name__}](#{p.__name__.lower()})" for p in r.payloads)
        out.append(f"| `{r.topic}` | {r.publisher} | {payloads} | {r.qos} | {'yes' if r.retain else 'no'} | "
                   f"{r.note} |")
    out += [
        "",
        "## Tensors",
        "",
        "A `TensorDict` maps a tensor's name (an actor's `state_dict` key, e.g. `net.0.weight`) to a TensorBlob:",
        "",
        *fields_table(TensorBlob),
        "",
        f"`dtype` is one of {', '.join(f'`{d}`' for d in sorted(ALLOWED_DTYPES))} (numpy spelling, little-endian); "
        "`data` is the C-order raw bytes, exactly `prod(shape) * itemsize` of them; at most "
        f"{MAX_NDIM} dimensions and {MAX_ELEMENTS:,} elements; floating values must be finite. Actors and gradients "
        "travel as `<f4`. `digest` (protocol/tensors.py) is the first 16 hex digits of the SHA-256 over each "
        "tensor's `name|dtype|shape|` and bytes, in sorted name order; receipts carry it.",
        "",
        "## Messages",
    ]
    for kind, model in MESSAGE_TYPES.items():
        doc = " ".join((model.__doc__ or "").split())
        out += ["", f"### {model.__name__}", "", f"`kind` = `{kind!r}`. {doc}", "", *fields_table(model)]
    out += ["", "### Receipt", "", " ".join((Receipt.__doc__ or "").split()), "", *fields_table(Receipt), ""]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m protocol.contract", description=__doc__.splitlines()[0])
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--markdown", action="store_true", help="print the contract (the default)")
    group.add_argument("--write", action="store_true", help=f"write it to {DOC.relative_to(DOC.parents[1])}")
    args = parser.parse_args(argv)
    text = markdown()
    if args.write:
        DOC.parent.mkdir(parents=True, exist_ok=True)
        DOC.write_text(text, encoding="utf-8")
        print(f"wrote {DOC}")
    else:
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
