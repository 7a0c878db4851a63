"""Kinematics (stewart_calib.model.kinematics) against its definitions, the paper and finite differences.

Poses are compared in local coordinates: translation norm [mm] and the rotation angle of
``R_aᵀ R_b`` [rad] (never raw Euler differences). Jacobians are compared with the shared
central-difference helper in :mod:`tests.numdiff`.
"""

from __future__ import annotations

import itertools

import gtsam
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from stewart_calib.model import kinematics as kin
from stewart_calib.model.platform import LegGeometry

from .numdiff import (
    EPS_MM,
    numerical_jacobian,
    numerical_pose3_jacobian,
    numerical_pose_jacobian,
    relative_error,
)
from .synthetic import nim_stewart, random_poses

PLATFORM = nim_stewart()
WS = PLATFORM.workspace
HALF_BOX = np.r_[[WS.translation_limit] * 3, [WS.rotation_limit] * 3]  # ±200 mm, ±20°
MECHANISMS = {"drive": PLATFORM.drive, "tracker": PLATFORM.tracker}

# Round-trip tolerance: 1e-9 mm / 1e-9 rad. FK is solved to 1e-11 mm on the lengths; the
# pose error is then ≤ cond(J) · 1e-11 with cond(J) ≲ 2.5e3 (mm, rad mixed) at the box corners,
# i.e. ≤ 3e-8 in the worst case but ~1e-11 measured: tol_mm=1e-9 alone would leave ~1e-9 mm.
ROUND_TRIP_MM = 1e-9
ROUND_TRIP_RAD = 1e-9
FK_TOL_MM = 1e-11
# Jacobian checks: the helper's steps give ~1e-10 relative error (tests/numdiff.py), so 1e-6
# fails any wrong term (a sign or a missing factor is an O(1) relative error) with wide margin.
JACOBIAN_REL_TOL = 1e-6

unit = st.floats(min_value=-1.0, max_value=1.0, allow_nan=False)  # hypothesis draws ±1 (edges) often
box_fraction = st.lists(unit, min_size=6, max_size=6).map(np.array)
CORNER = [1.0, -1.0, 1.0, -1.0, 1.0, -1.0]


