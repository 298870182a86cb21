"""``python -m deploy.docker``: run federations in containers from a script, through the Docker SDK for Python.

Builds the images (deploy/Dockerfile), then for each worker count: starts Mosquitto, the chief and N workers (one
simulated QUBE-Servo 2 per worker when the env is ``qube``) on a private network or the host's loopback, streams the
chief's progress, copies the run folder out of the chief's container and removes every container and network it
made, also on Ctrl-C or an error. ``--workers 2,4,8`` is a sweep: one run folder per count and a table at the end.
Needs ``pip install .[deploy]`` and a reachable Docker engine (DOCKER_HOST is honoured).
"""

from __future__ import annotations

import io
import signal
import socket
import sys
import tarfile
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

try:
    import docker
    import requests
    from docker.errors import APIError, BuildError, DockerException, NotFound
except ModuleNotFoundError:  # one line naming the extra, not a traceback
    from runtime.extras import require

    require("deploy", "docker", "requests")
    raise

from chief.settings import ChiefSettings
from deploy.settings import DockerSettings
from protocol.tasks import worker_seed
from runtime.records import SUMMARY, RunSummary
from runtime.settings import Settings, returns_code, to_env
from services.qube_sim.settings import SimRigSettings
from worker.settings import WorkerSettings

ROOT = Path(__file__).resolve().parent.parent
MOSQUITTO_DIR = ROOT / "deploy" / "mosquitto"
LABEL = "org.fedrl.launcher"
DESCRIPTION = (
    "Build the images and run one federation per worker count in Docker containers (Mosquitto, chief, N workers), "
    "copying each run folder to --out. Settings also come from the FEDRL_* variables of .env.example."
)


@dataclass
class RunResult:
    workers: int
    code: int
    wall_s: float
    run_dir: Path
    summary: RunSummary | None = None


