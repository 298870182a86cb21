"""Live web view of one federated run, fed by MQTT: ``python -m services.dashboard`` (see ``view.py``)."""
