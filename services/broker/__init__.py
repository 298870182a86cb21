"""The embedded amqtt broker, so one machine runs a whole federation with one command."""
