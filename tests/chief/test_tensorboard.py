"""Watch it learn in TensorBoard: workers' PPO statistics reach the chief's records, and the chief's event files
(CleanRL's tags, one run per worker, x = the worker's env steps) say exactly what metrics.jsonl says.

The event files are read back by parsing their TFRecord framing (CRC-checked) into tensorboardX's own Event proto,
so the test needs nothing beyond the `tb` extra."""

from __future__ import annotations

import importlib.util
import json
import logging
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from chief import tensorboard
from chief.audit import audit
from chief.rounds import RoundKeeper
from chief.wire import submission_of
from deploy.inprocess import run_federation
from deploy.settings import InprocessSettings
from protocol.codec import decode, encode
from protocol.messages import STAT_BOUNDS, WorkerUpdate
from protocol.tasks import task
from protocol.tensors import pack_arrays
from tests.tb_events import Scalars, read_board, read_event_file
from worker.federated import _loss_fields
from worker.ppo import UpdateStats

pytestmark = pytest.mark.xdist_group("test_tensorboard")  # its module fixture is made once, in one test process

needs_writer = pytest.mark.skipif(importlib.util.find_spec("tensorboardX") is None,
                                  reason="the tb extra (pip install .[tb]) writes the event files")

CLEANRL_TAGS = ("charts/episodic_return", "losses/value_loss", "losses/policy_loss", "losses/entropy",
                "losses/approx_kl", "losses/clipfrac")
LOSS_TAGS = {"actor_loss": "losses/policy_loss", "critic_loss": "losses/value_loss", "entropy": "losses/entropy",
             "approx_kl": "losses/approx_kl", "clip_fraction": "losses/clipfrac"}

