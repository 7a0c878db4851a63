"""Smoke test of ``python -m benchmarks.tracker_geometry --quick``: it runs and its table has every row.

The quick numbers mean little (one seed, 24 poses); the benchmark itself reports the accuracy.
"""

import numpy as np
import pytest

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


def test_an_honest_z2s_spread_is_that_of_its_correlated_parameters():
    """score's z² of n parameters spreads as χ²ₙ/n (variance 2/n) where they are independent, as one χ²₁ (2)
    where they move together; the honesty section's target is drawn from it."""
    n = 42
    stddev = np.linspace(0.01, 0.02, n)
    independent = {"stddev": stddev.tolist(), "covariance": np.diag(stddev**2).tolist()}
    assert tracker_geometry.z2_honest_variance(independent) == pytest.approx(2 / n)
    together = {"stddev": stddev.tolist(), "covariance": np.outer(stddev, stddev).tolist()}
    assert tracker_geometry.z2_honest_variance(together) == pytest.approx(2.0)
    # and it is the spread of z² over draws of e ~ N(0, C)
    rng = np.random.default_rng(3)
    A = rng.normal(size=(n, n)) * stddev
    covariance = A @ A.T / n
    sigma = np.sqrt(np.diag(covariance))
    draws = rng.multivariate_normal(np.zeros(n), covariance, 20000)
    z2 = np.mean((draws / sigma) ** 2, axis=1)
    stated = tracker_geometry.z2_honest_variance({"stddev": sigma.tolist(), "covariance": covariance.tolist()})
    assert np.var(z2) == pytest.approx(stated, rel=0.1)
