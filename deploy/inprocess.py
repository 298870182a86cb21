"""``python -m deploy.inprocess``: a whole federation in one process, for sweeps.

It starts one ChiefService and N WorkerServices, each in its own thread, on an in-memory hub (protocol/memory.py)
instead of an MQTT broker: the same services as ``make run``, unchanged, and every message goes through the same
msgpack codec. Only the broker, the sockets and the process start-ups are left out, and nothing times out (rounds
wait for every worker, as a sweep must be reproducible). It writes the same run folder (summary.json with ``"mode":
"in-process"``, metrics.jsonl, learning_curve.png, models/<id>.pt), which ``python -m chief.audit`` checks like any
other, without the chief's saved state (there is nothing to resume), plus timing.json for bench.runs: each worker's
own CPU seconds per episode and the chief's per round. For a given seed it gives the same per-worker episodes and
round records as a federation over MQTT (tests/e2e/test_inprocess_equivalence.py).
"""

from __future__ import annotations

import json
import math
import secrets
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import msgpack

from chief.edge import EdgeService
from chief.service import EXIT_ABORTED, EXIT_OK, ChiefService, Outputs
from chief.settings import ChiefSettings
from deploy.settings import InprocessSettings
from deploy.witness import Witness
from protocol import topics
from protocol.codec import RejectCounter, encode
from protocol.memory import Hub, MemoryConnection
from protocol.messages import RunStop
from protocol.transport import Connect, Handler
from runtime.model_file import ModelFileError
from runtime.records import RunSummary
from runtime.settings import returns_code
from worker.service import EXIT_ERROR, WorkerService
from worker.settings import WorkerSettings, handed_keys

RUN_ID = "inprocess"
#: Seconds the chief waits for every worker's hello (building N learners at once can take a while on a busy machine).
START_TIMEOUT = 600.0
#: Seconds the chief waits once every unfinished worker has failed or stopped before it ends the run as aborted. In
#: process nothing restarts a worker (and with round timeouts off a worker is offline only when it said so), so every
#: learner's result is already fixed and this only bounds the wait; over MQTT it is idle_timeout, 120 s.
IDLE_TIMEOUT = 2.0


