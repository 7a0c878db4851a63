"""Smoke test of ``python -m benchmarks.plan_poses --quick``: it runs and its table has every row.

The quick numbers mean little (one seed, 12 planned against 30 random poses); the benchmark itself
reports the accuracy (BENCHMARKS.md).
"""

import numpy as np

from benchmarks import plan_poses
from benchmarks.common import markdown


def test_quick_run_has_every_row_and_a_verdict_on_each_target():
    section = plan_poses.run(quick=True)
    assert [row.name for row in section.rows] == plan_poses.row_names()
    table = markdown(section).splitlines()
    assert sum(line.startswith("| ") and not line.startswith("| Benchmark") for line in table) == len(section.rows)
    assert all(isinstance(row.met, bool) for row in section.rows)
    for row in section.rows:
        for run in row.raw.get("runs", []):
            assert np.all(np.isfinite([*run["planned"], *run["random"]])), row.name
    (case,) = section.rows[-1].raw["cases"]
    assert case["line"].startswith("warning: predicted closed-loop") == case["warned"]


def test_a_row_within_60_percent_of_the_box_not_met_says_its_own_why():
    """Not the sentence of the rows against poses drawn as the evaluation poses are, whose key its name starts with."""
    from benchmarks.common import Row, Section, explain

    name = "hobby, laser tracker: planned / random within 60 % of the box"
    section = explain(Section("t", "", [Row(name, "0.99", "≤ 0.5", False)], {}), plan_poses.WHY)
    assert section.rows[0].why == plan_poses.INNER_WHY
