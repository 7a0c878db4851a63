"""The study at a glance, beside results.parquet: per (cell, method) quantiles, and plots.

* ``summary.csv``: one row per cell and method — the cell's settings, runs, failures, the
  fraction of runs whose NEES falls in the two-sided 95 % χ²(42) band (0.95 for a consistent
  estimator), and for every score its 5, 25, 50, 75 and 95 % quantiles over the seeds.
* ``summary.md``: the same as a readable table (medians, the interquartile range of RMS/CRB).
* ``plots/<score>.png``: per swept setting, the median and interquartile range of the score
  against the setting's values, one line per method (the other settings pooled).
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np
import pyarrow as pa
from scipy.stats import chi2

from ..io import atomic_path, atomic_write_text
from .spec import Family, SweepSpec

QUANTILES = (0.05, 0.25, 0.5, 0.75, 0.95)
SCORES = (
    "rms_mm",
    "rms_over_crb",
    "nees",
    "z2",
    "closed_loop_mm",
    "closed_loop_motion_mm",
    "closed_loop_nominal_motion_mm",
    "seconds",
    "cpu_seconds",
)
PLOTTED = ("rms_over_crb", "nees", "closed_loop_mm", "closed_loop_motion_mm", "seconds")
#: plotted on a log scale (they span decades across a grid)
LOG_SCALED = ("rms_over_crb", "nees", "closed_loop_mm", "closed_loop_motion_mm")


def nees_in_band(nees: np.ndarray, dof: np.ndarray) -> np.ndarray:
    """Whether each NEES lies in the two-sided 95 % band of χ² with its own degrees of freedom
    (42 for the tracker's δM, 48 with the stroke scales, 36 for an outside instrument's gauge-free
    δM and scales); False where there is none."""
    dof = np.where(np.isfinite(dof) & (dof > 0), dof, np.nan)
    low, high = chi2.ppf(0.025, dof), chi2.ppf(0.975, dof)
    with np.errstate(invalid="ignore"):
        return (nees >= low) & (nees <= high)


def summarise(spec: SweepSpec, table: pa.Table) -> list[dict]:
    """One dict per (cell, method) that has rows, in grid and method order."""
    columns = table.to_pydict()
    groups: dict[tuple[str, str], list[int]] = {}
    for r, key in enumerate(zip(columns["cell"], columns["method"], strict=True)):
        groups.setdefault(key, []).append(r)
    summary = []
    for cell in spec.cells:
        for method in spec.methods:
            rows = groups.get((cell.id, method))
            if not rows:
                continue
            entry = {
                "cell": cell.id,
                **{name: cell.settings[name] for name in spec.swept},
                "method": method,
                "runs": len(rows),
            }
            entry["failed"] = sum(1 for r in rows if columns["failure"][r])
            nees = np.array([columns["nees"][r] for r in rows], dtype=float)
            dof = np.array([columns["nees_dof"][r] for r in rows], dtype=float)
            entry["nees_in_band"] = float(np.mean(nees_in_band(nees, dof)))
            z2 = np.array([columns["z2"][r] for r in rows], dtype=float)
            entry["z2_mean"] = float(np.mean(z2[np.isfinite(z2)])) if np.isfinite(z2).any() else float("nan")
            for name in SCORES:
                values = np.array([columns[name][r] for r in rows], dtype=float)
                values = values[np.isfinite(values)]
                for q in QUANTILES:
                    entry[f"{name}_q{round(100 * q):02d}"] = (
                        float(np.quantile(values, q)) if values.size else float("nan")
                    )
            summary.append(entry)
    return summary


def write_summary(spec: SweepSpec, table: pa.Table, out: Path) -> list[Path]:
    """Write summary.csv, summary.md and the plots; returns the paths written."""
    summary = summarise(spec, table)
    if not summary:
        return []
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(summary[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in entry.items()} for entry in summary)
    atomic_write_text(out / "summary.csv", buffer.getvalue())
    atomic_write_text(out / "summary.md", _markdown(spec, summary))
    return [out / "summary.csv", out / "summary.md", *_plots(spec, table, out / "plots")]


def _tracker_dof(spec: SweepSpec) -> int | None:
    """The NEES's degrees of freedom with the tracker: δM of the first tracker cell's drive (a
    family's draws keep its legs); None without a tracker cell."""
    tracked = [cell for cell in spec.cells if cell.settings["instrument"] == "tracker"]
    if not tracked:
        return None
    platform = tracked[0].platform
    return (platform.like if isinstance(platform, Family) else platform).drive.n_params


def _markdown(spec: SweepSpec, summary: list[dict]) -> str:
    dof = _tracker_dof(spec)
    band = "" if dof is None else f", [{chi2.ppf(0.025, dof):.1f}, {chi2.ppf(0.975, dof):.1f}] for the tracker's {dof}"
    head = [
        *spec.swept,
        "method",
        "runs",
        "RMS [mm]",
        "RMS/CRB median [IQR]",
        "NEES median",
        "NEES in 95 % band",
        "z² median",
        "z² mean",
        "closed loop [mm]",
        "motion from home [mm] (nominal)",
        "s per run",
    ]
    lines = [
        f"# Sweep '{spec.name}'",
        "",
        f"{len(spec.cells)} cells × {len(spec.seeds)} seeds × {len(spec.methods)} methods; medians over the seeds "
        "(IQR: 25–75 % quantiles; NEES band: the two-sided 95 % band of χ² with the row's degrees of freedom"
        f"{band}). Quantiles of every score: summary.csv.",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]
    for e in summary:
        cells = [str(e[name]) for name in spec.swept] + [
            e["method"],
            f"{e['runs']}" + (f" ({e['failed']} failed)" if e["failed"] else ""),
        ]
        cells += [
            f"{e['rms_mm_q50']:.3g}",
            f"{e['rms_over_crb_q50']:.3g} [{e['rms_over_crb_q25']:.3g}–{e['rms_over_crb_q75']:.3g}]",
            f"{e['nees_q50']:.3g}",
            f"{e['nees_in_band']:.0%}",
            f"{e['z2_q50']:.3g}",
            f"{e['z2_mean']:.3g}",
            f"{e['closed_loop_mm_q50']:.3g}",
            f"{e['closed_loop_motion_mm_q50']:.3g} ({e['closed_loop_nominal_motion_mm_q50']:.3g})",
            f"{e['seconds_q50']:.2g}",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _plots(spec: SweepSpec, table: pa.Table, directory: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    directory.mkdir(exist_ok=True)
    columns = table.to_pydict()
    methods = np.array(columns["method"], dtype=object)
    axes_names = spec.swept or ["method"]
    written = []
    for score in PLOTTED:
        fig, panels = plt.subplots(1, len(axes_names), figsize=(4.5 * len(axes_names), 3.6), squeeze=False)
        values = np.array(columns[score], dtype=float)
        for panel, axis in zip(panels[0], axes_names, strict=True):
            ticks = spec.axes[axis] if axis != "method" else [None]
            setting = np.array(columns[axis], dtype=object) if axis != "method" else None
            for m, method in enumerate(spec.methods):
                medians, lows, highs = [], [], []
                for tick in ticks:
                    pick = (methods == method) & np.isfinite(values) & (True if setting is None else setting == tick)
                    chosen = values[pick]
                    q = np.quantile(chosen, [0.25, 0.5, 0.75]) if chosen.size else np.full(3, np.nan)
                    lows.append(q[1] - q[0])
                    medians.append(q[1])
                    highs.append(q[2] - q[1])
                x = np.arange(len(ticks)) + (m - (len(spec.methods) - 1) / 2) * 0.8 / max(1, len(spec.methods))
                if axis == "method":
                    x = np.array([m])
                panel.errorbar(
                    x, medians, yerr=[lows, highs], fmt="o-" if len(ticks) > 1 else "o", capsize=3, label=method
                )
            if axis == "method":
                panel.set_xticks(range(len(spec.methods)), spec.methods)
            else:
                panel.set_xticks(range(len(ticks)), [f"{t:g}" if isinstance(t, float) else str(t) for t in ticks])
                panel.set_xlabel(axis)
            panel.set_ylabel(score)
            if score in LOG_SCALED and np.nanmin(values, initial=np.inf) > 0:
                panel.set_yscale("log")
            panel.grid(alpha=0.3)
        panels[0][0].legend(fontsize="small")
        fig.suptitle(f"{spec.name}: {score} (median, 25–75 %)")
        fig.tight_layout()
        path = directory / f"{score}.png"
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=90, format="png")
        plt.close(fig)
        written.append(path)
    return written
