"""``python -m bench.identify``: how well the identification (rpi_bridge/identify.py's protocol, services/qube_sim/
identify.py's fit) recovers simulated rigs of every family outside ``lab`` (services/qube_sim/families.py).

Each rig: the profile's rig ``seed`` (its spread and non-ideal spread drawn as usual: the truth differs from the
profile), recorded through the bridge's ControlCore on a virtual clock, fitted over ``lab`` (so the fit never sees the
truth). Reported per rig and parameter: fitted value, truth, relative error, the stated relative 1-sigma; the held-out
and training RMS angle errors, whether the fit is trusted (else the refusal), rig seconds, record and fit wall seconds;
and per family the median |relative error| of each parameter. Seeds 501-510 are never used in tests. Writes
``bench/results/identify.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

from bench.output import write_report
from rpi_bridge.control import ControlConfig, identify_config
from rpi_bridge.identify import IDENTIFY_ATTEMPTS, IdentifyConfig, Recording
from rpi_bridge.selftest import SelfTestConfig
from services.qube_sim import families
from services.qube_sim.dynamics import QubeParams
from services.qube_sim.identify import fit_attempts, record_simulated
from services.qube_sim.profile import LAB, RigProfile

RESULTS = Path("bench/results")
#: The bridge's core with a self-test pulse of 8 ticks instead of 4: the 4x arm inertia rigs move too little on 4 to
#: pass it (a self-test matter, not the identification's).
CONTROL = ControlConfig(self_test=SelfTestConfig(pulse_ticks=8))
#: Fitted name -> the QubeParams field of the truth it is compared with.
TRUTH = {"Dr": "Dr", "Dp": "Dp", "coulomb_arm": "Cr", "static_arm": "Sr", "coulomb_pendulum": "Cp", "motor": "km",
         "deadzone_v": "deadzone", "mr": "mr", "Lr": "Lr", "Lp": "Lp", "cable_stiffness": "cable_stiffness"}


def true_value(name: str, truth: QubeParams) -> float:
    """The truth fitted value ``name`` is compared with: its field of :data:`TRUTH`; for static_arm the arm's
    breakaway, max(Sr, Cr): a rig whose spread drew its static friction below its Coulomb friction has flat friction
    at the Coulomb level (services/qube_sim/dynamics.py ``friction``), which a fit describes as a ratio of 1."""
    value = float(getattr(truth, TRUTH[name]))
    return max(value, truth.Cr) if name == "static_arm" else value


def rigs(families_: list[str], seeds: dict[str, list[int]]) -> list[tuple[str, RigProfile, int]]:
    """(family, profile, seed) of every rig: the sweep's extreme factors (each parameter's lowest and highest), the
    combined family and course."""
    out: list[tuple[str, RigProfile, int]] = []
    if "sweep" in families_:
        for name, factors in families.SWEEPS.items():
            for k in (min(factors), max(factors)):
                out += [("sweep", families.family(name, k), s) for s in seeds["sweep"]]
    if "combined" in families_:
        out += [("combined", families.combined(), s) for s in seeds["combined"]]
    if "course" in families_:
        out += [("course", families.course(), s) for s in seeds["course"]]
    return out


def protocol(text: str) -> dict[str, float]:
    """``--protocol``: comma-separated NAME=NUMBER overrides of rpi_bridge.identify.IdentifyConfig's scalar fields."""
    scalars = {f.name: f.type for f in dataclasses.fields(IdentifyConfig) if f.type in ("float", "int")}
    out: dict[str, float] = {}
    for item in filter(None, text.split(",")):
        name, _, value = item.partition("=")
        if name.strip() not in scalars:
            raise argparse.ArgumentTypeError(f"{name.strip()!r} is not one of {', '.join(sorted(scalars))}")
        try:
            number = float(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name.strip()}={value!r}: not a number") from None
        out[name.strip()] = int(number) if scalars[name.strip()] == "int" else number
    IdentifyConfig(**out)  # type: ignore[arg-type]  # its own checks: one clear line for an impossible protocol
    return out


def control(overrides: dict[str, float] | None = None) -> ControlConfig:
    """CONTROL, with the identification protocol's defaults changed by ``overrides`` (``--protocol``)."""
    if not overrides:
        return CONTROL
    changed = dataclasses.replace(identify_config(CONTROL), **overrides)  # type: ignore[arg-type]  # scalars only
    return dataclasses.replace(CONTROL, identify=changed)


class _ProtocolFailed(Exception):
    """The protocol could not finish on a rig (a result of bench.identify, not an error of it)."""


