"""Simulated rigs answered from their own processes (bench/scale.py): what a rig sees, not the benchmark's contention.

``RigProcess`` starts ``python -m bench.rigs``, which holds one bench.latency.AnsweredRig: the simulated rig in real
time (``services.qube_sim --clock realtime``, a process of its own) and the worker's side that answers its states
(the learner's forward pass, then a balancing rule's action) on its own interpreter, so that no thread of the
benchmark (its pipes to the device processes, its broker counters) shares a lock or a core queue with it. Driven by
JSON lines like bench.fleets: one ``{"answering": ...}`` once the first state is answered, then ``finish`` is
answered by the rig's measurement (AnsweredRig.finish); anything else, the pipe closing or SIGTERM ends it unmeasured,
its rig stopped.

One process per rig, not a pool: ``make scale`` attaches 1 rig by default (``--rigs``), whatever the number of
devices, and each answering process costs one interpreter with the learner (about 300 MB with torch); a pool would
put rigs back on one interpreter, which is what this module takes them away from.
"""

from __future__ import annotations

import argparse
import json
import queue
import signal
import subprocess
import sys
import threading
from typing import Any

from bench.fleets import pump


class RigProcess:
    """One simulated rig on ``url`` answered from its own process (``python -m bench.rigs``)."""

    def __init__(self, url: str, rig_id: str, timeout: float = 600.0) -> None:
        """``timeout``: how long the first answered state may take (the rig's first reset)."""
        self.rig_id = rig_id
        self.proc = subprocess.Popen([sys.executable, "-m", "bench.rigs", "--broker", url, "--rig-id", rig_id,
                                      "--timeout", str(timeout)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     text=True)
        self.lines: queue.Queue[str] = queue.Queue()
        assert self.proc.stdout is not None
        threading.Thread(target=pump, args=(self.proc.stdout, self.lines), daemon=True).start()
        self.timeout = timeout

    def _answer(self, timeout: float) -> dict[str, Any]:
        try:
            line = self.lines.get(timeout=timeout)
        except queue.Empty:
            raise TimeoutError(f"rig {self.rig_id}: no word from its answering process in {timeout:.0f} s") from None
        answer = json.loads(line) if line else {"error": f"its answering process exited ({self.proc.poll()})"}
        if "error" in answer:
            raise RuntimeError(f"rig {self.rig_id}: {answer['error']}")
        return dict(answer)

    def answering(self) -> None:
        """Until the first state is answered (the rig's first reset done)."""
        self._answer(self.timeout + 30)

    def finish(self) -> dict[str, Any]:
        """Stop answering and measure (bench.latency.AnsweredRig.finish, in the rig's process)."""
        self._send("finish")
        answer = self._answer(180)
        self.proc.wait(30)
        return answer

    def _send(self, what: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps({"do": what}) + "\n")
        self.proc.stdin.flush()

    def kill(self) -> None:
        """Stop without measuring (a failed point): SIGTERM, on which the process stops its rig; killed after 30 s."""
        try:
            self.proc.terminate()
            self.proc.wait(30)
        except (OSError, subprocess.TimeoutExpired):
            self.proc.kill()
            self.proc.wait()


def main(argv: list[str] | None = None) -> int:
    """One answered rig, driven by JSON lines on stdin, answered on stdout."""
    from bench.latency import AnsweredRig

    parser = argparse.ArgumentParser(prog="python -m bench.rigs", description=__doc__.splitlines()[0])
    parser.add_argument("--broker", required=True)
    parser.add_argument("--rig-id", required=True)
    parser.add_argument("--timeout", type=float, default=600.0, help="seconds the first answered state may take")
    args = parser.parse_args(argv)

    def say(answer: dict[str, Any]) -> None:
        print(json.dumps(answer), flush=True)

    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # through the finally below: the rig stops too
    rig: AnsweredRig | None = None
    try:
        rig = AnsweredRig(args.broker, args.rig_id)
        rig.answering(args.timeout)
        say({"answering": True})
        if json.loads(sys.stdin.readline() or "{}").get("do") == "finish":
            measured, rig = rig, None
            say(measured.finish())
    except Exception as exc:
        say({"error": f"{type(exc).__name__}: {exc}"})
        return 1
    finally:
        if rig is not None:
            rig.kill()
    return 0


if __name__ == "__main__":
    sys.exit(main())
