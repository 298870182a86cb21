"""``python -m services.broker``: the embedded amqtt MQTT broker (MQTT 3.1.1)."""

from __future__ import annotations

import argparse
import logging
import os

from services.broker.embedded import run


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m services.broker",
        description="Embedded amqtt MQTT broker for a one-machine federation. Binds 127.0.0.1 unless told otherwise; "
        "anonymous clients are allowed, so expose it beyond loopback only on a trusted network (use Mosquitto with "
        "the configs in deploy/mosquitto for real rigs).",
    )
    parser.add_argument("--host", default=os.environ.get("FEDRL_BROKER_HOST", "127.0.0.1"),
                        help="interface to bind (env FEDRL_BROKER_HOST, default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=int(os.environ.get("FEDRL_BROKER_PORT", "1883")),
                        help="TCP port (env FEDRL_BROKER_PORT, default 1883)")
    parser.add_argument("--log-level", default=os.environ.get("FEDRL_LOG_LEVEL", "INFO"),
                        help="logging level (env FEDRL_LOG_LEVEL, default INFO)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s broker %(levelname)s %(message)s")
    # amqtt logs every packet at INFO; keep it quiet unless asked.
    logging.getLogger("amqtt").setLevel(max(logging.WARNING, logging.getLogger().level))
    run(args.host, args.port)


if __name__ == "__main__":
    main()
