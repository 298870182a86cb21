"""``python -m deploy.run_local`` (what ``make run`` calls): a whole federation on one machine.

Starts the embedded broker (unless FEDRL_BROKER points at one) with this run's own users and ACL, the live dashboard
(``services.dashboard``, its URL printed), the chief and N workers as separate processes (plus one simulated
QUBE-Servo 2 rig per worker, lockstep clock, when the env is ``qube``), relays the chief's live progress (restarting
a chief that died: it resumes from its saved state), prints a summary table at the end and leaves summary.json,
metrics.jsonl, learning_curve.png, the workers' mature models and every process's log in the run folder.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO

from chief import strategies
from protocol.cli import add_device_noise, add_run_options, env, parse_checked
from protocol.mqtt import BrokerAddress
from protocol.tasks import worker_seed
from services.broker.embedded import make_credentials, start_broker_process


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m deploy.run_local",
        description="Run a federation on this machine: embedded MQTT broker, chief and N workers as separate "
        "processes. Every option also reads the FEDRL_* variable named in its help.",
    )
    parser.add_argument("--workers", type=int, default=int(w) if (w := env("FEDRL_WORKERS", "")) else None,
                        help="number of workers (env FEDRL_WORKERS; default 4, or 3 for qube as in the paper)")
    add_run_options(parser, strategies.names())
    add_device_noise(parser)
    parser.add_argument("--broker", default=env("FEDRL_BROKER", ""),
                        help="use this broker (mqtt://host:port) instead of starting the embedded one "
                        "(env FEDRL_BROKER)")
    parser.add_argument("--run-id", default=env("FEDRL_RUN_ID", ""),
                        help="run id / topic prefix (env FEDRL_RUN_ID; default: derived from the start time)")
    parser.add_argument("--run-dir", type=Path, default=Path(p) if (p := env("FEDRL_RUN_DIR", "")) else None,
                        help="run folder (env FEDRL_RUN_DIR; default runs/<time>-<env>-<policy>-s<seed>)")
    parser.add_argument("--dashboard-port", type=dashboard_port, default=env("FEDRL_DASHBOARD_PORT", "0"),
                        help="port of the live dashboard on 127.0.0.1 (env FEDRL_DASHBOARD_PORT; default 0 = any "
                        "free port, its URL is printed; 'off' = no dashboard)")
    parser.add_argument("--dashboard-linger", type=float, default=float(env("FEDRL_DASHBOARD_LINGER", "0")),
                        help="keep the dashboard up this many seconds after the run ended, to look at the final "
                        "state (env FEDRL_DASHBOARD_LINGER, default 0)")
    args = parse_checked(parser, argv)
    if args.dashboard_linger < 0:
        parser.error("--dashboard-linger must be >= 0")
    if args.workers is None:
        args.workers = 3 if args.env == "qube" else 4
    if args.workers < 1:
        parser.error("--workers must be at least 1")
    stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    args.run_id = args.run_id or f"r{stamp}"
    if args.run_dir is None:
        args.run_dir = Path("runs") / f"{stamp}-{args.env}-{args.policy}-s{args.seed}"
    return args


def dashboard_port(text: str) -> int | None:
    """A port 0-65535 (0 = any free one), or None for 'off'."""
    if text.strip().lower() in ("off", "none", "no", "false"):
        return None
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a port 0-65535 or 'off', got {text!r}") from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"expected a port 0-65535 or 'off', got {port}")
    return port


class Fleet:
    """The child processes of one run; stops them all on exit."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = log_dir
        self.procs: dict[str, subprocess.Popen] = {}
        self._files: list[IO[bytes]] = []

    def start(self, name: str, argv: list[str], env_vars: dict[str, str], stream: bool = False) -> subprocess.Popen:
        out: int | IO[bytes] = subprocess.PIPE
        if not stream:
            fh = (self.log_dir / f"{name}.log").open("wb")
            self._files.append(fh)
            out = fh
        proc = subprocess.Popen([sys.executable, *argv], stdout=out, stderr=subprocess.STDOUT,
                                env={**os.environ, **env_vars})
        self.procs[name] = proc
        return proc

    def add(self, name: str, proc: subprocess.Popen) -> None:
        self.procs[name] = proc

    def stop(self, grace: float = 10.0) -> None:
        deadline = time.monotonic() + grace
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.terminate()
        for proc in self.procs.values():
            try:
                proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        for fh in self._files:
            fh.close()


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    run_dir: Path = args.run_dir
    log_dir = run_dir / "logs"
    log_dir.mkdir(parents=True, exist_ok=True)
    fleet = Fleet(log_dir)
    t0 = time.monotonic()
    worker_ids = [f"w{i}" for i in range(args.workers)]
    rigs = {i: f"rig{i}" for i in range(args.workers)} if args.env == "qube" else {}
    login: Callable[[str], dict[str, str]] = lambda user: {}  # noqa: E731  (an external broker: the caller's env)
    try:
        if args.broker:
            broker = str(BrokerAddress.from_env(args.broker))
            print(f"using the broker at {broker}")
        else:
            # This run's own users and ACL: nothing else on the machine can connect, let alone publish as the chief.
            creds = make_credentials(run_dir / "broker", args.run_id, worker_ids,
                                     {worker_ids[i]: rig for i, rig in rigs.items()})
            login = creds.env
            with (log_dir / "broker.log").open("wb") as broker_log:
                proc, port = start_broker_process(credentials=creds, stdout=broker_log, stderr=subprocess.STDOUT)
            fleet.add("broker", proc)
            broker = f"mqtt://127.0.0.1:{port}"
            print(f"embedded broker on {broker} (users and ACL of this run in {creds.folder})")
        common = {"FEDRL_BROKER": broker, "FEDRL_RUN_ID": args.run_id, "FEDRL_ENV": args.env,
                  "PYTHONUNBUFFERED": "1"}
        url_file = log_dir / "dashboard.url"
        if args.dashboard_port is not None:  # first, so that it sees the run start
            url_file.unlink(missing_ok=True)
            dashboard = fleet.start("dashboard", ["-m", "services.dashboard", "--host", "127.0.0.1", "--port",
                                                  str(args.dashboard_port), "--url-file", str(url_file)],
                                    {**common, **login("observer")})
        for i, rig in rigs.items():
            fleet.start(f"qube-sim-{rig}", ["-m", "services.qube_sim"], {
                **common, **login(rig), "FEDRL_RIG_ID": rig, "FEDRL_SEED": str(worker_seed(args.seed, i)),
                "FEDRL_QUBE_CLOCK": env("FEDRL_QUBE_CLOCK", "lockstep")})
        for i, wid in enumerate(worker_ids):
            fleet.start(f"worker-{wid}", ["-m", "worker"], {
                **common, **login(wid), "FEDRL_WORKER_ID": wid, "FEDRL_DEVICE_NOISE": str(args.device_noise),
                "FEDRL_MODEL_DIR": str(run_dir / "models"), "FEDRL_RIG_ID": rigs.get(i, ""),
                "FEDRL_REPLY_TIMEOUT": str(max(120.0, 4 * args.round_timeout))})
        print(f"run {args.run_id}: {args.workers} workers on {args.env}, policy {args.policy}, seed {args.seed}; "
              f"logs in {log_dir}")
        if args.dashboard_port is not None:
            url = wait_for_url(dashboard, url_file)
            print(f"dashboard: {url}" if url else f"!! the dashboard did not start; see {log_dir / 'dashboard.log'}",
                  flush=True)
        chief_env = {
            **common, **login("chief"), "FEDRL_WORKERS": str(args.workers), "FEDRL_POLICY": args.policy,
            "FEDRL_SEED": str(args.seed), "FEDRL_MAX_EPISODES": str(args.max_episodes),
            "FEDRL_ROUND_TIMEOUT": str(args.round_timeout), "FEDRL_RUN_DIR": str(run_dir)}
        restarts = 0
        while True:
            chief = fleet.start("chief", ["-m", "chief"], chief_env, stream=True)
            code = relay(chief, log_dir / "chief.log", fleet)
            if code in CHIEF_FINAL_CODES or (run_dir / "summary.json").exists() or restarts >= MAX_CHIEF_RESTARTS:
                break
            restarts += 1
            print(f"!! the chief died (exit code {code}); restarting it ({restarts} of {MAX_CHIEF_RESTARTS}): it "
                  "resumes the run from its saved state", flush=True)
        wall = time.monotonic() - t0
        summary_path = run_dir / "summary.json"
        if not summary_path.exists():
            print(f"the chief exited with code {code} and wrote no summary; see {log_dir}", file=sys.stderr)
            return code or 1
        print_summary(json.loads(summary_path.read_text()), run_dir, wall)
        if args.dashboard_port is not None and args.dashboard_linger > 0 and dashboard.poll() is None:
            print(f"the dashboard stays up for {args.dashboard_linger:.0f} s (Ctrl-C ends it sooner)", flush=True)
            time.sleep(args.dashboard_linger)
        return code
    except KeyboardInterrupt:
        print("\ninterrupted; stopping every process", file=sys.stderr)
        fleet.stop(grace=5)
        return 130
    finally:
        fleet.stop()