def one(family: str, profile: RigProfile, seed: int, overrides: dict[str, float] | None = None,
        attempts: int = IDENTIFY_ATTEMPTS) -> dict[str, Any]:
    """Identify rig ``seed`` of ``profile`` as the pipeline does (a refused fit recorded again, up to ``attempts``
    recordings) and compare the last fit with the rig's truth."""
    truth = profile.rig_params(seed)
    row: dict[str, Any] = {"family": family, "profile": profile.name, "seed": seed}
    walls: list[float] = []

    def record(attempt: int) -> Recording:
        began = time.perf_counter()
        try:
            rec = record_simulated(profile, seed, control(overrides), attempt=attempt)
        except Exception as err:  # the protocol could not finish on this rig: that is a result
            raise _ProtocolFailed(str(err)) from err
        walls.append(time.perf_counter() - began)
        return rec

    spent, result = 0.0, None
    try:
        for attempt, (rec, fitted, refusal) in enumerate(fit_attempts(record, LAB, attempts)):
            result = fitted  # the last recording's fit is the one compared with the truth
            spent += rec.rig_seconds
            row.update(rig_seconds=round(spent, 1), attempts=attempt + 1, record_wall_s=round(walls[-1], 1),
                       outcome="trusted" if refusal is None else f"refused: {refusal}")
    except _ProtocolFailed as err:
        return {**row, "outcome": f"protocol failed: {err}"}
    if result is None:
        return row
    row["fit_wall_s"] = round(result.wall_s, 1)
    row["evaluations"] = result.iterations
    row["train_rms_deg"] = round(result.train_rms_deg, 3)
    row["heldout_rms_deg"] = round(result.heldout_rms_deg, 3)
    row["parameters"] = {name: {"fitted": result.values[name], "truth": (true := true_value(name, truth)),
                                "error": (result.values[name] / true - 1) if true else None,
                                "sigma": result.sigma[name]}
                         for name in TRUTH}
    row["parameters"]["delay_ms"] = {"fitted": result.values["delay_ms"], "sigma_ms": result.sigma["delay_ms"],
                                     "rig_delay_ms": profile.sensing_latency_ms + profile.action_delay_ms
                                     + profile.action_jitter_ms / 2}
    return row


