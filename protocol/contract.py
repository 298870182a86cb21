"""The wire contract, generated from the code: every topic (publisher, payload, QoS, retain) and every message's
fields with their types and constraints, read off the pydantic models.

``python -m protocol.contract`` prints it; ``docs/wire-contract.md`` is that output, kept in the repository
(a test checks it is up to date: ``python -m protocol.contract --write`` refreshes it).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pydantic import BaseModel
from pydantic.json_schema import DEFAULT_REF_TEMPLATE

from protocol.codec import MAX_PAYLOAD_BYTES
from protocol.messages import MESSAGE_TYPES, SCHEMA_VERSION, Played, Receipt
from protocol.routes import PROCESSES, ROUTES
from protocol.tensors import ALLOWED_DTYPES, MAX_ELEMENTS, MAX_NDIM, TensorBlob

DOC = Path(__file__).resolve().parents[1] / "docs" / "wire-contract.md"


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


#: The models messages are made of, besides tensors.
PARTS: tuple[type[BaseModel], ...] = (Receipt, Played)
#: Every model a payload is made of: the messages (Chunk last: it is transport), then their parts.
MODELS: tuple[type[BaseModel], ...] = (*MESSAGE_TYPES.values(), *PARTS, TensorBlob)


def json_schema(model: type[BaseModel], ref_template: str = DEFAULT_REF_TEMPLATE) -> dict[str, Any]:
    """The JSON Schema of a model's payload as it travels (serialization mode)."""
    return model.model_json_schema(mode="serialization", ref_template=ref_template)


def doc_of(model: type[BaseModel]) -> str:
    """A model's docstring as one line."""
    return " ".join((model.__doc__ or "").split())


def overview() -> list[str]:
    """The rules every payload and topic follows, as markdown paragraphs."""
    return [
        "MQTT 3.1.1. Every payload is the msgpack map of one message (below), with `schema_version` = "
        f"{SCHEMA_VERSION} and its `kind`; unknown fields are errors and floats must be finite. Payloads over "
        f"{MAX_PAYLOAD_BYTES:,} bytes are refused. "
        "Nothing is retained but the chief's claim of its run (`fedrl/<run>/claim`), and any other retained message "
        "is never acted on. Every federation message carries `tag`: an HMAC-SHA256 (hex) of the message's msgpack "
        "encoding without `tag`, map keys sorted, under its sender's key (protocol/auth.py), each derived from the "
        "run's key K (`FEDRL_RUN_KEY`) as the hex HMAC-SHA256 of a purpose under K: a worker's hello, status, "
        "update and mature actor under its own key (purpose `worker:<id>`, `FEDRL_WORKER_KEY`), what the chief or "
        "an edge says to the workers under the chief key (purpose `chief`, `FEDRL_CHIEF_KEY`), an edge's partial "
        "and a chief's claim under K itself. With a key, a receiver refuses a message without its sender's valid "
        "tag; workers also refuse an answer of another session than their RunStart's or for a round they have not "
        "submitted to. Topic levels `<run>`, `<id>` and `<rig>` are "
        "1-64 of `A-Z a-z 0-9 _ . : -`. A message must be of a kind its topic carries, and its `worker_id` or "
        "`rig_id` must be the `<id>` or `<rig>` of its topic (protocol/routes.py).",
        "Sessions are persistent (clean session off) under a client id with a random part; QoS 1 messages are "
        "at-least-once, and every receiver is idempotent: a worker's episode is counted once, an answer applied "
        "once.",
        "**Chunks.** A sender with a payload limit (`FEDRL_MAX_PAYLOAD`) sends a larger payload as `Chunk` "
        "messages on the message's own topic; receivers rejoin them (in index order, within the payload limit) before "
        "decoding the message. Chunks are the one kind any topic may carry.",
    ]


def tensor_encoding() -> str:
    """How tensors travel, as a markdown paragraph."""
    return (
        "A `TensorDict` maps a tensor's name (an actor's or critic's parameter name, e.g. `net.0.weight`: the names "
        "and shapes a worker announces in WorkerHello's `actor_spec` and `critic_spec`) to a TensorBlob, a map "
        "with the keys `dtype`, `shape` and `data`. "
        f"`dtype` is one of {', '.join(f'`{d}`' for d in sorted(ALLOWED_DTYPES))} (numpy spelling, little-endian); "
        "`data` is the C-order raw bytes (msgpack bin), exactly `prod(shape) * itemsize` of them; at most "
        f"{MAX_NDIM} dimensions and {MAX_ELEMENTS:,} elements; floating values must be finite. Actors and gradients "
        "travel as `<f4`. `digest` (protocol/tensors.py) is the first 16 hex digits of the SHA-256 over each "
        "tensor's `name|dtype|shape|` and bytes, in sorted name order; receipts carry it."
    )


def fields_table(model: type[BaseModel]) -> list[str]:
    """Markdown rows: field, type, required/default, constraints."""
    schema = json_schema(model)
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
        "Generated by `python -m protocol.contract --write` from the pydantic models in `protocol/`; do not edit. "
        "The same contract as an AsyncAPI 3.0 document: [asyncapi.yaml](asyncapi.yaml) "
        "(`python -m protocol.asyncapi --write`).",
    ]
    for paragraph in overview():
        out += ["", paragraph]
    out += [
        "",
        "## Processes",
        "",
        *(f"- **{name}**: {text}" for name, text in PROCESSES.items()),
        "",
        "## Topics",
        "",
        "| topic | publisher | subscribers | payload | QoS | retain | note |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in ROUTES:
        payloads = " or ".join(f"[{p.__name__}](#{p.__name__.lower()})" for p in r.payloads)
        out.append(f"| `{r.topic}` | {r.publisher} | {', '.join(r.subscribers)} | {payloads} | {r.qos} | "
                   f"{'yes' if r.retain else 'no'} | {r.remarks} |")
    out += ["", "## Tensors", "", tensor_encoding(), "", *fields_table(TensorBlob), "", "## Messages"]
    for kind, model in MESSAGE_TYPES.items():
        out += ["", f"### {model.__name__}", "", f"`kind` = `{kind!r}`. {doc_of(model)}", "", *fields_table(model)]
    for part in PARTS:
        out += ["", f"### {part.__name__}", "", doc_of(part), "", *fields_table(part)]
    return "\n".join([*out, ""])


def generated_file_main(argv: list[str] | None, prog: str, doc: str, path: Path, render: Callable[[], str]) -> int:
    """The command line of a generated document (``doc`` its module's docstring): print it, or ``--write`` it to
    ``path``."""
    parser = argparse.ArgumentParser(prog=prog, description=doc.splitlines()[0])
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--print", action="store_true", help="print it (the default)")
    group.add_argument("--write", action="store_true", help=f"write it to {path.relative_to(path.parents[1])}")
    args = parser.parse_args(argv)
    text = render()
    if args.write:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
        print(f"wrote {path}")
    else:
        print(text, end="" if text.endswith("\n") else "\n")
    return 0


def main(argv: list[str] | None = None) -> int:
    return generated_file_main(argv, "python -m protocol.contract", __doc__ or "", DOC, markdown)


if __name__ == "__main__":
    sys.exit(main())
