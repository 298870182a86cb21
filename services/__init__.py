"""Long-running services: the embedded MQTT broker and the simulated QUBE-Servo 2 rigs."""
