"""Compensation: IK with the true model puts the true robot exactly at the desired poses."""

import numpy as np
import pytest

from stewart_calib import kinematics as kin
from stewart_calib.compensation import compensate
from stewart_calib.errors import CalibError
from stewart_calib.estimators.base import Estimate
from tests.synthetic import nim_stewart, random_error, random_poses


def test_true_model_strokes_reach_the_poses_exactly():
    platform = nim_stewart()
    rng = np.random.default_rng(3)
    poses = random_poses(platform, 50, rng)
    delta = random_error(rng)
    truth = platform.drive.perturbed(delta)
    for model in (truth, Estimate(delta, None, "test")):
        strokes = compensate(model, poses, nominal=platform)
        sol = kin.forward_kinematics(truth, strokes, guess=kin.pose_to_rt(poses))
        position_mm, angle_deg = kin.pose_error(*kin.pose_to_rt(poses), sol.R, sol.t)
        # FK solves to 1e-9 mm in leg length; the pose inherits that within the Jacobian's gain.
        assert position_mm.max() < 1e-9
        assert np.radians(angle_deg).max() * 300.0 < 1e-9  # rotation at the platform radius [mm]
    # The nominal model's strokes miss by about the size of δM: compensation matters.
    sol = kin.forward_kinematics(truth, compensate(platform.drive, poses), guess=kin.pose_to_rt(poses))
    assert kin.pose_error(*kin.pose_to_rt(poses), sol.R, sol.t)[0].mean() > 0.5


def test_estimate_without_nominal_is_refused():
    with pytest.raises(CalibError, match="nominal"):
        compensate(Estimate(np.zeros(42), None, "test"), np.zeros((1, 6)))
