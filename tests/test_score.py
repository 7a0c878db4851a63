"""What an engineer looks for first (issue 28): ``stewart-calib score`` against a simulation's
truth, and the pose error before → after that ``calibrate``, ``validate`` and ``simulate
--controller`` print, checked against the files they wrote."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from stewart_calib import cli
from stewart_calib.instruments import gauge
from stewart_calib.io import read_log, read_result, read_truth, write_result
from stewart_calib.io.platform_file import load_platform
from stewart_calib.pipelines.score import tracker_frames


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    """The quick experiment simulated and calibrated (ekf, paper config); stderr of calibrate kept."""
    import contextlib
    import io

    out = tmp_path_factory.mktemp("quick")
    sim, result = out / "sim", out / "r.json"
    assert cli.main(["simulate", "--experiment", "quick", "--out", str(sim)]) == 0
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        argv = ["calibrate", "--platform", sim / "platform.toml", "--log", sim / "log.csv", "--method", "ekf"]
        assert cli.main([str(a) for a in [*argv, "--config", "paper", "--out", result]]) == 0
    return out, sim, result, err.getvalue()


def _pairs(line: str) -> dict[str, tuple[float, float]]:
    """``{axis: (before, after)}`` of a 'pose error RMS … x A → B mm, …, rotation C → D°' line."""
    return {m[0]: (float(m[1]), float(m[2])) for m in re.findall(r"(x|y|z|rotation) ([\d.e+-]+) → ([\d.e+-]+)", line)}


def test_score_of_a_calibration_and_of_the_truth_itself(quick, tmp_path, capsys):
    _, sim, result, _ = quick
    scores = tmp_path / "s.json"
    argv = ["score", "--platform", sim / "platform.toml", "--result", result, "--truth", sim / "truth.csv"]
    argv += ["--json", scores]
    assert cli.main([str(a) for a in argv]) == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith("stewart-calib score: parameters RMS ") and "closed loop" in line and "nominal model" in line
    s = json.loads(scores.read_text())
    assert s["closed_loop_mm"] < s["closed_loop_nominal_mm"]  # the calibration helps
    assert np.isfinite(s["z2"]) and s["poses"] == 200
    # the truth itself as the result: no parameter error, no closed-loop error (FK's tolerance); the elastic
    # result's truth is the robot's unloaded drive and true compliance (the robot settles under its weight),
    # in the frames its tracker's joints define (quick's tracker is 15 µm off its nominal geometry)
    perfect = read_result(result)
    platform = load_platform(sim / "platform.toml")
    truth = read_truth(sim / "truth.csv", platform)
    truth = gauge.moved_into(platform.drive, truth.unloaded, *tracker_frames(platform, truth))
    perfect["estimate"] = truth.tolist()
    perfect["error"] = (truth - np.array(perfect["nominal"])).tolist()
    elastic = platform.elastic
    perfect["compliance"]["estimate"] = elastic.true_compliance_mm_per_kN.tolist()
    write_result(tmp_path / "perfect.json", perfect)
    argv[argv.index(result)] = tmp_path / "perfect.json"
    assert cli.main([str(a) for a in argv]) == 0
    s = json.loads(scores.read_text())
    # the truth moved into the tracker's frames and written with 15 digits: zero to the digits written
    assert s["parameter_rms_mm"] < 1e-9 and s["closed_loop_mm"] < 1e-6 and s["closed_loop_deg"] < 1e-6
    assert s["compliance_max_error"] == 0.0 and s["truth"] == "unloaded" and s["closed_loop_settled"]


def test_calibrate_and_validate_print_the_pose_error_before_and_after(quick, tmp_path, capsys):
    """The tracker's pose (its FK of the readings) against the drive's FK of the strokes, per axis:
    the nominal model's x RMS is recomputed here from the log."""
    from stewart_calib.model import kinematics as kin

    _, sim, result, err = quick
    (line,) = [line for line in err.splitlines() if "pose error RMS" in line]
    pairs = _pairs(line)
    assert set(pairs) == {"x", "y", "z", "rotation"}
    assert all(after < before for before, after in pairs.values())
    platform = load_platform(sim / "platform.toml")
    log = read_log(sim / "log.csv", platform)
    seen = kin.forward_kinematics(platform.tracker, log.readings)
    model = kin.forward_kinematics(platform.drive, log.strokes)
    np.testing.assert_allclose(pairs["x"][0], np.sqrt(np.mean((seen.t[:, 0] - model.t[:, 0]) ** 2)), rtol=1e-3)
    argv = ["validate", "--platform", sim / "platform.toml", "--result", result, "--log", sim / "log.csv"]
    assert cli.main([str(a) for a in [*argv, "--out", tmp_path / "V.csv"]]) == 0
    (held,) = [line for line in capsys.readouterr().err.splitlines() if "pose error RMS" in line]
    assert _pairs(held) == pairs  # the same log: the same numbers


def test_simulate_prints_the_controllers_pose_error(quick, capsys):
    """The nominal controller's line is the RMS of true − desired in the files it wrote; a frozen
    controller's line gives the nominal model's error beside its own, and improves on it."""
    out, sim, result, _ = quick
    capsys.readouterr()
    assert cli.main(["simulate", "--experiment", "quick", "--out", str(out / "again")]) == 0
    (line,) = [line for line in capsys.readouterr().out.splitlines() if "pose error RMS" in line]
    platform = load_platform(sim / "platform.toml")
    log, truth = read_log(sim / "log.csv", platform), read_truth(sim / "truth.csv")
    x_rms = np.sqrt(np.mean((truth.true_poses[:, 0] - log.desired_poses[:, 0]) ** 2))
    assert f"x {x_rms:.4g} mm" in line, line
    argv = ["simulate", "--experiment", "quick", "--out", out / "frozen", "--controller", "frozen", "--result", result]
    assert cli.main([str(a) for a in argv]) == 0
    (line,) = [line for line in capsys.readouterr().out.splitlines() if "pose error RMS" in line]
    pairs = _pairs(line)
    assert set(pairs) == {"x", "y", "z", "rotation"} and all(after < before for before, after in pairs.values())
