"""Every number a user is shown is honest: the nominal model's "before" is its best registration
to an outside instrument (frame and target(s) fitted, as the calibration fits them)."""

from __future__ import annotations

import contextlib
import io
import re

import numpy as np
import pytest
from scipy.optimize import least_squares

from stewart_calib import cli
from stewart_calib.io import read_log
from stewart_calib.platform import load_platform
from tests.instrument_data import HOBBY
from tests.test_instrument_files import EXPERIMENT

POINTS = EXPERIMENT.replace(
    'kind = "pose"\nposition_sigma_mm = 0.2\norientation_sigma_deg = 0.05',
    'kind = "points"\nposition_sigma_mm = 0.1\ntargets_mm = [[40.0, 0.0, 5.0], [-20.0, 35.0, 5.0], [-20.0, -35.0, 8.0]]'
    "\ntarget_spread_mm = 15.0",
).replace("target_offset = [10.0, 5.0, 30.0, 0.0, 0.0, -90.0]\n", "")


def _run(argv: list) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        status = cli.main([str(a) for a in argv])
    return status, err.getvalue()


@pytest.fixture(scope="module", params=["pose", "points"])
def outside_run(request, tmp_path_factory):
    """A hobby hexapod seen by an outside instrument whose frame and target(s) are far from the
    platform file's (cameras 60 mm and 120° away, the rigid body's origin 30 mm off): the fit log,
    calibrated by ls, and calibrate's stderr."""
    work = tmp_path_factory.mktemp(request.param)
    text = EXPERIMENT if request.param == "pose" else POINTS
    (work / "e.toml").write_text(text.format(platform=HOBBY.as_posix()))
    assert cli.main(["simulate", "--experiment", str(work / "e.toml"), "--out", str(work / "sim")]) == 0
    lines = (work / "sim" / "log.csv").read_text().splitlines()
    stage = lines[0].split(",").index("stage")
    (work / "fit.csv").write_text("\n".join([lines[0], *(r for r in lines[1:] if r.split(",")[stage] == "fit")]) + "\n")
    argv = ["calibrate", "--platform", work / "sim" / "platform.toml", "--log", work / "fit.csv", "--method", "ls"]
    status, err = _run([*argv, "--out", work / "r.json"])
    assert status == 0, err
    return work, err


def _before(line: str) -> dict[str, float]:
    return {m[0]: float(m[1]) for m in re.findall(r"(x|y|z|rotation) ([\d.e+-]+) → ", line)}


def best_registration_rms(platform, log) -> dict[str, float]:
    """The nominal model's position RMS per instrument axis and rotation RMS at the frame and
    target(s) that minimise the whitened readings' residual: scipy's least squares over the
    instrument's tangent, from the platform file's frame and target(s) — no closed form."""
    from stewart_calib.instruments import outside_model
    from stewart_calib.validation import _model_poses, nominal_model

    model = outside_model(platform)
    R_X, t_X = _model_poses(platform, nominal_model(platform), log, "nominal")
    start = model.nominal_unknowns()

    def whitened(delta):
        e = model.readings_residual(start.retract(delta), log.readings, R_X, t_X)[0] / model.channel_sigma
        return np.nan_to_num(e).ravel()

    # the frame is 120° from its nominal: start from a few orientations and keep the best
    best = None
    for yaw in np.radians([0.0, 90.0, 180.0, 270.0]):
        x0 = np.zeros(start.size)
        x0[5] = yaw
        fit = least_squares(whitened, x0, x_scale="jac", xtol=1e-14, ftol=1e-14, gtol=1e-14)
        best = fit if best is None or fit.cost < best.cost else best
    unknowns = start.retract(best.x)
    predicted, _, orientation = model.prediction_errors(unknowns, R_X, t_X, log.readings)
    difference = model.position_differences(log.readings, predicted)
    rms = dict(zip("xyz", np.sqrt(np.mean(difference**2, axis=0)), strict=True))
    if orientation is not None:
        rms["rotation"] = float(np.sqrt(np.mean(orientation**2)))
    return rms


def test_calibrate_before_is_the_nominal_models_best_registration(outside_run):
    """Printed to 4 significant digits: the same optimum within the rounding (5e-4 relative)."""
    work, err = outside_run
    (line,) = [line for line in err.splitlines() if "pose error RMS" in line]
    platform = load_platform(work / "sim" / "platform.toml")
    expected = best_registration_rms(platform, read_log(work / "fit.csv", platform))
    printed = _before(line)
    assert set(printed) == set(expected)
    for axis, value in expected.items():
        assert printed[axis] == pytest.approx(value, rel=6e-4), (axis, line)
