"""Instrument models (spec §7): analytic Jacobians against central differences, the closed-form
registration against exact data and its refusals, the gauge basis, the drive's implicit Jacobian."""

from __future__ import annotations

import numpy as np
import pytest

from stewart_calib.errors import CalibError
from stewart_calib.instruments import gauge, points, pose
from stewart_calib.model import kinematics as kin
from stewart_calib.model import rotations
from tests.numdiff import EPS_MM, EPS_RAD, numerical_jacobian, numerical_pose_jacobian, relative_error
from tests.synthetic import nim_stewart, random_poses

#: central differences (steps of numdiff) agree to ~1e-10 relative; 1e-7 leaves room for FK's 1e-9 mm
JACOBIAN_RTOL = 1e-7


def _pose_unknowns(rng) -> pose.PoseUnknowns:
    return pose.PoseUnknowns.from_pose6(
        np.r_[rng.normal(0, 80, 3), rng.uniform(-3, 3, 3)], np.r_[rng.normal(0, 40, 3), rng.uniform(-3, 3, 3)]
    )


def _tangent_steps(n_rot: int, n_mm: int) -> np.ndarray:
    return np.r_[[EPS_RAD] * n_rot, [EPS_MM] * n_mm]


@pytest.mark.parametrize("seed", range(3))
def test_pose_residual_jacobians_match_central_differences(seed):
    rng = np.random.default_rng(seed)
    u = _pose_unknowns(rng)
    R_X, t_X = kin.pose_to_rt(np.r_[rng.normal(0, 100, 3), rng.normal(0, 0.4, 3)])
    measured = kin.rt_to_pose(*kin.retract(*pose.predict(u, R_X, t_X), rng.normal(0, 0.05, 6)))
    _, H_X, H_u = pose.residual(u, measured, R_X, t_X, jacobians=True)
    numeric_X = numerical_pose_jacobian(lambda R, t: pose.residual(u, measured, R, t)[0], R_X, t_X)
    steps = np.r_[_tangent_steps(3, 3), _tangent_steps(3, 3)]
    numeric_u = numerical_jacobian(lambda d: pose.residual(u.retract(d), measured, R_X, t_X)[0], np.zeros(12), steps)
    assert relative_error(H_X, numeric_X) < JACOBIAN_RTOL
    assert relative_error(H_u, numeric_u) < JACOBIAN_RTOL


@pytest.mark.parametrize("n_targets", [1, 3])
def test_points_residual_jacobians_match_central_differences(n_targets):
    rng = np.random.default_rng(n_targets)
    frame = _pose_unknowns(rng)
    u = points.PointsUnknowns(frame.R_frame, frame.t_frame, rng.normal(0, 80, (n_targets, 3)))
    R_X, t_X = kin.pose_to_rt(np.r_[rng.normal(0, 100, 3), rng.normal(0, 0.4, 3)])
    measured = points.predict(u, R_X, t_X).reshape(-1) + rng.normal(0, 0.1, 3 * n_targets)
    _, H_X, H_u = points.residual(u, measured, R_X, t_X, jacobians=True)
    numeric_X = numerical_pose_jacobian(lambda R, t: points.residual(u, measured, R, t)[0], R_X, t_X)
    numeric_u = numerical_jacobian(
        lambda d: points.residual(u.retract(d), measured, R_X, t_X)[0],
        np.zeros(u.size),
        _tangent_steps(3, 3 + 3 * n_targets),
    )
    assert relative_error(H_X, numeric_X) < JACOBIAN_RTOL
    assert relative_error(H_u, numeric_u) < JACOBIAN_RTOL


def test_pose_residual_jacobian_through_gtsam_retract():
    """The pose tangent is GTSAM's: ∂e/∂ξ through ``Pose3.retract`` equals ours."""
    gtsam = pytest.importorskip("gtsam")
    from tests.numdiff import numerical_pose3_jacobian

    rng = np.random.default_rng(7)
    u = _pose_unknowns(rng)
    R_X, t_X = kin.pose_to_rt(np.r_[rng.normal(0, 100, 3), rng.normal(0, 0.4, 3)])
    measured = kin.rt_to_pose(*kin.retract(*pose.predict(u, R_X, t_X), rng.normal(0, 0.05, 6)))
    _, H_X, _ = pose.residual(u, measured, R_X, t_X, jacobians=True)
    X = gtsam.Pose3(gtsam.Rot3(R_X), t_X)
    numeric = numerical_pose3_jacobian(
        lambda p: pose.residual(u, measured, p.rotation().matrix(), p.translation())[0], X
    )
    assert relative_error(H_X, numeric) < JACOBIAN_RTOL


def test_gauge_basis_is_orthonormal_and_free_of_rigid_joint_motion():
    platform = nim_stewart()
    B = gauge.free_basis(platform.drive)
    assert B.shape == (42, 30)
    np.testing.assert_allclose(B.T @ B, np.eye(30), atol=1e-12)
    base_columns, platform_columns = gauge.joint_columns(platform.drive)
    for columns, points_ in (
        (base_columns, platform.drive.base_joints),
        (platform_columns, platform.drive.platform_joints),
    ):
        np.testing.assert_allclose(gauge.rigid_directions(points_).T @ B[columns], 0.0, atol=1e-10)


