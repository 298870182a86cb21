"""Issue 32, item 1: every worker message is tagged with its worker's own key (protocol/auth.py). Keys derive from
the run key and the worker's id, the chief refuses and counts a worker message without its worker's tag, and on an
open broker forged updates, hellos and statuses in another worker's name change nothing: the run gives the clean
run's per-worker episodes and the audit passes, over Mosquitto and the embedded broker."""

from __future__ import annotations

import logging
import math
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from chief.audit import audit
from chief.service import ChiefService, Outputs
from chief.settings import ChiefSettings
from protocol import topics
from protocol.auth import MIN_KEY_LENGTH, WorkerKeys, chief_key, chief_key_of, key_bytes, signed, worker_key
from protocol.codec import decode, encode
from protocol.messages import Message, WorkerHello, WorkerStatus, WorkerUpdate
from protocol.mqtt import BrokerAddress, MqttConnection
from protocol.tensors import pack_arrays, unpack_arrays
from runtime.records import RunSummary
from worker.service import WorkerService
from worker.settings import WorkerSettings, handed_keys

KEY = "r" * 32
RAW = KEY.encode()
LOG = logging.getLogger("test")
pytestmark = pytest.mark.xdist_group("test_worker_keys")  # its module fixture is made once, in one test process
ENV, SEED, WORKERS, EPISODES = "CartPole-v0", 103, 2, 12


# -- keys ----------------------------------------------------------------------------------------------------


def test_keys_derive_from_the_run_key_and_the_id_and_reveal_neither_each_other() -> None:
    w0, w1, chief = worker_key(RAW, "w0"), worker_key(RAW, "w1"), chief_key(RAW)
    assert len({w0, w1, chief, KEY}) == 4 and all(len(k) == 64 and len(k) >= MIN_KEY_LENGTH for k in (w0, w1, chief))
    assert worker_key(RAW, "w0") == w0 and worker_key(b"another run key!", "w0") != w0  # deterministic, per run
    assert key_bytes(w0) == w0.encode()  # a derived key is a valid key setting
    handed = handed_keys(KEY, "w1")
    assert handed == {"worker_key": w1, "chief_key": chief, "run_key": None}  # never the run key


def test_a_worker_signs_with_its_own_key_and_checks_the_chief_with_the_chief_key() -> None:
    given = WorkerSettings.given(worker_id="w1", **handed_keys(KEY, "w1"))
    derived = WorkerSettings.given(worker_id="w1", run_key=KEY)  # a worker given the run key derives the same
    for cfg in (given, derived):
        assert cfg.own_key("w1") == worker_key(RAW, "w1").encode() and cfg.chief_check_key() == chief_key_of(RAW)
    plain = WorkerSettings.given(worker_id="w1")
    assert plain.own_key("w1") is None and plain.chief_check_key() is None  # no key: as before
    with pytest.raises(ValueError, match="go together"):
        WorkerSettings.given(worker_id="w1", worker_key=worker_key(RAW, "w1"))
    with pytest.raises(ValueError, match="one worker id"):
        WorkerSettings.given(**handed_keys(KEY, "w1"))  # an automatic id would not be the key's


def update(worker_id: str, episode: int = 1, ret: float = 20.0) -> WorkerUpdate:
    return WorkerUpdate(worker_id=worker_id, episode=episode, episode_return=ret, pi=ret, recent_returns=(ret,),
                        steps=int(ret), gradient=pack_arrays({"w": np.zeros(2, np.float32)}))


def test_worker_keys_refuse_a_message_without_its_workers_tag() -> None:
    keys = WorkerKeys(RAW)
    mine = worker_key(RAW, "w0").encode()
    assert keys.refusal(signed(update("w0"), mine)) is None
    assert keys.refusal(update("w0"))[0] == "unsigned"  # type: ignore[index]
    assert keys.refusal(signed(update("w1"), mine))[0] == "forged"  # type: ignore[index]  # w0 speaking for w1
    assert keys.refusal(signed(update("w0"), RAW))[0] == "forged"  # type: ignore[index]  # not even the run key
    assert keys.refusal(signed(update("w0", ret=21.0), mine).model_copy(update={"pi": 50.0}))[0] == "forged"  # type: ignore[index]
    assert WorkerKeys(None).refusal(update("w0")) is None  # a run without a key trusts every message


