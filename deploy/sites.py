"""Brokers per site joined to a core: the Mosquitto bridge of each site broker, derived from the wire contract.

Each site runs its own Mosquitto; its workers (and rigs) connect to it. The chief and the dashboard connect to the
core Mosquitto. A bridge on each site broker joins it to the core (docs/how-to/sites.md says why Mosquitto bridges,
and what survives a broker's death):

- **Which topics cross, and which way**, follows from protocol/routes.py and where each process runs (PLACEMENT): a
  route published at a site and read at the core goes ``out``; one published at the core and read at a site comes
  ``in``; the rest stays where it is (a rig's state and actions never leave its site, the chief's retained claim
  never leaves the core). Same QoS as the route.
- **What keeps messages across a broker's death** (each setting is explained where it is written, in
  ``bridge_section``): the bridge holds a persistent session on the core (``cleansession false`` under a fixed client
  id), so the core queues the chief's answers for a site whose broker is down, and the site queues its workers'
  updates while the core is down; both brokers persist their sessions and queues. What a ``kill -9`` takes with it
  (whatever arrived after the last autosave) the processes send again: a worker resends an unanswered update after a
  reconnect and every ``resend_interval``, the chief counts it once and answers a closed round again.
"""

from __future__ import annotations

import argparse
import os
import secrets
import shutil
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from deploy.mosquitto_conf import render
from protocol.routes import BRIDGE, CHIEF, DASHBOARD, EDGE, ROUTES, WORKER, Route
from protocol.topics import check_edge, check_id
from services.broker import mosquitto
from services.broker.embedded import free_port, stop_process
from worker.settings import handed_keys

HOST = "127.0.0.1"

Place = Literal["site", "core"]
SITE: Place = "site"
CORE: Place = "core"
#: Where each process of the contract runs: workers, rigs and edge chiefs at their site, the chief and the dashboard
#: at the core.
PLACEMENT: dict[str, Place] = {WORKER: SITE, BRIDGE: SITE, EDGE: SITE, CHIEF: CORE, DASHBOARD: CORE}
#: Seconds after which a worker at a site sends an unanswered update again (FEDRL_RESEND_INTERVAL; the default is
#: 30). A core that dies takes with it what it had acknowledged and not yet passed on, and nobody at a site sees it
#: go: the resend must come while the chief's round still waits (FEDRL_ROUND_TIMEOUT, 30 s by default).
RESEND_INTERVAL = 5.0
#: Seconds between a bridge's pings when idle: a core lost without a TCP reset (a host or link down) is noticed
#: within 1.5 of them, as the processes notice theirs (protocol.mqtt.KEEPALIVE).
KEEPALIVE = 15
#: Bridge reconnection: decorrelated jitter from the first to the second number of seconds (Mosquitto's default,
#: 5 to 30 s, could outlast a round's timeout; a site must be back well within the chief's round_timeout).
RESTART_TIMEOUT = (1, 5)


@dataclass(frozen=True)
class BridgeTopic:
    """One ``topic`` line of a bridge: a route's topic filter, the way it crosses and its QoS."""

    pattern: str
    direction: Literal["in", "out"]
    qos: int
    route: Route

    @property
    def line(self) -> str:
        return f"topic {self.pattern} {self.direction} {self.qos}"


def bridge_topics(run: str | None = None, placement: dict[str, Place] | None = None) -> list[BridgeTopic]:
    """The topics a site's bridge carries, in the contract's order: each route whose publisher and some subscriber
    are on different sides, for one run (``run``) or any (None: ``+``). A retained route never crosses: a copy left
    at a site would outlive the core's (the claim is cleared with an empty retained message)."""
    where = placement or PLACEMENT
    out: list[BridgeTopic] = []
    for route in ROUTES:
        publisher, readers = where[route.publisher], {where[s] for s in route.subscribers}
        if readers <= {publisher}:
            continue
        if route.retain:
            raise ValueError(f"{route.topic} is retained and would cross a bridge")
        pattern = route.filter(run=run) if run and "run" in route.parameters else route.filter()
        out.append(BridgeTopic(pattern, "out" if publisher == SITE else "in", route.qos, route))
    return out


@dataclass(frozen=True)
class Bridge:
    """A site broker's bridge to the core: the site's name, the core's ``host:port``, the run (None: any), and for a
    secured core the bridge's login and the CA that signed the core's certificate (TLS)."""

    site: str
    core: str
    run: str | None = None
    username: str | None = None
    password: str | None = None
    cafile: str | None = None

    def __post_init__(self) -> None:
        check_id(self.site, "site name")
        host, _, port = self.core.rpartition(":")
        if not host or not port.isdigit():
            raise ValueError(f"core broker {self.core!r}: give host:port")

    @property
    def client_id(self) -> str:
        """The bridge's client id on the core, fixed so that the core keeps its session across reconnects (a
        secured core with ``use_username_as_clientid`` uses the username instead, also fixed)."""
        return self.username or f"bridge-{self.site}"


