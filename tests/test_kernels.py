"""The compiled paths against their numpy definitions: fused EKF observation, pose difference,
FK on a degenerate geometry, FK with NaN and a zero-length leg."""

from __future__ import annotations

import numpy as np
import pytest

from stewart_calib.estimators.measurement import pose_difference
from stewart_calib.model import kinematics as kin
from stewart_calib.model.platform import LegGeometry

from .synthetic import nim_stewart, random_poses

PLATFORM = nim_stewart()
POSES = random_poses(PLATFORM, 5, np.random.default_rng(21))


@pytest.mark.parametrize("k", range(len(POSES)))
def test_leg_ekf_observation_equals_its_numpy_definition(k):
    rng = np.random.default_rng(k)
    drive, tracker = PLATFORM.drive, PLATFORM.tracker
    delta = rng.normal(0.0, 1.0, 42)
    R, t = kin.pose_to_rt(POSES[k])
    strokes = kin.inverse_kinematics(drive, R, t) + rng.normal(0.0, 0.5, 6)
    sigma_s, sigma_q = 0.002, 0.001
    # One pose goes through the compiled covariance, a batch of one through numpy's inverse.
    pose_cov = kin.pose_covariance_from_legs(tracker, R, t, sigma_s)
    pose_cov_ref = kin.pose_covariance_from_legs(tracker, R[None], t[None], sigma_s)[0]
    # a solve instead of an explicit inverse: relative rounding of cond(J_t) · 1e-16.
    np.testing.assert_allclose(pose_cov, pose_cov_ref, rtol=1e-10, atol=1e-12 * np.abs(pose_cov_ref).max())
    np.testing.assert_array_equal(pose_cov, pose_cov.T)
    r, H, R_meas, J_x = kin.leg_ekf_observation(drive, delta, R, t, strokes, pose_cov, sigma_q)

    model = drive.perturbed(delta)
    J_x_ref, H_ref = kin.leg_residual_jacobians(model, R, t)
    R_ref = J_x_ref @ pose_cov @ J_x_ref.T + sigma_q**2 * np.eye(6)
    # Same formulas, different evaluation order: rounding only (lengths ~1e3 mm → 1e-12 mm).
    np.testing.assert_allclose(r, kin.leg_residuals(model, R, t, strokes), rtol=0, atol=1e-10)
    np.testing.assert_allclose(H, H_ref, rtol=0, atol=1e-13)
    np.testing.assert_allclose(J_x, J_x_ref, rtol=0, atol=1e-10)
    np.testing.assert_allclose(R_meas, R_ref, rtol=1e-10, atol=1e-12 * np.abs(R_ref).max())
    np.testing.assert_array_equal(R_meas, R_meas.T)


def _leg_set_pose(guess=None):
    """The EKF's compiled observation through the tracker (known geometry) of ``PLATFORM``'s drive."""
    from stewart_calib.estimators.measurement import LegSetPose
    from stewart_calib.instruments.tracker import TrackerModel
    from stewart_calib.model.drive import drive_model

    pose = LegSetPose(TrackerModel(PLATFORM.tracker, 0.002), drive_model(PLATFORM), 0.001)
    pose.import_state({} if guess is None else {"R": guess[0], "t": guess[1]})
    return pose


@pytest.mark.parametrize("warm", [True, False])
def test_the_leg_set_observation_is_fk_then_the_observation_bit_for_bit(warm):
    """The ekf's compiled per-sample observation gives exactly what its three parts give (same kernels)."""
    rng = np.random.default_rng(3)
    drive, tracker = PLATFORM.drive, PLATFORM.tracker
    delta = rng.normal(0.0, 1.0, 42)
    R_true, t_true = kin.pose_to_rt(POSES[1])
    readings = kin.inverse_kinematics(tracker, R_true, t_true)
    strokes = kin.inverse_kinematics(drive, R_true, t_true) + rng.normal(0.0, 0.5, 6)
    guess = kin.pose_to_rt(POSES[2]) if warm else None  # a warm start far away: Newton still converges
    pose = _leg_set_pose(guess)
    nu, H, R_meas = pose.observe(delta, np.concatenate((strokes, readings)))
    R, t = pose.guess

    R_ref, t_ref = kin.solve_fk(tracker, readings, guess, "tracker")
    pose_cov = kin.pose_covariance_from_legs(tracker, R_ref, t_ref, 0.002)
    r_ref, H_ref, R_meas_ref, _ = kin.leg_ekf_observation(drive, delta, R_ref, t_ref, strokes, pose_cov, 0.001)
    for value, reference in ((R, R_ref), (t, t_ref), (-nu, r_ref), (H, H_ref), (R_meas, R_meas_ref)):
        np.testing.assert_array_equal(value, reference)
    np.testing.assert_allclose(t, t_true, atol=1e-6)