class _NoConnection:
    connected = threading.Event()
    connects = 0

    def __getattr__(self, name: str) -> object:
        return lambda *a, **k: None


def test_the_chief_counts_each_refused_worker_message_and_queues_only_its_workers_own(tmp_path: Path) -> None:
    chief = ChiefService(ChiefSettings.given(run_id="keys", workers=2, run_dir=tmp_path, run_key=KEY),
                         connect=lambda *a: _NoConnection())  # type: ignore[arg-type, return-value]
    w0, w1 = worker_key(RAW, "w0").encode(), worker_key(RAW, "w1").encode()
    hello = WorkerHello(worker_id="w1", env_id=ENV, actor_spec={"w": (2,)})
    status = WorkerStatus(worker_id="w1", state="error", detail="forged")
    sent = [(topics.UPDATE, update("w1")), (topics.UPDATE, signed(update("w1"), w0)),
            (topics.HELLO, hello), (topics.HELLO, signed(hello, w0)),
            (topics.STATUS, status), (topics.STATUS, signed(status, RAW)),
            (topics.UPDATE, signed(update("w1"), w1)), (topics.HELLO, signed(hello, w1))]
    for leaf, msg in sent:
        chief._on_message(topics.worker("keys", "w1", leaf), encode(msg))
    assert chief.rejects.as_dict() == {"unsigned": 3, "forged": 3}
    queued = [chief.events.get_nowait()[1] for _ in range(chief.events.qsize())]
    assert [(m.kind, m.tag) for m in queued] == [("update", signed(update("w1"), w1).tag),
                                                 ("hello", signed(hello, w1).tag)]


# -- a forger on an open broker --------------------------------------------------------------------------------


class Forger:
    """A client of an anonymous broker that holds w0's own key (a worker gone rogue) but not w1's or the run's:
    it says hello for a worker that does not exist, says w1 stopped or failed, and for every update of w1 it
    reads sends one in w1's name for two rounds ahead (return 50, zero gradient), untagged, under w0's key and
    under a key of its own."""

    def __init__(self, broker: str, run: str, keyed: bool = True) -> None:
        """``keyed``: the run has a key (else: only untagged forged updates, no hellos or statuses)."""
        self.run, self.keyed = run, keyed
        # Rounds ahead of the update it read. Without a key, 4: a forgery that arrived once its round was in reach
        # would count (the limit chief/rounds.py names), and 4 rounds leave the forger's thread time on a busy machine.
        self.ahead = 2 if keyed else 4
        self.conn = MqttConnection(BrokerAddress.parse(broker), client_id="forger").start()
        self.w0 = worker_key(RAW, "w0").encode()
        self.sent = 0
        self.conn.subscribe(topics.worker(run, "w1", topics.UPDATE), self._on_update)
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._chatter if keyed else self._stop.wait, daemon=True)
        self.thread.start()

    def _publish(self, worker_id: str, leaf: str, msg: Message) -> None:
        self.conn.publish(topics.worker(self.run, worker_id, leaf), encode(msg), qos=1)
        self.sent += 1

    def _each_key(self, msg: Any) -> list[Any]:
        return [msg, signed(msg, self.w0), signed(msg, b"a key of the forger's own")] if self.keyed else [msg]

    def _chatter(self) -> None:
        hello = WorkerHello(worker_id="w7", env_id=ENV, actor_spec={"w": (2,)})
        while not self._stop.wait(0.2):
            for msg in self._each_key(hello):
                self._publish("w7", topics.HELLO, msg)
            for state in ("stopped", "error", "offline"):
                for msg in self._each_key(WorkerStatus(worker_id="w1", state=state, detail="forged")):
                    self._publish("w1", topics.STATUS, msg)

    def _on_update(self, topic: str, payload: bytes) -> None:
        real = decode(payload)
        if not isinstance(real, WorkerUpdate) or real.pi == 50.0:
            return  # its own forgeries come back on the same topic
        zeros = pack_arrays({k: np.zeros_like(v) for k, v in unpack_arrays(real.gradient).items()})
        forged = real.model_copy(update={"episode": real.episode + self.ahead, "episode_return": 50.0, "pi": 50.0,
                                         "recent_returns": (50.0,), "gradient": zeros, "steps": 50, "receipt": None,
                                         "played": None, "tag": ""})
        for msg in self._each_key(forged):
            self._publish("w1", topics.UPDATE, msg)

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(5)
        self.conn.stop()