def records(run_dir: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


def f32(values: list[float]) -> list[float]:
    """What a TensorBoard scalar holds (float32)."""
    return [float(np.float32(v)) for v in values]


def expected_board(lines: list[dict[str, Any]]) -> dict[str, Scalars]:
    """The scalars metrics.jsonl implies, re-derived here independently of chief/tensorboard.py (one round per
    episode): the x of everything is the worker's env steps so far, in record order."""
    env_steps: dict[str, int] = defaultdict(int)
    transfers: dict[str, int] = defaultdict(int)
    out: dict[str, Scalars] = defaultdict(lambda: defaultdict(list))
    for r in lines:
        if r["type"] == "episode":
            w = r["worker"]
            env_steps[w] += r["steps"]
            out[w]["charts/episodic_return"].append((env_steps[w], r["return"]))
            for stat, tag in LOSS_TAGS.items():
                if r["kind"] == "update" and r["stats"][stat] is not None:
                    out[w][tag].append((env_steps[w], r["stats"][stat]))
        elif r["type"] == "round":
            for w, weight in r["weights"].items():
                out[w]["federation/contribution_weight"].append((env_steps[w], weight))
            for w, keep in (r["keep_weights"] if r["kind"] == "transfer" else {}).items():
                transfers[w] += 1
                out[w]["federation/keep_weight"].append((env_steps[w], keep))
                out[w]["federation/transfers"].append((env_steps[w], transfers[w]))
    return {w: {tag: [(x, float(np.float32(v))) for x, v in points] for tag, points in tags.items()}
            for w, tags in out.items()}


@pytest.fixture(scope="module")
def weighted_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 4-worker CartPole-v0 federation (policy weighted, seed 3: workers finish early, so there are transfers), in
    process: the chief's own round logic and records, the workers' own Algorithm 2 and PPO, messages through the
    wire codec."""
    run_dir = tmp_path_factory.mktemp("tb") / "weighted"
    summary = run_federation(InprocessSettings.given(env="CartPole-v0", policy="weighted", seed=3, workers=4,
                             max_episodes=600, run_dir=run_dir), plot=False)
    assert summary.episodes_to_all_solved is not None
    return run_dir


@needs_writer
@pytest.mark.slow  # the module's 4-worker federation to the end (weighted_run)
def test_every_worker_gets_cleanrl_tags_that_match_the_records(weighted_run: Path) -> None:
    lines = records(weighted_run)
    board = read_board(weighted_run)
    assert sorted(board) == ["w0", "w1", "w2", "w3"]
    for w, scalars in board.items():
        assert set(CLEANRL_TAGS) <= set(scalars), f"{w} lacks {set(CLEANRL_TAGS) - set(scalars)}"
        episodes = [r for r in lines if r["type"] == "episode" and r["worker"] == w]
        returns = scalars["charts/episodic_return"]
        assert len(returns) == len(episodes)  # one point per accepted episode
        assert [v for _, v in returns] == f32([r["return"] for r in episodes])
        assert [x for x, _ in returns] == list(np.cumsum([r["steps"] for r in episodes]))  # x: env steps
        assert [v for _, v in scalars["charts/performance_index"]] == f32([r["pi"] for r in episodes])
        updates = [r for r in episodes if r["kind"] == "update"]
        assert len(updates) == len(episodes) - 1  # it finished with a MatureParams: no PPO update in that one
        for stat, tag in LOSS_TAGS.items():
            assert [v for _, v in scalars[tag]] == f32([r["stats"][stat] for r in updates])
    expected = expected_board(lines)
    for w in board:
        for tag, points in expected[w].items():
            assert board[w][tag] == points, f"{w} {tag}"
    rounds = [r for r in lines if r["type"] == "round"]
    transfers = [r for r in rounds if r["kind"] == "transfer"]
    assert transfers, "seed 3 has workers finishing early"
    assert sum(len(board[w].get("federation/keep_weight", [])) for w in board) == sum(
        len(r["keep_weights"]) for r in transfers)
    assert sum(len(board[w]["federation/contribution_weight"]) for w in board) == sum(
        len(r["weights"]) for r in rounds)
    audit(weighted_run)  # the records the board was drawn from are the audited ones


@needs_writer
@pytest.mark.slow
def test_the_chief_writes_the_board_live_over_mqtt(tmp_path: Path) -> None:
    """`make run`'s launcher (embedded broker on a free loopback port, chief and 2 workers as processes): a point is
    in an event file while the chief is still running, and at the end the board says what metrics.jsonl says."""
    run_dir = tmp_path / "mqtt"
    argv = [sys.executable, "-m", "deploy.run_local", "--workers", "2", "--env", "CartPole-v0", "--policy", "weighted",
            "--seed", "1", "--max-episodes", "30", "--run-dir", str(run_dir), "--run-id", "tblive",
            "--dashboard-port", "off"]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    seen_live = False
    try:
        deadline = time.monotonic() + 300
        while proc.poll() is None and time.monotonic() < deadline and not seen_live:
            for events in (run_dir / "tensorboard").glob("*/events.out.tfevents.*"):
                if read_event_file(events).get("charts/episodic_return") and not (run_dir / "summary.json").exists():
                    seen_live = proc.poll() is None
            time.sleep(0.1)
        output, _ = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, output[-3000:]
    assert seen_live, "no point in an event file while the run was going"
    board = read_board(run_dir)
    assert sorted(board) == ["w0", "w1"]
    lines = records(run_dir)
    expected = expected_board(lines)
    for w, scalars in board.items():
        assert set(CLEANRL_TAGS) <= set(scalars)
        assert len(scalars["charts/episodic_return"]) == len(
            [r for r in lines if r["type"] == "episode" and r["worker"] == w])
        for tag, points in expected[w].items():
            assert scalars[tag] == points, f"{w} {tag}"


@needs_writer
@pytest.mark.slow  # the module's 4-worker federation to the end (weighted_run)
def test_the_offline_rebuild_draws_the_same_board(weighted_run: Path, tmp_path: Path) -> None:
    live = read_board(weighted_run)
    proc = subprocess.run([sys.executable, "-m", "chief.tensorboard", str(weighted_run)], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "tensorboard --logdir" in proc.stdout
    assert read_board(weighted_run) == live  # the old files were replaced, not added to
    assert subprocess.run([sys.executable, "-m", "chief.tensorboard", str(tmp_path)], capture_output=True,
                          timeout=120).returncode == 2  # no metrics.jsonl


@needs_writer
def test_a_large_run_is_drawn_once_at_its_end_and_the_same(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                           caplog: pytest.LogCaptureFixture) -> None:
    """Above LIVE_WORKERS workers the chief keeps no writer per worker during the run (each holds a file and a
    thread, and costs it time every round): it draws the board once, at the end, a group of workers at a time, and
    that board is the live one of the same run."""
    live_dir, late_dir = tmp_path / "live", tmp_path / "late"
    run_federation(InprocessSettings.given(env="CartPole-v0", policy="weighted", seed=3, workers=3, max_episodes=4,
                   run_dir=live_dir), plot=False)
    monkeypatch.setattr(tensorboard, "LIVE_WORKERS", 2)  # 3 workers: drawn at the end, two writers open at most
    opened: list[int] = []
    board_class = tensorboard.Board

    class Counting(board_class):  # type: ignore[misc, valid-type]
        def _write(self, points: list[tensorboard.Point]) -> None:
            super()._write(points)
            opened.append(len(self._writers))

    monkeypatch.setattr(tensorboard, "Board", Counting)
    with caplog.at_level(logging.INFO):
        run_federation(InprocessSettings.given(env="CartPole-v0", policy="weighted", seed=3, workers=3, max_episodes=4,
                       run_dir=late_dir), plot=False)
    assert "drawn at the end of the run" in caplog.text
    assert opened and max(opened) <= 2
    assert read_board(late_dir) == read_board(live_dir)


@needs_writer
def test_a_per_step_strategy_draws_each_episode_once(tmp_path: Path) -> None:
    """Under `sync` every mini-batch step is a round and sends its own statistics: an episode's losses and
    contribution weights are drawn once, as the means over its steps, at the episode's env steps."""
    run_dir = tmp_path / "sync"
    run_federation(InprocessSettings.given(env="CartPole-v0", policy="sync", seed=1, workers=2, max_episodes=4,
                   run_dir=run_dir), plot=False)
    lines = records(run_dir)
    board = read_board(run_dir)
    for w, scalars in board.items():
        mine = [r for r in lines if r.get("worker") == w and r["type"] in ("episode", "step")]
        episodes = [r for r in mine if r["type"] == "episode"]
        assert len(episodes) == 4 and len(scalars["charts/episodic_return"]) == 4
        x = np.cumsum([r["steps"] for r in episodes])
        for stat, tag in LOSS_TAGS.items():
            means = [np.mean([r["stats"][stat] for r in mine if r["episode"] == e["episode"]]) for e in episodes]
            assert [p[0] for p in scalars[tag]] == list(x)
            assert [p[1] for p in scalars[tag]] == pytest.approx(means, rel=1e-6, abs=1e-7)
        rounds = [r for r in lines if r["type"] == "round"]
        assert len(rounds) == 4 * 10  # K = 10 rounds per episode, drawn once per episode
        weights = [np.mean([r["weights"][w] for r in rounds if r["episode"] == e["episode"]]) for e in episodes]
        assert [p[1] for p in scalars["federation/contribution_weight"]] == pytest.approx(weights, rel=1e-6)
        assert [p[0] for p in scalars["federation/contribution_weight"]] == list(x)


def test_without_tensorboardx_the_run_goes_on_and_says_so_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                caplog: pytest.LogCaptureFixture) -> None:
    monkeypatch.setitem(sys.modules, "tensorboardX", None)  # `import tensorboardX` now raises ImportError
    with caplog.at_level(logging.WARNING):
        summary = run_federation(InprocessSettings.given(env="CartPole-v0", policy="weighted", seed=1, workers=2,
                                 max_episodes=3, run_dir=tmp_path / "run"), plot=False)
    assert summary.rounds == 3 and len(records(tmp_path / "run")) == 2 * 3 + 3
    said = [r.getMessage() for r in caplog.records if "tensorboardX" in r.getMessage()]
    assert len(said) == 1 and "not installed" in said[0] and "pip install .[tb]" in said[0]
    assert not (tmp_path / "run" / "tensorboard").exists()
    assert tensorboard.main([str(tmp_path / "run")]) == 1


