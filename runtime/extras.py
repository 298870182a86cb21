"""What each part of the package needs beyond the base install, and one clear line when it is missing.

``pip install .[bridge]`` on a Raspberry Pi installs every console script, but ``fedrl-worker`` needs torch and
gymnasium (the ``learn`` extra): without this check it would end in a ModuleNotFoundError traceback.
"""

from __future__ import annotations

import importlib.util
import sys


def missing(*modules: str) -> list[str]:
    """The modules of ``modules`` that cannot be imported here (found without importing them)."""
    out = []
    for name in modules:
        try:
            found = importlib.util.find_spec(name) is not None
        except (ImportError, ValueError):  # a parent package missing, or a module blanked out in sys.modules
            found = False
        if not found:
            out.append(name)
    return out


def require(extra: str, *modules: str) -> None:
    """Exit with one line (code 1) naming the extra to install when any of ``modules`` is missing."""
    gone = missing(*modules)
    if gone:
        sys.exit(f"{'this command' if not sys.argv[0] else sys.argv[0].rsplit('/', 1)[-1]} needs "
                 f"{', '.join(gone)}: install the '{extra}' extra (pip install '.[{extra}]' in the project's folder)")