def bridge_section(bridge: Bridge) -> str:
    """The Mosquitto configuration of a site broker's bridge to the core (appended to the site broker's own)."""
    lines = [
        f"# Bridge of site {bridge.site} to the core (deploy/sites.py; docs/how-to/sites.md).",
        f"connection {bridge.site}",
        f"address {bridge.core}",
        "bridge_protocol_version mqttv311",
        "# A persistent session on the core under a fixed client id: while this site's broker is down, the core",
        "# queues the chief's answers for it; while the core is down, this broker queues its workers' updates",
        "# (local_cleansession follows cleansession). Both brokers keep those queues in their persistence files.",
        f"remote_clientid {bridge.client_id}",
        f"local_clientid local-{bridge.client_id}",
        "cleansession false",
        "# Back within seconds after either broker restarts, well inside the chief's round timeout.",
        f"restart_timeout {RESTART_TIMEOUT[0]} {RESTART_TIMEOUT[1]}",
        f"keepalive_interval {KEEPALIVE}",
        "# The bridge's state, 1 or 0, retained on $SYS/broker/connection/<client id>/state at both ends.",
        "notifications true",
        "start_type automatic",
    ]
    if bridge.username:
        lines += [f"remote_username {bridge.username}", f"remote_password {bridge.password or ''}"]
    if bridge.cafile:
        lines += [f"bridge_cafile {bridge.cafile}", "bridge_tls_version tlsv1.2", "bridge_insecure false"]
    lines.append("# From protocol/routes.py: what a site publishes for the core (out), what the core sends it (in).")
    lines += [t.line for t in bridge_topics(bridge.run)]
    return "\n".join(lines) + "\n"


class LoopbackSites:
    """A core Mosquitto and site brokers bridged to it, on free ports of 127.0.0.1, each with persistence in its own
    folder (services/broker/mosquitto.py): for tests and benchmarks. ``kill`` and ``start`` one by name (the core is
    ``core``); a restarted broker keeps its port, so that its clients and bridges find it again."""

    def __init__(self, folder: Path, sites: Sequence[str], autosave: int = 1) -> None:
        self.folder, self.sites, self.autosave = folder, list(sites), autosave
        self.ports = {name: free_port(HOST) for name in [CORE, *self.sites]}
        self.procs: dict[str, subprocess.Popen] = {}
        for name in self.ports:
            (folder / name).mkdir(parents=True, exist_ok=True)
            self.start(name)

    def url(self, name: str) -> str:
        return f"mqtt://{HOST}:{self.ports[name]}"

    def start(self, name: str) -> None:
        """Start broker ``name`` (again) on its port, with what its persistence file holds."""
        extra = "" if name == CORE else bridge_section(Bridge(name, f"{HOST}:{self.ports[CORE]}"))
        self.procs[name], _ = mosquitto.start(self.folder / name, port=self.ports[name], persistence=True,
                                              autosave=self.autosave, extra=extra)

    def kill(self, name: str) -> None:
        """SIGKILL: the broker saves nothing more (what came since its last autosave is gone)."""
        self.procs[name].kill()
        self.procs[name].wait()

    def stop(self) -> None:
        for proc in self.procs.values():
            stop_process(proc)

    def __enter__(self) -> LoopbackSites:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


# -- a deployment's brokers: users, ACLs and configurations -----------------------------------------------------

MOSQUITTO_DIR = Path(__file__).parent / "mosquitto"
MAKE_USERS = MOSQUITTO_DIR / "make-users.sh"
#: What a broker's folder gets from write_deployment: secrets all (a site's mosquitto.conf holds its bridge's
#: password), never committed (deploy/k8s/example/.gitignore, deploy/swarm/.gitignore).
SECRET_FILES = ("acl", "passwd", "logins", "run_key", "mosquitto.conf", "credentials")


