"""``python -m chief.strategies``: list the federation strategies (``--markdown`` prints the README table)."""

from __future__ import annotations

import argparse
import sys

from chief import strategies


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m chief.strategies", description=__doc__.splitlines()[0])
    parser.add_argument("--markdown", action="store_true", help="print the README table")
    parser.add_argument("--workers", type=int, default=4, help="N for the 'tolerates' column (default 4)")
    args = parser.parse_args(argv)
    if args.markdown:
        print(strategies.markdown_table(args.workers))
        return 0
    for s in strategies.registry().values():
        print(f"{s.name:<12} {s.summary}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
