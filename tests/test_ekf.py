"""The shared Kalman update and both EKFs (paper eq. 14–19; leg-length EKF)."""

import math

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter
from scipy.stats import chi2

from stewart_calib.config import config_from_dict
from stewart_calib.errors import SampleRejected
from stewart_calib.estimators import make_estimator
from stewart_calib.estimators.base import feed
from stewart_calib.estimators.kalman import kalman_update
from stewart_calib.model import kinematics as kin
from stewart_calib.samples import Sample
from tests.synthetic import make_log, nim_stewart, random_error, random_poses, static_logs

PLATFORM = nim_stewart()


@pytest.fixture(scope="module")
def static_data():
    return static_logs(PLATFORM, 300, seed=11)


def run(method, log, **sections):
    """Feed ``log``; gated samples (the gate is on by default) are skipped, as every caller does."""
    est = make_estimator(method, PLATFORM, config_from_dict(sections))
    feed(est, log)
    return est


# ----------------------------------------------------------------------------- kalman_update


def test_scalar_case_by_hand():
    x, P = np.array([1.0]), np.array([[2.0]])
    nis, S = kalman_update(x, P, np.array([[1.0]]), np.array([3.0]), np.array([[1.0]]), np.array([[0.5]]), math.inf)
    # P⁻ = 2.5, S = 3.5, K = 2.5/3.5, x = 1 + 3K, P = 2.5 − 2.5²/3.5, NIS = 9/3.5
    assert S[0, 0] == pytest.approx(3.5, rel=1e-15)
    assert x[0] == pytest.approx(1.0 + 3.0 * 2.5 / 3.5, rel=1e-15)
    assert P[0, 0] == pytest.approx(2.5 - 2.5**2 / 3.5, rel=1e-15)
    assert nis == pytest.approx(9.0 / 3.5, rel=1e-15)


def test_two_state_case_by_hand():
    # Observing the first of two uncorrelated states: only it moves, the second is unchanged.
    x, P = np.zeros(2), np.diag([4.0, 9.0])
    kalman_update(x, P, np.array([[1.0, 0.0]]), np.array([2.0]), np.array([[1.0]]), np.zeros((2, 2)), math.inf)
    np.testing.assert_allclose(x, [2.0 * 4.0 / 5.0, 0.0], rtol=1e-15)
    np.testing.assert_allclose(P, np.diag([4.0 - 16.0 / 5.0, 9.0]), rtol=1e-15, atol=0)


def test_matches_filterpy():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(42, 42))
    P0 = A @ A.T / 42 + np.eye(42)
    H, z = rng.normal(size=(6, 42)), rng.normal(size=6)
    B = rng.normal(size=(6, 6))
    R, Q = B @ B.T + np.eye(6), np.eye(42) * 1e-3
    x, P = rng.normal(size=42), P0.copy()
    kf = KalmanFilter(42, 6)
    kf.x, kf.P, kf.F, kf.Q = x.reshape(42, 1).copy(), P0.copy(), np.eye(42), Q
    kf.predict()
    kf.update(z.reshape(6, 1), R, H)  # filterpy pitfall: a 1-D z with H turns x into 42×6
    kalman_update(x, P, H, z - H @ x, R, Q, math.inf)
    np.testing.assert_allclose(x, kf.x[:, 0], rtol=0, atol=1e-12 * np.abs(x).max())
    np.testing.assert_allclose(P, kf.P, rtol=0, atol=1e-12 * np.abs(P).max())


def test_gate_leaves_state_untouched():
    x, P = np.zeros(2), np.eye(2)
    nis, _ = kalman_update(x, P, np.eye(2), np.array([10.0, 0.0]), np.eye(2), np.eye(2), 9.0)
    assert nis == pytest.approx(100.0 / 3.0)  # S = P + Q + R = 3 I
    assert np.all(x == 0.0) and np.all(P == np.eye(2))


def test_covariance_stays_symmetric_positive_definite():
    rng = np.random.default_rng(1)
    x, P = np.zeros(42), np.eye(42) * 25.0
    Q, R = np.eye(42) * 1e-10, np.eye(6) * 1e-6
    for _ in range(10_000):  # tiny Q and R: the regime where P − K S Kᵀ loses definiteness first
        H = rng.normal(size=(6, 42))
        kalman_update(x, P, H, rng.normal(size=6) * 1e-3, R, Q, math.inf)
    assert np.abs(P - P.T).max() <= 1e-12 * np.abs(P).max()
    assert np.linalg.eigvalsh(P).min() > 0.0


