"""Smoke test of ``python -m benchmarks --quick``: it runs, and its report has every row.

The numbers of a quick run mean nothing (tiny inputs); this checks the suite still runs end
to end against the package as it is and that no section lost a row.
"""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_quick_run_writes_every_row(tmp_path):
    subprocess.run(
        [sys.executable, "-m", "benchmarks", "--quick", "--out-dir", str(tmp_path)], cwd=ROOT, check=True, timeout=900
    )  # a hang guard, not a speed test; the accuracy section starts a Dask local cluster
    report = (tmp_path / "quick.md").read_text(encoding="utf-8")
    results = json.loads((tmp_path / "quick.json").read_text(encoding="utf-8"))
    table_rows = [line for line in report.splitlines() if line.startswith("| ") and not line.startswith("| Benchmark")]

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
    assert len(table_rows) == sum(len(s["rows"]) for s in results["sections"])
    assert (tmp_path / "scale-quick.png").stat().st_size > 0
    assert (tmp_path / "scale-cli-quick.png").stat().st_size > 0
