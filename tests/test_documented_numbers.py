"""Every generated table in the README and the docs is the table of the results file it names: re-rendered from
that file here, it must be what the page shows (a number edited by hand, or a results file replaced without
``--report``, fails)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def block(page: Path, begin: str, end: str) -> str:
    """The text between a page's markers (the begin marker's line excluded)."""
    text = page.read_text()
    start, stop = text.find(begin), text.find(end)
    assert 0 <= start < stop, f"{page} has no {begin!r} ... {end!r} block"
    return text[text.index("\n", start) + 1:stop]


def test_the_readme_results_table_is_paper_json(monkeypatch: pytest.MonkeyPatch) -> None:
    from bench import report

    monkeypatch.chdir(ROOT)
    assert block(ROOT / "README.md", report.BEGIN, report.END) == report.headline(report.default_folders()[0], ROOT)


def test_the_results_page_is_every_results_file(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from bench import report

    monkeypatch.chdir(ROOT)
    page = tmp_path / "results.md"
    report.write_docs(report.default_folders(), page)
    assert (ROOT / "docs" / "results.md").read_text() == page.read_text()


@pytest.mark.parametrize(("page", "actions"), [("README.md", "paper"), ("docs/how-to/lab.md", "paper"),
                                               ("docs/how-to/lab.md", "levels")])
def test_the_lab_tables_are_their_results_files(page: str, actions: str) -> None:
    """Each action set's lab table (bench/results/lab.json for paper, lab-levels.json for levels) is its own file's;
    the README shows the paper's only."""
    from bench import lab

    assert actions in lab.REPORTED and Path(page) in lab.pages_of(actions)
    source = lab.results_file(actions)
    if not (ROOT / source).exists():
        pytest.skip(f"{source} not measured yet")
    report = json.loads((ROOT / source).read_text())
    assert report["qube_actions"] == actions
    notes = Path(page) != lab.BRIEF  # the README leaves the runs' notes to the lab page
    assert block(ROOT / page, *lab.markers(actions)) == lab.render(report, str(source), notes=notes)


def test_the_sim_to_real_tables_are_sim2real_json() -> None:
    from bench import sim2real

    source = Path("bench/results/sim2real.json")
    expected = sim2real.report(json.loads((ROOT / source).read_text()), str(source))
    assert block(ROOT / "docs/how-to/warm-start.md", sim2real.BEGIN, sim2real.END) == expected + "\n"
    data = json.loads((ROOT / source).read_text())
    page = " ".join((ROOT / "docs/how-to/warm-start.md").read_text().split())
    episodes = data["pretrains"]["randomised"]["episodes"]
    shots = {name: f"{z['balanced_to_end']} of {z['rigs']}" for name, z in data["zero_shot"].items()}
    trials = data["disturbed_trials"]
    assert f"whose pretrain of the same seed took {episodes} episodes" in page
    assert f"now needs {episodes} episodes" in page
    assert (f"still balances {shots['randomised']} unseen `lab` rigs zero-shot; the `ideal` one "
            f"{shots['ideal']}") in page
    assert f"{sum(t['balanced_to_end'] for t in trials)} of {len(trials)} fine-tuned controllers pass" in page
    assert f"(also {data['reference_trials']['balanced_to_end']} of {data['reference_trials']['rigs']})" in page


def test_the_out_of_distribution_tables_are_ood_json() -> None:
    from bench import ood

    source = Path("bench/results/ood.json")
    if not (ROOT / source).exists():
        assert block(ROOT / "README.md", ood.BEGIN, ood.END).strip() == "Not measured yet."
        return
    data = json.loads((ROOT / source).read_text())
    assert block(ROOT / "README.md", ood.BEGIN, ood.END) == ood.render_readme(data, str(source))
    assert block(ROOT / ood.DOCS, ood.BEGIN, ood.END) == ood.render_docs(data, str(source))


def test_the_identification_tables_are_their_results_files() -> None:
    from bench import identify

    page = ROOT / "docs/how-to/identify.md"
    data = json.loads((ROOT / identify.RESULTS / "identify.json").read_text())
    assert block(page, "<!-- identify:begin", "<!-- identify:end") == identify.markdown(data)
    assert (block(page, "<!-- identify-protocols:begin", "<!-- identify-protocols:end")
            == identify.protocols_markdown(identify.PROTOCOLS, ROOT))


def test_the_swing_up_tables_are_their_results_files() -> None:
    from bench import swingup

    page = ROOT / "docs/how-to/ood.md"
    study = json.loads((ROOT / swingup.OUT).read_text())
    assert block(page, "<!-- swingup:begin", "<!-- swingup:end") == swingup.markdown(study)
    heavy, ood = (json.loads((ROOT / p).read_text()) for p in (swingup.RESET_HEAVY, swingup.OOD_SWINGUP))
    assert block(page, "<!-- swingup-reset:begin", "<!-- swingup-reset:end") == swingup.reset_markdown(heavy, ood)


def test_the_tier_pages_figures_are_their_results_files() -> None:
    """docs/explanation/tiered.md quotes bench.savetime, bench.stragglers --edges and both make scale runs in prose:
    each figure it quotes is the one in the file it names."""
    page = (ROOT / "docs/explanation/tiered.md").read_text().replace("\n", " ")

    def results(name: str) -> dict:
        return json.loads((ROOT / "bench/results" / name).read_text())

    save = results("savetime.json")
    assert (f"{save['state_bytes_early']:,} bytes at round 10 and {save['state_bytes_last']:,} at round 500"
            in page)
    assert f"{save['save_ms_early']:.1f} ms at round 10 and {save['save_ms_last']:.1f} ms at round 500" in page
    assert f"**{save['ratio']:.2f}x, target at most 1.5x, met**" in page
    straggler = results("stragglers-edges.json")
    pairs = [f"{p:.1f}" for p in straggler["pair_slowdowns_pct"]]
    assert f"**{straggler['quorum_slowdown_pct']:.1f} %**" in page
    assert f"(pairs {', '.join(pairs[:-1])} and {pairs[-1]} %;" in page
    for name, run in (("scale.json", "first"), ("scale-load.json", "second")):
        points = {(p["n"], p["edges"]): p for p in results(name)["points"]}
        tiered, flat = points[(1024, 16)], points[(64, 0)]
        assert f"{tiered['root_bytes_per_round']:,}" in page
        assert f"{tiered['root_bytes_per_round'] / tiered['update_bytes']:.1f} updates' worth" in page
        ratio = tiered["root_cpu_ms_per_round"] / flat["root_cpu_ms_per_round"]
        assert (f"{tiered['root_cpu_ms_per_round']:.0f}" in page and f"{flat['root_cpu_ms_per_round']:.0f} ms in the "
                f"{run} run ({ratio:.2f}x)" in page), run


def test_the_identifications_of_the_ood_table_are_ood_json() -> None:
    """docs/how-to/ood.md counts the rigs identified for the table's self-test and reset columns: from ood.json."""
    page = (ROOT / "docs/how-to/ood.md").read_text().replace("\n", " ")
    entries = json.loads((ROOT / "bench/results/ood.json").read_text())["entries"]
    ident = [v for k, v in entries.items() if k.startswith("identify/")]
    assert f"Of the {len(ident)} rigs identified, {sum(v['ok'] for v in ident)} were trusted" in page


def test_the_bridge_page_reset_table_is_reset_json() -> None:
    from bench import reset

    data = json.loads((ROOT / "bench/results/reset.json").read_text())
    expected = reset.markdown({**data, "out": "bench/results/reset.json"})
    assert block(ROOT / reset.PAGE, reset.BEGIN, reset.END) == expected
