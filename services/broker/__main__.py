"""``python -m services.broker``: the embedded amqtt MQTT broker (MQTT 3.1.1)."""

from __future__ import annotations

import logging
import sys

from runtime.extras import require
from runtime.settings import returns_code
from services.broker.embedded import run
from services.broker.settings import BrokerSettings

DESCRIPTION = (
    "Embedded amqtt MQTT broker for a one-machine federation. Binds 127.0.0.1 unless told otherwise. Without "
    "--password-file anonymous clients are allowed, so expose it beyond loopback only on a trusted network (make run "
    "gives every run its own users and ACL; use Mosquitto with the configs in deploy/mosquitto for real rigs). "
    "Packets above --max-packet-size close their connection."
)


@returns_code
def main(argv: list[str] | None = None) -> int:
    require("broker", "amqtt")  # one clear line where the broker extra is not installed
    s = BrokerSettings.load(argv, prog="python -m services.broker", description=DESCRIPTION)
    logging.basicConfig(level=s.log_level, format="%(asctime)s broker %(levelname)s %(message)s")
    # amqtt logs every packet at INFO; keep it quiet unless asked.
    logging.getLogger("amqtt").setLevel(max(logging.WARNING, logging.getLogger().level))
    try:
        run(s.broker_host, s.broker_port, password_file=s.broker_password_file, acl_file=s.broker_acl_file,
            max_packet_size=s.broker_max_packet_size)
    except KeyboardInterrupt:
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