# ----------------------------------------------------------------------------- leg EKF


def test_ekf_noise_free(static_data):
    delta, clean, _ = static_data
    # Without process noise the linearisation error of the first updates (δM ~ 1 mm on
    # ~1000 mm legs: ~5e-4 mm) is locked into P and decays only like 1/N: measured
    # 7.4e-4 mm max at N = 300 (5e-4 at 1000, 1.7e-4 at 3000). 1e-6 mm is out of reach online.
    est = run("ekf", clean, noise={"random_walk_mm_per_sqrt_s": 0.0})
    assert np.abs(est.estimate().error - delta).max() < 2e-3
    # A random walk forgets those early linearisation points: the error then falls
    # geometrically (measured 6.5e-7 mm at 2000, 1.2e-8 at 3000 samples with 0.01 mm/√s).
    rng = np.random.default_rng(2)
    long, _ = make_log(PLATFORM, delta, random_poses(PLATFORM, 2500, rng), rng)
    est = run("ekf", long, noise={"random_walk_mm_per_sqrt_s": 0.01})
    assert np.abs(est.estimate().error - delta).max() <= 1e-6


def test_ekf_noisy_is_consistent(static_data):
    delta, _, noisy = static_data
    estimate = run("ekf", noisy, noise={"random_walk_mm_per_sqrt_s": 0.0}).estimate()
    e = estimate.error - delta
    nees = e @ np.linalg.solve(estimate.covariance, e)
    # χ²(42) two-sided 99.9 %: a covariance neither optimistic nor grossly pessimistic.
    assert chi2.ppf(0.0005, 42) < nees < chi2.ppf(0.9995, 42)
    # Each component within 4σ of its own reported stddev (42 × P(|z| > 4) ≈ 0.3 %).
    sigma = estimate.stddev
    assert np.all(np.abs(e) < 4.0 * sigma)  # measured max |e|/σ = 2.2
    # The RMS against the covariance's own prediction: for e ~ N(0, P), ‖e‖² has mean tr P and
    # variance 2 tr(P²) (a weighted sum of χ²(1)); mean + 4 sd bounds it. Measured 8.4 µm RMS
    # against a bound of 15 µm (tr P alone predicts 8.3 µm).
    P = estimate.covariance
    assert e @ e < np.trace(P) + 4.0 * np.sqrt(2.0 * np.sum(P * P))


def test_rejects_unusable_samples_and_leaves_state(static_data):
    _, _, noisy = static_data
    for method in ("ekf", "paper-ekf"):
        est = run(method, noisy.select(slice(0, 20)))
        before = est.estimate()
        bad_readings = noisy[20].readings.copy()
        bad_readings[2] = np.nan
        unreachable = np.array([318.0, -276.0, 318.0, -276.0, 318.0, -276.0])  # in range, no pose fits
        for readings in (bad_readings, unreachable):
            with pytest.raises(SampleRejected):
                est.update(Sample(noisy[20].t_s, noisy[20].strokes, readings))
        after = est.estimate()
        assert np.array_equal(after.error, before.error) and np.array_equal(after.covariance, before.covariance)
        assert after.samples_used == 20


def test_gating_rejects_an_outlier(static_data):
    _, _, noisy = static_data
    est = run("ekf", noisy.select(slice(0, 50)), ekf={"gate_probability": 0.999})
    before = est.estimate()
    strokes = noisy[50].strokes + np.r_[0.05, 0, 0, 0, 0, 0]  # a 50 µm encoder glitch, ~50σ
    with pytest.raises(SampleRejected, match="gated"):
        est.update(Sample(noisy[50].t_s, strokes, noisy[50].readings))
    assert np.array_equal(est.estimate().error, before.error)
    est.update(noisy[50])  # the clean sample passes the same gate
    assert est.estimate().samples_used == 51