def run_federation(s: InprocessSettings, *, plot: bool = True, progress: bool = False, tensorboard_files: bool = True,
                   models: bool = True, tolerate_failures: bool = False,
                   pace: dict[str, float] | None = None) -> RunSummary:
    """Run the federation ``s`` describes to its end; returns its summary (also written to ``s.run_dir``). The
    chief's, the edges' and the workers' settings are its children (Settings.child, as deploy.run_local builds
    them), made from ``s`` alone (nothing of this process's environment, as a container's): a warm start that does
    not fit the task is a ValueError before anything runs; a strategy that cannot be split runs flat (a note on
    stderr), worker i behind edge chief ``e{i mod edges}`` otherwise, each an EdgeService in its own thread, and the
    wire observed into GRADIENTS for the audit's exactness check. What is not the federation's: ``plot``,
    ``tensorboard_files`` (the TensorBoard event files, live as the chief writes them; the benchmarks leave them out
    of their timing) and ``progress`` (the chief's progress lines every 2 s, else only its last one) are the chief's
    outputs; ``models``: save each worker's mature model in ``run_dir/models/<id>.pt``, as make run does; ``pace``:
    worker -> how many times slower than its own pace it plays (a straggler, WorkerSettings.slowdown). A worker that
    fails (its rig could not reset, say) leaves the federation, and the run ends as aborted once no learner is left
    (IDLE_TIMEOUT); ``tolerate_failures``: return that run's summary, which says which workers did not solve (else a
    RuntimeError after the run, as for a bug)."""
    import torch  # after worker/'s check of the learn extra (one line where it is missing)

    torch.set_num_threads(1)
    edges, flat = s.tiering()
    if flat is not None:
        print(f"note: {flat}", file=sys.stderr)
    hub = Hub()
    key = secrets.token_hex(32)  # the run's key, as deploy/run_local.py makes one (protocol/auth.py)
    common: dict[str, Any] = {"run_id": RUN_ID, "run_key": key, "start_timeout": START_TIMEOUT}
    chiefs: dict[str, Any] = {**common, "round_timeout": math.inf}  # nothing times out: a sweep is reproducible
    chief_conn: list[_Timed] = []
    chief = ChiefService(
        s.child(ChiefSettings, inherit=False, **chiefs, idle_timeout=IDLE_TIMEOUT, edges=edges),
        connect=_timed(hub, topics.START, _answers, chief_conn),
        outputs=Outputs(state=False, tensorboard=tensorboard_files, plot=plot, progress=progress))
    services: dict[str, Callable[[], int]] = {"chief": chief.run}
    for e in range(edges):
        services[f"e{e}"] = EdgeService(s.child(ChiefSettings, inherit=False, **chiefs, role="edge",
                                                edge_id=f"e{e}", edges=0, run_dir=s.run_dir),
                                       connect=hub.connect).run
    witness = Witness(hub.connect, RUN_ID, s.run_dir) if edges else None
    worker_conns: dict[str, list[_Timed]] = {}
    for i in range(s.workers):
        wid = f"w{i}"
        worker_conns[wid] = []
        cfg = worker_settings(s, **{**common, **handed_keys(key, wid)}, worker_id=wid,
                              edge=f"e{i % edges}" if edges else None, slowdown=(pace or {}).get(wid, 1.0),
                              reply_timeout=math.inf, ack_timeout=math.inf, resend_interval=math.inf,
                              model_dir=s.run_dir / "models" if models else None)
        services[wid] = WorkerService(cfg, _timed(hub, topics.STATUS, _NewEpisode(), worker_conns[wid])).run
    codes = _run_threads(services)
    if codes["chief"] not in (EXIT_OK, EXIT_ABORTED):  # the workers (daemon threads) are told to stop, not awaited
        hub.route(topics.chief(RUN_ID, topics.STOP), encode(RunStop(
            run_id=RUN_ID, reason="the chief failed", episodes=0, all_solved=False, aborted=True,
            session=chief.session)))
        raise RuntimeError(f"the in-process chief failed (exit {codes['chief']!r})")
    for thread in [c for c in codes.values() if isinstance(c, threading.Thread)]:
        thread.join()
    if witness is not None:
        witness.save()
    failed = {w: c for w, c in codes.items() if c not in (EXIT_OK, EXIT_ABORTED)}
    if failed and not (tolerate_failures and all(c == EXIT_ERROR for c in failed.values())):
        raise RuntimeError(f"in-process workers failed: {failed}")
    summary = RunSummary.read(s.run_dir).model_copy(update={
        "run_id": s.run_dir.name, "mode": "in-process", "broker": None, "env_options": env_options(s) or None,
        "learner_set": s.learner_set or None})
    summary.write(s.run_dir)
    (s.run_dir / "timing.json").write_text(json.dumps(
        {"worker_s": {w: [round(x, 5) for x in c[0].seconds] for w, c in worker_conns.items() if c},
         "chief_s": [round(x, 5) for x in chief_conn[0].seconds]}) + "\n")
    return summary


_Threads = dict[str, Any]  # name -> exit code, the exception it raised, or its running thread


def _run_threads(services: dict[str, Callable[[], int]]) -> _Threads:
    """Start every service in a daemon thread (an interrupted caller does not hang on them); wait for the chief."""
    out: _Threads = {}

    def run(name: str, target: Callable[[], int]) -> None:
        try:
            out[name] = target()
        except BaseException as exc:  # handed to the caller
            out[name] = exc

    for name, target in services.items():
        thread = threading.Thread(target=run, args=(name, target), name=f"inprocess-{name}", daemon=True)
        out[name] = thread
        thread.start()
    chief = out["chief"]
    chief.join()
    return out


