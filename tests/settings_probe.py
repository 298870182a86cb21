"""``python -m tests.settings_probe``: a stand-in child process for the launcher tests. It loads the settings model
named by PROBE_MODEL (``module:Class``) from its environment and .env file, as the real process would, and writes
them as JSON to PROBE_OUT."""

from __future__ import annotations

import importlib
import os
import sys
from pathlib import Path

if __name__ == "__main__":
    module, _, name = os.environ["PROBE_MODEL"].partition(":")
    settings = getattr(importlib.import_module(module), name).load(sys.argv[1:], prog="settings_probe")
    Path(os.environ["PROBE_OUT"]).write_text(settings.model_dump_json())