def test_drift_ekf_tracks_ls_cannot():
    """Three leg lengths grow by 0.2 mm half-way; compare pose errors after compensation."""
    rng = np.random.default_rng(5)
    n = 500
    delta = random_error(rng)
    jump = np.zeros(42)
    jump[[6, 13, 20]] = 0.2  # l1, l2, l3
    errors = np.tile(delta, (n, 1))
    errors[n // 2 :] += jump
    log, _ = make_log(PLATFORM, errors, random_poses(PLATFORM, n, rng), rng, 0.002, 0.001)
    R, t = kin.pose_to_rt(random_poses(PLATFORM, 100, rng))
    true_drive = PLATFORM.drive.perturbed(delta + jump)

    def position_offsets_mm(model_delta):
        """Position offsets (N, 3) of the robot after the jump, commanded with IK(model)."""
        strokes = kin.inverse_kinematics(PLATFORM.drive.perturbed(model_delta), R, t)
        return kin.forward_kinematics(true_drive, strokes, guess=(R, t)).t - t

    def position_error_mm(model_delta):
        return np.linalg.norm(position_offsets_mm(model_delta), axis=-1).mean()

    ekf = run("ekf", log.select(slice(0, n // 2 + 50)), noise={"random_walk_mm_per_sqrt_s": 0.03}).estimate()
    ls_error = make_estimator("ls", PLATFORM).fit(log).error

    # The EKF's covariance P bounds the compensated offsets: a model error e moves pose k by
    # J_k e (J_k = position rows of J_p), and for any linear map (J e)ᵀ(J P Jᵀ)⁻¹(J e) ≤ eᵀP⁻¹e,
    # which is χ²(42) for a consistent filter. So every pose's Mahalanobis offset lies below
    # χ²₄₂(0.999) — measured 0.7 for the EKF 50 samples after the jump, while the pre-jump model
    # gives ~1700 and a model half-way through the jump ~420.
    J = kin.error_jacobian(true_drive, R, t)[:, :3, :]
    S_inv = np.linalg.inv(np.einsum("kij,jl,kml->kim", J, ekf.covariance, J))
    bound = chi2.ppf(0.999, 42)

    def worst_mahalanobis(model_delta):
        d = position_offsets_mm(model_delta)
        return np.einsum("ki,kij,kj->k", d, S_inv, d).max()

    assert worst_mahalanobis(ekf.error) < bound
    assert worst_mahalanobis(ls_error) > bound  # ls cannot follow the jump
    # LS fits the whole log with one model: it lands about half-way through the jump (both
    # measured 96 µm); 20 % allows for the unequal information of the two halves' poses.
    half = position_error_mm(delta + jump / 2)
    assert abs(position_error_mm(ls_error) - half) < 0.2 * half


# ----------------------------------------------------------------------------- paper EKF


def test_paper_ekf_with_papers_q_and_r(static_data):
    delta, clean, _ = static_data
    est = run("paper-ekf", clean)
    R, t = kin.pose_to_rt(random_poses(PLATFORM, 100, np.random.default_rng(9)))
    true_drive = PLATFORM.drive.perturbed(delta)

    def position_error_mm(model_delta):
        strokes = kin.inverse_kinematics(PLATFORM.drive.perturbed(model_delta), R, t)
        sol = kin.forward_kinematics(true_drive, strokes, guess=(R, t))
        return kin.pose_error(R, t, sol.R, sol.t)[0].mean()

    # Q = 1e-5 I, R = 4e-2 I (§4.1) on 300 noise-free samples: parameter RMS 1 mm → 0.165 mm;
    # mean position error after compensation 2.1 mm (nominal) → measured below 0.1 mm.
    estimate = est.estimate()
    error = estimate.error
    # The filter's P is no bound on this error (R = 4e-2 against noise-free data: measured
    # max |e|/σ = 0.2, and 4σ ≈ 5.6 mm would pass the uncalibrated model). Derive it instead from
    # the information form: a linear KF on noise-free data has P_N⁻¹ e_N = P_0⁻¹ e_0, so
    # e_N = P_N P_0⁻¹ e_0 with e_0 = −δ (Q = 1e-5 per update is negligible against P_0 = 25 mm²:
    # measured the same error with Q = 0; the EKF's relinearisation moves e_N by 2-6 %).
    # δ ~ N(0, σ_δ² I) with σ_δ = 1 mm (static_logs), so e_N ~ N(0, σ_δ² M), M = (P_N P_0⁻¹)²:
    # ‖e_N‖² has mean σ_δ² tr M and variance 2 σ_δ⁴ tr M²; mean + 4 sd bounds it.
    # Measured RMS 0.165 mm (expected 0.21) against a bound of 0.39 mm (nominal: 1 mm).
    sigma_delta, p0 = 1.0, config_from_dict({}).noise.prior_sigma_mm ** 2
    G = estimate.covariance / p0
    M = G @ G
    e = error - delta
    assert e @ e < sigma_delta**2 * np.trace(M) + 4.0 * sigma_delta**2 * np.sqrt(2.0 * np.sum(M * M))
    assert position_error_mm(error) < 0.1 * position_error_mm(np.zeros(42))


def _effective_sample_size(x):
    """``n / (1 + 2 Σ ρ_k)`` over the initial positive autocorrelations (Geyer's truncation)."""
    xc = x - x.mean()
    total = 0.0
    for k in range(1, len(x) // 2):
        rho = float(xc[:-k] @ xc[k:] / (xc @ xc))
        if rho <= 0.0:
            break
        total += rho
    return len(x) / (1.0 + 2.0 * total)


def test_adaptive_paper_ekf_fixes_wrong_r(static_data):
    _, _, noisy = static_data
    nis_mean, bound = {}, {}
    for adaptive in (False, True):
        # R = 1e-3 I is ~100× the tracker's position variance (~1e-5 mm², measured by the
        # adaptive filter itself); with it the filter is over-cautious and NIS ≪ 6.
        config = config_from_dict({"paper_ekf": {"adaptive": adaptive, "measurement_noise": 1e-3}})
        est = make_estimator("paper-ekf", PLATFORM, config)
        nis = []
        for sample in noisy:
            est.update(sample)
            nis.append(est.filter.nis)
        x = np.array(nis[150:])  # the adapted R settles once the 50-sample window has filled
        nis_mean[adaptive] = x.mean()
        # 4 sd of the mean: the NIS's own variance (measured 22, not χ²(6)'s 12: R is estimated)
        # over the effective sample size (measured lag-1 autocorrelation 0.04: n_eff 140 of 150).
        bound[adaptive] = 4.0 * np.sqrt(x.var(ddof=1) / _effective_sample_size(x))
    # What a consistent adaptive filter gives is not 6: R is the sample covariance of the last
    # m = 50 innovations (ν_k independent of it), so NIS = νᵀ R̂⁻¹ ν is Hotelling's T² and
    # E[NIS] = p m / (m − p − 1) = 6·50/43 = 6.98 (the inverse of an estimated covariance is
    # biased large). The adapted filter is thus ~16 % overconfident by construction of the window
    # (measured 6.96 here; 7.00 ± 0.41 over 30 seeds; 7.4 on a 3000-sample log).
    m, p = config.paper_ekf.adaptive_window, 6
    expected = p * m / (m - p - 1)
    assert abs(nis_mean[True] - expected) < bound[True]  # measured 6.96 ± 1.6 (4 sd)
    # and the fixed, too large R is far outside that band (measured 0.02): the check has teeth.
    assert nis_mean[False] < expected - bound[True]
    assert abs(nis_mean[True] - 6.0) < abs(nis_mean[False] - 6.0)


def test_paper_ekf_angle_unit_deg_is_r_rescaled_for_radians(static_data):
    # Y and J_p in degrees with R = r is the same filter as radians with the orientation
    # entries of R divided by (180/π)²: the gain and the state must agree to round-off.
    log = list(static_data[2])[:40]
    in_deg = run("paper-ekf", log, paper_ekf={"angle_unit": "deg"})
    in_rad = make_estimator("paper-ekf", PLATFORM, config_from_dict({}))
    in_rad.R = np.diag(np.r_[np.full(3, 0.04), np.full(3, 0.04 / math.degrees(1.0) ** 2)])
    for sample in log:
        in_rad.update(sample)
    np.testing.assert_allclose(in_deg.estimate().error, in_rad.estimate().error, rtol=0, atol=1e-9)
    np.testing.assert_allclose(in_deg.estimate().covariance, in_rad.estimate().covariance, rtol=1e-9, atol=1e-12)
    # and the unit matters: radians with the plain R = 0.04 I is a different filter
    assert np.max(np.abs(in_deg.estimate().error - run("paper-ekf", log).estimate().error)) > 1e-2