def workspace_pose(fraction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` at ``home + fraction · (±200 mm, ±20°)``."""
    return kin.pose_to_rt(WS.home + fraction * HALF_BOX)


def assert_same_pose(R_a, t_a, R_b, t_b, tol_mm=ROUND_TRIP_MM, tol_rad=ROUND_TRIP_RAD):
    position_mm, angle_deg = kin.pose_error(R_a, t_a, R_b, t_b)
    assert np.max(position_mm) <= tol_mm, f"position differs by {np.max(position_mm):.3g} mm"
    assert np.max(np.radians(angle_deg)) <= tol_rad, f"rotation differs by {np.max(np.radians(angle_deg)):.3g} rad"


# ----------------------------------------------------------------------------- FK / IK


@pytest.mark.parametrize("mechanism", MECHANISMS)
@settings(max_examples=40, deadline=None)
@given(fraction=box_fraction)
@example(fraction=np.ones(6))
@example(fraction=-np.ones(6))
@example(fraction=np.array(CORNER))
def test_fk_of_ik_is_the_pose(mechanism, fraction):
    legs = MECHANISMS[mechanism]
    R, t = workspace_pose(fraction)
    solution = kin.forward_kinematics(legs, kin.inverse_kinematics(legs, R, t), tol_mm=FK_TOL_MM)
    assert_same_pose(R, t, solution.R, solution.t)


# Stroke boxes about home whose 64 corners all reach FK (checked): ±30 mm on every leg moves
# the platform by up to ~70 mm / ~20°, inside the workspace of both mechanisms.
STROKE_HALF_RANGE_MM = 30.0


@pytest.mark.parametrize("mechanism", MECHANISMS)
@settings(max_examples=40, deadline=None)
@given(fraction=box_fraction)
@example(fraction=np.ones(6))
@example(fraction=np.array(CORNER))
def test_ik_of_fk_is_the_lengths(mechanism, fraction):
    legs = MECHANISMS[mechanism]
    strokes = kin.inverse_kinematics(legs, *kin.pose_to_rt(WS.home)) + STROKE_HALF_RANGE_MM * fraction
    solution = kin.forward_kinematics(legs, strokes, tol_mm=FK_TOL_MM)
    # IK(FK(q)) − q is the FK residual itself: ≤ tol_mm by construction, ≤ 1e-9 mm asked.
    np.testing.assert_allclose(
        kin.inverse_kinematics(legs, solution.R, solution.t), strokes, rtol=0, atol=ROUND_TRIP_MM
    )


@pytest.mark.parametrize("mechanism", MECHANISMS)
def test_batched_fk_equals_single(mechanism):
    legs = MECHANISMS[mechanism]
    poses = random_poses(PLATFORM, 20, np.random.default_rng(1))
    strokes = kin.inverse_kinematics(legs, *kin.pose_to_rt(poses))
    batch = kin.forward_kinematics(legs, strokes.reshape(4, 5, 6), tol_mm=FK_TOL_MM)
    assert batch.R.shape == (4, 5, 3, 3) and batch.iterations.shape == (4, 5)
    for k, q in enumerate(strokes):
        single = kin.forward_kinematics(legs, q, tol_mm=FK_TOL_MM)
        i, j = divmod(k, 5)
        # Same Newton iterates per pose; only the last bits of batched BLAS may differ.
        assert single.iterations == batch.iterations[i, j]
        assert_same_pose(single.R, single.t, batch.R[i, j], batch.t[i, j], tol_mm=1e-12, tol_rad=1e-14)


@pytest.mark.parametrize("mechanism", MECHANISMS)
def test_warm_start_needs_no_more_iterations_than_cold(mechanism):
    legs = MECHANISMS[mechanism]
    # A 1 kHz trajectory: 100 ms of a circle of 150 mm radius at 1 rev/s plus a 10° roll sweep.
    time_s = np.arange(100) * 1e-3
    poses = np.tile(WS.home, (len(time_s), 1))
    poses[:, 0] += 150.0 * np.cos(2 * np.pi * time_s)
    poses[:, 1] += 150.0 * np.sin(2 * np.pi * time_s)
    poses[:, 3] += np.radians(10.0) * np.sin(2 * np.pi * time_s)
    R, t = kin.pose_to_rt(poses)
    strokes = kin.inverse_kinematics(legs, R, t)
    cold = kin.forward_kinematics(legs, strokes[1:]).iterations
    warm = np.array(
        [kin.forward_kinematics(legs, strokes[k], guess=(R[k - 1], t[k - 1])).iterations for k in range(1, len(poses))]
    )
    assert np.all(warm <= cold)
    assert warm.sum() < cold.sum()


def fk_tolerance_bound(tracker, drive, R, t) -> float:
    """How far two FK solves of the same strokes, each leaving its leg lengths within FK's tolerance,
    can put the tracker's readings apart [mm]: the lengths differ by up to 2·tol, the pose by
    ``J_d⁻¹`` of that, the readings by ``J_t J_d⁻¹`` of it (first order, ∞-norm), plus the rounding
    of leg lengths near a metre (a few ulps)."""
    gain = np.abs(kin.leg_pose_jacobian(tracker, R, t) @ np.linalg.inv(kin.leg_pose_jacobian(drive, R, t))).sum(axis=-1)
    return float(2 * kin.FK_TOLERANCE_MM * gain.max() + 16 * np.finfo(float).eps * 2000.0)


def test_tracker_reading_residuals_are_batch_fk_and_ik():
    # one compiled pass whose Newton solves start from the sample before (or the other drive's
    # solution): the batch FK from the level guess, then IK, to within what FK's tolerance leaves
    # open — on poses far apart (poor warm starts), with a sample whose strokes no pose reaches
    platform = nim_stewart()
    rng = np.random.default_rng(3)
    R, t = kin.pose_to_rt(random_poses(platform, 200, rng))
    readings = kin.inverse_kinematics(platform.tracker, R, t) + rng.normal(0.0, 0.01, (200, 6))
    strokes = kin.inverse_kinematics(platform.drive, R, t)
    strokes[50, 0] += 3000.0  # one leg 3 m longer than the rest
    drives = [platform.drive, platform.drive.perturbed(rng.normal(0.0, 1.0, 42))]
    each_strokes = [strokes, strokes * 1.001]
    residuals, converged = kin.tracker_reading_residuals(platform.tracker, readings, drives, each_strokes)
    assert np.array_equal(converged, np.arange(200)[None, :].repeat(2, axis=0) != 50)
    for drive, q, got in zip(drives, each_strokes, residuals, strict=True):
        fk = kin.forward_kinematics(drive, np.delete(q, 50, axis=0))
        expected = np.delete(readings, 50, axis=0) - kin.inverse_kinematics(platform.tracker, fk.R, fk.t)
        assert np.abs(np.delete(got, 50, axis=0) - expected).max() <= fk_tolerance_bound(
            platform.tracker, drive, fk.R, fk.t
        )


def test_fk_along_a_log_is_the_batch_fk():
    # each pose from the one before (a log in order), cold after a sample that does not converge and after
    # a jump: the level-guess batch's solutions, to what FK's tolerance leaves open, and the same failures
    platform = nim_stewart()
    rng = np.random.default_rng(4)
    path = np.cumsum(rng.normal(0.0, 0.3, (300, 6)), axis=0) * np.array([1.0, 1.0, 1.0, 1e-3, 1e-3, 1e-3])
    poses = np.asarray(WS.home) + path
    poses[150] = random_poses(platform, 1, rng)[0]  # a jump across the workspace and back
    R, t = kin.pose_to_rt(poses)
    readings = kin.inverse_kinematics(platform.tracker, R, t)
    readings[100, 0] += 3000.0  # one leg 3 m longer than the rest
    readings[200, 2] = np.nan
    along = kin.forward_kinematics(platform.tracker, readings, strict=False, along=True)
    batch = kin.forward_kinematics(platform.tracker, readings, strict=False)
    assert np.array_equal(along.converged, batch.converged) and not along.converged[[100, 200]].any()
    ok = batch.converged
    # lengths within 1e-9 mm; the pose within the leg Jacobian's inverse of that (a few here)
    assert np.abs(along.t - batch.t)[ok].max() <= 1e-7
    assert np.abs(along.R - batch.R)[ok].max() <= 1e-10
    assert along.iterations[ok].mean() < batch.iterations[ok].mean()


def test_fk_refuses_inconsistent_lengths():
    legs = PLATFORM.drive
    strokes = kin.inverse_kinematics(legs, *kin.pose_to_rt(WS.home))
    strokes[2] = 10_000.0 - legs.initial_lengths[2]  # one leg 10 m, the others at home
    with pytest.raises(kin.FKError, match=r"did not converge.*unreachable"):
        kin.forward_kinematics(legs, strokes)
    report = kin.forward_kinematics(legs, strokes, strict=False)
    assert not report.converged
    # Far from any consistent pose: the residual stays at the scale of the 9 m mismatch.
    assert report.residual_mm > 1.0


def test_fk_refuses_nan_and_reports_it_per_pose():
    legs = PLATFORM.tracker
    strokes = np.zeros((3, 6))
    strokes[1, 4] = np.nan
    with pytest.raises(kin.FKError, match=r"\(pose \(1,\)\): non-finite lengths"):
        kin.forward_kinematics(legs, strokes)
    report = kin.forward_kinematics(legs, strokes, strict=False)
    np.testing.assert_array_equal(report.converged, [True, False, True])
    assert np.all(np.isfinite(report.R[[0, 2]])) and np.all(np.isfinite(report.t[[0, 2]]))


def test_fk_refuses_too_few_iterations():
    legs = PLATFORM.drive
    R, t = workspace_pose(np.array(CORNER))
    strokes = kin.inverse_kinematics(legs, R, t)
    # From the level default guess a box corner needs ≥ 4 Newton steps to reach 1e-9 mm.
    with pytest.raises(kin.FKError, match="after 1 Newton iterations"):
        kin.forward_kinematics(legs, strokes, max_iterations=1)
    report = kin.forward_kinematics(legs, strokes, max_iterations=1, strict=False)
    assert not report.converged and report.iterations == 1 and report.residual_mm > 1e-9


def test_tracker_reads_zero_at_home():
    readings = kin.inverse_kinematics(PLATFORM.tracker, *kin.pose_to_rt(WS.home))
    # Table 2 rounds the joint coordinates to 10 µm (±5 µm each); the six leg lengths at home
    # then agree only to ±2.5 µm (measured 2.48 µm max), so 3 µm is the rounding, not slack.
    assert np.max(np.abs(readings)) <= 3e-3


def test_drive_strokes_are_zero_at_home():
    strokes = kin.inverse_kinematics(PLATFORM.drive, *kin.pose_to_rt(WS.home))
    # The assumed drive geometry is rounded to 1 µm and its initial lengths to 1 nm:
    # ≤ 1 µm (measured 0.44 µm).
    assert np.max(np.abs(strokes)) <= 1e-3


# ----------------------------------------------------------------------------- error model

J_P_POSES = random_poses(PLATFORM, 3, np.random.default_rng(3))
J_P_POSES[0] = WS.home + np.array(CORNER) * HALF_BOX * 0.9  # near an edge of the workspace


def fk_pose_vector(legs: LegGeometry, strokes: np.ndarray, guess) -> np.ndarray:
    """``[t [mm], rpy [rad]]`` (paper's δE coordinates) of FK solved to 1e-12 mm."""
    solution = kin.forward_kinematics(legs, strokes, guess=guess, tol_mm=1e-12)
    return np.concatenate([solution.t, kin.rotation_to_rpy(solution.R)], axis=-1)


@pytest.mark.parametrize("pose", J_P_POSES, ids=["edge", "random1", "random2"])
def test_error_jacobian_matches_finite_differences_of_fk(pose):
    drive = PLATFORM.drive
    R, t = kin.pose_to_rt(pose)
    strokes = kin.inverse_kinematics(drive, R, t)  # fixed strokes
    M = drive.as_vector()
    numeric = numerical_jacobian(lambda m: fk_pose_vector(LegGeometry.from_params(m), strokes, (R, t)), M, EPS_MM)
    assert relative_error(kin.error_jacobian(drive, R, t), numeric) <= JACOBIAN_REL_TOL


def test_error_jacobian_linearisation_is_second_order():
    drive = PLATFORM.drive
    R, t = kin.pose_to_rt(J_P_POSES[1])
    strokes = kin.inverse_kinematics(drive, R, t)
    E0 = fk_pose_vector(drive, strokes, (R, t))
    J_p = kin.error_jacobian(drive, R, t)
    direction = np.random.default_rng(4).normal(0.0, 1.0, 42)  # δM of ~1 mm per parameter

    def linearisation_error(scale):
        delta = scale * direction
        remainder = fk_pose_vector(drive.perturbed(delta), strokes, (R, t)) - E0 - J_p @ delta
        return np.linalg.norm(remainder[:3]), np.linalg.norm(remainder[3:])  # [mm], [rad]

    errors = np.array([linearisation_error(s) for s in (1.0, 0.5, 0.25)])  # (3 scales, [mm, rad])
    # Second order: the remainder scales as |δM|², so each halving divides it by 4. Position
    # and rotation are checked apart (mixing mm and rad would hide the rotation rows): scaling
    # either block of J_p by 1.01 leaves a first-order remainder and ratios ≈ 2.0–2.4.
    # FK noise (~1e-12 mm, 1e-15 rad) is far below the smallest remainders (~2e-3 mm, 3e-6 rad).
    assert np.all(errors[-1] > [1e-6, 1e-9])
    ratios = errors[:-1] / errors[1:]
    assert np.all((ratios >= 3.0) & (ratios <= 5.0)), ratios


@pytest.mark.parametrize("mechanism", MECHANISMS)
@pytest.mark.parametrize("pose", J_P_POSES, ids=["edge", "random1", "random2"])
def test_leg_residual_jacobians_match_finite_differences(mechanism, pose):
    legs = MECHANISMS[mechanism]
    R, t = kin.pose_to_rt(pose)
    strokes = kin.inverse_kinematics(legs, R, t) + np.array([0.3, -0.2, 0.1, 0.0, 0.5, -0.4])  # r ≠ 0
    H_pose, H_params = kin.leg_residual_jacobians(legs, R, t)

    numeric_pose = numerical_pose_jacobian(lambda R_, t_: kin.leg_residuals(legs, R_, t_, strokes), R, t)
    assert relative_error(H_pose, numeric_pose) <= JACOBIAN_REL_TOL

    pose3 = gtsam.Pose3(gtsam.Rot3(R), t)
    numeric_pose3 = numerical_pose3_jacobian(
        lambda p: kin.leg_residuals(legs, p.rotation().matrix(), p.translation(), strokes), pose3
    )
    assert relative_error(H_pose, numeric_pose3) <= JACOBIAN_REL_TOL  # GTSAM's H convention

    numeric_params = numerical_jacobian(
        lambda m: kin.leg_residuals(LegGeometry.from_params(m), R, t, strokes), legs.as_vector(), EPS_MM
    )
    assert relative_error(H_params, numeric_params) <= JACOBIAN_REL_TOL


def test_leg_pose_jacobian_batched_equals_single():
    R, t = kin.pose_to_rt(J_P_POSES)
    batched = kin.leg_pose_jacobian(PLATFORM.tracker, R, t)
    single = np.stack([kin.leg_pose_jacobian(PLATFORM.tracker, R[k], t[k]) for k in range(len(R))])
    np.testing.assert_allclose(batched, single, rtol=0, atol=1e-12)


@pytest.mark.parametrize("pose", J_P_POSES[:2], ids=["edge", "random1"])
def test_pose_covariance_from_legs_matches_monte_carlo(pose):
    tracker = PLATFORM.tracker
    sigma_mm = 0.005  # 5 µm reading noise: FK is linear to ~σ²/L ≈ 2.5e-8 mm here
    R, t = kin.pose_to_rt(pose)
    readings = kin.inverse_kinematics(tracker, R, t)
    n = 4000
    noisy = readings + np.random.default_rng(5).normal(0.0, sigma_mm, (n, 6))
    solution = kin.forward_kinematics(tracker, noisy, guess=(R, t), tol_mm=1e-11)
    # Body-tangent coordinates of each FK pose about the true pose (the chart of kin.retract).
    omega = Rotation.from_matrix(R.T @ solution.R).as_rotvec()
    v = (solution.t - t) @ R
    xi = np.hstack([omega, v])
    sample = xi.T @ xi / n  # about the known mean: N·sample ~ Wishart(Σ, N)

    sigma = kin.pose_covariance_from_legs(tracker, R, t, sigma_mm)
    L_inv = np.linalg.inv(np.linalg.cholesky(sigma))
    whitened = L_inv @ sample @ L_inv.T  # ~ Wishart(I, N)/N if Σ is right
    # Under Wishart(I, N)/N the diagonal has sd √(2/N) = 0.022 and the off-diagonal √(1/N) = 0.016;
    # 5 sd over the 21 entries gives a false-alarm probability < 1e-5 (measured: ≤ 2.5 sd);
    # Σ scaled by 1.2 (0.8) puts the diagonal 8 (13) sd off, so a wrong Σ cannot pass.
    deviation = np.abs(whitened - np.eye(6))
    assert np.max(np.diag(deviation)) <= 5 * np.sqrt(2 / n)
    assert np.max(deviation[~np.eye(6, dtype=bool)]) <= 5 * np.sqrt(1 / n)


def test_fk_has_no_nans_at_box_corners():
    """Smoke-level but numeric: all 64 box corners of both mechanisms solve to 1e-9 mm."""
    fractions = np.array(list(itertools.product([-1.0, 1.0], repeat=6)))
    R, t = workspace_pose(fractions)
    for legs in MECHANISMS.values():
        solution = kin.forward_kinematics(legs, kin.inverse_kinematics(legs, R, t), tol_mm=FK_TOL_MM)
        assert np.all(np.isfinite(solution.R)) and np.all(solution.residual_mm <= FK_TOL_MM)
        assert_same_pose(R, t, solution.R, solution.t)
