"""Start a Mosquitto broker on a free loopback port, for the tests and the benchmarks (the one place that does).

Anonymous clients on 127.0.0.1, TCP_NODELAY as in deploy/mosquitto/mosquitto.conf (Nagle with delayed ACKs turns a
sub-millisecond QoS 1 round trip into 40-90 ms) and, by default, the same packet limit as the embedded broker.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

from services.broker.embedded import free_port, wait_for_port
from services.broker.settings import MAX_PACKET_SIZE

HOST = "127.0.0.1"


def binary() -> str:
    """The mosquitto executable (Debian installs it into /usr/sbin, outside a user's PATH)."""
    return shutil.which("mosquitto") or "/usr/sbin/mosquitto"


def available() -> bool:
    """Whether Mosquitto is installed (apt-get install mosquitto)."""
    return shutil.which("mosquitto") is not None or Path("/usr/sbin/mosquitto").exists()


def start(folder: Path, port: int | None = None, max_packet_size: int | None = MAX_PACKET_SIZE,
          persistence: bool = False, autosave: int = 1, extra: str = "") -> tuple[subprocess.Popen, int]:
    """Mosquitto on ``port`` (default: a free one, never 1883) of 127.0.0.1, its configuration and log in ``folder``;
    ``max_packet_size`` (the codec's payload limit plus headers by default; None: Mosquitto's own, none) closes the
    connection of a client sending a bigger packet. With ``persistence`` it keeps sessions and queued messages
    across a restart (in ``folder``, saved every ``autosave`` seconds and when it stops; a ``kill -9`` loses what
    came since the last save). ``extra`` is appended to the configuration (a bridge to another broker, say:
    deploy/sites.py). Returns the process (stop it with ``embedded.stop_process``) and the port."""
    port = port or free_port(HOST)
    store = f"persistence true\npersistence_location {folder}/\nautosave_interval {autosave}\n" if persistence else (
        "persistence false\n")
    if os.geteuid() == 0:
        store += "user root\n"  # as root, Mosquitto would switch to its own user, who cannot write the folder
    limit = f"max_packet_size {max_packet_size}\n" if max_packet_size is not None else ""
    conf = folder / f"mosquitto-{port}.conf"
    conf.write_text(f"listener {port} {HOST}\nallow_anonymous true\nset_tcp_nodelay true\n{limit}{store}"
                    f"log_dest stderr\n{extra}")
    with (folder / f"mosquitto-{port}.log").open("ab") as log:  # a restart on the same port goes on with it
        proc = subprocess.Popen([binary(), "-c", str(conf)], stdout=log, stderr=subprocess.STDOUT)
    wait_for_port(HOST, port, proc=proc)
    return proc, port
