"""A worker's storage fault: it says ``storage`` on its status topic (the chief then stops the run resumably,
tests/deploy/test_interrupt.py) and ends with the StorageError that its main turns into one line and exit 5."""

from __future__ import annotations

import errno
import queue
from types import SimpleNamespace

import pytest

from protocol import topics
from protocol.codec import decode
from protocol.memory import Hub, MemoryConnection
from runtime.cli import run_service
from runtime.storage import EXIT_STORAGE, StorageError
from worker.service import WorkerService
from worker.settings import WorkerSettings


def test_a_full_disk_is_said_on_the_status_topic_and_ends_with_exit_5(monkeypatch: pytest.MonkeyPatch,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    hub = Hub()
    heard: queue.Queue[bytes] = queue.Queue()
    listener = MemoryConnection(hub, "listener").start()
    listener.subscribe(topics.worker("disk", "w0", topics.STATUS), lambda t, p: heard.put(p))
    fault = StorageError(errno.ENOSPC, "No space left on device", "/runs/x/workers/disk.w0.state.pt")
    monkeypatch.setattr(WorkerService, "_join", lambda self: SimpleNamespace())
    monkeypatch.setattr(WorkerService, "_learn", lambda self, start: (_ for _ in ()).throw(fault))
    service = WorkerService(WorkerSettings.given(run_id="disk", worker_id="w0"),
                            connect=lambda cid, will, rejects: MemoryConnection(hub, cid, will, rejects))
    assert run_service("worker", lambda: service) == EXIT_STORAGE
    status = decode(heard.get(timeout=5))
    assert (status.state, status.detail) == ("storage", str(fault))  # type: ignore[attr-defined]
    assert capsys.readouterr().err == f"worker: {fault}\n"
    listener.stop()