@dataclass(frozen=True)
class Site:
    """A site: its name and how many workers and rigs it has. Worker i is ``<name>-w<i>`` and drives rig
    ``<name>-rig<i>`` (make-users.sh's convention, with the site's name as the prefix)."""

    name: str
    workers: int
    rigs: int = 0

    @classmethod
    def parse(cls, text: str) -> Site:
        """``a=4`` (4 workers) or ``a=4:2`` (4 workers, 2 of them with a rig)."""
        name, _, counts = text.partition("=")
        workers, _, rigs = counts.partition(":")
        if not (workers.isdigit() and (rigs == "" or rigs.isdigit())):
            raise ValueError(f"site {text!r}: give NAME=WORKERS or NAME=WORKERS:RIGS")
        site = cls(check_id(name, "site name"), int(workers), int(rigs or 0))
        try:  # its edge chief is named after it (edge_id)
            check_edge(site.edge_id)
        except ValueError as err:
            raise ValueError(f"site {text!r}: its edge chief is named after it, and {err}") from None
        if site.rigs > site.workers:
            raise ValueError(f"site {text!r}: more rigs than workers (worker i drives rig i)")
        return site

    @property
    def worker_ids(self) -> list[str]:
        return [f"{self.name}-w{i}" for i in range(self.workers)]

    @property
    def rig_ids(self) -> list[str]:
        return [f"{self.name}-rig{i}" for i in range(self.rigs)]

    @property
    def edge_id(self) -> str:
        """The id of the site's edge chief in a tiered run (docs/explanation/tiered.md): the site's name."""
        return self.name

    @property
    def bridge_user(self) -> str:
        return f"bridge-{self.name}"


def bridge_acl(site: Site, run: str | None = None) -> str:
    """The core's ACL entry for a site's bridge: it publishes what the site's own workers, rigs and edge chief publish
    (so one site cannot speak for another's), reads what the chief sends them, and keeps its state notification."""
    lines = [f"# Site {site.name}'s bridge (deploy/sites.py).", f"user {site.bridge_user}",
             f"topic write $SYS/broker/connection/{site.bridge_user}/state"]
    for topic in bridge_topics(run):
        route = topic.route
        if topic.direction == "in":
            lines.append(f"topic read {topic.pattern}")
            continue
        level, names = next((level, names) for level, names in (("id", site.worker_ids), ("edge", [site.edge_id]),
                                                                 ("rig", site.rig_ids)) if level in route.parameters)
        fixed = {"run": run} if run and "run" in route.parameters else {}
        lines += [f"topic write {route.filter(**fixed, **{level: name})}" for name in names]
    return "\n".join(lines) + "\n"


def make_users(folder: Path, *args: str) -> None:
    """deploy/mosquitto/make-users.sh into ``folder`` (users, hashed passwords, ACL, credentials/<user>.env)."""
    done = subprocess.run(["bash", str(MAKE_USERS), "-o", str(folder), "--force", *args], capture_output=True,
                          text=True)
    if done.returncode != 0:
        raise RuntimeError(f"make-users.sh failed: {done.stderr.strip()}")


def add_user(folder: Path, user: str, password: str, acl: str) -> None:
    """One more user in a broker folder made by make-users.sh: its hashed password and its ACL entry."""
    done = subprocess.run(["mosquitto_passwd", "-b", str(folder / "passwd"), user, password], capture_output=True,
                          text=True)
    if done.returncode != 0:
        raise RuntimeError(f"mosquitto_passwd failed: {done.stderr.strip() or done.stdout.strip()}")
    with (folder / "acl").open("a", encoding="utf-8") as fh:
        fh.write("\n" + acl)


def logins(folder: Path) -> str:
    """``user:password`` lines of a broker folder's credentials/<user>.env files (one secret for the replicas of
    a site's workers, each of which picks its own line)."""
    out = []
    for path in sorted((folder / "credentials").glob("*.env")):
        env = dict(line.split("=", 1) for line in path.read_text(encoding="utf-8").split())
        out.append(f"{env['FEDRL_MQTT_USERNAME']}:{env['FEDRL_MQTT_PASSWORD']}\n")
    return "".join(out)


def write_deployment(out: Path, sites: Sequence[Site], core: str, base: Path, run: str | None = None,
                     core_ca: str | None = None) -> list[Path]:
    """Every broker's folder for a multi-site deployment: ``core/`` (the chief's and the dashboard's users, one
    user per site bridge) and ``site-<name>/`` (its workers', rigs' and edge chief's users, its mosquitto.conf:
    ``base`` plus its bridge to ``core`` (host:port), over TLS when ``core_ca`` names the core's CA as the site
    broker sees it).
    Each folder also holds the run's key (``run_key``, the same everywhere: an orchestrator takes a folder per
    place), and so does each process's credentials/<user>.env, but a worker's, which holds its own key and the chief
    key (``with_key``). Passwords and the key are random; files with secrets are private. Returns the folders."""
    base_conf = render(base.read_text(encoding="utf-8"), os.environ)  # its ${VAR:-default}s filled in
    run_args = ["--run", run] if run else []
    key = secrets.token_hex(32)
    core_dir = out / CORE
    make_users(core_dir, "-w", "0", "--dashboard", *run_args)
    (core_dir / "mosquitto.conf").write_text(base_conf, encoding="utf-8")
    private(core_dir / "run_key", key)
    with_key(core_dir, key)
    folders = [core_dir]
    for site in sites:
        folder = out / f"site-{site.name}"
        make_users(folder, "-w", str(site.workers), "-r", str(site.rigs), "--worker-prefix", f"{site.name}-w",
                   "--rig-prefix", f"{site.name}-rig", "--no-chief", "--edge", site.edge_id, *run_args)
        password = secrets.token_urlsafe(24)
        add_user(core_dir, site.bridge_user, password, bridge_acl(site, run))
        bridge = Bridge(site.name, core, run, site.bridge_user, password, core_ca)
        private(folder / "mosquitto.conf", base_conf + "\n" + bridge_section(bridge))
        private(folder / "logins", logins(folder))
        private(folder / "run_key", key)
        with_key(folder, key)
        folders.append(folder)
    return folders