class _Timed(MemoryConnection):
    """A hub connection that notes its service's own CPU seconds per unit of work: its main thread's (the service
    publishes from it) plus its handlers' (decoding, on the delivery thread). A unit ends at a publication that
    ``ends`` accepts; the first ends at the first one on the topic ending with ``start``."""

    def __init__(self, hub: Hub, client_id: str, will: tuple[str, bytes] | None, rejects: RejectCounter | None,
                 start: str, ends: Callable[[str, bytes], bool]) -> None:
        super().__init__(hub, client_id, will, rejects)
        self.seconds: list[float] = []
        self._start, self._ends = start, ends
        self._since: float | None = None
        self._handlers_s = 0.0

    def subscribe(self, topic_filter: str, handler: Handler, qos: int = 1) -> None:
        def timed(topic: str, payload: bytes) -> None:
            began = time.thread_time()
            try:
                handler(topic, payload)
            finally:
                self._handlers_s += time.thread_time() - began

        super().subscribe(topic_filter, timed, qos)

    def publish(self, topic: str, payload: bytes, qos: int = 1, retain: bool = False) -> Any:
        now = time.thread_time() + self._handlers_s
        if self._since is None:
            if topic.endswith("/" + self._start):
                self._since = now
        elif self._ends(topic, payload):
            self.seconds.append(now - self._since)
            self._since = now
        return super().publish(topic, payload, qos, retain)


def _timed(hub: Hub, start: str, ends: Callable[[str, bytes], bool], into: list[_Timed]) -> Connect:
    """A protocol.transport.Connect that makes a _Timed connection and keeps it in ``into``."""
    def connect(client_id: str, will: tuple[str, bytes] | None = None, rejects: RejectCounter | None = None) -> _Timed:
        conn = _Timed(hub, client_id, will, rejects, start, ends)
        into.append(conn)
        return conn

    return connect


def _answers(topic: str, payload: bytes) -> bool:
    """The chief's unit of work: a round, ended by its answer."""
    return topic.rsplit("/", 1)[-1] in ("aggregate", "transfer")


class _NewEpisode:
    """A worker's unit of work: an episode, ended by its first submission (the CPU seconds of its answers' steps
    are counted with the next one's)."""

    def __init__(self) -> None:
        self.last = 0

    def __call__(self, topic: str, payload: bytes) -> bool:
        if not topic.endswith("/" + topics.UPDATE):
            return False
        episode = int(msgpack.unpackb(payload, raw=False)["episode"])
        new, self.last = episode > self.last, max(episode, self.last)
        return new


def worker_settings(s: InprocessSettings, **values: Any) -> WorkerSettings:
    """A worker's settings in the run ``s`` describes: its child, built from ``s`` and ``values`` alone."""
    return s.child(WorkerSettings, inherit=False, **values)


def env_options(s: InprocessSettings) -> dict[str, Any]:
    """The workers' task options of these settings (qube-local: the rig profile, randomisation and clock), as a
    worker derives them (WorkerSettings.env_options)."""
    return worker_settings(s).env_options()


@returns_code
def main(argv: list[str] | None = None) -> int:
    s = InprocessSettings.load(argv, prog="python -m deploy.inprocess", description=__doc__.splitlines()[0])
    options = env_options(s)
    if options:
        print(f"rigs: {', '.join(f'{k} {v}' for k, v in options.items())}")
    try:
        summary = run_federation(s, progress=True, tolerate_failures=True)
    except ModelFileError as err:  # a warm start's model that does not fit: one line, exit 2
        print(f"python -m deploy.inprocess: {err}", file=sys.stderr)
        return 2
    last, reason = summary.episodes_to_all_solved, summary.end_reason
    failed = [w.id for w in summary.workers if not w.solved and (w.detail or "").startswith("error")]
    outcome = (f"all workers solved by episode {last}" if last is not None else f"not all solved ({reason}"
               + (f"; failed: {', '.join(failed)}, see the lines above" if failed else "") + ")")
    print(f"{s.env} / {s.policy} / seed {s.seed}: {outcome}; {summary.wall_s or 0.0:.1f} s; results in {s.run_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
