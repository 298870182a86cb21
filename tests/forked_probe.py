"""``python -m tests.forked_probe``: what a forked process sees (tests/deploy/test_forked.py).

Prints its environment's FEDRL_PROBE, whether it leads its own process group and whether torch was imported before
it ran, then sleeps FEDRL_PROBE_SLEEP seconds and exits with FEDRL_PROBE_CODE.
"""

from __future__ import annotations

import os
import sys
import time

if __name__ == "__main__":
    preloaded = "torch" in sys.modules
    print(f"probe={os.environ.get('FEDRL_PROBE')} own_group={os.getpgid(0) == os.getpid()} torch={preloaded}")
    print("to stderr", file=sys.stderr)
    time.sleep(float(os.environ.get("FEDRL_PROBE_SLEEP", "0")))
    sys.exit(int(os.environ.get("FEDRL_PROBE_CODE", "0")))
