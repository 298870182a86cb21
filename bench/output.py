"""How a benchmark writes its JSON: the command that made it and the machine it ran on, beside its own fields."""

from __future__ import annotations

import json
import os
import platform
import sys
from pathlib import Path
from typing import Any


def command(module: str, argv: list[str] | None) -> str:
    """The command line that reproduces this invocation: ``python -m <module> <args>``."""
    return " ".join([f"python -m {module}", *(argv if argv is not None else sys.argv[1:])])


def write_report(out: Path, module: str, argv: list[str] | None, fields: dict[str, Any], indent: int = 1) -> None:
    """Write ``{"command", "machine", "cpus", **fields}`` to ``out`` (its folder made) and say so."""
    report = {"command": command(module, argv), "machine": platform.platform(), "cpus": os.cpu_count(), **fields}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=indent) + "\n")
    print(f"wrote {out}")


def write_block(pages: tuple[Path, ...] | list[Path], begin: str, end: str, block: str) -> None:
    """Put ``block`` between the ``begin`` and ``end`` markers of each page (generated tables in README and docs); a
    ValueError for a page without them."""
    for page in pages:
        text = page.read_text()
        start, stop = text.find(begin), text.find(end)
        if start < 0 or stop < start:
            raise ValueError(f"{page} has no {begin!r} ... {end!r} block")
        page.write_text(text[:start + len(begin)] + "\n" + block + text[stop:])
        print(f"wrote the table into {page}")


def append_line(out: Path, line: dict[str, Any]) -> None:
    """Print one result line and append it to the JSON-lines file ``out`` (a tuning log: each run adds its line)."""
    print(json.dumps(line), flush=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    with out.open("a") as log:
        log.write(json.dumps(line) + "\n")
