"""ekf, isam2 and lm on a motion-capture (pose) log: every method at the Cramér–Rao bound of the
joint unknowns (drive, stroke scale, instrument frame and target), started by ``calibrate``'s
closed-form registration, with the noise model of the data (spec §7, issue 13)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from stewart_calib.config import load_estimator_config
from stewart_calib.simulation.instrument import InstrumentTruth
from stewart_calib.workflows.calibration import run_calibration
from tests.instrument_data import hobby, make_case
from tests.test_instrument_ls import FAR_FRAME, POINTS, POINTS_TRUTH, POSE_TRUTH, _normalised_errors

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


#: three targets on one line, the first and last 60 mm either side of the middle
ON_A_LINE = np.array([[60.0, 0.0, 25.0], [0.0, 0.0, 25.0], [-60.0, 0.0, 25.0]])


@pytest.mark.parametrize("method", ["ekf", "isam2", "lm"])
def test_targets_on_a_line_give_every_method_a_finite_estimate_near_the_bound(method):
    """Targets on one line fix no pose by themselves (the rotation about the line is free): the
    methods take the pose from the drive's kinematics then, as with one or two targets. Before,
    their singular loose pose sent ekf, lm and isam2 to NaN and a refusal naming 'RMS leg residual nan'."""
    platform = hobby(replace(POINTS, targets=ON_A_LINE))
    truth = replace(POINTS_TRUTH, target_offset=np.zeros(ON_A_LINE.size), target_spread_mm=0.0)
    case = make_case(platform, 40, 7, truth)
    estimate = run_calibration(platform, case.log, method, load_estimator_config(None, OVERRIDES)).estimate
    z = _normalised_errors(case, estimate)
    assert np.all(np.isfinite(z))
    assert math.sqrt(np.mean(np.square(z))) <= 2.0, (
        f"{method}: RMS error / CRB = {math.sqrt(np.mean(np.square(z))):.3f}"
    )


def test_targets_fix_a_pose_only_off_a_line():
    """The loose pose of a reading: none where the three targets lie within σ/0.01 rad (5 mm here)
    of one line; a pose whose covariance bounds the rotation about it where they lie 10 mm off."""
    from stewart_calib.instruments import instrument_model, instrument_theta
    from stewart_calib.instruments.points import LOOSE_ROTATION_SIGMA_RAD
    from stewart_calib.model import kinematics as kin

    R_X, t_X = kin.pose_to_rt(np.array([[2.0, -3.0, 250.0, 0.05, -0.02, 0.1]]))
    for off_mm, fixed in ((0.0, False), (4.0, False), (10.0, True)):
        targets = np.array([[60.0, 0.0, 25.0], [0.0, off_mm, 25.0], [-60.0, 0.0, 25.0]])
        platform = hobby(replace(POINTS, targets=targets))
        model = instrument_model(platform, load_estimator_config(None, OVERRIDES).noise)
        theta = instrument_theta(model, None)
        z = kin.transform_points(R_X[0], t_X[0], targets).reshape(-1)  # the frame at the origin of {J}
        pose = model.pose(z, theta, None)
        assert (pose is not None) == fixed, off_mm
        if fixed:
            np.testing.assert_allclose(pose.t, t_X[0], atol=1e-9)
            assert np.sqrt(np.max(np.linalg.eigvalsh(pose.covariance[:3, :3]))) <= LOOSE_ROTATION_SIGMA_RAD


@pytest.mark.parametrize("method", ["ekf", "isam2", "lm"])
def test_method_with_the_instrument_metres_away_is_as_near_the_truth_as_ls(method):
    """Motion capture's origin 2.7 m from the robot, encoder zeros ~15 mm and stroke scales ~3 % off (a
    hobby build): what registration leaves of the frame's orientation moves its origin's place by the
    lever arm, which the instrument's prior must allow (at 20 mm there ekf, isam2 and lm stood 3.1×,
    3.0× and 1.6× ls's error, in units of the bound). ls has no prior: the peer on the same logs."""
    platform = hobby()
    config = load_estimator_config("motion-capture", OVERRIDES)
    z: dict[str, list] = {method: [], "ls": []}
    for run in range(RUNS):
        truth = InstrumentTruth(FAR_FRAME, POSE_TRUTH.target_offset)
        case = make_case(platform, 80, 100 + run, truth, length_spread_mm=15.0, scale_spread=0.03)
        for name in z:
            z[name].append(_normalised_errors(case, run_calibration(platform, case.log, name, config).estimate))
    ratio = {name: math.sqrt(np.mean(np.square(found))) for name, found in z.items()}
    assert ratio[method] <= 1.25 * ratio["ls"], ratio
