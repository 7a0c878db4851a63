"""Factors: residuals against the kinematics' leg-length model and GTSAM's own factors;
analytic Jacobians against central differences through ``Pose3.retract`` (relative ≤ 1e-6)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from stewart_calib.factors import drive_leg, gauge, instrument, instrument_pose, pose_misfit, random_walk
from stewart_calib.instruments.tracker import TrackerModel
from stewart_calib.model import kinematics as kin
from stewart_calib.model.drive import DriveModel, drive_model, stroke_term
from stewart_calib.model.unknowns import UnknownLayout
from tests.numdiff import numerical_jacobian, numerical_pose3_jacobian, relative_error
from tests.synthetic import nim_stewart, random_error, random_poses

X, P = gtsam.symbol("x", 0), gtsam.symbol("p", 0)
UNIT = gtsam.noiseModel.Unit.Create(1)  # whitened == unwhitened, so linearize() shows the raw H


@pytest.fixture(scope="module")
def platform():
    return nim_stewart()


@pytest.fixture(scope="module")
def cases(platform):
    """Five workspace poses (as Pose3) and a 1 mm parameter error."""
    rng = np.random.default_rng(11)
    poses = [
        gtsam.Pose3(gtsam.Rot3(R), t) for R, t in zip(*kin.pose_to_rt(random_poses(platform, 5, rng)), strict=True)
    ]
    return poses, random_error(rng, 1.0)


def _values(pose: gtsam.Pose3, delta: np.ndarray | None = None) -> gtsam.Values:
    values = gtsam.Values()
    values.insert(X, pose)
    if delta is not None:
        values.insert(P, delta)
    return values


def test_drive_leg_factor_residual_is_the_leg_length_model(platform, cases):
    poses, delta = cases
    truth = platform.drive.perturbed(delta)
    spec = drive_leg.DriveLegs.of(np.arange(6), drive_model(platform))
    for pose in poses:
        R, t = pose.rotation().matrix(), pose.translation()
        strokes = kin.inverse_kinematics(truth, R, t) + 0.3  # 0.3 mm off: a nonzero residual
        expected = kin.leg_residuals(truth, R, t, strokes)
        got = drive_leg.factor(X, P, spec, strokes, gtsam.noiseModel.Unit.Create(6)).unwhitenedError(
            _values(pose, delta)
        )
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9)
        np.testing.assert_allclose(expected, -0.3, atol=1e-9)


@pytest.mark.parametrize("legs", [np.arange(6), [2], [4, 1]])
def test_drive_leg_factor_jacobians_match_central_differences(platform, cases, legs):
    poses, delta = cases
    spec = drive_leg.DriveLegs.of(legs, drive_model(platform))
    strokes = 10.0 * np.arange(6) - 20.0
    noise = gtsam.noiseModel.Unit.Create(len(spec.legs))
    for pose in poses:
        f = drive_leg.factor(X, P, spec, strokes, noise)
        A, b = f.linearize(_values(pose, delta)).jacobian()
        np.testing.assert_allclose(-b, f.unwhitenedError(_values(pose, delta)), rtol=1e-12)
        H_pose = numerical_pose3_jacobian(lambda p, f=f: f.unwhitenedError(_values(p, delta)), pose)
        H_params = numerical_jacobian(lambda d, f=f, pose=pose: f.unwhitenedError(_values(pose, d)), delta)
        assert relative_error(A[:, :6], H_pose) <= 1e-6
        assert relative_error(A[:, 6:], H_params) <= 1e-6
        for row, i in enumerate(spec.legs):  # leg i's row touches only its own seven columns of δM
            assert np.count_nonzero(A[row, 6:]) == 7 and np.all(A[row, 6 + 7 * i : 13 + 7 * i] != 0)


def test_drive_leg_factor_with_stroke_scale_matches_central_differences(platform, cases):
    # the unknown vector [δM | k1..k6]: leg i's row has −q_i in column 42 + i, and (1 + k) scales the stroke
    poses, delta = cases
    drive = DriveModel(platform.drive, (stroke_term(np.full(6, 0.01), 0.05),))
    spec = drive_leg.DriveLegs.of(np.arange(6), drive)
    strokes = 10.0 * np.arange(6) - 20.0
    unknowns = np.r_[delta, np.linspace(-0.02, 0.02, 6)]
    f = drive_leg.factor(X, P, spec, strokes, gtsam.noiseModel.Unit.Create(6))
    A, _ = f.linearize(_values(poses[0], unknowns)).jacobian()
    numeric = numerical_jacobian(lambda u: f.unwhitenedError(_values(poses[0], u)), unknowns)
    assert relative_error(A[:, 6:], numeric) <= 1e-6
    np.testing.assert_allclose(A[:, 6 + 42 :], -np.diag(strokes))
    R, t = poses[0].rotation().matrix(), poses[0].translation()
    expected = kin.leg_residuals(platform.drive.perturbed(delta), R, t, (1.0 + 0.01 + unknowns[42:]) * strokes)
    np.testing.assert_allclose(f.unwhitenedError(_values(poses[0], unknowns)), expected, atol=1e-9)


def test_instrument_factor_of_the_tracker_residual_and_jacobian(platform, cases):
    poses, _ = cases
    model = TrackerModel(platform.tracker, 0.002)
    for pose in poses:
        R, t = pose.rotation().matrix(), pose.translation()
        readings = kin.inverse_kinematics(platform.tracker, R, t) - 0.05
        for channels in [*model.groups(readings), np.arange(6)]:  # per ruler, and all six in one factor
            f = instrument.factor(model, X, readings, channels, gtsam.noiseModel.Unit.Create(len(channels)))
            np.testing.assert_allclose(f.unwhitenedError(_values(pose)), np.full(len(channels), 0.05), atol=1e-9)
            A, _ = f.linearize(_values(pose)).jacobian()
            numeric = numerical_pose3_jacobian(lambda p, f=f: f.unwhitenedError(_values(p)), pose)
            assert relative_error(A, numeric) <= 1e-6


def test_instrument_factor_on_the_unknown_vector_has_the_model_jacobian(platform, cases):
    # The tracker's geometry as unknowns, placed after δM: ∂r/∂p is the model's ∂r/∂θ in those columns.
    poses, delta = cases
    model = TrackerModel(platform.tracker, 0.002, geometry_sigma_mm=0.05)
    layout = UnknownLayout((model.unknowns,), n_params=platform.drive.n_params)
    block = layout.slice("instrument")
    unknowns = np.r_[delta, np.random.default_rng(1).normal(0.0, 0.05, 42)]
    pose = poses[0]
    readings = kin.inverse_kinematics(platform.tracker, pose.rotation().matrix(), pose.translation())
    f = instrument.factor(model, X, readings, np.array([2]), UNIT, P, block, layout.size)
    values = _values(pose, unknowns)
    H_params = f.linearize(values).jacobian()[0][:, 6:]
    numeric = numerical_jacobian(lambda u: f.unwhitenedError(_values(pose, u)), unknowns)
    assert relative_error(H_params, numeric) <= 1e-6
    assert np.all(H_params[:, :42] == 0.0)
    # the compiled rows (compiled_unknown_legs) are the model's residual, bit for bit
    theta = model.unknowns.nominal + unknowns[block]
    R, t = pose.rotation().matrix(), pose.translation()
    for channels in (np.array([2]), np.arange(6)):
        unit = gtsam.noiseModel.Unit.Create(len(channels))
        f = instrument.factor(model, X, readings + 0.01, channels, unit, P, block, layout.size)
        reference = model.residual(R, t, theta, readings + 0.01, channels)
        np.testing.assert_array_equal(f.unwhitenedError(values), reference.r)
        A = f.linearize(values).jacobian()[0]
        np.testing.assert_array_equal(A[:, :6], reference.J_pose)
        np.testing.assert_array_equal(A[:, 6:][:, block], reference.J_instrument)
        assert np.all(A[:, 6 : 6 + block.start] == 0.0)


def test_gauge_factor_is_the_linear_constraint(platform):
    C = UnknownLayout(
        (TrackerModel(platform.tracker, 0.002, geometry_sigma_mm=0.05).unknowns,), n_params=platform.drive.n_params
    ).gauge_rows(platform.drive)
    x = np.random.default_rng(2).normal(size=C.shape[1])
    values = gtsam.Values()
    values.insert(P, x)
    f = gauge.factor(P, C)
    np.testing.assert_allclose(f.unwhitenedError(values), C @ x)
    A, _ = f.linearize(values).jacobian()
    np.testing.assert_allclose(A * gauge.SIGMA, C)


def test_instrument_pose_prior_equals_gtsam_prior_factor(platform, cases):
    poses, _ = cases
    for k, pose in enumerate(poses):
        measured, R, t = pose, pose.rotation().matrix(), pose.translation()
        noise = gtsam.noiseModel.Gaussian.Covariance(kin.pose_covariance_from_legs(platform.tracker, R, t, 0.002))
        ours, reference = instrument_pose.factor(X, measured, noise), gtsam.PriorFactorPose3(X, measured, noise)
        # Far enough from the measurement that Logmap's derivative is not the identity.
        values = _values(measured.retract(np.array([0.05, -0.1, 0.02 * k, 3.0, -4.0, 5.0])))
        assert ours.error(values) == pytest.approx(reference.error(values), rel=1e-12)
        assert relative_error(ours.whitenedError(values), reference.whitenedError(values)) <= 1e-12
        (A, b), (A_ref, b_ref) = ours.linearize(values).jacobian(), reference.linearize(values).jacobian()
        assert relative_error(A, A_ref) <= 1e-12
        assert relative_error(b, b_ref) <= 1e-12
        _, H = instrument_pose.residual(measured, values.atPose3(X), jacobians=True)
        numeric = numerical_pose3_jacobian(
            lambda p, measured=measured: instrument_pose.residual(measured, p)[0], values.atPose3(X)
        )
        assert relative_error(H, numeric) <= 1e-6


def test_random_walk_sigma_and_between_factor():
    assert random_walk.sigma_mm(1e-3, 4.0, 1e-5) == pytest.approx(2e-3)
    assert random_walk.sigma_mm(0.0, 4.0, 1e-5) == 1e-5  # the near-hard floor at walk 0
    f = random_walk.factor(1, 2, np.full(42, 0.5))
    values = gtsam.Values()
    values.insert(1, np.ones(42))
    values.insert(2, np.arange(42.0))
    np.testing.assert_allclose(f.whitenedError(values), (np.arange(42.0) - 1.0) / 0.5)
    prior = random_walk.prior(1, np.full(42, 5.0))
    assert prior.error(values) == pytest.approx(0.5 * 42 / 25.0)


def test_pose_instrument_factor_is_the_models_residual_in_one_compiled_call():
    # factors/_kernels.pose_reading_rows against PoseModel.residual through the factor: a reading near the
    # prediction, one on it (e ≈ 0) and one turned by π about an axis (Log's branch near π).
    from stewart_calib.instruments import pose as pose_model
    from stewart_calib.model.rotations import rotation_to_rpy, so3_exp
    from tests.test_instrument_models import _models

    model = _models()[0]
    rng = np.random.default_rng(5)
    size, block = model.unknowns.size + 3, slice(3, 3 + model.unknowns.size)  # the model's columns after others'
    for case in range(6):
        unknowns = rng.normal(0.0, 0.02, size)
        theta = model.unknowns.nominal + unknowns[block]
        R, t = kin.pose_to_rt(np.r_[rng.normal(0, 20, 3) + [0, 0, 200], rng.normal(0, 0.1, 3)])
        R_P, t_P = pose_model.predict(pose_model.PoseUnknowns.from_pose6(theta[:6], theta[6:]), R, t)
        axis = rng.normal(size=3)
        turn = [np.zeros(3), np.pi * axis / np.linalg.norm(axis), rng.normal(0, 0.01, 3)][case % 3]
        z = np.r_[t_P + rng.normal(0, 0.1, 3), rotation_to_rpy(R_P @ so3_exp(turn))]
        reference = model.residual(R, t, theta, z, np.arange(6))
        f = instrument.factor(model, X, z, np.arange(6), gtsam.noiseModel.Unit.Create(6), P, block, size)
        values = _values(gtsam.Pose3(gtsam.Rot3(R), t), unknowns)
        A_pose, A_params = (f.linearize(values).jacobian()[0][:, cols] for cols in (slice(0, 6), slice(6, None)))
        np.testing.assert_allclose(f.unwhitenedError(values), reference.r, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(A_pose, reference.J_pose, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(A_params[:, block], reference.J_instrument, rtol=1e-12, atol=1e-12)
        assert np.all(A_params[:, :3] == 0.0)


def test_pose_misfit_adds_its_rows_to_the_drive_leg_and_tracker_factors(platform, cases):
    # a static pose's misfit b (the tracker's six channels, then the six legs) added to each factor's rows:
    # the residual is the factor's own plus b[rows], its Jacobians the factor's and the rows' selector on b
    poses, delta = cases
    B = pose_misfit.misfit_key(0)
    b = np.random.default_rng(5).normal(0.0, 0.01, 12)
    model = TrackerModel(platform.tracker, 0.002)
    spec = drive_leg.DriveLegs.of([4, 1], drive_model(platform))
    strokes = 10.0 * np.arange(6) - 20.0
    pose = poses[1]
    R, t = pose.rotation().matrix(), pose.translation()
    readings = kin.inverse_kinematics(platform.tracker, R, t) - 0.05
    made = [
        (drive_leg.factor(X, P, spec, strokes, gtsam.noiseModel.Unit.Create(2)), [X, P], 6 + spec.legs),
        (instrument.factor(model, X, readings, np.array([3, 0]), gtsam.noiseModel.Unit.Create(2)), [X], [3, 0]),
    ]

    def values(p, d, misfit):
        v = _values(p, d)
        v.insert(B, misfit)
        return v

    for plain, keys, rows in made:
        noise = plain.noiseModel()
        if len(keys) == 2:
            f = drive_leg.factor(X, P, spec, strokes, noise, misfit=(B, rows))
        else:
            f = instrument.factor(model, X, readings, np.array([3, 0]), noise, misfit=(B, np.asarray(rows)))
        assert list(f.keys()) == [*keys, B]
        expected = plain.unwhitenedError(_values(pose, delta)) + b[rows]
        np.testing.assert_allclose(f.unwhitenedError(values(pose, delta, b)), expected, rtol=0, atol=1e-12)
        A, _ = f.linearize(values(pose, delta, b)).jacobian()
        H_pose = numerical_pose3_jacobian(lambda p, f=f: f.unwhitenedError(values(p, delta, b)), pose)
        H_b = numerical_jacobian(lambda m, f=f: f.unwhitenedError(values(pose, delta, m)), b)
        assert relative_error(A[:, :6], H_pose) <= 1e-6
        assert relative_error(A[:, -12:], H_b) <= 1e-9
        if len(keys) == 2:
            H_params = numerical_jacobian(lambda d, f=f: f.unwhitenedError(values(pose, d, b)), delta)
            assert relative_error(A[:, 6:-12], H_params) <= 1e-6


def test_pose_misfit_conditional_with_the_marginal_prior_is_the_joint_gaussian():
    # b | p of a joint N(mean, Σ) of [p; b], with N(mean_p, Σ_pp) on p: the graph's information is Σ⁻¹
    # and its optimum the mean (how isam2's rebuild keeps a pose's misfit held across a snapshot)
    rng = np.random.default_rng(3)
    n, m = 4, 3
    A = rng.normal(size=(n + m, n + m))
    covariance, mean = A @ A.T + 0.1 * np.eye(n + m), rng.normal(size=n + m)
    B = pose_misfit.misfit_key(2)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorVector(P, mean[:n], gtsam.noiseModel.Gaussian.Covariance(covariance[:n, :n])))
    conditional = pose_misfit.conditional(P, B, mean, covariance, n)
    graph.add(conditional)
    values = gtsam.Values()
    values.insert(P, rng.normal(size=n))
    values.insert(B, rng.normal(size=m))
    ordering = gtsam.Ordering()
    ordering.push_back(P)
    ordering.push_back(B)
    information = graph.linearize(values).hessian(ordering)[0]
    np.testing.assert_allclose(information, np.linalg.inv(covariance), rtol=1e-9, atol=1e-9)
    H, _ = conditional.linearize(values).jacobian()
    whitened = lambda x: conditional.whitenedError(_vector_values(x[:n], x[n:], B))  # noqa: E731
    x = np.concatenate((values.atVector(P), values.atVector(B)))
    assert relative_error(H, numerical_jacobian(whitened, x)) <= 1e-9
    optimum = gtsam.GaussNewtonOptimizer(graph, values).optimize()
    np.testing.assert_allclose(np.r_[optimum.atVector(P), optimum.atVector(B)], mean, atol=1e-9)


def _vector_values(p: np.ndarray, b: np.ndarray, key: int) -> gtsam.Values:
    values = gtsam.Values()
    values.insert(P, p)
    values.insert(key, b)
    return values
