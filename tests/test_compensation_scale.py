"""Compensation through the encoders' stroke scale (spec §7: a leg is ``l_i + (1 + k_i) q_i`` long):
the commanded strokes must put the *true* drive, whose encoders read (1 + k_i) mm per logged mm,
at the desired pose."""

from __future__ import annotations

import json

import numpy as np

from stewart_calib import cli
from stewart_calib.analysis.compensation import compensate
from stewart_calib.io import write_pose_list
from stewart_calib.io.platform_file import load_platform
from stewart_calib.model import kinematics as kin
from stewart_calib.model.drive import DriveModel, stroke_term
from stewart_calib.model.platform import PARAMETER_NAMES

K = np.array([0.03, -0.02, 0.05, 0.0, -0.04, 0.01])


def _desired(platform) -> np.ndarray:
    home = platform.workspace.home
    return np.array([home, home + [5.0, -3.0, 4.0, 0.02, -0.01, 0.03]])


def test_commanded_strokes_land_the_scaled_drive_on_the_pose():
    platform = load_platform("hobby-hexapod")
    poses = _desired(platform)
    strokes = compensate(DriveModel(platform.drive, (stroke_term(K),)), poses)
    # the real legs move (1 + k_i) q_i: forward kinematics of those lengths must give the desired pose
    solution = kin.forward_kinematics(platform.drive, strokes * (1.0 + K))
    R, t = kin.pose_to_rt(poses)
    position_mm, rotation_rad = kin.pose_error(R, t, solution.R, solution.t)
    assert np.max(position_mm) < 1e-6 and np.max(rotation_rad) < 1e-9
    # and they differ from the unscaled IK by the factor itself, not by round-off
    plain = compensate(platform.drive, poses)
    np.testing.assert_allclose(strokes * (1.0 + K), plain, rtol=1e-12, atol=1e-9)


def test_compensate_cli_applies_the_results_stroke_scale(tmp_path, capsys):
    platform = load_platform("hobby-hexapod")
    poses = _desired(platform)
    result = {
        "format": "stewart-calib/result@1",
        "method": "ls",
        "platform": platform.name,
        "parameter_names": list(PARAMETER_NAMES),
        "nominal": platform.drive.as_vector().tolist(),
        "estimate": platform.drive.as_vector().tolist(),
        "error": [0.0] * 42,
        "stddev": None,
        "samples_used": 10,
        "samples_skipped": 0,
        "stroke_scale": {"names": [f"k{i}" for i in range(1, 7)], "estimate": K.tolist(), "stddev": [0.001] * 6},
    }
    (tmp_path / "r.json").write_text(json.dumps(result))
    write_pose_list(tmp_path / "poses.csv", poses)
    code = cli.main(
        [
            "compensate",
            "--platform",
            "hobby-hexapod",
            "--result",
            str(tmp_path / "r.json"),
            "--poses",
            str(tmp_path / "poses.csv"),
            "--out",
            str(tmp_path / "q.csv"),
        ]
    )
    assert code == 0
    written = np.genfromtxt(tmp_path / "q.csv", delimiter=",", names=True)
    strokes = np.column_stack([written[f"q{i}_mm"] for i in range(1, 7)])
    np.testing.assert_allclose(strokes, compensate(DriveModel(platform.drive, (stroke_term(K),)), poses), atol=1e-6)
