"""Raspberry Pi bridge for a Quanser QUBE-Servo 2 on SPI: frame codec, device, velocity filter, calibration,
self-test, reset controller, control core, loop and MQTT adapter.

Kept free of heavy imports (no torch, no gymnasium): it installs on a Pi with ``pip install .[bridge]``.
"""
