"""``python -m deploy.run_local`` (what ``make run`` calls): a whole federation on one machine.

Starts the embedded broker (unless FEDRL_BROKER points at one) with this run's own users and ACL, the live dashboard
(``services.dashboard``, its URL printed), the chief and N workers as separate processes (plus one simulated
QUBE-Servo 2 rig per worker, lockstep clock, when the env is ``qube``), relays the chief's live progress (restarting
a chief that died: it resumes from its saved state), prints a summary table at the end and leaves summary.json,
metrics.jsonl, learning_curve.png, the workers' mature models and every process's log in the run folder.

Ctrl-C reaches only the launcher (each child runs in its own process group): it passes the interrupt on to the chief,
which ends the run resumably (summary.json with end reason ``interrupted``, the curve, its saved state; each worker
saves its own in ``workers/``, worker/resume.py), and prints the command that resumes the run. A second Ctrl-C stops
every process at once. SIGTERM (``kill``, ``timeout``) and SIGHUP (a closed terminal, a dropped ssh connection) are
handled as Ctrl-C is; after a SIGHUP the launcher's output goes to ``logs/launcher.log`` (the terminal is gone).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import os
import secrets
import shlex
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

from chief import failover
from chief.claim import EXIT_CLAIMED
from chief.service import EXIT_INTERRUPTED
from chief.settings import ChiefSettings
from deploy import sites
from deploy.forked import ForkedProcess
from deploy.settings import RIG_TASKS, LocalRunSettings, default_workers
from deploy.witness import Witness
from protocol.messages import INTERRUPTED
from protocol.mqtt import DEFAULT_BROKER, PROBE_TIMEOUT, BrokerAddress, connect_problem
from protocol.tasks import worker_seed
from protocol.transport import Connect
from runtime.cli import exits_on_storage_faults
from runtime.records import SUMMARY, RigTime, RunSummary
from runtime.settings import MqttSettings, RunMqttSettings, Settings, env_name, flags, returns_code, to_env
from runtime.storage import EXIT_STORAGE, storage_errors
from services.broker.embedded import make_credentials, start_broker_process
from services.dashboard.service import wait_for_url
from services.dashboard.settings import DashboardSettings
from services.qube_sim.settings import SimRigSettings
from worker.settings import WorkerSettings, handed_keys


def load(argv: list[str] | None = None) -> LocalRunSettings:
    """The launcher's settings, with the run's defaults filled in (worker count, run id, run folder)."""
    s = LocalRunSettings.load(argv, prog="python -m deploy.run_local")
    stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    return s.model_copy(update={
        "workers": s.workers or default_workers(s.env),
        "run_id": s.run_id or f"r{stamp}",
        "run_dir": s.run_dir or Path("runs") / f"{stamp}-{s.env}-{s.policy}-s{s.seed}"})


class Fleet:
    """The child processes of one run; stops them all on exit."""

    def __init__(self, log_dir: Path, fork_workers: bool = False) -> None:
        self.log_dir = log_dir
        self.fork_workers = fork_workers
        self.procs: dict[str, subprocess.Popen | ForkedProcess] = {}
        self.started: dict[str, tuple[str, Settings]] = {}  # name -> (module, settings): to start it again
        self._files: list[IO[bytes]] = []

    def start(self, name: str, module: str, settings: Settings, stream: bool = False) -> subprocess.Popen:
        """``python -m module`` with ``settings`` as its FEDRL_* variables, in its own process group (a Ctrl-C in
        the terminal reaches the launcher only, which decides who hears of it). Logs are appended to: a resumed
        run keeps the first part's. With ``fork_workers``, a worker is forked from the fork server instead
        (deploy/forked.py)."""
        self.started[name] = (module, settings)
        env = {**os.environ, **to_env(settings), "PYTHONUNBUFFERED": "1"}
        log = self.log_dir / f"{name}.log"
        if self.fork_workers and module == "worker" and not stream:
            forked = ForkedProcess(module, env, log)
            self.procs[name] = forked
            return forked  # type: ignore[return-value]  # Popen's interface, as far as the launcher uses it
        out: int | IO[bytes] = subprocess.PIPE
        if not stream:
            fh = log.open("ab")
            self._files.append(fh)
            out = fh
        proc = subprocess.Popen([sys.executable, "-m", module], stdout=out, stderr=subprocess.STDOUT, env=env,
                                process_group=0)
        self.procs[name] = proc
        return proc

    def start_again(self, name: str) -> subprocess.Popen:
        """Start a child that ended again, as it was started (its log appended to)."""
        module, settings = self.started[name]
        return self.start(name, module, settings)

    def add(self, name: str, proc: subprocess.Popen | ForkedProcess) -> None:
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


def stop_like_ctrl_c(log_dir: Path) -> dict[int, Any]:
    """Handle SIGTERM and SIGHUP as Ctrl-C (a KeyboardInterrupt): the run ends resumably, with its summary and its
    resume command, and no process of it is left behind. After a SIGHUP the terminal is gone: what the launcher
    prints from then on is appended to ``log_dir/launcher.log``. Returns the handlers it replaced."""

    def handler(signum: int, frame: object) -> None:
        if signum == signal.SIGHUP and not getattr(sys.stdout, "name", "").endswith("launcher.log"):
            sys.stdout = sys.stderr = open(log_dir / "launcher.log", "a", buffering=1)  # to the end
        raise KeyboardInterrupt

    return {sig: signal.signal(sig, handler) for sig in (signal.SIGTERM, signal.SIGHUP)}


@returns_code
@exits_on_storage_faults("python -m deploy.run_local")
def main(argv: list[str] | None = None) -> int:
    s = load(argv)
    assert s.workers is not None and s.run_id is not None and s.run_dir is not None  # load fills them in
    check_children(s)  # before anything starts: a bad setting is one line, exit 2
    if s.init_model is not None and not warm_start_fits(s):
        return 2
    run_dir: Path = s.run_dir
    log_dir = run_dir / "logs"
    log_dir.mkdir(parents=True, exist_ok=True)
    found = stop_like_ctrl_c(log_dir)
    fleet = Fleet(log_dir, fork_workers=s.fork_workers)
    t0 = time.monotonic()
    worker_ids = [f"w{i}" for i in range(s.workers)]
    rigs = {i: f"rig{i}" for i in range(s.workers)} if s.env == "qube" else {}
    edges = edge_of(s, worker_ids)
    try:
        reached = start_broker(s, fleet, worker_ids, rigs, edges)
        if reached is None:  # nothing started: leave no empty run folder behind
            for folder in (log_dir, run_dir):
                with contextlib.suppress(OSError):
                    folder.rmdir()
            return 1
        broker, login = reached
        common: dict[str, Any] = {"broker": broker, "run_id": s.run_id}
        # The run's key (protocol/auth.py): FEDRL_RUN_KEY if set, else a new one; the chief, the edges and the
        # dashboard get it in their environment (to_env), never on a command line; each worker only its own key and
        # the chief key (start_devices).
        key = s.child(ChiefSettings, **common, run_dir=run_dir).run_key or secrets.token_hex(32)
        url_file = log_dir / "dashboard.url"
        if s.dashboard_port is not None:  # first, so that it sees the run start
            url_file.unlink(missing_ok=True)
            dashboard = fleet.start("dashboard", "services.dashboard", s.child(
                DashboardSettings, **common, **login("observer"), run_key=key, dashboard_host="127.0.0.1",
                dashboard_port=s.dashboard_port, dashboard_url_file=url_file))
        for k, e in enumerate(sorted(set(edges.values()), key=lambda e: int(e[1:]))):
            # Before the workers (it passes the root's RunStart on to them); with sites, at its workers' site (its
            # own: no other edge can stand in for it there, chief/failover.py).
            at = {**common, "broker": s.site_brokers[k], "site": e} if s.site_brokers else common
            fleet.start(f"edge-{e}", "chief", s.child(ChiefSettings, **at, **login(e), run_key=key,
                                                      role="edge", edge_id=e, edges=0, run_dir=run_dir))
        witness = (Witness(_observer(broker, s.run_id, login), s.run_id, run_dir) if s.witness and edges
                   else None)
        start_devices(s, fleet, common, login, key, worker_ids, rigs, edges)
        print(f"run {s.run_id}: {s.workers} workers on {s.env}{rigs_of(s)}, learner {s.algo}, policy {s.policy}, "
              f"seed {s.seed}; logs in {log_dir}")
        if s.dashboard_port is not None:
            url = wait_for_url(dashboard, url_file)
            print(f"dashboard: {url}" if url else f"!! the dashboard did not start; see {log_dir / 'dashboard.log'}",
                  flush=True)
        code = run_chief(fleet, s.child(ChiefSettings, **common, **login("chief"), run_key=key, run_dir=run_dir,
                                        edges=len(set(edges.values()))), run_dir)
        if witness is not None:
            print(f"witness: every gradient and root aggregate in {witness.save()}")
        code = report(s, code, time.monotonic() - t0)
        ended = (run_dir / SUMMARY).exists() and code != EXIT_INTERRUPTED
        if ended and s.dashboard_port is not None and s.dashboard_linger > 0 and dashboard.poll() is None:
            print(f"the dashboard stays up for {s.dashboard_linger:.0f} s (Ctrl-C ends it sooner)", flush=True)
            try:
                time.sleep(s.dashboard_linger)
            except KeyboardInterrupt:  # the run is over: ending the wait early keeps its exit code
                print("\nthe dashboard stops", file=sys.stderr)
        return code
    except KeyboardInterrupt:
        print("\ninterrupted; stopping every process", file=sys.stderr)
        fleet.stop(grace=5)
        return 130
    finally:
        # Stopping already: a repeated kill must not cut the stop short. The handlers it found come back afterwards,
        # so that a caller in this process (a test, a benchmark) and what it starts later still end on SIGTERM.
        for sig in found:
            signal.signal(sig, signal.SIG_IGN)
        try:
            fleet.stop()
        finally:
            for sig, handler in found.items():
                signal.signal(sig, handler)


def check_children(s: LocalRunSettings) -> None:
    """Build every child's settings as it will read them (the launcher's, then its own FEDRL_* variables and .env
    file), so that a bad one is refused (one line, SystemExit 2) before a broker or a process starts."""
    assert s.run_id is not None and s.run_dir is not None
    where: dict[str, Any] = {"broker": s.broker or DEFAULT_BROKER, "run_id": s.run_id}
    s.child(ChiefSettings, **where, run_dir=s.run_dir)
    s.child(WorkerSettings, **where, worker_id="w0")
    if s.env == "qube" and s.simulate_rigs:
        for i in range(s.workers or 0):  # each rig: a profile or model folder must hold its file
            s.child(SimRigSettings, **where, rig_id=f"rig{i}", seed=worker_seed(s.seed, i))
    if s.dashboard_port is not None:
        s.child(DashboardSettings, **where, dashboard_host="127.0.0.1", dashboard_port=s.dashboard_port)


def rigs_of(s: LocalRunSettings) -> str:
    """The simulated rigs of a QUBE-Servo 2 run as the start line says them (empty for the other tasks)."""
    if s.env not in RIG_TASKS:
        return ""
    randomize = "" if s.randomize is None else f", randomize {s.randomize:g}"
    return f" (rig profile {s.rig_profile or 'ideal'}{randomize}, clock {s.qube_clock})"


def warm_start_fits(s: LocalRunSettings) -> bool:
    """Whether ``--init-model`` names a model for this task (else one line on stderr)."""
    from worker.model import open_init_model  # torch: only for a warm start

    assert s.init_model is not None
    try:
        init, _ = open_init_model(s.init_model, s.env, algo=s.algo, qube_actions=s.qube_actions)
    except ValueError as err:
        print(f"python -m deploy.run_local: {err}", file=sys.stderr)
        return False
    print(f"warm start: every worker from {init.file} (networks {init.digest[:12]})")
    return True


Login = Callable[[str], dict[str, Any]]


def edge_of(s: LocalRunSettings, worker_ids: list[str]) -> dict[str, str]:
    """A tiered run's worker -> edge chief (worker i behind ``e<i mod N>``); empty for a flat run, and for a strategy
    that cannot be split (after a note saying so)."""
    edges, flat = s.tiering()
    if flat is not None:
        print(f"note: {flat}", file=sys.stderr)
    return {w: f"e{i % edges}" for i, w in enumerate(worker_ids)} if edges else {}


def _observer(broker: str, run_id: str, login: Login) -> Connect:
    """A Connect for a read-only MQTT client of the run (the dashboard's login)."""
    return RunMqttSettings.given(broker=broker, run_id=run_id, **login("observer")).connector()


def start_broker(s: LocalRunSettings, fleet: Fleet, worker_ids: list[str], rigs: dict[int, str],
                 edges: dict[str, str] | None = None) -> tuple[str, Login] | None:
    """The broker's URL and the login of each process: FEDRL_BROKER's (None, after one line, when it cannot be
    reached), or an embedded broker with this run's own users and ACL."""
    assert s.run_dir is not None and s.run_id is not None
    if s.broker:
        address = BrokerAddress.parse(s.broker)
        # An MQTT CONNECT with the login and TLS settings of those who connect there: the chief, a site's workers.
        logins: list[tuple[str, str, MqttSettings]] = [
            (s.broker, "FEDRL_BROKER / --broker", s.child(ChiefSettings, broker=s.broker, run_id=s.run_id,
                                                          run_dir=s.run_dir)),
            *((u, "--site-brokers", s.child(WorkerSettings, broker=u, run_id=s.run_id)) for u in s.site_brokers)]
        for url, flag, login in logins:
            problem = connect_problem(login.address(), timeout=BROKER_PROBE_S)
            if problem is not None:  # before anything starts: restarts and resumes are for brokers lost mid-run
                print(f"cannot reach the MQTT broker at {BrokerAddress.parse(url)}: {problem} (check {flag})",
                      file=sys.stderr)
                return None
        print(f"using the broker at {address}" + (f", the workers those of {len(s.site_brokers)} sites"
                                                    if s.site_brokers else ""))
        return s.broker, lambda user: {}  # an external broker: the caller's login
    # This run's own users and ACL: nothing else on the machine can connect, let alone publish as the chief.
    with storage_errors(s.run_dir / "broker"):  # a write names no file: name the folder
        creds = make_credentials(s.run_dir / "broker", s.run_id, worker_ids,
                                 {worker_ids[i]: rig for i, rig in rigs.items()}, edges)
    with (fleet.log_dir / "broker.log").open("ab") as broker_log:
        proc, port = start_broker_process(credentials=creds, stdout=broker_log, stderr=subprocess.STDOUT,
                                          process_group=0)  # as Fleet.start: Ctrl-C is the launcher's
    fleet.add("broker", proc)
    broker = f"mqtt://127.0.0.1:{port}"
    print(f"embedded broker on {broker} (users and ACL of this run in {creds.folder})")
    return broker, creds.login


def start_devices(s: LocalRunSettings, fleet: Fleet, common: dict[str, Any], login: Login, key: str,
                  worker_ids: list[str], rigs: dict[int, str], edges: dict[str, str] | None = None) -> None:
    """The simulated rigs and the workers (worker i drives rig i), each on its site's broker when there are sites
    (``--site-brokers``, round robin), where a worker resends an unanswered update every deploy.sites.RESEND_INTERVAL
    seconds unless told otherwise (what a dying core took with it, nobody at a site saw go)."""
    assert s.run_dir is not None
    at_site = [{**common, "broker": s.site_brokers[i % len(s.site_brokers)]} if s.site_brokers else common
               for i in range(len(worker_ids))]
    for i, rig in (rigs.items() if s.simulate_rigs else ()):
        fleet.start(f"qube-sim-{rig}", "services.qube_sim", s.child(
            SimRigSettings, **at_site[i], **login(rig), rig_id=rig, seed=worker_seed(s.seed, i)))
    for i, wid in enumerate(worker_ids):
        worker = s.child(WorkerSettings, **at_site[i], **login(wid), worker_id=wid, model_dir=s.run_dir / "models",
                         state_dir=s.run_dir / "workers", rig_id=rigs.get(i),
                         reply_timeout=max(120.0, 4 * s.round_timeout), edge=(edges or {}).get(wid),
                         **handed_keys(key, wid))
        if s.site_brokers and "resend_interval" not in worker.model_fields_set:  # unless FEDRL_RESEND_INTERVAL says
            worker = worker.model_copy(update={"resend_interval": sites.RESEND_INTERVAL})
        fleet.start(f"worker-{wid}", "worker", worker)


def run_chief(fleet: Fleet, chief: Settings, run_dir: Path) -> int:
    """Run the chief to its end, relaying its progress; a chief that died is restarted (it resumes the run)."""
    restarts = 0
    while True:
        code = relay(fleet.start("chief", "chief", chief, stream=True), fleet.log_dir / "chief.log", fleet)
        if code in CHIEF_FINAL_CODES or (run_dir / SUMMARY).exists() or restarts >= MAX_CHIEF_RESTARTS:
            return code
        restarts += 1
        print(f"!! the chief died (exit code {code}); restarting it ({restarts} of {MAX_CHIEF_RESTARTS}): it "
              "resumes the run from its saved state", flush=True)


def report(s: LocalRunSettings, code: int, wall: float) -> int:
    """The summary table and next steps (or why there is none, or how to resume); the launcher's exit code."""
    assert s.run_dir is not None and s.run_id is not None
    summary_path = s.run_dir / SUMMARY
    if code in (2, EXIT_CLAIMED):  # refused before it ran (its line is above): a summary there is an earlier part's
        print(f"the chief refused to run (exit code {code}); see above or {s.run_dir / 'logs' / 'chief.log'}",
              file=sys.stderr)
        return code
    if not summary_path.exists():
        hint = (f"; free space or fix the folder's permissions, then the same command with --run-id {s.run_id} "
                f"--run-dir {s.run_dir} resumes from the saved state") if code == EXIT_STORAGE else ""
        print(f"the chief exited with code {code} and wrote no summary; see {s.run_dir / 'logs'}{hint}",
              file=sys.stderr)
        return code or 1
    summary = RunSummary.read(s.run_dir)
    if s.learner_set and summary.learner_set != s.learner_set:  # the chief never sees the workers' learner settings
        summary = summary.model_copy(update={"learner_set": s.learner_set})
        summary.write(s.run_dir)
    print_summary(summary, s, wall)
    if summary.end_reason == INTERRUPTED:
        print(f"\nthe run stopped on a storage fault after {summary.rounds} rounds (the chief's log names it); once "
              "there is room, resume it:" if code == EXIT_STORAGE else
              f"\nthe run was interrupted after {summary.rounds} rounds; its state is saved. To resume it:")
        print(f"  {resume_command(s)}", flush=True)
        return EXIT_STORAGE if code == EXIT_STORAGE else EXIT_INTERRUPTED
    return code


#: Seconds the launcher waits for the broker's answer to its MQTT CONNECT before it gives up (the run has not started).
BROKER_PROBE_S = PROBE_TIMEOUT


#: Chief exit codes that end a run (done, bad setting, no workers, aborted, storage fault, another chief holds the
#: run, interrupted); any other means it died. A storage fault is not retried: the chief's state is intact, so the
#: same command resumes once there is room.
CHIEF_FINAL_CODES = (0, 2, 3, 4, EXIT_STORAGE, EXIT_CLAIMED, EXIT_INTERRUPTED)
MAX_CHIEF_RESTARTS = 5


def relay(chief: subprocess.Popen, log_path: Path, fleet: Fleet) -> int:
    """Print the chief's progress as it comes and keep a copy; warn when a worker dies. A Ctrl-C goes on to the
    chief, which ends the run resumably, and the relay goes on until it has; a second one propagates."""
    try:
        _relay(chief, log_path, fleet)
    except KeyboardInterrupt:
        print("\ninterrupted: the chief saves the run and writes its summary (Ctrl-C again stops every process at "
              "once)", file=sys.stderr, flush=True)
        chief.send_signal(signal.SIGINT)
        _relay(chief, log_path, fleet)
    return chief.wait()


def _relay(chief: subprocess.Popen, log_path: Path, fleet: Fleet) -> None:
    assert chief.stdout is not None
    reported: set[str] = set()
    restarts: dict[str, int] = {}
    with log_path.open("ab") as log_file:
        for line in iter(chief.stdout.readline, b""):
            log_file.write(line)
            log_file.flush()
            text = line.decode(errors="replace")
            sys.stdout.write(text)
            sys.stdout.flush()
            for name, proc in fleet.procs.items():
                code = proc.poll()
                if code not in (None, 0, EXIT_INTERRUPTED) and name not in reported:  # 130: stopped with the run
                    reported.add(name)
                    print(f"!! {name} exited with code {code}; see {fleet.log_dir / (name + '.log')}", flush=True)
            edge = failover.dead_edge_in(text)
            if edge is not None:
                _start_edge_again(fleet, f"edge-{edge}", restarts, reported)


#: Times the launcher starts a dead edge chief again in one run (each once the root has found it dead).
MAX_EDGE_RESTARTS = 3


def _start_edge_again(fleet: Fleet, name: str, restarts: dict[str, int], reported: set[str]) -> None:
    """Start an edge chief that died again, once the root has found it dead (its workers have gone to a stand-in
    then, or wait for it where its site has no other edge): it rejoins at the root's open round (chief/failover.py)."""
    proc = fleet.procs.get(name)
    if proc is None or proc.poll() in (None, 0, EXIT_INTERRUPTED):
        return  # not ours, alive (a silence, not a death: the root takes it back when it speaks), or ended with the run
    if restarts.get(name, 0) >= MAX_EDGE_RESTARTS:
        print(f"!! {name} died again: not started again (it was {MAX_EDGE_RESTARTS} times)", flush=True)
        return
    restarts[name] = restarts.get(name, 0) + 1
    reported.discard(name)
    fleet.start_again(name)
    print(f"!! {name} started again ({restarts[name]} of {MAX_EDGE_RESTARTS}): it rejoins at the root's round",
          flush=True)


def this_python() -> str:
    """This interpreter as a user would type it here: relative under the current folder (``.venv/bin/python``),
    else its absolute path (never a bare ``python``, which may be another interpreter without the packages)."""
    return os.path.relpath(sys.executable) if Path(sys.executable).is_relative_to(Path.cwd()) else sys.executable


#: Settings a printed command does not carry over: the run's identity (a new run gets its own, a resume names it). A
#: warm start is carried, except by the command that starts a run from this one (it names its own model).
NOT_CARRIED = frozenset({"run_id", "run_dir"})
#: The processes of a run, which read their own FEDRL_* variables beyond the settings the launcher hands them.
CHILDREN: tuple[type[Settings], ...] = (ChiefSettings, WorkerSettings, SimRigSettings, DashboardSettings)


def run_variables(s: LocalRunSettings) -> dict[str, str]:
    """The FEDRL_* variables that start a run with this one's settings: each of the launcher's settings that is not
    its default (flag, variable or .env file alike), then each variable a child process of the run read for itself
    (a sim rig's loop timing, the log level...). Secrets (variable-only settings) stay where they are."""
    fields = LocalRunSettings.model_fields
    given, defaults = to_env(s), to_env(LocalRunSettings.model_construct())
    out = {var: given[var] for name, field in fields.items()
           if name not in NOT_CARRIED and flags(name, field) and (var := env_name(name, field)) is not None
           and given[var] != defaults[var]}
    if s.workers == default_workers(s.env):
        out.pop(env_name("workers", fields["workers"]) or "", None)
    children = [c for c in CHILDREN if (c is not SimRigSettings or s.env == "qube")
                and (c is not DashboardSettings or s.dashboard_port is not None)]
    for cls in children:
        for name, field in cls.model_fields.items():
            var = env_name(name, field)
            if name in fields or var is None or var in out or not flags(name, field):
                continue
            if (value := s.variable(var)) is not None:
                out[var] = value
    return out


def run_command(s: LocalRunSettings, tail: list[str], **values: str) -> str:
    """A shell command that starts a launcher with this run's settings (:func:`run_variables`), then ``values``
    (more FEDRL_* variables), then ``tail`` (``make run``, or this interpreter's ``-m deploy.run_local ...``): what
    every command the launcher prints is made of."""
    variables = {**run_variables(s), **values}
    return " ".join([*(f"{var}={shlex.quote(value)}" for var, value in variables.items()), shlex.join(tail)])


def resume_command(s: LocalRunSettings) -> str:
    """The command that resumes this run: its settings, and ``--run-id`` and ``--run-dir`` naming it."""
    assert s.run_id is not None and s.run_dir is not None
    return run_command(s, [this_python(), "-m", "deploy.run_local", "--run-id", s.run_id, "--run-dir", str(s.run_dir)])


def warm_start_command(s: LocalRunSettings, init_model: Path) -> str:
    """The command that starts a new run with this run's settings from ``init_model`` (a model or a run folder)."""
    return run_command(s, ["make", "run"], FEDRL_INIT_MODEL=str(init_model))


def linger_command(s: LocalRunSettings, seconds: float = 600) -> str:
    """The command that runs this run's settings again with the dashboard kept up ``seconds`` after the end."""
    on = {} if s.dashboard_port is not None else {"FEDRL_DASHBOARD_PORT": "0"}
    return run_command(s, ["make", "run"], **on, FEDRL_DASHBOARD_LINGER=f"{seconds:g}")


def print_summary(summary: RunSummary, s: LocalRunSettings, wall: float) -> None:
    assert s.run_dir is not None
    run_dir = s.run_dir
    print()
    print(f"{'worker':<12}{'solved':<8}{'episodes':>9}{'final PI':>11}  state")
    for w in summary.workers:
        pi = "-" if w.final_pi is None else f"{w.final_pi:.1f}"
        print(f"{w.id:<12}{'yes' if w.solved else 'no':<8}{w.episodes:>9}{pi:>11}  {w.state}")
    all_solved = summary.episodes_to_all_solved
    print(f"\n{summary.env} / {summary.policy} / seed {summary.seed}: "
          + (f"all workers solved by episode {all_solved}" if all_solved is not None
             else f"not all solved ({summary.end_reason})")
          + f"; chief wall time {summary.wall_s or 0.0:.1f} s, launcher {wall:.1f} s")
    print_rig_time(summary)
    print(f"results: {run_dir}/summary.json, metrics.jsonl, learning_curve.png")
    print_next_steps(summary, s)


def print_rig_time(summary: RunSummary) -> None:
    """QUBE-Servo 2 tasks: each rig's time (balance + reset = rig time; idle waiting for the federation) and the last
    rig's, from summary.json (nothing for the gymnasium tasks)."""
    rigs: list[tuple[str, RigTime]] = [(w.id, w.rig) for w in summary.workers if w.rig]
    if not rigs:
        return
    print(f"\n{'rig time':<12}{'balance steps':>14}{'balance s':>11}{'reset s':>10}{'rig s':>10}{'idle s':>10}")
    last = summary.last_rig
    for wid, r in rigs + ([(f"last: {last.id}", last)] if last else []):
        idle = f"{r.idle_s:.1f}" + ("*" if r.idle == "modelled" else "")
        print(f"{wid:<12}{r.balance_steps:>14}{r.balance_s:>11.1f}{r.reset_s:>10.1f}{r.rig_s:>10.1f}{idle:>10}")
    if any(r.idle == "modelled" for _, r in rigs):
        print("(* idle modelled on the simulated clock: a round closes when its slowest rig is ready)")


def print_next_steps(summary: RunSummary, s: LocalRunSettings) -> None:
    """The footer: how to evaluate a controller, audit the run, view TensorBoard, warm-start from this run and keep
    the dashboard up (the last two with every setting of this run, run_command)."""
    assert s.run_dir is not None
    run_dir, py = s.run_dir, this_python()
    solved = [w.id for w in summary.workers if w.solved]
    print("\nnext steps:")
    if solved:  # the model records its task (a rig's controller runs on the in-process rig)
        print(f"  evaluate a controller:  {py} -m worker.evaluate {run_dir}/models/{solved[0]}.pt")
        print(f"  start a run from it:    {warm_start_command(s, run_dir)}")
    print(f"  audit the run:          {py} -m chief.audit {run_dir}")
    print(f"  TensorBoard:            make tensorboard RUN={run_dir}   (installs the viewer first)")
    print(f"  keep the dashboard up:  {linger_command(s)}   (seconds after the run ended)")

if __name__ == "__main__":
    sys.exit(main())
