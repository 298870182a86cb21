"""Protocol: round trips, and every kind of bad payload rejected with a clear reason."""

from __future__ import annotations

import ast
import re
import subprocess
import sys

import msgpack
import numpy as np
import pytest

from protocol import topics
from protocol.codec import DecodeError, RejectCounter, decode, encode
from protocol.messages import (
    STAT_BOUNDS,
    ChiefAck,
    ChiefAggregate,
    ChiefTransfer,
    MatureParams,
    QubeAction,
    QubeState,
    Receipt,
    RunStart,
    RunStop,
    WorkerHello,
    WorkerStatus,
    WorkerUpdate,
)
from protocol.mqtt import BrokerAddress
from protocol.rounds import PER_EPISODE, RoundShape
from protocol.tensors import TensorBlob, check_spec, digest, pack_arrays, unpack_arrays
from tests.paths import ROOT


def grad(seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {"net.0.weight": rng.normal(size=(128, 4)).astype(np.float32), "net.0.bias": np.zeros(128, np.float32)}


def update(**over: object) -> WorkerUpdate:
    fields = dict(worker_id="w0", episode=3, episode_return=20.0, pi=15.5, recent_returns=[11.0, 20.0], steps=20,
                  gradient=pack_arrays(grad()))
    fields.update(over)
    return WorkerUpdate(**fields)  # type: ignore[arg-type]


def test_update_round_trip_keeps_arrays_bit_exact() -> None:
    msg = update()
    back = decode(encode(msg), WorkerUpdate)
    assert back == msg
    arrays = unpack_arrays(back.gradient)
    for name, arr in grad().items():
        assert arrays[name].dtype == np.float32
        np.testing.assert_array_equal(arrays[name], arr)
    arrays["net.0.bias"][0] = 1.0  # unpacked arrays are writable copies


def test_tensor_bytes_are_raw_not_lists() -> None:
    payload = encode(update())
    # 128*4 + 128 float32 values = 2560 bytes of data; a tolist() encoding would be ~9 bytes per value.
    assert 2560 < len(payload) < 2560 + 400


@pytest.mark.parametrize(
    "msg",
    [
        WorkerHello(worker_id="w1", env_id="CartPole-v0", actor_spec={"a": (2, 3)}),
        WorkerStatus(worker_id="w1", state="offline"),
        MatureParams(worker_id="w1", episode=9, episode_return=200.0, pi=196.0, recent_returns=[196.0] * 10,
                     params=pack_arrays(grad(1)), receipt=Receipt(round=8, applied="transfer", digest="ab", keep=0.5)),
        update(receipt=Receipt(round=2, applied="missed")),
        ChiefAck(worker_id="w1", round=9, episode=9, accepted=False, reason="not_mature: PI 10"),
        ChiefAggregate(round=4, episode=4, gradient=None, weights={}, contributors=["w0"]),
        ChiefAggregate(round=11, episode=4, step=1, gradient=pack_arrays(grad(2)), weights={"w0": 0.5, "w1": 0.5},
                       contributors=["w0", "w1"]),
        ChiefTransfer(round=5, episode=5, source_worker="w1", source_pi=196.0, params=pack_arrays(grad(3)),
                      keep_weights={"w0": 0.4}, finished=["w1"]),
        RunStart(run_id="r1", env_id="Acrobot-v1", policy="weighted", seed=3, max_episodes=10, tc=-100.0,
                 r_floor=-500.0, workers=["w0", "w1"]),
        QubeState(rig_id="rig0", seq=7, t=1.5, theta=0.1, alpha=-0.02, theta_dot=0.0, alpha_dot=1.0),
        QubeAction(rig_id="rig0", seq=7, command=-60),
    ],
)
def test_every_message_round_trips(msg: object) -> None:
    assert decode(encode(msg)) == msg  # type: ignore[arg-type]


def reason_of(payload: bytes, *expected: type, max_bytes: int | None = None) -> str:
    with pytest.raises(DecodeError) as info:
        if max_bytes is None:
            decode(payload, *expected)
        else:
            decode(payload, *expected, max_bytes=max_bytes)
    return info.value.reason


def raw_update(**over: object) -> dict:
    obj = update().model_dump(mode="python")
    obj.update(over)
    return obj


def test_rejects_garbage_and_non_maps() -> None:
    assert reason_of(b"\xc1\xff\x00garbage") == "malformed"
    assert reason_of(msgpack.packb([1, 2, 3])) == "malformed"
    assert reason_of(b"") == "malformed"


def test_rejects_unknown_version_and_kind() -> None:
    assert reason_of(msgpack.packb(raw_update(schema_version=2))) == "version"
    assert reason_of(msgpack.packb(raw_update(kind="teleport"))) == "unknown_kind"
    assert reason_of(encode(update()), ChiefAggregate) == "unexpected_kind"


def test_rejects_oversized_payload() -> None:
    payload = encode(update())
    assert reason_of(payload, max_bytes=len(payload) - 1) == "oversized"


def bad_blob(**over: object) -> dict:
    blob = TensorBlob.from_array(np.ones((2, 3), np.float32)).model_dump(mode="python")
    blob.update(over)
    return blob


@pytest.mark.parametrize(
    "blob",
    [
        bad_blob(dtype="object"),  # not an allowed dtype
        bad_blob(dtype=">f4"),  # big-endian is not what we send
        bad_blob(shape=[3, 3]),  # shape does not match the bytes
        bad_blob(shape=[-2, -3]),
        bad_blob(data=b"\x00" * 5),
        bad_blob(data=np.array([1, np.nan, 2, 3, 4, 5], np.float32).tobytes()),  # NaN gradient
        bad_blob(data=np.array([1, np.inf, 2, 3, 4, 5], np.float32).tobytes()),
        bad_blob(shape=[1] * 9, data=b"\x00\x00\x80\x3f"),  # too many dimensions
        bad_blob(dtype="<i4", shape=[2**31, 2**31, 4], data=b""),  # the product overflows int64 to 0
        bad_blob(dtype="<i4", shape=[2**62, 4], data=b""),
    ],
)
def test_rejects_bad_tensors(blob: dict) -> None:
    payload = msgpack.packb(raw_update(gradient={"net.0.weight": blob}), use_bin_type=True)
    assert reason_of(payload) == "invalid"


def test_rejects_nan_scalars_missing_fields_and_extra_fields() -> None:
    assert reason_of(msgpack.packb(raw_update(pi=float("nan")), use_bin_type=True)) == "invalid"
    obj = raw_update()
    del obj["pi"]
    assert reason_of(msgpack.packb(obj, use_bin_type=True)) == "invalid"
    assert reason_of(msgpack.packb(raw_update(surprise=1), use_bin_type=True)) == "invalid"
    assert reason_of(msgpack.packb(raw_update(worker_id="w0/#"), use_bin_type=True)) == "invalid"


@pytest.mark.parametrize("stat", sorted(STAT_BOUNDS))
def test_ppo_statistics_must_be_finite_and_within_their_bounds(stat: str) -> None:
    low, high = STAT_BOUNDS[stat]
    for value in (low, high, None):
        assert decode(msgpack.packb(raw_update(**{stat: value}), use_bin_type=True), WorkerUpdate) == update(
            **{stat: value})
    for bad in (float("nan"), float("inf"), float("-inf"), low - 1.0, high * 1.5 + 1.0):
        with pytest.raises(DecodeError, match=stat) as info:
            decode(msgpack.packb(raw_update(**{stat: bad}), use_bin_type=True), WorkerUpdate)
        assert info.value.reason == "invalid"
    assert reason_of(msgpack.packb(raw_update(**{stat: "0.5"}), use_bin_type=True)) == "invalid"  # no coercion


def test_an_update_without_ppo_statistics_still_counts() -> None:
    """An older worker sends none (or only the first three): the missing ones decode as None."""
    obj = raw_update()
    for stat in STAT_BOUNDS:
        del obj[stat]
    msg = decode(msgpack.packb(obj, use_bin_type=True), WorkerUpdate)
    assert all(getattr(msg, stat) is None for stat in STAT_BOUNDS)
    full = update(actor_loss=-0.1, critic_loss=2.0, entropy=0.6, approx_kl=0.01, clip_fraction=0.25)
    assert decode(encode(full), WorkerUpdate) == full


def test_error_message_names_the_field() -> None:
    with pytest.raises(DecodeError, match="episode"):
        decode(msgpack.packb(raw_update(episode=0), use_bin_type=True))


def test_check_spec_names_the_difference() -> None:
    spec = {"net.0.weight": (128, 4), "net.0.bias": (128,)}
    check_spec(grad(), spec, "ok")
    with pytest.raises(ValueError, match=r"net\.0\.weight has shape"):
        check_spec(grad(), {**spec, "net.0.weight": (64, 4)}, "g")
    with pytest.raises(ValueError, match="missing"):
        check_spec({"net.0.bias": np.zeros(128)}, spec, "g")


def test_reject_counter_counts_by_reason(caplog: pytest.LogCaptureFixture) -> None:
    import logging

    counter = RejectCounter(logging.getLogger("t"))
    for payload in (b"\xc1", msgpack.packb(raw_update(schema_version=9))):
        try:
            decode(payload)
        except DecodeError as err:
            counter.reject_error("some/topic", err)
    assert counter.as_dict() == {"malformed": 1, "version": 1}
    assert counter.total == 2
    assert "some/topic" in caplog.text


def test_topics_and_ids() -> None:
    assert topics.worker("r1", "w0", topics.UPDATE) == "fedrl/r1/worker/w0/update"
    assert topics.chief("r1", topics.AGGREGATE) == "fedrl/r1/chief/aggregate"
    assert topics.rig("rig0", topics.ACTION) == "qube/rig0/action"
    for bad in ("", "a/b", "a+b", "#", "x" * 65):
        with pytest.raises(ValueError):
            topics.worker(bad, "w0", "x")


def test_broker_address_parsing() -> None:
    assert BrokerAddress.parse("mqtt://10.0.0.5:1884") == BrokerAddress("10.0.0.5", 1884)
    assert BrokerAddress.parse("localhost").port == 1883
    tls = BrokerAddress.parse("mqtts://u:p%40ss@broker.example:8884", ca_file="/ca.pem")
    assert (tls.tls, tls.username, tls.password, tls.port, tls.ca_file) == (True, "u", "p@ss", 8884, "/ca.pem")
    assert BrokerAddress.parse("mqtts://h").port == 8883
    with pytest.raises(ValueError, match="scheme"):
        BrokerAddress.parse("http://h:1")
    with pytest.raises(ValueError):
        BrokerAddress.parse("mqtt://h:notaport")


def test_protocol_imports_no_torch_or_gymnasium() -> None:
    code = "import protocol, protocol.mqtt, protocol.tasks, runtime.cli, runtime.settings, sys; " \
           "assert 'torch' not in sys.modules and 'gymnasium' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_protocol_imports_no_other_project_package() -> None:
    """The wire contract is the bottom layer: no import of another project package, and no module named by a
    string for importlib to load."""
    others = {"runtime", "chief", "worker", "rpi_bridge", "services", "deploy", "bench", "tests"}
    for path in sorted((ROOT / "protocol").glob("*.py")):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            assert not [n for n in names if n.split(".")[0] in others or n == "importlib"], (path.name, names)
            if isinstance(node, ast.Constant) and isinstance(node.value, str):  # "chief.settings:ChiefSettings"
                module = re.fullmatch(r"([a-z_]+)(\.[a-z_]+)+(:\w+)?", node.value)
                assert not (module and module.group(1) in others), (path.name, node.value)


def test_digest_is_the_same_for_arrays_and_their_blobs() -> None:
    arrays = grad(4)
    assert digest(arrays) == digest(pack_arrays(arrays)) == digest(decode(encode(update(gradient=pack_arrays(
        arrays))), WorkerUpdate).gradient)
    changed = {**arrays, "net.0.bias": arrays["net.0.bias"] + 1e-7}
    assert digest(changed) != digest(arrays) and len(digest(arrays)) == 16


def test_recent_returns_are_bounded_by_the_pi_window() -> None:
    assert reason_of(msgpack.packb(raw_update(recent_returns=[1.0] * 11), use_bin_type=True)) == "invalid"
    assert reason_of(msgpack.packb(raw_update(recent_returns=[]), use_bin_type=True)) == "invalid"


def test_the_wire_contract_document_is_up_to_date() -> None:
    from protocol import contract

    assert contract.DOC.read_text(encoding="utf-8") == contract.markdown(), (
        "docs/wire-contract.md is out of date: python -m protocol.contract --write")
    kinds = {p.model_fields["kind"].default for r in contract.ROUTES for p in r.payloads}
    assert kinds == set(contract.MESSAGE_TYPES) - {"chunk"}, "every message kind has a topic in the contract"


@pytest.mark.parametrize(("change", "what"), [
    (dict(schema_version=1.0), "version"),
    (dict(schema_version=True), "version"),
    (dict(episode="3"), "invalid"),
    (dict(episode=True), "invalid"),
    (dict(pi="15.5"), "invalid"),
    (dict(steps=20.0), "invalid"),
    (dict(worker_id=7), "invalid"),
])
def test_nothing_is_coerced(change: dict, what: str) -> None:
    assert reason_of(msgpack.packb(raw_update(**change), use_bin_type=True)) == what


def test_a_message_must_be_of_a_kind_its_topic_carries() -> None:
    payload = encode(update())
    assert decode(payload, topic="fedrl/r1/worker/w0/update") == update()
    assert reason_of_topic(payload, "fedrl/r1/worker/w0/hello") == "wrong_topic"
    assert reason_of_topic(payload, "fedrl/r1/chief/aggregate") == "wrong_topic"
    assert reason_of_topic(payload, "qube/rig0/action") == "wrong_topic"
    assert reason_of_topic(payload, "somewhere/else") == "wrong_topic"
    stop = encode(RunStop(run_id="r1", reason="x", episodes=1, all_solved=False))
    assert reason_of_topic(stop, "fedrl/r1/chief/aggregate") == "wrong_topic"
    assert decode(stop, topic="fedrl/r1/chief/stop").kind == "run_stop"


def test_the_id_a_message_carries_must_be_the_one_its_topic_names() -> None:
    """A worker speaking for another, or a rig's message on another rig's topic, is refused as ``spoofed``."""
    payload = encode(update())  # worker w0
    assert reason_of_topic(payload, "fedrl/r1/worker/w1/update") == "spoofed"
    with pytest.raises(DecodeError, match="payload says worker 'w0', topic says 'w1'"):
        decode(payload, topic="fedrl/r1/worker/w1/update")
    state = encode(QubeState(rig_id="rigA", seq=1, t=0.0, theta=0.0, alpha=0.0, theta_dot=0.0, alpha_dot=0.0))
    assert decode(state, topic="qube/rigA/state").kind == "qube_state"
    assert reason_of_topic(state, "qube/rigB/state") == "spoofed"
    assert decode(state, QubeState).rig_id == "rigA"  # without a topic there is nothing to compare with


def reason_of_topic(payload: bytes, topic: str) -> str:
    with pytest.raises(DecodeError) as info:
        decode(payload, topic=topic)
    return info.value.reason


def test_a_round_is_numbered_over_its_episode_and_step() -> None:
    """round = (e - 1) * K + s + 1 and back; an episode's rounds; a message's round checked against its episode and
    step; one round per episode numbers rounds as episodes; RunStart carries the shape."""
    shape = RoundShape(per_episode=3)
    assert [shape.number(e, s) for e in (1, 2, 3) for s in range(3)] == list(range(1, 10))
    assert [shape.of(n) for n in (1, 3, 4, 9)] == [(1, 0), (1, 2), (2, 0), (3, 2)]
    assert list(shape.rounds_of(2)) == [4, 5, 6] and shape.last_of(3) == 9
    assert shape.ends_episode(6) and not shape.ends_episode(5) and shape.per_step and not PER_EPISODE.per_step
    assert shape.agrees(5, 2, 1) and not shape.agrees(4, 2, 1) and not shape.agrees(5, 2, 3)
    assert PER_EPISODE.number(7) == 7 and PER_EPISODE.of(7) == (7, 0)
    for episode, step in ((0, 0), (1, 3), (1, -1)):
        with pytest.raises(ValueError, match="no round"):
            shape.number(episode, step)
    with pytest.raises(ValueError, match="numbered from 1"):
        shape.of(0)
    with pytest.raises(ValueError):
        RoundShape(per_episode=0)
    start = RunStart(run_id="r1", env_id="CartPole-v0", policy="sync", seed=3, max_episodes=10, tc=195.0,
                     r_floor=0.0, workers=["w0"], rounds_per_episode=3)
    assert start.shape == shape