def test_the_leg_set_observation_with_an_unknown_drive_term_is_the_drive_models():
    """With the stroke scale unknown (columns 42…47 of the state) and an unknown after them, the compiled
    observation is the drive model's (its extensions and ``∂r/∂x_drive`` with the terms) at the
    tracker's FK pose, 0 on the other unknown's column."""
    from stewart_calib.estimators.measurement import LegSetPose
    from stewart_calib.instruments.tracker import TrackerModel
    from stewart_calib.model.drive import drive_model

    rng = np.random.default_rng(4)
    drive = drive_model(PLATFORM, outside_instrument=True)
    assert drive.size == 48
    x = np.r_[rng.normal(0.0, 1.0, 42), rng.normal(0.0, 0.01, 6), 3.0]
    R_true, t_true = kin.pose_to_rt(POSES[3])
    readings = kin.inverse_kinematics(PLATFORM.tracker, R_true, t_true)
    strokes = kin.inverse_kinematics(PLATFORM.drive, R_true, t_true) + rng.normal(0.0, 0.5, 6)
    pose = LegSetPose(TrackerModel(PLATFORM.tracker, 0.002), drive, 0.001)
    nu, H, R_meas = pose.observe(x, np.concatenate((strokes, readings)))
    R, t = pose.guess
    pose_cov = kin.pose_covariance_from_legs(PLATFORM.tracker, R, t, 0.002)
    r_ref, H_ref, R_meas_ref, _ = drive.observation(x[:48], R, t, drive.inputs(strokes), pose_cov, 0.001)
    np.testing.assert_allclose(-nu, r_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(H[:, :48], H_ref, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(H[:, 48], 0.0)
    np.testing.assert_allclose(R_meas, R_meas_ref, rtol=1e-12, atol=0)


def test_the_leg_set_observation_refuses_readings_without_a_pose_as_fk_failure():
    from stewart_calib.errors import SampleRejected

    with pytest.raises(SampleRejected, match="tracker forward kinematics did not converge") as err:
        _leg_set_pose().observe(np.zeros(42), np.r_[np.zeros(6), np.nan, np.zeros(5)])
    assert err.value.reason == SampleRejected.FK_FAILED


def test_pose_difference_is_wrapped_rpy_difference_and_broadcasts():
    R, t = kin.pose_to_rt(POSES)
    R_m, t_m = kin.pose_to_rt(POSES[::-1] + np.r_[0.0, 0.0, 0.0, 2 * np.pi, 0.0, -2 * np.pi])
    Y = pose_difference(R, t, R_m, t_m)
    d_rpy = kin.rotation_to_rpy(R) - kin.rotation_to_rpy(R_m)
    expected = np.concatenate([t - t_m, np.angle(np.exp(1j * d_rpy))], axis=-1)
    np.testing.assert_allclose(Y, expected, rtol=0, atol=1e-13)
    # One measured pose against a batch of model poses broadcasts like numpy.
    np.testing.assert_allclose(
        pose_difference(R[0], t[0], R_m, t_m), pose_difference(R[[0] * len(R)], t[[0] * len(R)], R_m, t_m)
    )


def test_fk_on_a_degenerate_geometry_takes_least_squares_steps():
    # All platform joints at one point: the rotation columns of the leg Jacobian are exactly 0
    # (singular J); the least-squares step still trilaterates the point from six lengths.
    legs = LegGeometry(PLATFORM.tracker.base_joints, np.zeros((6, 3)), np.zeros(6))
    point = np.array([30.0, -20.0, 900.0])
    lengths = np.linalg.norm(point - legs.base_joints, axis=-1)
    solution = kin.forward_kinematics(legs, lengths, tol_mm=1e-9)
    assert np.linalg.norm(solution.t - point) <= 1e-9
    np.testing.assert_array_equal(solution.R, np.eye(3))  # no information, no rotation step


def test_fk_zero_length_leg_reports_nan_not_an_exception():
    # A leg of zero length at the guess makes n_i = 0/0: numpy semantics (NaN, not ZeroDivisionError).
    legs = LegGeometry(np.zeros((6, 3)), np.zeros((6, 3)), np.ones(6))
    report = kin.forward_kinematics(legs, np.zeros(6), guess=(np.eye(3), np.zeros(3)), strict=False)
    assert not report.converged
    with pytest.raises(kin.FKError, match="did not converge"):
        kin.forward_kinematics(legs, np.zeros(6), guess=(np.eye(3), np.zeros(3)))


def test_fk_per_pose_geometry_solves_each_pose_with_its_own_legs():
    # Pose k with geometry k in one batched call equals k single solves with LegGeometry k
    # (the same compiled loop, so bit for bit), and a geometry/stroke shape mismatch is refused.
    rng = np.random.default_rng(5)
    drive = PLATFORM.drive
    deltas = rng.normal(0.0, 2.0, (len(POSES), 42))
    geometries = [drive.perturbed(delta) for delta in deltas]
    R, t = kin.pose_to_rt(POSES)
    strokes = np.stack([kin.inverse_kinematics(g, R[k], t[k]) for k, g in enumerate(geometries)])
    home_R, home_t = kin.pose_to_rt(PLATFORM.workspace.home)
    base, plat, lengths = (
        np.stack([getattr(g, name) for g in geometries])
        for name in ("base_joints", "platform_joints", "initial_lengths")
    )

    batched = kin.forward_kinematics_per_pose(base, plat, lengths, strokes, guess=(home_R, home_t))
    for k, g in enumerate(geometries):
        single = kin.forward_kinematics(g, strokes[k], guess=(home_R, home_t))
        np.testing.assert_array_equal(batched.R[k], single.R)
        np.testing.assert_array_equal(batched.t[k], single.t)
        assert batched.iterations[k] == single.iterations
        # Each pose is recovered (its own geometry, not pose 0's): tolerance 1e-9 mm on ~1e3 mm legs.
        assert np.linalg.norm(batched.t[k] - t[k]) <= 1e-8
        assert kin.rotation_angle(R[k].T @ batched.R[k]) <= 1e-10
    assert batched.converged.all() and (batched.residual_mm <= 1e-9).all()
    # Solving every pose with geometry 0 instead would miss by the perturbation (~mm).
    shared = kin.forward_kinematics(geometries[0], strokes, guess=(home_R, home_t))
    assert np.linalg.norm(shared.t[1:] - t[1:], axis=-1).min() > 1e-3

    with pytest.raises(ValueError, match="base_joints must have shape"):
        kin.forward_kinematics_per_pose(base[:1], plat, lengths, strokes, guess=(home_R, home_t))


@pytest.mark.parametrize("seed", range(3))
def test_the_pose_instrument_kernel_equals_its_lie_group_definition(seed):
    """``_kernels.pose_instrument_observation`` (PoseModel.pose) against the composition it compiles:
    ``X = F M G⁻¹``, ``Ad_G N Ad_Gᵀ`` and ``[Ad_{G M⁻¹}, −Ad_G] (∂θ/∂[φ, γ])⁻¹`` in numpy."""
    from stewart_calib.instruments.pose import theta_tangent_jacobian
    from stewart_calib.model import _kernels, rotations

    rng = np.random.default_rng(seed)
    theta = np.r_[rng.normal(0, 100, 3), rng.uniform(-3, 3, 3), rng.normal(0, 50, 3), rng.uniform(-1.2, 1.2, 3)]
    z = np.r_[rng.normal(0, 100, 3), rng.uniform(-3, 3, 3)]
    orientation_variance, position_variance = 1e-6, 0.04
    R_X, t_X, covariance, J = _kernels.pose_instrument_observation(z, theta, orientation_variance, position_variance)
    (R_F, t_F), (R_M, t_M), (R_G, t_G) = kin.pose_to_rt(theta[:6]), kin.pose_to_rt(z), kin.pose_to_rt(theta[6:])
    R_expected, t_expected = rotations.compose(*rotations.compose(R_F, t_F, R_M, t_M), *rotations.inverse(R_G, t_G))
    Ad_G = rotations.adjoint(R_G, t_G)
    noise = np.diag([orientation_variance] * 3 + [position_variance] * 3)
    J_tangent = np.hstack([rotations.adjoint(*rotations.compose(R_G, t_G, *rotations.inverse(R_M, t_M))), -Ad_G])
    np.testing.assert_allclose(R_X, R_expected, rtol=0, atol=1e-14)
    np.testing.assert_allclose(t_X, t_expected, rtol=1e-14, atol=1e-12)
    np.testing.assert_allclose(covariance, Ad_G @ noise @ Ad_G.T, rtol=1e-12, atol=1e-18)
    expected = J_tangent @ np.linalg.inv(theta_tangent_jacobian(theta))
    np.testing.assert_allclose(J, expected, rtol=0, atol=1e-12 * np.abs(expected).max())
