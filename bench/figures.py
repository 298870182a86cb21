"""The paper's figures from the benchmark's results: ``python -m bench.figures [RESULTS_DIR]`` redraws them from
``paper-<task>.json``.

- ``fig5-episodes.png`` / ``fig5-steps.png`` (paper Figure 5): per task and strategy, the mean over seeds of each
  run's mean PI over its workers, against the episode (or the mean env steps per worker), with the band between
  the 25th and 75th percentile over seeds. A finished worker keeps its last PI; a run that ended keeps its last
  value. The dotted line is TC.
- ``fig7-episodes.png`` / ``fig7-steps.png`` (paper Figure 7): per task, the last worker's episodes (or env steps)
  to finish, one box per strategy plus the references (one worker of ours alone, SB3 zoo PPO), every run a dot;
  unfinished runs are drawn as red crosses above the boxes and counted in the label.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from bench.runs import algo_of, learner_blocks, outcome

REFERENCE_LABELS = {"single": "1 worker (ours)", "sb3": "SB3 zoo"}


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _grid(n: int) -> tuple[int, int]:
    cols = min(n, 3)
    return math.ceil(n / cols), cols


def mean_curve(runs: list[dict[str, Any]], axis: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """(x, mean, q25, q75) over the runs' curves on a common grid; None without curves."""
    curves = [r["curve"] for r in runs if r.get("curve") and r["curve"]["episode"]]
    if not curves:
        return None
    key = "episode" if axis == "episodes" else "steps"
    end = max(c[key][-1] for c in curves)
    x = np.arange(1, int(end) + 1) if axis == "episodes" else np.linspace(0.0, float(end), 300)
    rows = []
    for c in curves:
        xs = np.asarray(c[key], float)
        ys = np.asarray([np.nan if v is None else v for v in c["pi"]], float)
        ok = ~np.isnan(ys)
        if not ok.any():
            continue
        row = np.interp(x, xs[ok], ys[ok])  # holds the last value past the run's end
        row[x < xs[ok][0]] = np.nan
        rows.append(row)
    if not rows:
        return None
    data = np.vstack(rows)
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            return x, np.nanmean(data, 0), np.nanpercentile(data, 25, 0), np.nanpercentile(data, 75, 0)


def run_groups(rep: dict[str, Any], references: tuple[str, ...]) -> list[tuple[str, list[dict[str, Any]]]]:
    """A task's runs by learner and strategy, then by each reference kind, labelled as the figures show them (the
    learner named when the task has more than one)."""
    blocks = learner_blocks(rep)
    groups = []
    for algo, block in blocks.items():
        mine = [r for r in rep["runs"] if algo_of(r) == algo]
        prefix = f"{algo} " if len(blocks) > 1 else ""
        groups += [(prefix + s, [r for r in mine if r["kind"] == "federation" and r["strategy"] == s])
                   for s in block.get("strategies", [])]
        groups += [(prefix + REFERENCE_LABELS[k], [r for r in mine if r["kind"] == k]) for k in references]
    return groups


def fig5(reports: dict[str, dict[str, Any]], path: Path, axis: str = "episodes") -> Path:
    plt = _plt()
    rows, cols = _grid(len(reports))
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 3.8 * rows), dpi=100, squeeze=False)
    for ax, (task, rep) in zip(axes.flat, reports.items(), strict=False):
        for label, runs in run_groups(rep, ("single",)):
            curve = mean_curve(runs, axis)
            if curve is None:
                continue
            x, mean, lo, hi = curve
            style = "--" if label.endswith(REFERENCE_LABELS["single"]) else "-"
            (line,) = ax.plot(x, mean, style, linewidth=1.4, label=label)
            ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.15, linewidth=0)
        ax.axhline(rep["tc"], color="black", linestyle=":", linewidth=1.2, label=f"TC {rep['tc']:g}")
        ax.set_title(f"{task}, {rep['workers']} workers, {len(rep['seeds']['report'])} seeds", fontsize=10)
        ax.set_xlabel("episode" if axis == "episodes" else "env steps per worker (mean over workers)")
        ax.set_ylabel("PI (mean of the last 10 returns)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
    for ax in list(axes.flat)[len(reports):]:
        ax.axis("off")
    fig.suptitle("Mean learning curve over seeds (band: 25th-75th percentile)", fontsize=11)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def fig7(reports: dict[str, dict[str, Any]], path: Path, axis: str = "episodes") -> Path:
    plt = _plt()
    rows, cols = _grid(len(reports))
    fig, axes = plt.subplots(rows, cols, figsize=(5.6 * cols, 3.9 * rows), dpi=100, squeeze=False)
    for ax, (task, rep) in zip(axes.flat, reports.items(), strict=False):
        groups = [(label, runs) for label, runs in run_groups(rep, ("single", "sb3")) if runs]
        done_all = []
        for i, (_, runs) in enumerate(groups):
            values = [_value(r, axis) for r in runs]
            done = [v for v in values if v is not None]
            done_all += done
            if done:
                ax.boxplot([done], positions=[i], widths=0.55, showfliers=False, medianprops={"color": "black"})
                jitter = np.linspace(-0.15, 0.15, len(done)) if len(done) > 1 else [0.0]
                ax.scatter(np.asarray(jitter) + i, done, s=12, alpha=0.7, zorder=3)
        top = max(done_all, default=1.0) * 1.08
        for i, (_, runs) in enumerate(groups):
            missed = sum(1 for r in runs if _value(r, axis) is None)
            if missed:
                ax.scatter([i], [top], marker="x", color="red", zorder=4)
                ax.annotate(f"{missed} unfinished", (i, top), textcoords="offset points", xytext=(0, 5),
                            ha="center", fontsize=7, color="red")
        ax.set_xticks(range(len(groups)), [f"{label}\n{_count(runs, axis)}" for label, runs in groups],
                      fontsize=7, rotation=30, ha="right")
        ax.set_ylim(0, top * 1.12)
        ax.set_ylabel("last worker's episodes to finish" if axis == "episodes" else "last worker's env steps")
        ax.set_title(f"{task} (M = {rep['max_episodes']})", fontsize=10)
        ax.grid(axis="y", alpha=0.3)
    for ax in list(axes.flat)[len(reports):]:
        ax.axis("off")
    fig.suptitle("Episodes until the last worker finished, per strategy" if axis == "episodes"
                 else "Env steps until the last worker finished, per strategy", fontsize=11)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def _value(r: dict[str, Any], axis: str) -> float | None:
    eps, steps = outcome(r)
    return eps if axis == "episodes" else steps


def _count(runs: list[dict[str, Any]], axis: str) -> str:
    return f"{sum(1 for r in runs if _value(r, axis) is not None)}/{len(runs)}"


def draw_all(reports: dict[str, dict[str, Any]], out: Path) -> list[Path]:
    """The four figures into ``out``."""
    return [fig5(reports, out / "fig5-episodes.png", "episodes"), fig5(reports, out / "fig5-steps.png", "steps"),
            fig7(reports, out / "fig7-episodes.png", "episodes"), fig7(reports, out / "fig7-steps.png", "steps")]


def load_reports(results: Path) -> dict[str, dict[str, Any]]:
    """The per-task reports of a results folder, in paper.json's task order."""
    index = json.loads((results / "paper.json").read_text())
    return {t: json.loads((results / f"paper-{t}.json").read_text()) for t in index["tasks"]}


if __name__ == "__main__":
    folder = Path(sys.argv[1]) if len(sys.argv) > 1 else Path("bench/results")
    for p in draw_all(load_reports(folder), folder):
        print(p)
