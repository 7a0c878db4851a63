"""``python -m benchmarks``: a quick run of the light sections works end to end, and BENCHMARKS.md is
what the generator assembles from the saved results of every section.

The numbers of a quick run mean nothing (tiny inputs); this checks the suite still runs end
to end against the package as it is and that no section lost a row. The heavy sections (start-up,
tracker geometry, planned poses, the elastic robot, the hobby stand-in, the honesty grid) have
their own quick tests or are measured by hand; their saved results are checked here.
"""

import json
import re
import subprocess
import sys
from pathlib import Path

from benchmarks import report

ROOT = Path(__file__).resolve().parents[1]
#: the sections the quick run measures (seconds each on two cores)
LIGHT = ("speed", "accuracy", "robustness", "scale", "scale-cli", "link")
HISTORY = re.compile(r"\b(issue|session)s? [0-9]+\b|\b[0-9a-f]{7,40}\b")


def test_quick_run_writes_every_row(tmp_path):
    subprocess.run(
        [sys.executable, "-m", "benchmarks", "--quick", "--out-dir", str(tmp_path), "--only", *LIGHT],
        cwd=ROOT,
        check=True,
        timeout=900,
    )  # a hang guard, not a speed test; the accuracy section starts a Dask local cluster
    text = (tmp_path / "quick.md").read_text(encoding="utf-8")
    records = [json.loads(report.results_path(name, True, tmp_path).read_text(encoding="utf-8")) for name in LIGHT]
    table_rows = [line for line in text.splitlines() if line.startswith("| ") and not line.startswith("| Benchmark")]

    from benchmarks import robustness
    from benchmarks.accuracy import METHODS, PAPER_EKF_MATCHED
    from benchmarks.common import GEOMETRIES

    expected = [
        "tracker FK, single solve, warm start",
        "FK batched",
        "paper-ekf / ekf update, 42 states, 6 observations",
        "online per-sample cost, ekf",
        "online per-sample cost, paper-ekf",
        "ls batch on",
        "isam2 update per sample",
        "isam2 flat",
        *(f"{geometry}: {method}" for geometry in GEOMETRIES for method in METHODS),
        *(f"drift: {method}" for method in ("ls", "paper-ekf", "ekf", "isam2", PAPER_EKF_MATCHED)),
        *(f"{method} at 100 samples" for method in ("ekf", "paper-ekf", "isam2", "isam2 full history")),
        "imports of `stewart-calib --help`",
        "imports of `calibrate ekf, 100 samples`",
        "calibrate ekf at 300 samples",
        *robustness.row_names(),
        "link over OPC UA",
        "link over ADS",
    ]
    for name in expected:
        assert sum(row.startswith(f"| {name}") for row in table_rows) == 1, name
    assert len(table_rows) == len(expected)
    assert len(table_rows) == sum(len(s["rows"]) for r in records for s in r["sections"])
    for record in records:  # every section says where and when it was measured
        assert record["date"] and record["machine"]["cpu"] and record["command"].startswith("python -m benchmarks")
        assert report.measured_line(record) in text
    assert (tmp_path / "scale-quick.png").stat().st_size > 0
    assert (tmp_path / "scale-cli-quick.png").stat().st_size > 0


def test_benchmarks_md_is_generated_from_the_saved_results():
    """Every section of BENCHMARKS.md comes from benchmarks/results/, with its machine and date."""
    text = (ROOT / "BENCHMARKS.md").read_text(encoding="utf-8")
    assert text == report.assemble(), "BENCHMARKS.md is not what `python -m benchmarks` assembles: regenerate it"
    for name, title in report.SECTIONS.items():
        record = report.load(name, False)
        assert record is not None, f"no saved results for section {name}"
        assert [s.title for s in record["sections"]] == [title]
        assert {"date", "command", "machine"} <= set(record)
    headings = [line[3:] for line in text.splitlines() if line.startswith("## ")]
    assert headings == list(report.SECTIONS.values())
    assert text.count("\nMeasured by `") == len(report.SECTIONS)


def test_benchmarks_md_has_no_history():
    """No issue or session numbers and no commit hashes: history belongs in the commit messages."""
    text = (ROOT / "BENCHMARKS.md").read_text(encoding="utf-8")
    assert [m.group(0) for m in HISTORY.finditer(text)] == []


def test_every_target_not_met_says_why():
    for name in report.SECTIONS:
        for section in report.load(name, False)["sections"]:
            for row in section.rows:
                assert row.met is not False or row.why, f"{section.title}: {row.name}"


def test_the_machine_line_names_the_blas_kernels():
    """Kernels round differently and move plan's poses (benchmarks.plan_poses, the machine's BLAS): the section's
    machine line says which ran, as the process loaded them."""
    from benchmarks.common import blas_kernels

    kernels = blas_kernels()
    assert kernels is not None and kernels.startswith("OpenBLAS ")  # numpy's wheels ship OpenBLAS
    line = report.measured_line({"command": "c", "machine": {"cpu": "A CPU", "cores": 2, "blas_kernels": kernels}})
    assert f"machine: A CPU, 2 cores, {kernels} kernels;" in line