def medians(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per family: median |relative error| and median stated sigma of each parameter over its fitted rigs, and the
    medians of held-out error, rig and fit seconds."""
    out: dict[str, Any] = {}
    for family in sorted({r["family"] for r in rows}):
        fitted = [r for r in rows if r["family"] == family and "parameters" in r]
        if not fitted:
            continue
        summary: dict[str, Any] = {"rigs": len([r for r in rows if r["family"] == family]),
                                   "trusted": sum(r["outcome"] == "trusted" for r in fitted)}
        for name in TRUTH:
            errors = [abs(e) for r in fitted if (e := r["parameters"].get(name, {}).get("error")) is not None]
            if errors:
                summary[name] = {"median_abs_error": round(statistics.median(errors), 4),
                                 "max_abs_error": round(max(errors), 4),
                                 "median_sigma": round(statistics.median(
                                     r["parameters"][name]["sigma"] for r in fitted if name in r["parameters"]), 4)}
        for key in ("heldout_rms_deg", "train_rms_deg", "rig_seconds", "fit_wall_s", "record_wall_s"):
            summary[f"median_{key}"] = round(statistics.median(r[key] for r in fitted), 3)
        out[family] = summary
    return out


#: The four values the issue's identification target names (each within 20 % of the truth).
TARGET = ("Dp", "Dr", "coulomb_arm", "motor")
#: The protocol-length comparison on tuning rigs (``--protocols-markdown``): the protocol of each file.
PROTOCOLS = {
    "120 s (25 s decay, 2 breakaways per direction, 60 s PRBS: the protocol before)":
        RESULTS / "identify-protocol-120s.json",
    "90 s (as 120 s, 30 s PRBS)": RESULTS / "identify-protocol-90s.json",
    "80 s (12 s decay, 1 breakaway per direction, 35 s PRBS: the default)": RESULTS / "identify-protocol-80s.json",
}


def _pct(x: float) -> str:
    return f"{100 * x:.1f}%"


def _within(fitted: list[dict[str, Any]], name: str) -> int:
    """How many fitted rigs have ``name`` within 20 % of the truth."""
    return sum(abs(r["parameters"][name]["error"]) <= 0.2 for r in fitted)


def markdown(data: dict[str, Any]) -> str:
    """The benchmark's table for the docs (``--markdown``): per family, the median |relative error| of each fitted
    value (the median stated 1-sigma in brackets), the median held-out error, rig and fit seconds; then how many rigs
    had each of the target's values within 20 %."""
    head = f"Generated from `{RESULTS / 'identify.json'}`, made by `{data['command']}` ({data['wall_s']:.0f} s).\n\n"
    names = [n for n in TRUTH if any(n in m for m in data["medians"].values())]  # a file from before a value was fitted
    rows = ["| family | rigs | trusted | " + " | ".join(f"`{n}`" for n in names) + " | held-out RMS | rig s | fit s |",
            "| --- " * (len(names) + 6) + "|"]
    for family, m in data["medians"].items():
        cells = [f"{_pct(m[n]['median_abs_error'])} ({_pct(m[n]['median_sigma'])})" if n in m else "-" for n in names]
        rows.append(f"| {family} | {m['rigs']} | {m['trusted']} | " + " | ".join(cells)
                    + f" | {m['median_heldout_rms_deg']:.2f} deg | {m['median_rig_seconds']:.0f} | "
                    f"{m['median_fit_wall_s']:.0f} |")
    fitted = [r for r in data["results"] if "parameters" in r]
    within = ", ".join(f"{n} {_within(fitted, n)}" for n in TARGET)
    tail = (f"\nTrusted: {sum(r['outcome'] == 'trusted' for r in data['results'])} of {len(data['results'])} rigs. "
            f"Within 20 % of the truth, of {len(fitted)} fitted rigs: {within}.\n")
    return head + "\n".join(rows) + "\n" + tail


def protocols_markdown(files: dict[str, Path], root: Path = Path(".")) -> str:
    """The protocol lengths compared on the same tuning rigs (``--protocols-markdown``): one row per file (under
    ``root``)."""
    rows = ["| protocol | rigs | trusted | rig s, median | " + " | ".join(f"`{n}`: median, within 20 %" for n in TARGET)
            + " | held-out RMS |", "| --- " * (len(TARGET) + 5) + "|"]
    commands = []
    for label, path in files.items():
        data = json.loads((root / path).read_text())
        commands.append(f"`{data['command']}`")
        fitted = [r for r in data["results"] if "parameters" in r]
        cells = [f"{_pct(statistics.median(abs(r['parameters'][n]['error']) for r in fitted))}, "
                 f"{_within(fitted, n)}" for n in TARGET]
        rows.append(f"| {label} | {len(data['results'])} | {sum(r['outcome'] == 'trusted' for r in data['results'])} | "
                    f"{statistics.median(r['rig_seconds'] for r in fitted):.0f} | " + " | ".join(cells)
                    + f" | {statistics.median(r['heldout_rms_deg'] for r in fitted):.2f} deg |")
    head = "Generated from " + ", ".join(f"`{p}`" for p in files.values()) + ", made by " + "; ".join(commands)
    return head + ".\n\n" + "\n".join(rows) + "\n"


def seed_list(text: str) -> list[int]:
    if "-" in text:
        a, b = text.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(x) for x in text.split(",")]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.identify", description=__doc__.splitlines()[0])
    parser.add_argument("--families", nargs="+", choices=["sweep", "combined", "course"],
                        default=["sweep", "combined", "course"])
    parser.add_argument("--combined-seeds", type=seed_list, default=seed_list("501-510"), metavar="A-B|A,B,..")
    parser.add_argument("--course-seeds", type=seed_list, default=seed_list("501-505"), metavar="A-B|A,B,..")
    parser.add_argument("--sweep-seeds", type=seed_list, default=seed_list("501"), metavar="A-B|A,B,..")
    parser.add_argument("--jobs", type=int, default=1, help="rigs in parallel (processes)")
    parser.add_argument("--protocol", type=protocol, default={}, metavar="NAME=X,..",
                        help="change the protocol's defaults (rpi_bridge/identify.py IdentifyConfig), e.g. "
                             "decay_s=12,prbs_s=35,breakaway_repeats=1")
    parser.add_argument("--out", type=Path, default=RESULTS / "identify.json")
    parser.add_argument("--markdown", action="store_true", help="only print --out's table for the docs")
    parser.add_argument("--protocols-markdown", action="store_true",
                        help="only print the protocol lengths' comparison for the docs (bench/results/"
                             "identify-protocol-*.json)")
    args = parser.parse_args(argv)
    if args.markdown or args.protocols_markdown:
        print(markdown(json.loads(args.out.read_text())) if args.markdown else protocols_markdown(PROTOCOLS), end="")
        return 0
    todo = rigs(args.families, {"combined": args.combined_seeds, "course": args.course_seeds,
                                "sweep": args.sweep_seeds})
    began = time.perf_counter()
    rows = []
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        for row in pool.map(one, *zip(*todo, strict=True), [args.protocol] * len(todo)):
            brief = {k: row.get(k) for k in ("family", "profile", "seed", "outcome", "heldout_rms_deg", "fit_wall_s")}
            if "parameters" in row:
                brief.update({k: round(row["parameters"][k]["error"], 3) for k in ("Dp", "Dr", "coulomb_arm", "motor")})
            print(json.dumps(brief), flush=True)
            rows.append(row)
    write_report(args.out, "bench.identify", argv,
                 {"base": "lab", "protocol": args.protocol, "wall_s": round(time.perf_counter() - began, 1),
                  "medians": medians(rows), "results": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
