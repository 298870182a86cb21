"""``python -m deploy.mosquitto_conf [FILE]``: a Mosquitto configuration with its ``${VAR:-default}`` placeholders
filled in from the environment, on stdout (Mosquitto reads no variables itself).

deploy/mosquitto/mosquitto.prod.conf takes its ports and paths this way, so that a broker on a host that has one
already (or outside the official image) needs no edited copy: ``FEDRL_MQTT_LOCAL_PORT=1884 python -m
deploy.mosquitto_conf > deploy/mosquitto/secrets/mosquitto.conf``. ``python -m deploy.sites`` fills in its base the
same way. A placeholder without a default whose variable is unset is one line and exit code 2.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
from collections.abc import Mapping
from pathlib import Path

#: ``${NAME}`` or ``${NAME:-default}`` (the shell's spelling, as in the compose files).
PLACEHOLDER = re.compile(r"\$\{([A-Z_][A-Z0-9_]*)(?::-([^}]*))?\}")
PROD_CONF = Path(__file__).resolve().parent / "mosquitto" / "mosquitto.prod.conf"


def render(text: str, environ: Mapping[str, str]) -> str:
    """``text`` with every placeholder replaced by its variable (when set and not empty) or its default; a ValueError
    names a placeholder that has neither."""

    def value(match: re.Match[str]) -> str:
        name, default = match.group(1), match.group(2)
        if environ.get(name):
            return environ[name]
        if default is None:
            raise ValueError(f"${{{name}}} has no default: set {name}")
        return default

    return PLACEHOLDER.sub(value, text)


def placeholders(text: str) -> dict[str, str | None]:
    """Each placeholder's variable and its default (None: none), in order."""
    return {m.group(1): m.group(2) for m in PLACEHOLDER.finditer(text)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m deploy.mosquitto_conf", description=__doc__.splitlines()[0])
    parser.add_argument("file", nargs="?", type=Path, default=PROD_CONF,
                        help="the configuration (default: deploy/mosquitto/mosquitto.prod.conf)")
    args = parser.parse_args(argv)
    try:
        sys.stdout.write(render(args.file.read_text(encoding="utf-8"), os.environ))
    except (OSError, ValueError) as err:
        print(f"python -m deploy.mosquitto_conf: {args.file}: {getattr(err, 'strerror', None) or err}",
              file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