def test_to_gauge_satisfies_the_gauge_and_keeps_leg_lengths():
    platform = nim_stewart()
    rng = np.random.default_rng(4)
    true = platform.drive.as_vector() + rng.normal(0, 3.0, 42)
    moved, (R_J, t_J), (R_D, t_D) = gauge.to_gauge(platform.drive, true)
    delta = moved - platform.drive.as_vector()
    B = gauge.free_basis(platform.drive)
    np.testing.assert_allclose(delta - B @ (B.T @ delta), 0.0, atol=1e-9)
    # a pose X becomes T_J'_J X T_D'_D⁻¹: every leg keeps its length
    from stewart_calib.model.platform import LegGeometry

    R, t = kin.pose_to_rt(random_poses(platform, 1, rng)[0])
    R2, t2 = rotations.compose(*rotations.compose(R_J, t_J, R, t), *rotations.inverse(R_D, t_D))
    np.testing.assert_allclose(
        kin.leg_lengths(LegGeometry.from_params(moved), R2, t2),
        kin.leg_lengths(LegGeometry.from_params(true), R, t),
        atol=1e-9,
    )


def _poses(n: int, seed: int):
    platform = nim_stewart()
    return kin.pose_to_rt(random_poses(platform, n, np.random.default_rng(seed)))


def test_register_pose_recovers_any_frame_and_target_exactly():
    R_X, t_X = _poses(12, 5)
    u = pose.PoseUnknowns.from_pose6(
        np.r_[100.0, -80.0, 40.0, 2.0, -1.0, 3.0], np.r_[10.0, 20.0, -30.0, 0.5, 1.2, -2.0]
    )
    R_M, t_M = pose.predict(u, R_X, t_X)
    found = pose.register_pose(R_X, t_X, R_M, t_M, np.r_[[1e-4] * 3, [0.01] * 3])
    np.testing.assert_allclose(found.file_values(), u.file_values(), atol=1e-9)


def test_register_points_recovers_frame_and_targets_with_dropouts():
    R_X, t_X = _poses(20, 6)
    rng = np.random.default_rng(6)
    u = points.PointsUnknowns(*kin.pose_to_rt(np.r_[-60.0, 30.0, 90.0, 0.3, -2.5, 1.0]), rng.normal(0, 100, (3, 3)))
    measured = points.predict(u, R_X, t_X).reshape(20, -1)
    measured[::2, 3:6] = np.nan
    measured[1::3, 0:3] = np.nan
    found = points.register_points(R_X, t_X, measured, 0.01)
    np.testing.assert_allclose(found.file_values(), u.file_values(), atol=1e-8)


def test_refit_frame_recovers_a_moved_frame():
    R_X, t_X = _poses(15, 8)
    u = pose.PoseUnknowns.from_pose6(np.r_[30.0, 5.0, -20.0, 0.2, 0.1, 2.0], np.r_[1.0, 2.0, 3.0, 0.1, 0.0, 0.3])
    measured = kin.rt_to_pose(*pose.predict(u, R_X, t_X))
    start = pose.PoseUnknowns(np.eye(3), np.zeros(3), u.R_target, u.t_target)
    from dataclasses import replace

    from stewart_calib.model.platform import Instrument

    platform = replace(nim_stewart(), instrument=Instrument("pose", position_sigma_mm=0.1, orientation_sigma_rad=1e-3))
    found = pose.PoseModel(platform).refit_frame(start, R_X, t_X, measured)
    np.testing.assert_allclose(found.file_values(), u.file_values(), atol=1e-9)


def test_registration_refuses_identical_poses_with_the_reason():
    R_X, t_X = _poses(1, 9)
    R_X, t_X = np.repeat(R_X, 5, axis=0), np.repeat(t_X, 5, axis=0)
    u = pose.PoseUnknowns.from_pose6(np.zeros(6), np.zeros(6))
    with pytest.raises(CalibError, match="1 distinct pose"):
        pose.register_pose(R_X, t_X, *pose.predict(u, R_X, t_X), np.r_[[1e-3] * 3, [0.1] * 3])
    measured = points.predict(points.PointsUnknowns(np.eye(3), np.zeros(3), np.ones((1, 3))), R_X, t_X).reshape(5, 3)
    with pytest.raises(CalibError, match="distinct pose"):
        points.register_points(R_X, t_X, measured, 0.1)


def test_registration_refuses_poses_that_do_not_rotate():
    R_X, t_X = _poses(6, 10)
    R_X = np.repeat(R_X[:1], 6, axis=0)  # translations only
    u = pose.PoseUnknowns.from_pose6(np.r_[0, 0, 0, 0.1, 0.2, 0.3], np.zeros(6))
    with pytest.raises(CalibError, match="rotate about two different axes"):
        pose.register_pose(R_X, t_X, *pose.predict(u, R_X, t_X), np.r_[[1e-3] * 3, [0.1] * 3])


# ----------------------------------------------------------------------------- the InstrumentModel protocol


