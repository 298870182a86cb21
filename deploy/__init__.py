"""Launchers and deployment assets: local processes, Docker, Mosquitto configs, Raspberry Pi units."""
