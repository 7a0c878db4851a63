"""``lm``'s random walk on a robot that stands still: the rate from the data (the window differences,
as ``isam2``'s front end measures it), not the configured one taken as given (issue 24's check)."""

from __future__ import annotations

import numpy as np

from stewart_calib.config import config_from_dict
from stewart_calib.estimators import make_estimator
from tests.synthetic import make_log, nim_stewart, random_error, random_poses


def test_lm_on_a_still_robot_stays_near_the_constant_fit_under_the_default_walk():
    """1500 samples at 10 Hz of a constant δM, the default config (a walk of 1 µm/√s, the data's noise
    adapted): taken as given, the walk let the last window's estimate stand on its last seconds, away
    from the constant fit (one variable, walk 0) by a Mahalanobis d² of 687–1145 in the constant fit's
    covariance (seeds 0–3; its own error's is 30–44, χ²(42)); at the rate the window differences' likelihood
    leaves, 30–135 (142–406 at the χ² test's before it; on benchmarks.elastic's check lm's closed-loop error
    came down from 1.4–3.1 µm to isam2's)."""
    platform = nim_stewart()
    rng = np.random.default_rng(0)
    error = random_error(rng, 1.0)
    log, _ = make_log(
        platform, error, random_poses(platform, 1500, rng), rng, reading_sigma_mm=0.002, stroke_sigma_mm=0.001
    )
    walking = make_estimator("lm", platform, config_from_dict({})).fit(log)
    still = make_estimator("lm", platform, config_from_dict({"noise": {"random_walk_mm_per_sqrt_s": 0.0}})).fit(log)
    d = walking.error - still.error
    assert float(d @ np.linalg.solve(still.covariance, d)) < 300.0  # 135 here, 687 at the configured rate
