"""The drive model (stewart_calib.model.drive): its residual is the leg-length model, its Jacobians match
central differences (pose through ``kinematics.retract``), its compiled forms (the extensions'
kernel, the drive-leg factor's) equal its numpy ones — for the stroke term alone and for a drive
with a second term on inputs of its own, as a new error source adds one."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from stewart_calib.factors import drive_leg
from stewart_calib.model import _kernels, rotations
from stewart_calib.model import kinematics as kin
from stewart_calib.model.drive import DriveModel, LegTerm, drive_model, stroke_term
from tests.numdiff import numerical_jacobian, numerical_pose_jacobian, relative_error
from tests.synthetic import nim_stewart, random_error, random_poses


def _second_term(prior_sigma: float | None) -> LegTerm:
    """A term ``(0 + c_i) · (−f_i / 1000)`` on inputs 6…11: the form of a leg compliance."""
    names = tuple(f"c{i}" for i in range(1, 7))
    return LegTerm("compliance", names, 0.0, np.linspace(0.01, 0.06, 6), 6, -1e-3, prior_sigma, "leg_forces")


@pytest.fixture(scope="module")
def setting():
    platform = nim_stewart()
    rng = np.random.default_rng(3)
    R, t = kin.pose_to_rt(random_poses(platform, 4, rng))
    drives = {
        "stroke": DriveModel(platform.drive, (stroke_term(np.full(6, 0.01), 0.05),)),
        "two terms": DriveModel(platform.drive, (stroke_term(np.full(6, 0.01), 0.05), _second_term(0.01))),
        "known second": DriveModel(platform.drive, (stroke_term(np.zeros(6)), _second_term(None))),
    }
    return platform, rng, R, t, drives


def _state(drive: DriveModel, rng) -> tuple[np.ndarray, np.ndarray]:
    x = np.r_[random_error(rng, 0.5), rng.normal(0.0, 0.01, drive.size - 42)]
    inputs = np.r_[rng.uniform(-20.0, 20.0, 6), rng.uniform(-300.0, 300.0, drive.input_width - 6)]
    return x, inputs


@pytest.mark.parametrize("name", ["stroke", "two terms", "known second"])
def test_residual_and_jacobians_match_the_leg_length_model_and_central_differences(setting, name):
    platform, rng, R, t, drives = setting
    drive = drives[name]
    x, inputs = _state(drive, rng)
    values = drive.term_values(x)
    extensions = sum(
        (term.offset + v) * term.gain * inputs[term.input_start : term.input_start + 6]
        for term, v in zip(drive.terms, values, strict=True)
    )
    for k in range(len(R)):
        r = drive.residual(x, R[k], t[k], inputs)
        np.testing.assert_allclose(
            r, kin.leg_residuals(platform.drive.perturbed(x[:42]), R[k], t[k], extensions), atol=1e-9
        )
        J_pose, J_x = drive.jacobians(x, R[k], t[k], inputs)
        assert J_x.shape == (6, drive.size)
        numeric_pose = numerical_pose_jacobian(lambda R_, t_: drive.residual(x, R_, t_, inputs), R[k], t[k])
        numeric_x = numerical_jacobian(lambda x_, k=k: drive.residual(x_, R[k], t[k], inputs), x, 1e-4)
        assert relative_error(J_pose, numeric_pose) <= 1e-6
        assert relative_error(J_x, numeric_x) <= 1e-6


@pytest.mark.parametrize("name", ["stroke", "two terms"])
def test_forward_and_inverse_kinematics_and_the_pose_jacobian(setting, name):
    _, rng, R, t, drives = setting
    drive = drives[name]
    x, inputs = _state(drive, rng)
    strokes = drive.inverse_kinematics(R, t, x, np.broadcast_to(inputs, (len(R), drive.input_width)))
    u = np.array(np.broadcast_to(inputs, (len(R), drive.input_width)))
    u[:, :6] = strokes
    np.testing.assert_allclose(drive.residual(x, R, t, u), 0.0, atol=1e-9)
    fk = drive.forward_kinematics(u, x, guess=(R, t), tol_mm=1e-12)
    np.testing.assert_allclose(fk.t, t, atol=1e-8)
    dxi = drive.pose_jacobian(x, fk.R[0], fk.t[0], u[0])

    def tangent(x_):
        solution = drive.forward_kinematics(u[:1], x_, guess=(fk.R[:1], fk.t[:1]), tol_mm=1e-12)
        return np.r_[rotations.so3_log(fk.R[0].T @ solution.R[0]), fk.R[0].T @ (solution.t[0] - fk.t[0])]

    assert relative_error(dxi, numerical_jacobian(tangent, x, 1e-6)) < 1e-6


@pytest.mark.parametrize("name", ["stroke", "two terms", "known second"])
def test_compiled_extensions_and_factor_rows_equal_the_model(setting, name):
    _, rng, R, t, drives = setting
    drive = drives[name]
    x, inputs = _state(drive, rng)
    starts, gains, offsets, values, _ = drive.kernel_terms()
    out = np.empty(6)
    _kernels.leg_extensions(starts, gains, np.ascontiguousarray(offsets[:, None] + values), inputs, out)
    np.testing.assert_array_equal(out, drive.extensions(inputs))

    unknowns = np.r_[x, 0.3]  # a column after the drive's, as an instrument's
    pose = gtsam.Pose3(gtsam.Rot3(R[0]), t[0])
    values_ = gtsam.Values()
    values_.insert(gtsam.symbol("x", 0), pose)
    values_.insert(gtsam.symbol("p", 0), unknowns)
    factor = drive_leg.factor(
        gtsam.symbol("x", 0),
        gtsam.symbol("p", 0),
        drive_leg.DriveLegs.of(np.arange(6), drive),
        inputs,
        gtsam.noiseModel.Unit.Create(6),
    )
    np.testing.assert_allclose(factor.unwhitenedError(values_), drive.residual(x, R[0], t[0], inputs), atol=1e-12)
    A = factor.linearize(values_).jacobian()[0]
    J_pose, J_x = drive.jacobians(x, R[0], t[0], inputs)
    np.testing.assert_allclose(A[:, :6], J_pose, atol=1e-12)
    np.testing.assert_allclose(A[:, 6 : 6 + drive.size], J_x, atol=1e-12)
    assert np.all(A[:, 6 + drive.size :] == 0.0)


def test_platform_drive_and_what_a_calibration_hands_on(setting):
    platform = setting[0]
    assert drive_model(platform).blocks == ()
    assert [b.key for b in drive_model(platform, outside_instrument=True).blocks] == ["stroke_scale"]
    error, k = random_error(np.random.default_rng(1), 0.5), np.linspace(-0.02, 0.03, 6)
    calibrated = drive_model(platform).calibrated(error, {"stroke_scale": k})
    assert calibrated.blocks == ()
    handed = calibrated.onto(platform)
    np.testing.assert_array_equal(handed.stroke_scale, k)
    np.testing.assert_array_equal(handed.drive.as_vector(), platform.drive.perturbed(error).as_vector())
    # the inputs of a term on the leg forces come from the masses the drive carries: none here
    with pytest.raises(ValueError, match="a rigid drive carries no leg forces"):
        setting[4]["two terms"].inverse_kinematics(np.eye(3), np.array([0.0, 0.0, 500.0]))
