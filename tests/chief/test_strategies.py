"""The strategy registry: found by scanning chief/strategies/, the single source of names for the CLI, the chief
and the docs, and each strategy's aggregation on hand-computed numbers."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from chief import strategies
from chief.rounds import RoundKeeper
from chief.strategies import median, trimmed
from protocol.rounds import RoundShape
from protocol.tasks import task
from tests.paths import ROOT


def grads(*values: float) -> dict[str, dict[str, np.ndarray]]:
    return {f"w{i}": {"g": np.array([v, -v], np.float32)} for i, v in enumerate(values)}


def test_registry_holds_the_paper_policies_and_the_robust_ones() -> None:
    assert strategies.names() == ["independent", "median", "plain", "sync", "trimmed", "weighted"]
    assert strategies.get("weighted").keep_weight(0.3) == 0.3
    with pytest.raises(ValueError, match="choose one of independent, median, plain, sync, trimmed, weighted"):
        strategies.get("fedavg")


def test_a_new_strategy_is_one_new_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "halfmean.py").write_text(
        "from chief.strategies.base import Aggregate, Strategy\n"
        "from chief import federation\n"
        "def aggregate(g, p):\n"
        "    w = {k: 1.0 / len(g) for k in g}\n"
        "    return Aggregate(federation.weighted_sum(g, w), w)\n"
        "STRATEGY = Strategy('halfmean', 'test', aggregate, lambda p: 0.5, lambda n: 0, 'none')\n")
    monkeypatch.setattr(strategies, "__path__", [*strategies.__path__, str(tmp_path)])
    assert "halfmean" in strategies.registry()


def test_the_round_shape_is_the_strategys() -> None:
    """The paper's strategies have one round per episode whatever K; ``sync`` has K, one per PPO mini-batch step,
    and cannot run with fewer than 2; the round keeper takes only its strategy's shape."""
    assert {name: strategies.get(name).rounds(10).per_episode for name in strategies.names()} == {
        "independent": 1, "median": 1, "plain": 1, "sync": 10, "trimmed": 1, "weighted": 1}
    with pytest.raises(ValueError, match="at least 2 steps"):
        strategies.get("sync").rounds(1)
    with pytest.raises(ValueError, match="other rounds than 10 per episode"):
        RoundKeeper(["w0"], "weighted", task("CartPole-v0"), 10, 1.0, shape=RoundShape(per_episode=10))


def test_median_and_trimmed_by_hand() -> None:
    # N = 4: both drop the extremes per coordinate and average the middle two.
    for module in (median, trimmed):
        out = module.aggregate(grads(1.0, 2.0, 3.0, 1e30), {}).gradient
        np.testing.assert_allclose(out["g"], [2.5, -2.5])
    # N = 5: the median takes the middle value, the trimmed mean drops one per tail and averages three.
    np.testing.assert_allclose(median.aggregate(grads(1, 2, 4, 8, -1e30), {}).gradient["g"], [2.0, -2.0])
    np.testing.assert_allclose(trimmed.aggregate(grads(1, 2, 4, 8, -1e30), {}).gradient["g"], [7 / 3, -7 / 3],
                               rtol=1e-6)
    # N = 8: trimmed drops two per tail.
    assert trimmed.trim(8) == 2 and trimmed.trim(4) == 1 and trimmed.trim(3) == 1 and trimmed.trim(2) == 0
    # N = 2: nothing to trim, both are the mean.
    np.testing.assert_allclose(trimmed.aggregate(grads(1, 3), {}).gradient["g"], [2.0, -2.0])
    np.testing.assert_allclose(median.aggregate(grads(1, 3), {}).gradient["g"], [2.0, -2.0])


def test_tolerance_is_documented_for_each_n() -> None:
    assert [strategies.get("median").tolerates(n) for n in (1, 2, 3, 4, 5, 8)] == [0, 0, 1, 1, 2, 3]
    assert [strategies.get("trimmed").tolerates(n) for n in (2, 3, 4, 8)] == [0, 1, 1, 2]
    assert strategies.get("weighted").tolerates(4) == strategies.get("plain").tolerates(4) == 0


def test_the_docs_table_is_generated_from_the_registry() -> None:
    page = (ROOT / "docs" / "explanation" / "strategies.md").read_text(encoding="utf-8")
    block = re.search(r"<!-- strategies:begin -->\n(.*?)\n<!-- strategies:end -->", page, re.S)
    assert block is not None, "docs/explanation/strategies.md lacks the generated strategy table"
    assert block.group(1).strip() == strategies.markdown_table().strip(), (
        "the strategy table in docs/explanation/strategies.md is out of date: python -m chief.strategies --markdown")


def test_cli_choices_come_from_the_registry() -> None:
    out = subprocess.run([sys.executable, "-m", "chief", "--policy", "nope"], capture_output=True, text=True)
    assert out.returncode == 2 and "median" in out.stderr and "trimmed" in out.stderr
    listing = subprocess.run([sys.executable, "-m", "chief.strategies"], capture_output=True, text=True, check=True)
    assert [line.split()[0] for line in listing.stdout.splitlines()] == strategies.names()
