"""Honesty of the error bars over a grid: ``python -m benchmarks.honesty [--out DIR] [--seeds N] [--update-report]``.

Runs (or resumes) the sweep of ``configs/sweeps/honesty.toml`` — ekf, isam2 and lm on the
in-situ tracker, motion capture and a laser tracker, with the reading noise 0.2–5× what the
estimators are told, glitches 0 / 5 % and a drifting robot or not — on the local Dask cluster,
and tells per method and instrument the share of runs whose NEES falls in the two-sided 95 %
χ² band of its degrees of freedom, and the mean z² of every cell. Targets: NEES in band in
≥ 90 % of the runs, and the mean z² in [0.5, 2] in every cell. ``--update-report`` saves the
section's results in benchmarks/results/ and regenerates BENCHMARKS.md (as ``python -m
benchmarks --only honesty`` does). Finished tasks in DIR are kept (the sweep resumes).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.stats import binom, chi2

from benchmarks.common import ROOT, Row, Section, markdown

SPEC = ROOT / "configs" / "sweeps" / "honesty.toml"
NEES_TARGET = 0.90
Z2_RANGE = (0.5, 2.0)


def honesty_section(spec, table) -> Section:
    """One row per method and instrument from the sweep's rows."""
    from stewart_calib.sweep.summary import nees_in_band, summarise

    columns = table.to_pydict()
    cells = summarise(spec, table)
    rows = []
    for method in spec.methods:
        for instrument in spec.axes["instrument"]:
            pick = [
                r
                for r, (m, i) in enumerate(zip(columns["method"], columns["instrument"], strict=True))
                if m == method and i == instrument
            ]
            if not pick:
                continue
            nees = np.array([columns["nees"][r] for r in pick], dtype=float)
            dof = np.array([columns["nees_dof"][r] or np.nan for r in pick], dtype=float)
            share = float(np.mean(nees_in_band(nees, dof)))
            z2 = [
                c["z2_mean"] for c in cells if c["method"] == method and c.get("instrument", instrument) == instrument
            ]
            worst = min(
                (c for c in cells if c["method"] == method and c.get("instrument", instrument) == instrument),
                key=lambda c: c["nees_in_band"],
            )
            failed = sum(1 for r in pick if columns["failure"][r])
            in_range = all(Z2_RANGE[0] <= v <= Z2_RANGE[1] for v in z2)
            row = Row(
                f"{method} on {instrument}",
                f"NEES in band **{share:.0%}** of {len(pick)} runs (worst cell {worst['nees_in_band']:.0%}: "
                f"{_settings(worst, spec)}); mean z² per cell {min(z2):.2f}–{max(z2):.2f}"
                + (f"; {failed} runs failed" if failed else ""),
                f"≥ {NEES_TARGET:.0%} in band; mean z² in [{Z2_RANGE[0]:g}, {Z2_RANGE[1]:g}] in every cell",
                share >= NEES_TARGET and in_range and not failed,
                {"share_in_band": share, "z2_mean_per_cell": z2, "runs": len(pick), "failed": failed},
            )
            if not row.met and not failed and in_range:
                row.why = _outside_why(nees, dof)
            rows.append(row)
    return Section("Honesty over a grid", note(spec), rows)


def _outside_why(nees: np.ndarray, dof: np.ndarray) -> str:
    """Where a row's NEES fall outside their band (too small: σ too large; too large: over-confident), and how
    likely an honest 95 % band leaves out as many (no cause is known for such a miss)."""
    from stewart_calib.sweep.summary import nees_in_band

    outside = int(np.sum(~nees_in_band(nees, dof)))
    below = int(np.sum(nees < chi2.ppf(0.025, dof)))
    chance = float(binom.sf(outside - 1, len(nees), 0.05))
    return (
        f"{below} NEES below the band (σ too large) and {outside - below} above it (over-confident), mean NEES / dof "
        f"{np.mean(nees / dof):.3f}: an honest 95 % band leaves out {outside} or more of {len(nees)} runs with "
        f"probability {chance:.2g}"
    )


def section(quick: bool = False, out: Path | None = None, seeds: int | None = None, workers: int | None = None):
    """Run (or resume) the sweep in ``out`` and summarise it (``quick``: one seed a cell, in a scratch directory)."""
    import tempfile

    from stewart_calib.sweep import load_spec, run_sweep
    from stewart_calib.sweep.summary import write_summary

    spec = load_spec(SPEC)
    if quick or seeds is not None:
        spec = spec.pilot(1 if quick else seeds)
    with tempfile.TemporaryDirectory(prefix="stewart-calib-honesty-") as scratch:
        out = Path(scratch) if quick else (out or ROOT / "out" / "honesty")
        result = run_sweep(spec, out, workers=workers)
        write_summary(spec, result.table, out)
    return honesty_section(spec, result.table)


def note(spec) -> str:
    """The section's methods paragraph."""
    return (
        f"`configs/sweeps/honesty.toml`: {spec.n_cells} cells × {len(spec.seeds)} seeds, {spec.axes['samples'][0]} "
        "random workspace poses a run on nim-stewart; reading noise (tracker rulers, motion capture, laser tracker) "
        "0.2 / 1 / 5 × what the estimators are told, glitches 0 / 5 %, drift 0 / 0.002 mm/√s (the estimators' walk "
        "matched), the estimators' noise adaptation on as users run them. NEES band: the two-sided 95 % band of χ² "
        "with the row's degrees of freedom (42 tracker; 36 outside instruments: the 30 gauge-free directions of δM "
        "and the stroke scales). No peer: the reported σ against the true error. Per cell and seed: "
        "`DIR/summary.csv`; the rows (`DIR/results.parquet`) are not committed."
    )


def _settings(cell: dict, spec) -> str:
    return ", ".join(f"{name} {cell[name]}" for name in spec.swept if name != "instrument")


def main(argv: list[str] | None = None) -> int:
    from benchmarks import report

    parser = argparse.ArgumentParser(prog="python -m benchmarks.honesty", description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "honesty", help="the sweep's directory (resumed)")
    parser.add_argument("--seeds", type=int, help="only the first N seeds of every cell")
    parser.add_argument("--workers", type=int, help="local Dask workers (default: one per core)")
    parser.add_argument("--update-report", action="store_true", help="save the results and regenerate BENCHMARKS.md")
    args = parser.parse_args(argv)
    info = report.start(" ".join(["python -m benchmarks.honesty", *(sys.argv[1:] if argv is None else argv)]))
    result = section(False, args.out, args.seeds, args.workers)
    print(markdown(result))
    if args.update_report:
        report.save("honesty", [result], info, quick=False)
        report.write()
    return 0


if __name__ == "__main__":
    sys.exit(main())
