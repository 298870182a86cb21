"""Settings of the embedded amqtt broker."""

from __future__ import annotations

from pydantic import FilePath

from protocol.codec import MAX_PAYLOAD_BYTES
from runtime.settings import LogLevel, Port, Settings, setting

#: The largest MQTT packet the broker takes: the codec's payload limit plus room for the topic and headers.
MAX_PACKET_SIZE = MAX_PAYLOAD_BYTES + 64 * 1024


class BrokerSettings(Settings):
    """The embedded amqtt MQTT broker (MQTT 3.1.1) for a one-machine federation."""

    broker_host: str = setting("127.0.0.1", "interface to bind", aliases=["--host"])
    broker_port: Port = setting(1883, "TCP port", aliases=["--port"])
    broker_password_file: FilePath | None = setting(None, "only users of this file connect (user:argon2-hash lines; "
                                                "unset: anonymous clients allowed)", aliases=["--password-file"])
    broker_acl_file: FilePath | None = setting(None, 'JSON {"publish": {user: [topic filters]}, "subscribe": {...}}: '
                                           "where each user may publish and subscribe (unset: anywhere)",
                                           aliases=["--acl-file"])
    broker_max_packet_size: int = setting(MAX_PACKET_SIZE, "largest packet in bytes (the codec's payload limit "
                                          "plus headers)", aliases=["--max-packet-size"], ge=1024)
    log_level: LogLevel = setting("INFO", "DEBUG, INFO, WARNING or ERROR")