def wait_for_url(proc: subprocess.Popen, url_file: Path, timeout: float = 20.0) -> str | None:
    """The URL the dashboard wrote once it served its page, or None when it exited or took too long."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if url_file.exists():
            return url_file.read_text().strip()
        if proc.poll() is not None:
            return None
        time.sleep(0.05)
    return None


#: Chief exit codes that end a run (done, bad setting, no workers, aborted); any other means it died.
CHIEF_FINAL_CODES = (0, 2, 3, 4)
MAX_CHIEF_RESTARTS = 5


def relay(chief: subprocess.Popen, log_path: Path, fleet: Fleet) -> int:
    """Print the chief's progress as it comes and keep a copy; warn when a worker dies."""
    assert chief.stdout is not None
    reported: set[str] = set()
    with log_path.open("ab") as log_file:
        for line in iter(chief.stdout.readline, b""):
            log_file.write(line)
            log_file.flush()
            sys.stdout.write(line.decode(errors="replace"))
            sys.stdout.flush()
            for name, proc in fleet.procs.items():
                code = proc.poll()
                if code not in (None, 0) and name not in reported:
                    reported.add(name)
                    print(f"!! {name} exited with code {code}; see {fleet.log_dir / (name + '.log')}", flush=True)
    return chief.wait()


def print_summary(summary: dict, run_dir: Path, wall: float) -> None:
    print()
    print(f"{'worker':<12}{'solved':<8}{'episodes':>9}{'final PI':>11}  state")
    for w in summary["workers"]:
        pi = "-" if w.get("final_pi") is None else f"{w['final_pi']:.1f}"
        print(f"{w['id']:<12}{'yes' if w['solved'] else 'no':<8}{w['episodes']:>9}{pi:>11}  {w['state']}")
    all_solved = summary.get("episodes_to_all_solved")
    print(f"\n{summary['env']} / {summary['policy']} / seed {summary['seed']}: "
          + (f"all workers solved by episode {all_solved}" if all_solved is not None
             else f"not all solved ({summary['end_reason']})")
          + f"; chief wall time {summary['wall_s']:.1f} s, launcher {wall:.1f} s")
    print(f"results: {run_dir}/summary.json, metrics.jsonl, learning_curve.png")


if __name__ == "__main__":
    sys.exit(main())
