"""Simulated QUBE-Servo 2 rigs: physics and a simulated SPI peer."""