@needs_writer
def test_a_board_that_cannot_write_never_stops_the_run(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "tensorboard").write_text("a file where the folder should be")
    with caplog.at_level(logging.ERROR):
        summary = run_federation(InprocessSettings.given(env="CartPole-v0", policy="weighted", seed=1, workers=2,
                                 max_episodes=3, run_dir=run_dir), plot=False)
    assert summary.rounds == 3
    assert len([r for r in caplog.records if "TensorBoard" in r.getMessage()]) == 1


def test_the_chief_records_the_statistics_it_accepted(tmp_path: Path) -> None:
    """Through the wire and the round state machine: an accepted update's statistics are in its record (null where
    the worker sent none); a refused one leaves no record."""
    keeper = RoundKeeper(["w0", "w1"], "weighted", task("CartPole-v0"), 10, 30.0)
    gradient = pack_arrays({"g": np.ones(3, np.float32)})
    stats = dict(actor_loss=-0.02, critic_loss=3.5, entropy=0.69, approx_kl=0.004, clip_fraction=0.125)
    sent = WorkerUpdate(worker_id="w0", episode=1, episode_return=20.0, pi=20.0, recent_returns=[20.0], steps=20,
                        gradient=gradient, **stats)
    verdict = keeper.submit(submission_of(decode(encode(sent), WorkerUpdate)), now=0.0)
    assert verdict.status == "accepted" and verdict.record(0.0)["stats"] == stats
    older = WorkerUpdate(worker_id="w1", episode=1, episode_return=30.0, pi=30.0, recent_returns=[30.0], steps=30,
                         gradient=gradient, actor_loss=0.1)
    verdict = keeper.submit(submission_of(decode(encode(older), WorkerUpdate)), now=0.0)
    assert verdict.record(0.0)["stats"] == {**dict.fromkeys(STAT_BOUNDS), "actor_loss": 0.1}
    lying = WorkerUpdate(worker_id="w0", episode=2, episode_return=20.0, pi=99.0, recent_returns=[20.0, 20.0],
                         steps=20, gradient=gradient, **stats)
    assert keeper.submit(submission_of(lying), now=1.0).status == "rejected"  # never recorded (pi_mismatch)