@pytest.fixture(scope="module")
def clean(tmp_path_factory: pytest.TempPathFactory) -> RunSummary:
    """The same federation without a forger, in process: what the attacked runs must equal."""
    from deploy.inprocess import run_federation
    from deploy.settings import InprocessSettings

    return run_federation(InprocessSettings.given(env=ENV, policy="weighted", seed=SEED, workers=WORKERS,
                          max_episodes=EPISODES, run_dir=tmp_path_factory.mktemp("clean")), plot=False,
                          tensorboard_files=False)


def attacked_run(broker: str, run_dir: Path, run: str, forger_keyed: bool, key: str | None) -> tuple[ChiefService,
                                                                                                  Forger]:
    """A federation (under ``key``, or none) with a Forger beside it, to its end: the chief, whose run must equal
    the clean one per worker (asserted here), and the forger."""
    chief = ChiefService(ChiefSettings.given(broker=broker, run_id=run, workers=WORKERS, env=ENV,
                                             policy="weighted", seed=SEED, max_episodes=EPISODES,
                                             round_timeout=math.inf, start_timeout=60, idle_timeout=120,
                                             run_dir=run_dir, run_key=key),
                         outputs=Outputs(state=False, tensorboard=False, plot=False, progress=False))
    forger = Forger(broker, run, keyed=forger_keyed)
    workers = [WorkerService(WorkerSettings.given(broker=broker, run_id=run, worker_id=f"w{i}", env=ENV,
                                                  reply_timeout=120, start_timeout=60, ack_timeout=120,
                                                  resend_interval=60, **(handed_keys(key, f"w{i}") if key else {})))
               for i in range(WORKERS)]
    threads = [threading.Thread(target=w.run, daemon=True) for w in workers]
    time.sleep(0.5)  # the forger's first hellos are out before any worker's
    for t in threads:
        t.start()
    try:
        assert chief.run() == 0
    finally:
        for t in threads:
            t.join(timeout=60)
        forger.stop()
    return chief, forger


def per_worker(summary: RunSummary | dict) -> list[tuple[str, int, int]]:
    """Each worker's id, episodes and env steps, of a summary or of a chief's summary data."""
    typed = summary if isinstance(summary, RunSummary) else RunSummary.model_validate(summary)
    return [(w.id, w.episodes, w.steps) for w in typed.workers]


@pytest.mark.slow
def test_forged_worker_messages_change_nothing(any_broker: str, tmp_path: Path, clean: dict) -> None:
    chief, forger = attacked_run(any_broker, tmp_path / "run", f"forged-workers-{time.monotonic_ns()}", True, KEY)
    assert per_worker(chief.summary("", True, 0)) == per_worker(clean)
    refused = chief.rejects.as_dict()
    assert forger.sent > 0 and refused.get("unsigned", 0) > 0 and refused.get("forged", 0) > 0, refused
    assert set(refused) <= {"unsigned", "forged"}, refused  # nothing forged got as far as the rounds
    audit(tmp_path / "run")


@pytest.mark.slow
def test_without_a_key_an_update_for_a_round_ahead_still_never_displaces_the_real_one(amqtt_broker: str,
                                                                                      tmp_path: Path,
                                                                                      clean: dict) -> None:
    """Issue 32's probe on an open broker and a run without a key: for every update of w1, one in its name for
    rounds ahead (return 50, zero gradient). Each is held and refused as unreachable when its round opens; w1's real
    updates all count (none `inconsistent`), so the run is the clean one and the audit passes (chief/rounds.py)."""
    chief, forger = attacked_run(amqtt_broker, tmp_path / "run", f"ahead-{time.monotonic_ns()}", False, None)
    assert per_worker(chief.summary("", True, 0)) == per_worker(clean)
    refused = chief.rejects.as_dict()
    assert forger.sent > 0 and refused.get("unreachable", 0) > 0 and "inconsistent" not in refused, refused
    audit(tmp_path / "run")