def _models():
    from dataclasses import replace

    from stewart_calib.config import NoiseConfig
    from stewart_calib.instruments import instrument_model
    from stewart_calib.model.platform import Instrument
    from tests.instrument_data import hobby

    pose_platform = hobby()
    pose_platform = replace(
        pose_platform,
        instrument=replace(
            pose_platform.instrument,
            frame=np.r_[40.0, -20.0, 10.0, 0.3, -0.2, 2.0],
            target=np.r_[5.0, 8.0, 30.0, 0.1, 0.2, -1.5],
        ),
    )
    points_platform = hobby(
        Instrument(
            "points",
            np.r_[40.0, -20.0, 10.0, 0.3, -0.2, 2.0],
            np.zeros(6),
            np.array([[60.0, 0.0, 25.0], [-30.0, 50.0, 25.0], [-30.0, -50.0, 40.0]]),
            0.05,
        )
    )
    return [instrument_model(p, NoiseConfig()) for p in (pose_platform, points_platform)]


@pytest.mark.parametrize("which", [0, 1])
def test_instrument_model_residual_and_pose_jacobians(which):
    """The protocol's Jacobians (θ in pose6 coordinates) against central differences, and ``pose``
    inverting the prediction."""
    from stewart_calib.instruments.base import InstrumentModel

    model = _models()[which]
    assert isinstance(model, InstrumentModel)
    rng = np.random.default_rng(which)
    theta = model.unknowns.nominal + rng.normal(0, 0.01, model.unknowns.size)
    R, t = kin.pose_to_rt(np.r_[5.0, -3.0, 200.0, 0.1, -0.05, 0.2])
    exact = model.residual(R, t, theta, np.zeros(model.channel_sigma.size), np.arange(model.channel_sigma.size))
    z = (
        -exact.r
        if model.kind == "points"
        else kin.rt_to_pose(*pose.predict(pose.PoseUnknowns.from_pose6(theta[:6], theta[6:]), R, t))
    )
    z = z + rng.normal(0, 0.01, z.size)
    channels = np.concatenate(model.groups(z))
    res = model.residual(R, t, theta, z, channels)
    steps = np.where(model.unknowns.file_scale > 1, EPS_RAD, EPS_MM)
    numeric_theta = numerical_jacobian(lambda th: model.residual(R, t, th, z, channels).r, theta, steps)
    numeric_pose = numerical_pose_jacobian(lambda R_, t_: model.residual(R_, t_, theta, z, channels).r, R, t)
    assert relative_error(res.J_instrument, numeric_theta) < JACOBIAN_RTOL
    assert relative_error(res.J_pose, numeric_pose) < JACOBIAN_RTOL

    seen = model.pose(z, theta, None)
    np.testing.assert_allclose(model.residual(seen.R, seen.t, theta, z, channels).r, 0.0, atol=0.05)

    def tangent(th):
        moved = model.pose(z, th, None)
        return np.r_[rotations.so3_log(seen.R.T @ moved.R), seen.R.T @ (moved.t - seen.t)]

    assert relative_error(seen.J_instrument, numerical_jacobian(tangent, theta, steps)) < 1e-6
    assert np.all(np.linalg.eigvalsh(seen.covariance) > 0)


def test_points_pose_hands_over_what_the_readings_hold_beyond_the_pose():
    """Three targets' nine coordinates fix a pose and three distances: ``pose`` gives the fit's residual
    along the directions no pose moves, with its ∂/∂θ (the fit's own pose moving with θ) and σ² I."""
    model = _models()[1]
    rng = np.random.default_rng(5)
    theta = model.unknowns.nominal + rng.normal(0, 0.01, model.unknowns.size)
    R, t = kin.pose_to_rt(np.r_[5.0, -3.0, 200.0, 0.1, -0.05, 0.2])
    channels = np.arange(model.channel_sigma.size)
    z = -model.residual(R, t, theta, np.zeros(channels.size), channels).r + rng.normal(0, 0.05, channels.size)
    seen = model.pose(z, theta, None)
    redundant = seen.redundant
    A = model.residual(seen.R, seen.t, theta, z, channels).J_pose
    across = np.eye(channels.size) - A @ np.linalg.solve(A.T @ A, A.T)  # onto what no pose moves
    fitted = model.residual(seen.R, seen.t, theta, z, channels).r
    assert redundant.r.shape == (3,)
    np.testing.assert_allclose(redundant.r @ redundant.r, fitted @ across @ fitted, rtol=1e-8)
    np.testing.assert_allclose(redundant.covariance, 0.05**2 * np.eye(3))
    steps = np.where(model.unknowns.file_scale > 1, EPS_RAD, EPS_MM)

    def at_its_pose(th):
        moved = model.pose(z, th, None)
        return model.residual(moved.R, moved.t, th, z, channels).r

    D = numerical_jacobian(at_its_pose, theta, steps)
    assert relative_error(redundant.J_instrument.T @ redundant.J_instrument, D.T @ across @ D) < 1e-5
    assert model.pose(z[:6].tolist() + [np.nan] * 3, theta, None) is None  # two targets: no pose at all
