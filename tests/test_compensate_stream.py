"""``compensate --poses - --out -`` (spec §16): each pose's row as soon as its line has come."""

from __future__ import annotations

import os
import select
import subprocess
import sys

import numpy as np

from stewart_calib import io
from stewart_calib.analysis.compensation import compensate
from stewart_calib.workflows.online import OnlineCalibrator
from tests.synthetic import NIM_STEWART, ROOT, nim_stewart

#: a guard against a hang (a row never flushed), not a timing: the answer comes in milliseconds
HANG_S = 120


def _line(process) -> str:
    ready, _, _ = select.select([process.stdout], [], [], HANG_S)
    assert ready, "no row came back: not flushed as soon as the pose was read"
    return process.stdout.readline().decode().rstrip("\n")


def test_each_pose_is_answered_before_the_next_is_sent_and_an_unreachable_one_goes_on(tmp_path):
    platform = nim_stewart()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "stewart_calib",
            "compensate",
            "--platform",
            str(NIM_STEWART),
            "--poses",
            "-",
            "--out",
            "-",
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
    )
    poses_deg = [[3.0, -2.0, 1130.0, 1.5, -2.0, 4.0], [0.0, 0.0, 3000.0, 0.0, 0.0, 0.0], [-10.0, 5.0, 1100.0, 0, 3, -1]]
    try:
        process.stdin.write(b"t_s,x_mm,y_mm,z_mm,roll_deg,pitch_deg,yaw_deg\n")
        process.stdin.flush()
        assert _line(process) == ",".join([*io.POSE_COLUMNS, *io.STROKE_COLUMNS])
        rows = []
        for k, pose in enumerate(poses_deg):
            process.stdin.write((",".join(map(str, [k, *pose])) + "\n").encode())
            process.stdin.flush()  # the pipe stays open: the row must come before the next pose
            rows.append(_line(process).split(","))
    finally:
        process.stdin.close()
        err = process.stderr.read().decode()
        process.wait(HANG_S)
    assert process.returncode == 0
    for pose, row in zip(poses_deg, rows, strict=True):
        np.testing.assert_array_equal(np.array(row[:6], dtype=float), pose)
    expected = compensate(nim_stewart().drive, np.array([np.r_[p[:3], np.radians(p[3:])] for p in poses_deg])[[0, 2]])
    np.testing.assert_allclose(np.array([rows[0][6:], rows[2][6:]], dtype=float), expected, rtol=0, atol=1e-9)
    assert rows[1][6:] == [""] * 6
    assert err.splitlines() == [
        "stewart-calib compensate: <stdin>: row 3: z = 3000 mm is +1874.2 mm from home, beyond the workspace's ±200 mm"
    ]
    # the Python API takes the same degrees
    np.testing.assert_allclose(
        OnlineCalibrator(platform, "ekf").compensated_strokes(np.array(poses_deg)[[0, 2]]), expected, atol=1e-9
    )