@dataclass
class Launcher:
    """One Docker client, the images it built and the containers/networks it still owns."""

    args: DockerSettings
    client: docker.DockerClient = field(default_factory=docker.from_env)
    session: str = field(default_factory=lambda: uuid.uuid4().hex[:8])
    containers: list[Any] = field(default_factory=list)
    networks: list[Any] = field(default_factory=list)

    def image(self, role: str) -> str:
        return f"{self.args.image_prefix}/{role}:{self.args.image_tag}"

    # -- images ----------------------------------------------------------------------------------------------------

    def build(self, roles: list[str]) -> None:
        """Build each role's target of deploy/Dockerfile, printing the build's steps as they come."""
        for role in roles:
            print(f"== building {self.image(role)}", flush=True)
            stream = self.client.api.build(
                path=str(ROOT), dockerfile="deploy/Dockerfile", target=role, tag=self.image(role), rm=True,
                forcerm=True, decode=True,
                network_mode=None if self.args.build_network == "default" else self.args.build_network,
                buildargs={"BASE_IMAGE": self.args.base_image, "TORCH_INDEX_URL": self.args.torch_index_url or ""},
            )
            for chunk in stream:
                if "error" in chunk:
                    raise BuildError(chunk["error"], [])
                line = chunk.get("stream", "").rstrip()
                if line.startswith("Step "):
                    print(f"   {line}", flush=True)

    # -- containers ------------------------------------------------------------------------------------------------

    def start(self, name: str, image: str, network: str, **kwargs: Any) -> Any:
        net: dict[str, Any] = {"network_mode": "host"} if network == "host" else {"network": network}
        container = self.client.containers.run(image, name=name, detach=True, labels={LABEL: self.session},
                                               **net, **kwargs)
        self.containers.append(container)
        return container

    def start_broker(self, run: str, network: str) -> str:
        """Mosquitto with the project's config; returns the URL the other containers use."""
        port = self.args.mqtt_port if network == "host" else 1883
        if network == "host" and port_in_use(port):
            raise RuntimeError(f"127.0.0.1:{port} is already in use; pick another --mqtt-port")
        conf = "mosquitto.loopback.conf" if network == "host" else "mosquitto.conf"
        probe = ["CMD", "mosquitto_sub", "-h", "127.0.0.1", "-p", str(port), "-t", "$SYS/broker/version",
                 "-C", "1", "-W", "3"]
        broker = self.start(
            f"fedrl-{run}-mosquitto", self.args.mosquitto_image, network,
            command=["mosquitto", "-c", "/mosquitto/config/mosquitto.conf", "-p", str(port)],
            volumes={str(MOSQUITTO_DIR / conf): {"bind": "/mosquitto/config/mosquitto.conf", "mode": "ro"}},
            healthcheck={"test": probe, "interval": 1_000_000_000, "timeout": 5_000_000_000, "retries": 30},
        )
        wait_healthy(broker, timeout=60)
        host = "127.0.0.1" if network == "host" else broker.name
        return f"mqtt://{host}:{port}"

    def teardown(self) -> None:
        """Remove every container and network of this launcher, whatever state they are in."""
        for container in reversed(self.containers):
            try:
                container.remove(force=True, v=True)
            except NotFound:
                pass
            except APIError as err:
                print(f"!! could not remove {container.name}: {err}", file=sys.stderr)
        self.containers.clear()
        for net in self.networks:
            try:
                net.remove()
            except (NotFound, APIError) as err:
                print(f"!! could not remove network {net.name}: {err}", file=sys.stderr)
        self.networks.clear()

    # -- one run ---------------------------------------------------------------------------------------------------

    def run(self, workers: int) -> RunResult:
        a = self.args
        run = f"d{self.session}-w{workers}"
        run_dir = a.sweep_dir / f"{time.strftime('%Y%m%d-%H%M%S')}-{a.env}-{a.policy}-w{workers}-s{a.seed}"
        t0 = time.monotonic()
        network = "host"
        if a.docker_network == "bridge":
            net = self.client.networks.create(f"fedrl-{run}", driver="bridge", labels={LABEL: self.session})
            self.networks.append(net)
            network = net.name
        broker = self.start_broker(run, network)
        common = {"broker": broker, "run_id": run}
        print(f"== run {run}: {workers} workers on {a.env}, policy {a.policy}, seed {a.seed}, broker {broker}",
              flush=True)
        for i in range(workers):
            rig = f"rig{i}" if a.env == "qube" else None
            if rig is not None:
                self.start(f"fedrl-{run}-qube-sim-{i}", self.image("qube-sim"), network, environment=container_env(
                    a.child(SimRigSettings, inherit=False, **common, rig_id=rig, seed=worker_seed(a.seed, i))))
            self.start(f"fedrl-{run}-worker-{i}", self.image("worker"), network, environment=container_env(
                a.child(WorkerSettings, inherit=False, **common, worker_id=f"w{i}", rig_id=rig,
                        reply_timeout=max(120.0, 4 * a.round_timeout))))
        chief = self.start(f"fedrl-{run}-chief", self.image("chief"), network, environment=container_env(
            a.child(ChiefSettings, inherit=False, **common, workers=workers, run_dir=Path("/runs/run"))))
        run_dir.mkdir(parents=True, exist_ok=True)
        relay = threading.Thread(target=stream_logs, args=(chief, run_dir / "chief.log"), daemon=True)
        relay.start()
        try:
            code = int(chief.wait(timeout=a.run_timeout)["StatusCode"])
        except requests.exceptions.ConnectionError:
            raise TimeoutError(f"run {run} took longer than {a.run_timeout:.0f} s") from None
        relay.join(timeout=5)
        copy_out(chief, "/runs/run", run_dir)
        save_logs(self.containers, run_dir / "logs")
        summary = RunSummary.read(run_dir) if (run_dir / SUMMARY).exists() else None
        return RunResult(workers, code, time.monotonic() - t0, run_dir, summary)


