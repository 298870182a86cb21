"""Raspberry Pi bridge for a Quanser QUBE-Servo 2 on SPI: frame codec, device, velocity filter, reset
controller.

Kept free of heavy imports (no torch, no gymnasium): it installs on a Pi with ``pip install .[bridge]``.
"""
