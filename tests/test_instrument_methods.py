"""ekf, isam2 and lm on a motion-capture (pose) log: every method at the Cramér–Rao bound of the
joint unknowns (drive, stroke scale, instrument frame and target), started by ``calibrate``'s
closed-form registration, with the noise model of the data (spec §7, issue 13)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stewart_calib.calibration import run_calibration
from stewart_calib.config import load_estimator_config
from tests.instrument_data import hobby, make_case
from tests.test_instrument_ls import POINTS, POINTS_TRUTH, POSE_TRUTH, _normalised_errors

#: Monte Carlo runs per method: 2 × 60 unknowns put the mean z² at 1 ± 0.13, so the issue's 1.2 on
#: the RMS ratio (1.44 on z²) sits 3.4 standard deviations above an efficient estimator
RUNS = 2

#: the simulated encoders are exact (the stroke scale is identified by default with a pose instrument)
OVERRIDES = ["noise.stroke_sigma_mm=0.001"]


@pytest.mark.parametrize("method", ["ekf", "isam2", "lm"])
def test_method_reaches_the_cramer_rao_bound_on_a_pose_log(method):
    platform = hobby()
    config = load_estimator_config("motion-capture", OVERRIDES)
    z = []
    for run in range(RUNS):
        case = make_case(platform, 80, 100 + run, POSE_TRUTH)
        z.append(_normalised_errors(case, run_calibration(platform, case.log, method, config).estimate))
    ratio = math.sqrt(np.mean(np.square(z)))
    assert ratio <= 1.2, f"{method}: RMS error / CRB = {ratio:.3f}"


def test_ekf_reaches_the_cramer_rao_bound_on_a_points_log_with_the_default_config():
    """Three targets, 15 % of them unseen, the frame ~100 mm and 60° from nominal, the default
    config as ``calibrate`` runs it: ekf's start-up batch solved as one pass linearised at the prior
    left it at 1.36× the bound on these runs (2.3× over three)."""
    platform = hobby(POINTS)
    config = load_estimator_config(None, OVERRIDES)
    z = []
    for run in range(RUNS):
        case = make_case(platform, 100, 100 + run, POINTS_TRUTH)
        z.append(_normalised_errors(case, run_calibration(platform, case.log, "ekf", config).estimate))
    ratio = math.sqrt(np.mean(np.square(z)))
    assert ratio <= 1.2, f"ekf: RMS error / CRB = {ratio:.3f}"
