"""The paper's batch least squares (eq. 9–11, Gauss–Newton)."""

import dataclasses

import numpy as np
import pytest

from stewart_calib.analysis.identifiability import identifiability_report
from stewart_calib.config import NoiseConfig, config_from_dict
from stewart_calib.estimators import make_estimator
from stewart_calib.workflows.planning import design_covariance, plan_poses
from tests.synthetic import make_log, nim_stewart, random_error, random_poses, static_logs

PLATFORM = nim_stewart()


@pytest.fixture(scope="module")
def data():
    return static_logs(PLATFORM, 200, seed=21)


def test_noise_free_recovers_truth(data):
    delta, clean, _ = data
    # The identifiability report's paper-form J_p at the true geometry and the same poses is the
    # matrix the paper's LS ends on, once it scales the rotation rows by the report's length (the mean
    # joint radius of the true drive, 300.05 mm; the default rotation_weight_mm is 300).
    truth = dataclasses.replace(PLATFORM, drive=PLATFORM.drive.perturbed(delta))
    report = identifiability_report(truth, clean.desired_poses, NoiseConfig())
    config = config_from_dict({"ls": {"weighting": "paper", "rotation_weight_mm": report.rotation_row_scale_mm}})
    ls = make_estimator("ls", PLATFORM, config)
    estimate = ls.fit(clean)
    # Exact data: only FK's 1e-9 mm tolerance and the GN stopping rule limit it (measured 5e-10).
    assert np.abs(estimate.error - delta).max() <= 1e-6
    # LS's last J_p is taken at a geometry within tolerance_mm (1e-7 mm) of the truth and at
    # poses within FK's 1e-9 mm. J_p's entries change with the geometry as Δ/ℓ, ℓ the platform's
    # lengths (legs ~1000 mm, joint radii ~300 mm); with ℓ ≥ 1 mm as a generous floor they move
    # by < 1e-7 relative, so (Weyl) each singular value by < 1e-7 σmax. Measured 6.5e-13
    # relative; condition number 370.5 (the nominal geometry's report says 371.0, but δM moves
    # J_p by ‖ΔA‖ = 0.21 > σmin = 0.08, so no bound ties that one to the fit).
    s = ls.singular_values
    assert s.shape == (42,)
    length_floor_mm = 1.0
    atol = config.ls.tolerance_mm / length_floor_mm * s[0]
    np.testing.assert_allclose(s, report.paper_singular_values, rtol=0, atol=atol)
    assert report.verdict == "identifiable"


def test_noisy_agrees_with_ekf_and_its_covariance(data):
    delta, _, noisy = data
    ls = make_estimator("ls", PLATFORM).fit(noisy)
    ekf = make_estimator("ekf", PLATFORM, config_from_dict({"noise": {"random_walk_mm_per_sqrt_s": 0.0}}))
    for sample in noisy:
        ekf.update(sample)
    ekf = ekf.estimate()
    sigma_ls, sigma_ekf = ls.stddev, ekf.stddev
    # Each within 4σ of the truth by its own covariance (the LS σ is its whitened fit's on the
    # readings' and strokes' noise).
    assert np.all(np.abs(ls.error - delta) < 4 * sigma_ls)
    assert np.all(np.abs(ekf.error - delta) < 4 * sigma_ekf)
    # The two use the same data and noise model in different forms (LS: pose rows whitened by their
    # covariance; EKF: the leg-length model, filtered), so they agree to within their combined uncertainty.
    assert np.all(np.abs(ls.error - ekf.error) < 4 * np.hypot(sigma_ls, sigma_ekf))


def test_too_few_samples_is_rank_deficient(data):
    _, clean, _ = data
    ls = make_estimator("ls", PLATFORM)
    for sample in clean.select(slice(0, 5)):  # 30 equations for 42 unknowns
        ls.update(sample)
    estimate = ls.estimate()
    assert estimate.covariance is None
    assert len(ls.singular_values) == 30 and estimate.samples_used == 5


@pytest.mark.parametrize("weighting", ["noise", "paper"])
def test_covariance_is_that_of_the_estimates_over_noise_draws(weighting):
    """Over 40 noise draws at one robot and 200 poses, the errors' normalised squares ``dᵀ P⁻¹ d`` (P
    the reported covariance) sum to what an honest P gives, with the rows whitened by their noise and
    with the paper's pose-form weighting (its covariance the sandwich). Each is ``42 F(42, ν)`` (a
    χ²(42) over the noise scale's χ²(ν)/ν, ν = 6·200 − 42 the residual's degrees of freedom); the sum
    of 40 is normal to within a few %, so 3.3 σ of it is a two-sided 0.1 % gate. For the paper's
    weighting ``σ̂² (AᵀA)⁻¹``, which takes a pose's six weighted rows as independent of one variance,
    sums to 1.27× (2 142 here, 7.8 σ above the mean)."""
    rng = np.random.default_rng(43)
    poses, delta = random_poses(PLATFORM, 200, rng), random_error(rng)
    draws, unknowns, dof = 40, 42, 6 * 200 - 42
    config = config_from_dict({"ls": {"weighting": weighting}})
    nees = 0.0
    for _ in range(draws):
        log, _ = make_log(PLATFORM, delta, poses, rng, reading_sigma_mm=0.002, stroke_sigma_mm=0.001)
        estimate = make_estimator("ls", PLATFORM, config).fit(log)
        d = estimate.error - delta
        nees += d @ np.linalg.solve(estimate.covariance, d)
    mean = draws * unknowns * dof / (dof - 2)
    variance = 2 * dof**2 * (unknowns + dof - 2) / (unknowns * (dof - 2) ** 2 * (dof - 4))  # of F(42, ν)
    sd = unknowns * np.sqrt(draws * variance)
    assert abs(nees - mean) < 3.3 * sd, f"Σ dᵀP⁻¹d = {nees:.0f}, honest {mean:.0f} ± {sd:.0f}"


def test_on_planned_poses_the_error_is_the_bound_plan_states():
    """On plan's 60 A-optimal poses, over 30 noise draws, the RMS error of the default (noise-whitened)
    fit is the Cramér–Rao bound that ``plan`` and ``identifiability`` state (``design_covariance`` at the
    true geometry; measured 0.95×), where the paper's pose-form weighting leaves 1.44×. The mean of
    ``‖d‖²`` over 30 draws of 42 correlated errors spreads by ~5 % (measured: 0.95–1.06× on random and
    planned poses), so 0.85–1.15× in RMS."""
    rng = np.random.default_rng(7)
    delta = random_error(rng, 0.5)
    poses = plan_poses(PLATFORM, 60, rng=np.random.default_rng(3))
    truth = dataclasses.replace(PLATFORM, drive=PLATFORM.drive.perturbed(delta))
    bound = np.trace(design_covariance(truth, poses, NoiseConfig()))
    draws, squares = 30, 0.0
    for _ in range(draws):
        log, _ = make_log(PLATFORM, delta, poses, rng, reading_sigma_mm=0.002, stroke_sigma_mm=0.001)
        squares += float(np.sum((make_estimator("ls", PLATFORM).fit(log).error - delta) ** 2))
    ratio = np.sqrt(squares / draws / bound)
    assert 0.85 < ratio < 1.15, f"RMS error {ratio:.3f}× the Cramér–Rao bound"
