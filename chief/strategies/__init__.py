"""The federation strategies, one module each, found by scanning this package (Flower keeps its strategies the
same way). Adding a strategy is one new module defining ``STRATEGY`` (a ``base.Strategy``) plus its test.

>>> names()
['independent', 'median', 'plain', 'sync', 'trimmed', 'weighted']
"""

from __future__ import annotations

import importlib
import pkgutil

from chief.strategies.base import Aggregate, Strategy

__all__ = ["Aggregate", "Strategy", "get", "markdown_table", "names", "registry"]

#: The paper's strategy (PI-weighted gradients, Eq. 8-10, and soft transfer, Eq. 11): every default names it.
DEFAULT = "weighted"


def registry() -> dict[str, Strategy]:
    """Every strategy module of this package, by name."""
    found: dict[str, Strategy] = {}
    for info in pkgutil.iter_modules(__path__):
        if info.name in ("base",) or info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{__name__}.{info.name}")
        strategy = getattr(module, "STRATEGY", None)
        if not isinstance(strategy, Strategy):
            raise TypeError(f"{module.__name__} defines no STRATEGY")
        if strategy.name in found:
            raise ValueError(f"two strategies are named {strategy.name!r}")
        found[strategy.name] = strategy
    return dict(sorted(found.items()))


_REGISTRY = registry()


def names() -> list[str]:
    return list(_REGISTRY)


def get(name: str) -> Strategy:
    """The strategy called ``name``, or a ValueError listing the known ones."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown federation policy {name!r}; choose one of {', '.join(_REGISTRY)}") from None


def markdown_table(workers: int = 4) -> str:
    """The README's strategy table, generated from the registry."""
    rows = [f"| policy | what it does | tolerates at N = {workers} | robustness |", "| --- | --- | --- | --- |"]
    for s in _REGISTRY.values():
        rows.append(f"| `{s.name}` | {s.summary} | {s.tolerates(workers)} of {workers} | {s.robustness} |")
    return "\n".join(rows)
