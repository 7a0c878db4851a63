"""Compensation: IK with the true model puts the true robot exactly at the desired poses."""

import numpy as np
import pytest

from stewart_calib import kinematics as kin
from stewart_calib.compensation import compensate
from stewart_calib.errors import CalibError
from stewart_calib.estimate import Estimate
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


def test_cli_writes_strokes_that_reach_the_poses(tmp_path):
    from stewart_calib import io
    from stewart_calib.cli import main
    from stewart_calib.io import read_pose_list, write_pose_list
    from tests.synthetic import NIM_STEWART

    platform = nim_stewart()
    rng = np.random.default_rng(4)
    delta = random_error(rng)
    poses = random_poses(platform, 20, rng)
    io.write_result(tmp_path / "r.json", io.result_dict(Estimate(delta, None, "ls", 1), platform))
    write_pose_list(tmp_path / "poses.csv", poses)
    argv = ["compensate", "--platform", str(NIM_STEWART), "--result", str(tmp_path / "r.json")]
    assert main([*argv, "--poses", str(tmp_path / "poses.csv"), "--out", str(tmp_path / "q.csv")]) == 0
    text = (tmp_path / "q.csv").read_text().splitlines()
    assert text[0].split(",")[-6:] == [f"q{i}_mm" for i in range(1, 7)]
    strokes = np.array([row.split(",")[-6:] for row in text[1:]], dtype=float)
    np.testing.assert_allclose(read_pose_list(tmp_path / "q.csv"), poses, rtol=0, atol=1e-12)
    sol = kin.forward_kinematics(platform.drive.perturbed(delta), strokes, guess=kin.pose_to_rt(poses))
    assert kin.pose_error(*kin.pose_to_rt(poses), sol.R, sol.t)[0].max() < 1e-9  # FK tolerance

    # A result for another platform (different nominal) is refused, and nothing is written.
    other = io.result_dict(Estimate(delta, None, "ls", 1), platform.with_drive(platform.drive.perturbed(np.ones(42))))
    io.write_result(tmp_path / "other.json", other)
    argv = ["compensate", "--platform", str(NIM_STEWART), "--result", str(tmp_path / "other.json")]
    assert main([*argv, "--poses", str(tmp_path / "poses.csv"), "--out", str(tmp_path / "q2.csv")]) == 2
    assert not (tmp_path / "q2.csv").exists()
