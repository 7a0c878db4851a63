"""BENCHMARKS.md, assembled from every section's saved results.

Each benchmark section's results are saved on their own, ``benchmarks/results/NAME.json`` (a quick
run's ``NAME-quick.json``): the :class:`~benchmarks.common.Section` s it measured, the command, the
date and the machine it ran on. The report is always assembled from the saved results of every
section, so rerunning one section (``python -m benchmarks --only NAME``) replaces that section alone,
and every section states the machine and date it was measured on.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

from benchmarks.common import ROOT, Section, machine, markdown

RESULTS = ROOT / "benchmarks" / "results"

#: every section's name (``--only NAME``) in the report's order, and its title
SECTIONS = {
    "speed": "Speed",
    "reference": "Prismatic speed beside the reference code",
    "accuracy": "Accuracy",
    "robustness": "Robustness and honesty (default configuration)",
    "scale": "Scale",
    "scale-cli": "Scale through the CLI",
    "startup": "Start-up through the CLI",
    "tracker-geometry": "Tracker geometry",
    "tracker-geometry-honesty": "The tracker's geometry error measured by calibrate",
    "plan-poses": "Planned poses for outside instruments",
    "prediction": "Predicted errors against the truth",
    "prediction-power": "calibrate's bands over a thousand robots",
    "elastic": "The elastic robot",
    "elastic-geometries": "The elastic check on other geometries",
    "elastic-payload": "An unannounced payload on the paper's experiment",
    "hobby": "The real data's stand-in: every method against the builders' 48-parameter fit",
    "honesty": "Honesty over a grid",
    "link": "Live link to a controller",
    "rotary": "The rotary (servo-horn) hexapod",
    "tilt": "The elastic robot on a tilting mount",
    "thermal": "Temperature: the warm-up",
}

#: 1-minute load average per core above which a section says its machine was loaded
LOADED_PER_CORE = 0.5
VERSIONS = ("python", "numpy", "scipy", "numba", "gtsam", "filterpy", "stewart_calib")
NOT_STATED = "not stated"


def results_path(name: str, quick: bool, directory: Path = RESULTS) -> Path:
    return directory / f"{name}{'-quick' if quick else ''}.json"


def start(command: str) -> dict:
    """The machine, the load and the clock as a section's measurement starts."""
    info = {"command": command, "machine": machine()}
    info["machine"]["load_before"] = list(os.getloadavg())
    info["start"] = time.perf_counter()
    return info


def save(name: str, sections: list[Section], info: dict, quick: bool, directory: Path = RESULTS) -> Path:
    """Save ``sections`` as section ``name``'s results, with :func:`start`'s ``info`` completed."""
    info = dict(info)
    info["machine"]["load_after"] = list(os.getloadavg())
    info["seconds"] = time.perf_counter() - info.pop("start")
    info["date"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    path = results_path(name, quick, directory)
    directory.mkdir(parents=True, exist_ok=True)
    record = {"name": name, **info, "sections": [s.to_dict() for s in sections]}
    path.write_text(json.dumps(record, indent=1, ensure_ascii=False, default=float) + "\n", encoding="utf-8")
    return path


def load(name: str, quick: bool, directory: Path = RESULTS) -> dict | None:
    path = results_path(name, quick, directory)
    if not path.exists():
        return None
    record = json.loads(path.read_text(encoding="utf-8"))
    record["sections"] = [Section.from_dict(s) for s in record["sections"]]
    return record


def measured_line(record: dict) -> str:
    """Where and when a section was measured: command, date, machine, load and versions."""
    host = record.get("machine", {})
    cores = f", {host['cores']} cores" if host.get("cores") else ""
    cores += f", {host['blas_kernels']} kernels" if host.get("blas_kernels") else ""
    minutes = f" in {record['seconds'] / 60:.1f} min" if record.get("seconds") else ""
    if "load_before" in host:
        before, after = host["load_before"][0], host["load_after"][0]
        load = f"1-min load average {before:.2f} before, {after:.2f} after"
        if host.get("cores") and max(before, after) / host["cores"] > LOADED_PER_CORE:
            load += " (a loaded machine, shared with other work: absolute times are pessimistic, ratios less so)"
    else:
        load = f"load {host.get('load', NOT_STATED)}"
    versions = [f"{k} {host[k]}" for k in VERSIONS if k in host]
    return (
        f"Measured by `{record['command']}`{minutes}; date: {record.get('date', NOT_STATED)}; machine: "
        f"{host.get('cpu', NOT_STATED)}{cores}; {load}" + (f"; {', '.join(versions)}." if versions else ".")
    )


def assemble(quick: bool = False, directory: Path = RESULTS, report: Path | None = None) -> str:
    """The report from every section's saved results in ``directory`` (sections never measured are left out)."""
    report = report or (ROOT / "BENCHMARKS.md" if not quick else directory / "quick.md")
    records = [r for r in (load(name, quick, directory) for name in SECTIONS) if r is not None]
    sections = [(record, s) for record in records for s in record["sections"]]
    targets = [(s.title, row) for _, s in sections for row in s.rows if row.met is not None]
    met = sum(bool(row.met) for _, row in targets)
    missed = "; ".join(f"{title}: {row.name}" for title, row in targets if not row.met)
    lines = [
        "# Benchmarks",
        "",
        "Generated by `python -m benchmarks" + (" --quick" if quick else "") + "` from the saved results of "
        "every section (`benchmarks/results/`, one JSON file a section, raw numbers included); "
        "`python -m benchmarks --only NAME …` measures some sections again and regenerates this page. "
        "Each section states the command, the machine and the date it was measured on. Times are per call "
        "(median and p99 over many calls) unless a section says otherwise; comparisons with a peer are "
        "measured side by side in the same run.",
        "",
        f"Targets: **{met} of {len(targets)} met**" + (f"; not met — {missed}." if missed else "."),
        "",
    ]
    for record, section in sections:
        lines += [f"## {section.title}", "", measured_line(record), "", markdown(section), ""]
        if section.plot:
            plot = os.path.relpath(directory / section.plot, report.parent)
            lines += [f"![{section.title.lower()}: time per sample and memory]({plot})", ""]
    return "\n".join(lines).rstrip("\n") + "\n"


def write(quick: bool = False, directory: Path = RESULTS, report: Path | None = None) -> Path:
    report = report or (ROOT / "BENCHMARKS.md" if not quick else directory / "quick.md")
    report.write_text(assemble(quick, directory, report), encoding="utf-8")
    return report
