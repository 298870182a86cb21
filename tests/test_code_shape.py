"""The code stays readable: no function of the project is longer than 80 lines (tests included)."""

from __future__ import annotations

import ast

from tests.paths import ROOT

PACKAGES = ("protocol", "runtime", "chief", "worker", "rpi_bridge", "services", "deploy", "bench", "tests")
MAX_LINES = 80


def test_no_function_is_longer_than_80_lines() -> None:
    long = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    lines = (node.end_lineno or node.lineno) - node.lineno + 1
                    if lines > MAX_LINES:
                        long.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({lines} lines)")
    assert not long, "functions longer than 80 lines:\n" + "\n".join(long)
