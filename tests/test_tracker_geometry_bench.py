"""Smoke test of ``python -m benchmarks.tracker_geometry --quick``: it runs and its table has every row.

The quick numbers mean little (one seed, 24 poses); the benchmark itself reports the accuracy.
"""

import numpy as np

from benchmarks import tracker_geometry
from benchmarks.common import markdown


def test_quick_run_has_every_row_and_a_verdict_on_each_target():
    section = tracker_geometry.run(quick=True)
    assert [row.name for row in section.rows] == tracker_geometry.row_names()
    table = markdown(section).splitlines()
    assert sum(line.startswith("| ") and not line.startswith("| Benchmark") for line in table) == len(section.rows)
    for row in section.rows:
        for case in tracker_geometry.CASES:
            assert np.all(np.isfinite(row.raw.get(case, []))), row.name
    targets = [row for row in section.rows if row.target]
    assert [row.name for row in targets] == [
        f"{m} / lm-joint, tracker identified" for m in tracker_geometry.ONLINE_METHODS
    ]
    assert all(isinstance(row.met, bool) and np.isfinite(row.raw["ratio"]) for row in targets)
