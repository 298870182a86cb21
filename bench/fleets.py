"""A fleet of simulated devices spread over processes (bench/scale.py).

One process cannot hold 1,024 MQTT devices: paho watches its sockets with select(), which fails past file descriptor
1023, and a thousand network threads share one interpreter lock. ``SpreadFleet`` starts one process per slice of at
most ``per_process`` devices (``python -m bench.fleets``, each a bench.cost.ScriptedFleet of its slice) and drives
them in step over their pipes, one JSON line per command and answer: ``join`` (hellos until the RunStart), ``round``
(every device publishes its update at once, waits for the answer; the process then takes the aggregate for the next
round's receipts) and ``stop``. Times are CLOCK_MONOTONIC (time.monotonic), one clock across the processes.
"""

from __future__ import annotations

import argparse
import json
import queue
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from typing import IO, Any

import numpy as np

#: Devices per process: well under select()'s 1,024 descriptors, and few enough network threads per interpreter.
PER_PROCESS = 128
#: Seconds between two looks at the federation's processes while the devices wait for an answer.
WATCH_S = 1.0
#: What a fleet looks at while it waits: why the federation it talks to cannot answer any more (a process of it
#: exited), or None while it can.
Watch = Callable[[], str | None]


class SpreadFleet:
    """``devices`` simulated devices (w0 ... w<devices - 1>, device i behind edge ``e<i mod edges>``), in processes
    of at most ``per_process``; the same rounds as one ScriptedFleet."""

    def __init__(self, broker: str, devices: int, arrays: dict[str, np.ndarray], edges: int = 0,
                 per_process: int = PER_PROCESS, timeout: float = 600.0, watch: Watch | None = None) -> None:
        """``watch``: looked at every WATCH_S while waiting, a command fails at once when it names a reason."""
        self.watch = watch
        self.busy = True  # until every process said it is ready
        spec = json.dumps({k: list(v.shape) for k, v in arrays.items()})
        self.procs: list[subprocess.Popen[str]] = []
        self.lines: list[queue.Queue[str]] = []
        for first in range(0, devices, per_process):
            count = min(per_process, devices - first)
            proc = subprocess.Popen(
                [sys.executable, "-m", "bench.fleets", "--broker", broker, "--first", str(first), "--count", str(count),
                 "--edges", str(edges), "--spec", spec], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
            self.procs.append(proc)
            lines: queue.Queue[str] = queue.Queue()
            assert proc.stdout is not None
            threading.Thread(target=pump, args=(proc.stdout, lines), daemon=True).start()
            self.lines.append(lines)
        try:
            self._answers(timeout)  # every slice connected
            self.busy = False
        except BaseException:
            self.stop()
            raise

    def _answers(self, timeout: float) -> list[dict[str, Any]]:
        """Every process's answer to the last command, waited for up to ``timeout`` s in all (TimeoutError), or
        until ``watch`` says the federation is gone (RuntimeError)."""
        deadline = time.monotonic() + timeout
        return [self._answer(k, deadline) for k in range(len(self.lines))]

    def _answer(self, k: int, deadline: float) -> dict[str, Any]:
        while True:
            try:
                line = self.lines[k].get(timeout=max(0.0, min(WATCH_S, deadline - time.monotonic())))
                break
            except queue.Empty:
                gone = self.watch() if self.watch is not None else None
                if gone is not None:
                    raise RuntimeError(f"device process {k} waits in vain: {gone}") from None
                if time.monotonic() >= deadline:
                    raise TimeoutError(f"device process {k} did not answer in time") from None
        answer = json.loads(line) if line else {"error": f"device process {k} exited ({self.procs[k].poll()})"}
        if "error" in answer:
            raise RuntimeError(f"device process {k}: {answer['error']}")
        return dict(answer)

    def _command(self, cmd: dict[str, Any], timeout: float) -> list[dict[str, Any]]:
        self.busy = True  # until every process answered: a process still at it does not read a "stop"
        for proc in self.procs:
            assert proc.stdin is not None
            proc.stdin.write(json.dumps(cmd) + "\n")
            proc.stdin.flush()
        answers = self._answers(timeout)
        self.busy = False
        return answers

    def join(self, timeout: float = 600.0) -> None:
        """Hellos until the chief's RunStart reaches every process."""
        self._command({"do": "join", "timeout": timeout}, timeout + 5)

    def round(self, episode: int, timeout: float = 600.0) -> dict[str, float]:
        """One round of every device: the seconds from the first publish until the first and the last device had
        the aggregate."""
        got = self._command({"do": "round", "episode": episode, "timeout": timeout}, timeout + 5)
        start = min(a["start"] for a in got)
        return {"first_s": min(a["first"] for a in got) - start, "last_s": max(a["last"] for a in got) - start}

    def stop(self) -> None:
        """Stop every process: a ``stop`` command, or SIGTERM where the last command failed (its processes may
        still wait for their answers); each one left after 30 s is killed."""
        for proc in self.procs:
            try:
                if proc.poll() is None and self.busy:
                    proc.terminate()
                elif proc.poll() is None and proc.stdin is not None:
                    proc.stdin.write(json.dumps({"do": "stop"}) + "\n")
                    proc.stdin.close()
            except OSError:
                pass
        deadline = time.monotonic() + 30
        for proc in self.procs:
            try:
                proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def pump(stream: IO[str], lines: queue.Queue[str]) -> None:
    """A device process's answers, line by line; an empty line when it exits."""
    for line in stream:
        lines.put(line)
    lines.put("")


def main(argv: list[str] | None = None) -> int:
    """One slice of a SpreadFleet: its devices, driven by JSON lines on stdin, answered on stdout."""
    from bench.cost import ScriptedFleet

    parser = argparse.ArgumentParser(prog="python -m bench.fleets", description=__doc__.splitlines()[0])
    parser.add_argument("--broker", required=True)
    parser.add_argument("--first", type=int, required=True)
    parser.add_argument("--count", type=int, required=True)
    parser.add_argument("--edges", type=int, default=0)
    parser.add_argument("--spec", required=True, help="the actor's tensor shapes, as JSON")
    args = parser.parse_args(argv)

    def say(answer: dict[str, Any]) -> None:
        print(json.dumps(answer), flush=True)

    arrays = {k: np.zeros(shape, np.float32) for k, shape in json.loads(args.spec).items()}
    try:
        fleet = ScriptedFleet(args.broker, args.count, arrays, edges=args.edges, first=args.first,
                              connect_timeout=120.0)
    except Exception as exc:
        say({"error": f"{type(exc).__name__}: {exc}"})
        return 1
    say({"ready": len(fleet.ids)})
    previous = None
    try:
        for line in sys.stdin:
            cmd = json.loads(line)
            try:
                if cmd["do"] == "join":
                    fleet.join(timeout=cmd["timeout"])
                    say({"joined": True})
                elif cmd["do"] == "round":
                    times = fleet.round(cmd["episode"], previous, timeout=cmd["timeout"])
                    previous = fleet.latest(cmd["episode"], timeout=cmd["timeout"])
                    say(times)
                else:
                    break
            except Exception as exc:
                say({"error": f"{type(exc).__name__}: {exc}"})
    finally:
        fleet.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
