"""Settings of the live dashboard."""

from __future__ import annotations

from pathlib import Path

from runtime.settings import Port, RunKeySettings, RunMqttSettings, Words, setting

DEFAULT_PORT = 8050


class DashboardSettings(RunMqttSettings, RunKeySettings):
    """The live web page of one run, served on 127.0.0.1 and fed by MQTT; with the run's key (``FEDRL_RUN_KEY``) it
    shows only the chief and worker messages tagged with the keys derived from it and counts the others as refused."""

    dashboard_host: str = setting("127.0.0.1", "interface to serve on (0.0.0.0 exposes the page to the network, as "
                                  "inside a container)", aliases=["--host"])
    dashboard_port: Port = setting(DEFAULT_PORT, "TCP port (0 = any free port)", aliases=["--port"])
    dashboard_rigs: Words = setting([], "rig ids to show, comma-separated (unset: every rig on the broker)",
                                    aliases=["--rigs"])
    dashboard_max_points: int = setting(4000, "points per worker curve kept for a page that connects later",
                                        aliases=["--max-points"], ge=2)
    dashboard_url_file: Path | None = setting(None, "write the page's URL into this file once it is served (for "
                                              "launchers)", aliases=["--url-file"])