def container_env(settings: Settings) -> dict[str, str]:
    """A container's environment: its settings as FEDRL_* variables, output unbuffered."""
    return {**to_env(settings), "PYTHONUNBUFFERED": "1"}


def wait_healthy(container: Any, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        container.reload()
        state = container.attrs["State"]
        if state.get("Health", {}).get("Status") == "healthy":
            return
        if state["Status"] == "exited":
            raise RuntimeError(f"{container.name} exited: {container.logs(tail=20).decode(errors='replace')}")
        time.sleep(0.5)
    tail = container.logs(tail=20).decode(errors="replace")
    raise TimeoutError(f"{container.name} not healthy within {timeout:.0f} s; its log ends:\n{tail}")


def port_in_use(port: int) -> bool:
    try:
        socket.create_connection(("127.0.0.1", port), timeout=1).close()
    except OSError:
        return False
    return True


def stream_logs(container: Any, path: Path) -> None:
    """Print a container's output as it comes (and keep a copy)."""
    with path.open("wb") as fh:
        for chunk in container.logs(stream=True, follow=True):
            fh.write(chunk)
            sys.stdout.write(chunk.decode(errors="replace"))
            sys.stdout.flush()


def copy_out(container: Any, src: str, dest: Path) -> None:
    """Copy the folder ``src`` of a (stopped) container into ``dest``."""
    try:
        bits, _ = container.get_archive(src)
    except NotFound:
        print(f"!! {container.name} has no {src}", file=sys.stderr)
        return
    with tarfile.open(fileobj=io.BytesIO(b"".join(bits))) as tar:
        for member in tar.getmembers():
            name = Path(member.name)
            parts = name.parts[1:]  # drop the archive's top folder
            if not parts or not (member.isfile() or member.isdir()) or ".." in parts:
                continue
            target = dest.joinpath(*parts)
            if member.isdir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            extracted = tar.extractfile(member)
            if extracted is not None:
                target.write_bytes(extracted.read())


def save_logs(containers: list[Any], folder: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for container in containers:
        try:
            (folder / f"{container.name}.log").write_bytes(container.logs())
        except (NotFound, APIError):
            pass


@contextmanager
def interrupts_as_exceptions() -> Iterator[None]:
    """Turn SIGTERM into KeyboardInterrupt so that teardown runs for both."""
    def handler(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def print_table(results: list[RunResult]) -> None:
    print(f"\n{'workers':>7}  {'exit':>4}  {'all solved at':>13}  {'end':<20}  {'wall s':>7}  run folder")
    for r in results:
        solved = r.summary.episodes_to_all_solved if r.summary else None
        end = r.summary.end_reason if r.summary else "no summary"
        print(f"{r.workers:>7}  {r.code:>4}  {'-' if solved is None else solved:>13}  "
              f"{end:<20}  {r.wall_s:>7.1f}  {r.run_dir}")


@returns_code
def main(argv: list[str] | None = None) -> int:
    args = DockerSettings.load(argv, prog="python -m deploy.docker", description=DESCRIPTION)
    try:
        launcher = Launcher(args)
    except DockerException as err:
        print(f"deploy.docker: no Docker engine: {err}", file=sys.stderr)
        return 1
    results: list[RunResult] = []
    with interrupts_as_exceptions():
        try:
            if args.build:
                launcher.build(["chief", "worker"] + (["qube-sim"] if args.env == "qube" else []))
            for workers in args.workers:
                try:
                    results.append(launcher.run(workers))
                finally:
                    launcher.teardown()
        except KeyboardInterrupt:
            print("\ninterrupted; containers removed", file=sys.stderr)
            return 130
        except (DockerException, RuntimeError, TimeoutError) as err:
            print(f"deploy.docker: {err}", file=sys.stderr)
            return 1
        finally:
            launcher.teardown()
    print_table(results)
    return max((r.code for r in results), default=1)


if __name__ == "__main__":
    sys.exit(main())