def test_a_worker_sends_only_what_the_wire_takes() -> None:
    """Non-finite or out-of-bounds statistics go as None (the message must still be sent); float32 rounding's
    slightly negative approx-KL goes as 0."""
    stats = UpdateStats(actor_loss=float("nan"), critic_loss=float("inf"), entropy=0.5, approx_kl=-3e-9,
                        clip_fraction=1.5, memory_size=10)
    fields = _loss_fields(stats)
    assert fields == {"actor_loss": None, "critic_loss": None, "entropy": 0.5, "approx_kl": 0.0,
                      "clip_fraction": None}
    WorkerUpdate(worker_id="w0", episode=1, episode_return=1.0, pi=1.0, recent_returns=[1.0], steps=1,
                 gradient=pack_arrays({"g": np.ones(1, np.float32)}), **fields)


def test_the_writer_keeps_the_chief_torch_free() -> None:
    """tensorboardX would import torch (185 MiB) into the torch-free chief; the chief's writer does without it, and
    torch still imports afterwards in the same process."""
    code = ("import sys, tempfile\n"
            "from chief import tensorboard\n"
            "w = tensorboard._writer_class()(tempfile.mkdtemp()); w.add_scalar('a', 1.0, 1); w.close()\n"
            "assert 'torch' not in sys.modules, 'tensorboardX pulled torch into the chief'\n"
            "import torch\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