def with_key(folder: Path, key: str) -> None:
    """Add the run's key to each process's credentials/<user>.env (its whole environment file, FEDRL_ENV_FILE); a
    worker's (the file names its FEDRL_WORKER_ID) gets its own key and the chief key instead (protocol/auth.py)."""
    for path in (folder / "credentials").glob("*.env"):
        text = path.read_text(encoding="utf-8")
        wid = next((line.split("=", 1)[1].strip() for line in text.splitlines()
                    if line.startswith("FEDRL_WORKER_ID=")), None)
        lines = ([f"FEDRL_RUN_KEY={key}"] if wid is None else
                 [f"FEDRL_{name.upper()}={value}" for name, value in handed_keys(key, wid).items() if value])
        path.write_text(text + ("" if text.endswith("\n") else "\n") + "".join(f"{line}\n" for line in lines),
                        encoding="utf-8")


def private(path: Path, text: str) -> None:
    """Write a file only its owner can read (it holds a password)."""
    path.touch(mode=0o600, exist_ok=True)
    path.chmod(0o600)
    path.write_text(text, encoding="utf-8")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m deploy.sites", description="Write the brokers of a multi-site deployment (a core and one "
        "broker per site, bridged to it): one folder per broker with its users, passwords, ACL, mosquitto.conf "
        "(a site's with its bridge) and the run's key.")
    parser.add_argument("--site", action="append", type=Site.parse, required=True, metavar="NAME=WORKERS[:RIGS]",
                        help="a site and how many workers (and rigs) it has; repeat for each site")
    parser.add_argument("--core", required=True, metavar="HOST:PORT", help="the core broker as the sites reach it")
    parser.add_argument("--core-ca", metavar="PATH", help="TLS to the core: its CA certificate, as the site brokers "
                        "see it (e.g. /mosquitto/certs/core-ca.crt)")
    parser.add_argument("--run", help="the one run these users may take part in (default: any)")
    parser.add_argument("--base", type=Path, default=MOSQUITTO_DIR / "mosquitto.prod.conf",
                        help="every broker's configuration before its bridge, its ${VAR:-default} placeholders filled "
                        "in from the environment (python -m deploy.mosquitto_conf; default: mosquitto.prod.conf; "
                        "mosquitto.overlay.conf on an orchestrator)")
    parser.add_argument("-o", "--out", type=Path, default=MOSQUITTO_DIR / "secrets" / "sites",
                        help="folder to write (default: deploy/mosquitto/secrets/sites, git-ignored)")
    parser.add_argument("--force", action="store_true", help="replace the secrets the folder holds")
    args = parser.parse_args(argv)
    try:
        if args.run is not None:
            check_id(args.run, "run id")
        if shutil.which("mosquitto_passwd") is None:
            raise ValueError("needs mosquitto_passwd, to hash the passwords (apt-get install mosquitto)")
        Bridge("check", args.core)
        names = [s.name for s in args.site]
        if len(set(names)) != len(names) or CORE in names:
            raise ValueError(f"site names must differ from each other and from {CORE!r}: {names}")
        if list(args.out.glob("*/run_key")) and not args.force:
            raise ValueError(f"{args.out} holds a deployment's secrets already; pass --force to replace them")
        args.out.mkdir(parents=True, exist_ok=True)
        folders = write_deployment(args.out, args.site, args.core, args.base, args.run, args.core_ca)
    except (ValueError, RuntimeError, OSError) as err:
        print(f"python -m deploy.sites: {err}", file=sys.stderr)
        return 2
    for folder in folders:
        print(f"wrote {folder}/ (users, ACL, mosquitto.conf, run_key: FEDRL_RUN_KEY of the chiefs and the "
              "dashboard, from which each worker's credentials hold its own key and the chief key)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
