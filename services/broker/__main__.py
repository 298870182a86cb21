"""``python -m services.broker``: the embedded amqtt MQTT broker (MQTT 3.1.1)."""

from __future__ import annotations

import argparse
import logging
import os
from pathlib import Path

from services.broker.embedded import MAX_PACKET_SIZE, run


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m services.broker",
        description="Embedded amqtt MQTT broker for a one-machine federation. Binds 127.0.0.1 unless told otherwise. "
        "Without --password-file anonymous clients are allowed, so expose it beyond loopback only on a trusted "
        "network (make run gives every run its own users and ACL; use Mosquitto with the configs in deploy/mosquitto "
        "for real rigs). Packets above --max-packet-size close their connection.",
    )
    parser.add_argument("--host", default=os.environ.get("FEDRL_BROKER_HOST", "127.0.0.1"),
                        help="interface to bind (env FEDRL_BROKER_HOST, default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=int(os.environ.get("FEDRL_BROKER_PORT", "1883")),
                        help="TCP port (env FEDRL_BROKER_PORT, default 1883)")
    parser.add_argument("--password-file", type=Path, default=None,
                        help="only users of this file connect (user:argon2-hash lines); default: anonymous allowed")
    parser.add_argument("--acl-file", type=Path, default=None,
                        help='JSON {"publish": {user: [topic filters]}, "subscribe": {...}}: where each user may '
                        "publish and subscribe (default: anywhere)")
    parser.add_argument("--max-packet-size", type=int, default=MAX_PACKET_SIZE,
                        help=f"largest packet in bytes (default {MAX_PACKET_SIZE}: the codec's payload limit plus "
                        "headers)")
    parser.add_argument("--log-level", default=os.environ.get("FEDRL_LOG_LEVEL", "INFO"),
                        help="logging level (env FEDRL_LOG_LEVEL, default INFO)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s broker %(levelname)s %(message)s")
    # amqtt logs every packet at INFO; keep it quiet unless asked.
    logging.getLogger("amqtt").setLevel(max(logging.WARNING, logging.getLogger().level))
    for path in (args.password_file, args.acl_file):
        if path is not None and not path.is_file():
            parser.error(f"no such file: {path}")
    run(args.host, args.port, password_file=args.password_file, acl_file=args.acl_file,
        max_packet_size=args.max_packet_size)


if __name__ == "__main__":
    main()
