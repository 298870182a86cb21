"""The chief: Algorithm 1 of the paper. Pure federation math (federation.py), the round state machine
(rounds.py), the MQTT adapter (service.py) and the run report (report.py)."""
