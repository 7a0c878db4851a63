"""Compensation: IK with the true model puts the true robot exactly at the desired poses."""

import dataclasses

import numpy as np
import pytest

from stewart_calib.analysis.compensation import compensate
from stewart_calib.errors import CalibError
from stewart_calib.estimate import Estimate
from stewart_calib.model import kinematics as kin
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


def test_cli_writes_strokes_that_reach_the_poses(tmp_path, capsys):
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
    # its status line names the command, as every command's does (the strokes are in the file, not on stdout)
    assert capsys.readouterr().out == f"stewart-calib compensate: wrote 20 stroke rows to {tmp_path / 'q.csv'}\n"
    text = (tmp_path / "q.csv").read_text().splitlines()
    assert text[0].split(",")[-6:] == [f"q{i}_mm" for i in range(1, 7)]
    strokes = np.array([row.split(",")[-6:] for row in text[1:]], dtype=float)
    np.testing.assert_allclose(read_pose_list(tmp_path / "q.csv"), poses, rtol=5e-15, atol=1e-12)  # 15 digits
    sol = kin.forward_kinematics(platform.drive.perturbed(delta), strokes, guess=kin.pose_to_rt(poses))
    assert kin.pose_error(*kin.pose_to_rt(poses), sol.R, sol.t)[0].max() < 1e-9  # FK tolerance

    # A result for another platform (different nominal) is refused, and nothing is written.
    other = io.result_dict(
        Estimate(delta, None, "ls", 1), dataclasses.replace(platform, drive=platform.drive.perturbed(np.ones(42)))
    )
    io.write_result(tmp_path / "other.json", other)
    argv = ["compensate", "--platform", str(NIM_STEWART), "--result", str(tmp_path / "other.json")]
    assert main([*argv, "--poses", str(tmp_path / "poses.csv"), "--out", str(tmp_path / "q2.csv")]) == 2
    assert not (tmp_path / "q2.csv").exists()


def test_online_and_cli_refuse_unreachable_poses_alike(tmp_path, capsys):
    from stewart_calib import io
    from stewart_calib.analysis.compensation import PoseOutOfRange
    from stewart_calib.cli import main
    from stewart_calib.workflows.online import OnlineCalibrator
    from tests.synthetic import NIM_STEWART

    platform = nim_stewart()
    home = platform.workspace.home
    roll_in_degrees = np.array([0.0, 0.0, 1100.0, 5.0, 0.0, 0.0])  # 5 "rad": the user meant degrees
    with pytest.raises(PoseOutOfRange) as online:
        OnlineCalibrator(platform, "ekf").compensated_strokes_rad(np.vstack([home, roll_in_degrees]))
    assert online.value.pose_index == 1
    assert (
        online.value.reason
        == "roll = 5 rad (286.5°) is beyond the workspace's ±20° about home (angles in rad, not degrees?)"
    )
    # inside the box but beyond a stroke: a platform whose stroke range is narrower than its box
    narrow = dataclasses.replace(platform, stroke_range=(-50.0, 50.0))
    with pytest.raises(
        PoseOutOfRange, match=r"^pose 0: the pose needs q\d_mm = .*, outside the stroke range \[-50.0, 50.0\] mm$"
    ):
        OnlineCalibrator(narrow, "ekf").compensated_strokes_rad(home + [0, 0, 150.0, 0, 0, 0])

    io.write_result(tmp_path / "r.json", io.result_dict(Estimate(np.zeros(42), None, "ekf", 1), platform))
    io.write_pose_list(tmp_path / "poses.csv", roll_in_degrees[None])
    assert (
        main(
            [
                "compensate",
                "--platform",
                str(NIM_STEWART),
                "--result",
                str(tmp_path / "r.json"),
                "--poses",
                str(tmp_path / "poses.csv"),
                "--out",
                str(tmp_path / "q.csv"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert err == f"stewart-calib compensate: error: {tmp_path / 'poses.csv'}: row 2: {online.value.reason}"
    assert not (tmp_path / "q.csv").exists()


def test_a_result_naming_another_platform_is_refused(tmp_path, capsys):
    from stewart_calib import io
    from stewart_calib.cli import main
    from tests.synthetic import NIM_STEWART

    platform = nim_stewart()
    result = io.result_dict(Estimate(np.zeros(42), None, "ekf", 1), platform)
    io.write_result(tmp_path / "r.json", {**result, "platform": "other-hexapod"})
    io.write_pose_list(tmp_path / "poses.csv", platform.workspace.home[None])
    assert (
        main(
            [
                "compensate",
                "--platform",
                str(NIM_STEWART),
                "--result",
                str(tmp_path / "r.json"),
                "--poses",
                str(tmp_path / "poses.csv"),
                "--out",
                str(tmp_path / "q.csv"),
            ]
        )
        == 2
    )
    assert (
        capsys.readouterr()
        .err.strip()
        .endswith(
            "key 'platform': expected 'nim-stewart' (the platform given), got 'other-hexapod' (a result for another "
            "platform?)"
        )
    )
    assert not (tmp_path / "q.csv").exists()
