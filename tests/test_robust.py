"""The default configuration survives glitches from the first sample on, recovers from a
lock-out, and measures the noise it is given (issue 14; :mod:`stewart_calib.estimators.robust`).

Tolerances come from the noise: a sample's NIS is χ²(6), the NEES of a consistent 42-parameter
estimate χ²(42); a scale estimated from ``d`` residual degrees of freedom has a relative
standard deviation ``√(2/d)``.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from stewart_calib.config import EstimatorConfig, config_from_dict
from stewart_calib.errors import CalibError, SampleRejected
from stewart_calib.estimators import make_estimator
from stewart_calib.estimators.base import feed
from stewart_calib.samples import Sample
from stewart_calib.workflows.online import OnlineCalibrator
from tests.synthetic import make_log, nim_stewart, random_error, random_poses

N = 120
ALLOWED_RATIO = 1.5  # issue 14: RMS with glitches ≤ 1.5 × RMS clean
#: a consistent estimate's NEES lies in this band but once in 10³ runs
NEES_BAND = chi2.ppf([0.0005, 0.9995], 42)


@pytest.fixture(scope="module")
def platform():
    return nim_stewart()


def _log(platform, seed: int, noise_factor: float = 1.0, n: int = N):
    rng = np.random.default_rng(seed)
    error = random_error(rng, 1.0)
    log, _ = make_log(
        platform,
        error,
        random_poses(platform, n, rng),
        rng,
        reading_sigma_mm=0.002 * noise_factor,
        stroke_sigma_mm=0.001 * noise_factor,
    )
    return log, error, rng


def _with_glitches(log, rng, rows, low_mm, high_mm):
    bad = log.select(slice(None))
    bad.readings = log.readings.copy()
    bad.readings[rows, rng.integers(0, 6, len(rows))] += rng.uniform(low_mm, high_mm, len(rows)) * rng.choice(
        [-1, 1], len(rows)
    )
    return bad


def _rms(x) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def _nees(estimate, truth) -> float:
    e = estimate.error - truth
    return float(e @ np.linalg.solve(estimate.covariance, e))


def _run(platform, method, log, config=None):
    estimator = make_estimator(method, platform, config or EstimatorConfig())
    rejected = feed(estimator, log)
    return estimator, rejected


@pytest.mark.parametrize("method", ["ekf", "isam2"])
@pytest.mark.parametrize("size_mm", [(0.5, 2.0), (50.0, 50.0)])
def test_glitches_from_the_first_sample_on_do_not_poison_the_default_estimate(platform, method, size_mm):
    log, error, rng = _log(platform, 3)
    rows = np.r_[0, 1, rng.choice(np.arange(2, N), 2, replace=False)]  # the first two samples, and two more
    bad = _with_glitches(log, rng, rows, *size_mm)
    clean_estimator, _ = _run(platform, method, log)
    estimator, rejected = _run(platform, method, bad)
    assert sorted(k for k, _ in rejected) == sorted(rows.tolist())  # every glitch refused, no clean sample
    assert {err.reason for _, err in rejected} == {SampleRejected.GATED}
    rms_clean = _rms(clean_estimator.estimate().error - error)
    assert _rms(estimator.estimate().error - error) <= ALLOWED_RATIO * rms_clean
    assert NEES_BAND[0] <= _nees(estimator.estimate(), error) <= NEES_BAND[1]


#: samples of the noise-scale test: the default walk (1 µm/√s) exceeds what these data show, and
#: until the windows have measured the walk it absorbs part of the noise; at 0.2× the noise the
#: scale was still 0.68–1.01 of the truth after 120 samples (seeds 0–7), 0.88–1.02 after 300.
SCALE_SAMPLES = 300
#: on quieter data the adaptive covariance is wider than the scale alone makes it, by the share of
#: the walk the window differences do not reject yet (see the test)
QUIET_WALK_SHARE = 0.35


@pytest.mark.parametrize("noise_factor", [0.2, 5.0])
def test_the_default_config_measures_noise_five_times_off(platform, noise_factor):
    log, error, _ = _log(platform, 4, noise_factor, SCALE_SAMPLES)
    estimator, rejected = _run(platform, "ekf", log)
    assert len(rejected) <= 1  # the gate refuses a clean sample once in 10⁴ (and the start-up batch alike)
    # s² from ~N·6 − 42 residual degrees of freedom: 4 relative standard deviations
    tolerance = 4 * np.sqrt(2 / (SCALE_SAMPLES * 6 - 42))
    assert estimator.noise_scale() ** 2 == pytest.approx(noise_factor**2, rel=tolerance)
    assert NEES_BAND[0] <= _nees(estimator.estimate(), error) <= NEES_BAND[1]
    # fixed noise stays available: the configured covariance, off by the factor (on quieter data,
    # where the configured σ gates nothing; on noisier data it would gate the good samples). Over
    # the first N samples, where the fixed config's walk has not yet widened its covariance apart.
    if noise_factor < 1.0:
        log, _, _ = _log(platform, 4, noise_factor)
        estimator, _ = _run(platform, "ekf", log)
        tolerance = 4 * np.sqrt(2 / (N * 6 - 42))
        fixed, _ = _run(platform, "ekf", log, config_from_dict({"robust": {"adapt_noise": False}}))
        assert fixed.noise_scale() is None
        ratio = np.median(np.diag(estimator.estimate().covariance) / np.diag(fixed.estimate().covariance))
        # the walk the window differences do not reject yet widens the adaptive covariance by up to
        # ~25 % here (ratio 1.08–1.26 × the factor², seeds 4–9, NEES/42 0.69–1.14; when the scale
        # stood as measured at the default walk after the walk was lowered, 0.65–0.93 ×, NEES/42 up
        # to 1.81 and clean samples gated)
        assert (1.0 - tolerance) * noise_factor**2 <= ratio <= (1.0 + QUIET_WALK_SHARE) * noise_factor**2


#: the scale's excess over 1 on a smooth path (see the test): the largest of seeds 1, 2 and 8
SMOOTH_PATH_EXCESS = 1.124


def test_clean_data_at_the_configured_noise_measure_scale_one_on_a_smooth_path(platform):
    """The window batches' noise scale on a smooth 10 Hz path (each window's pass from the prior
    wanders by millimetres in weakly observed directions: it must linearise where it is) is 1, or
    a little above: never below, where the gate would refuse clean samples. Every window is taken
    (``noise_every_samples`` 30), so the bias is measured on all the samples.

    A 3 s arc of the path determines few directions, and there the window's prior, centred on the
    running estimate, and its pass's own linearisation disagree with the window's samples by more
    than their σ: successive windows differ by 2.4× their covariance on average, up to 100× in a
    few directions. The walk test takes that for a walk (main's χ² test raised the rate to
    4–33 µm/√s, the likelihood test to 0.6–28) and the walk absorbs part of the excess that is
    left in the scale: 1.085 / 1.124 / 1.085 on seeds 1 / 2 / 8 (main 1.036 / 1.074 / 1.036).
    Passes linearised at the running estimate (one Gauss–Newton step) remove the spurious walk
    (0.16–0.20 µm/√s) but the scale falls to 0.90–0.92, the prior's mean having seen the window's
    samples; not taken."""
    from benchmarks.common import synthetic_stream

    log, _ = synthetic_stream(platform, 3000, np.random.default_rng(8), 10.0, smooth=True)
    estimator = make_estimator("ekf", platform, config_from_dict({"robust": {"noise_every_samples": 30}}))
    scales, rejected = [], 0
    for k, sample in enumerate(log):
        try:
            estimator.update(sample)
        except SampleRejected:
            rejected += 1
        if k >= 600 and k % 100 == 0:
            scales.append(estimator.robust.noise_scale2)
    assert rejected <= 2  # 0.3 expected at the 0.9999 gate
    # ~8 independent memories of 300 samples (6 readings each): the mean's σ is ~1.2 %; 4σ below 1,
    # and above it the excess of the windows' misfit (above) with 4σ on top
    sigma = np.sqrt(2 / (8 * 300 * 6))
    assert 1.0 - 4 * sigma <= np.mean(scales) <= SMOOTH_PATH_EXCESS + 4 * sigma


#: samples, walk [mm/√s] and noise factor of the fast-walk scale test: 10× the default walk, 0.3× its noise
FAST_WALK_LOG = (300, 0.01, 0.3)
#: the measured s² the test allows at most (see the test)
FAST_WALK_SCALE2 = 3.0


def test_a_robot_drifting_faster_than_told_does_not_read_its_walk_as_noise(platform):
    """A robot drifting 10× faster than told, its readings at 0.3× the told noise (s² = 0.09): each
    sample's walk spreads its rows ~200× the noise, so a window's residuals hardly tell the noise from
    the walk, and the log's likelihood at the true walk is flat in s² up to ~0.5 but falls by 12 at
    s² = 1 and by 80 at 3 (benchmarks/robustness.py's honesty log, seed 0). The start-up batch and
    the windows before the first difference measure the scale at the configured walk (12–20): kept in
    the scale's memory, they left s² at 3.3–7.5 at the end (seeds 0–4), the readings reported 2–3×
    noisier than told while they are 3× quieter. Dropped once the window at the walk found rejects
    them: 0.15–0.61. Above 3 the likelihood at the true walk rejects the scale."""
    n, walk_mm_per_sqrt_s, noise_factor = FAST_WALK_LOG
    for seed in range(3):
        rng = np.random.default_rng(seed)
        steps = rng.normal(0.0, walk_mm_per_sqrt_s * np.sqrt(0.1), (n, 42))
        steps[0] = 0.0
        errors = random_error(rng, 1.0) + np.cumsum(steps, axis=0)
        log, _ = make_log(
            platform, errors, random_poses(platform, n, rng, fraction=0.8), rng, 0.002 * noise_factor,
            0.001 * noise_factor,
        )  # fmt: skip
        estimator, _ = _run(platform, "ekf", log)
        assert estimator.noise_scale() ** 2 <= FAST_WALK_SCALE2
        assert NEES_BAND[0] <= _nees(estimator.estimate(), errors[-1]) <= NEES_BAND[1]


def test_a_walk_faster_than_the_robot_does_not_take_the_start_up_scale_to_its_floor():
    """Clean data at the configured noise of a robot standing still, the configured walk so fast that
    one sample's walk spreads each row 20× the noise (benchmarks.elastic table 3's 0.02 mm/√s is
    such a walk): the start-up window's scale is 1. Measured at that walk, each pass took the samples
    for smoother than their noise and lowered the scale, which let the walk fit more: the scale fell
    to its floor 0.01 on every seed. A static window of 30 samples of six rows on ten unknowns leaves
    170 degrees of freedom, σ ≈ √(2/170) ≈ 0.11 (0.13 measured over the 20 seeds): 4σ for each, and
    the mean over 20 within 4σ/√20."""
    from stewart_calib.config import RobustConfig
    from stewart_calib.estimators.robust import RobustFilter
    from stewart_calib.model.unknowns import UnknownLayout

    n, rows, samples, sigma, walk_mm_per_sqrt_s = 10, 6, 30, 0.01, 0.14
    spread = np.sqrt(2 / (rows * samples - n))

    def observe(prepared, x):
        H, z = prepared[: rows * n].reshape(rows, n), prepared[rows * n :]
        return z - H @ x, H, sigma**2 * np.eye(rows)

    scales = []
    for seed in range(20):
        rng = np.random.default_rng(seed)
        truth = rng.normal(0.0, 1.0, n)
        f = RobustFilter(
            "toy",
            10.0,
            walk_mm_per_sqrt_s,
            0.9999,
            observe,
            RobustConfig(startup_samples=samples),
            rows,
            layout=UnknownLayout(n_params=n),
        )
        for k in range(samples):
            H = rng.normal(size=(rows, n))
            f.update(0.1 * k, np.concatenate((H.ravel(), H @ truth + rng.normal(0.0, sigma, rows))))
        assert f.started and f.measured_noise
        scales.append(f.noise_scale2)
    assert np.all(np.abs(np.array(scales) - 1.0) <= 4 * spread)
    assert np.mean(scales) == pytest.approx(1.0, abs=4 * spread / np.sqrt(len(scales)))


def test_the_compiled_pass_equals_observing_sample_by_sample(platform):
    """The ekf's batches run one compiled pass (tracker of known geometry, δM alone); observing each
    buffered sample through the estimator's observation gives the same filter (rounding only)."""
    from benchmarks.common import synthetic_stream

    log, _ = synthetic_stream(platform, 400, np.random.default_rng(9), 10.0, smooth=True)
    runs = []
    for compiled in (True, False):
        estimator = make_estimator("ekf", platform)
        assert estimator.robust._compiled_rows is not None
        if not compiled:
            estimator.robust._compiled_rows = None
        feed(estimator, log)
        runs.append(estimator)
    (a, b) = runs
    np.testing.assert_allclose(a.filter.x, b.filter.x, rtol=0, atol=1e-9)
    # the walk rate's Newton root stops at a relative step of 1e-6: rounding can end it one step apart,
    # and P carries that walk (Q = q Δt) at ~1e-9 of its size
    assert a.robust.walk_rate_mm2_per_s == pytest.approx(b.robust.walk_rate_mm2_per_s, rel=1e-6)
    np.testing.assert_allclose(a.filter.P, b.filter.P, rtol=0, atol=1e-8 * np.abs(b.filter.P).max())
    # the windows' passes run at that walk rate, each window's covariance at the scale it updates,
    # and the next scale from passes at both: the scale moves by at most the walk's relative 1e-6
    assert a.robust.noise_scale2 == pytest.approx(b.robust.noise_scale2, rel=1e-6)


@pytest.mark.parametrize("m", [3, 6, 9])
def test_variance_components_are_the_post_fit_residual_and_its_expectation(m):
    from stewart_calib.estimators.kalman import variance_components

    rng = np.random.default_rng(m)
    A, B = rng.normal(size=(m, m)), rng.normal(size=(m, m))
    S, R = A @ A.T + m * np.eye(m), B @ B.T + np.eye(m)
    nu = rng.normal(size=m)
    u = np.linalg.solve(S, nu)
    observed, expected = variance_components(S, nu, R)
    assert observed == pytest.approx(u @ R @ u, rel=1e-12)
    assert expected == pytest.approx(np.trace(np.linalg.solve(S, R)), rel=1e-12)


def test_a_jump_the_random_walk_cannot_follow_is_recovered_from(platform):
    """0.2 mm on three leg lengths at once: the gate refuses the new samples until the lock-out
    is seen, then the recent samples are solved afresh and tracking goes on."""
    rng = np.random.default_rng(5)
    delta = random_error(rng)
    jump = np.zeros(42)
    jump[[6, 13, 20]] = 0.2
    errors = np.tile(delta, (200, 1))
    errors[100:] += jump
    log, _ = make_log(platform, errors, random_poses(platform, 200, rng), rng, 0.002, 0.001)
    estimator, rejected = _run(platform, "ekf", log)
    assert estimator.robust.recoveries >= 1
    assert min(k for k, _ in rejected) >= 100  # nothing before the jump refused
    assert len(rejected) < 50  # the new state is found within a few windows, not gated on and on
    assert NEES_BAND[0] <= _nees(estimator.estimate(), delta + jump) <= NEES_BAND[1]


def test_a_stream_of_nothing_but_glitches_is_refused_in_one_line(platform):
    log, _, rng = _log(platform, 6)
    bad = _with_glitches(log, rng, np.arange(N), 0.5, 2.0)
    calibrator = OnlineCalibrator(platform, "ekf")
    feed(calibrator, bad)
    with pytest.raises(
        CalibError, match=r"^ekf: the log does not fit .* the samples scatter .* × the configured noise σ"
    ) as err:
        calibrator.result()
    assert "\n" not in str(err.value)


def test_a_non_finite_sample_is_refused_with_the_state_untouched(platform):
    log, _, _ = _log(platform, 7, n=40)
    for method in ("ekf", "isam2"):
        estimator, _ = _run(platform, method, log)
        before = estimator.export_state()
        for bad in (np.r_[np.nan, log.readings[0, 1:]], np.r_[np.inf, log.readings[0, 1:]]):
            with pytest.raises(SampleRejected) as err:
                estimator.update(Sample(100.0, log.strokes[0], bad))
            assert err.value.reason == SampleRejected.NON_FINITE
        after = estimator.export_state()
        _assert_same_tree(before, after)


def _assert_same_tree(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        if isinstance(a[key], dict):
            _assert_same_tree(a[key], b[key])
        else:
            np.testing.assert_array_equal(a[key], b[key])


def _state_arrays(state: dict, prefix: str = "") -> dict:
    flat = {}
    for key, value in state.items():
        flat.update(
            _state_arrays(value, f"{prefix}{key}/") if isinstance(value, dict) else {prefix + key: np.asarray(value)}
        )
    return flat


def test_a_block_of_samples_is_exactly_the_samples_one_by_one(platform):
    """``update_block`` (the steady recursion compiled over runs of samples) leaves the estimator in
    the state sample-by-sample updates leave it, with the same refusals, late rejections and
    per-sample estimates, through a start-up glitch, gated glitches, a lock-out, a non-finite
    stroke, a stroke out of range, a time going back and the noise windows. Equal to rounding: the
    same kernels, but inlined into the compiled recursion fastmath may sum in another order (bit for
    bit in one process, 1e-8 of δM apart in another); the walk rate's Newton root stops at a
    relative step of 1e-6, so it may end one step apart."""
    from benchmarks.common import synthetic_stream
    from stewart_calib.estimators.base import update_block, update_each

    log, _ = synthetic_stream(platform, 1500, np.random.default_rng(3), 10.0, smooth=True)
    log.readings[10, 3] += 2.0  # left out late by the start-up batch
    log.readings[500, 2] += 5.0
    log.readings[700:712, 1] += 3.0  # a lock-out
    log.strokes[900, 0] = np.nan
    log.strokes[950, 4] = 1e4
    log.t_s[1000] = log.t_s[999] - 1.0
    runs = []
    for by_block in (False, True):
        estimator = make_estimator("ekf", platform)
        errors, refused = np.empty((len(log), 42)), []
        for start in range(0, len(log), 400):
            block = log.select(slice(start, start + 400))
            run = (update_block if by_block else update_each)(estimator, block, errors[start : start + len(block)])
            refused.append([[(start + j, err.reason, str(err)) for j, err in part] for part in run])
        runs.append((estimator, errors, refused))
    (one, errors_one, refused_one), (block, errors_block, refused_block) = runs
    assert refused_block == refused_one
    assert sum(len(part[0]) + len(part[1]) for part in refused_one) >= 6  # the faults were met
    assert one.robust.recoveries == block.robust.recoveries >= 1
    np.testing.assert_allclose(errors_block, errors_one, rtol=0, atol=1e-6)  # [mm]; δM's σ here ~1e-3 mm
    state_one, state_block = _state_arrays(one.export_state()), _state_arrays(block.export_state())
    assert state_block.keys() == state_one.keys()
    for key, expected in state_one.items():
        if expected.dtype.kind == "f":
            scale = np.abs(expected[np.isfinite(expected)]).max(initial=0)  # an infinite entry (a gate off) is no scale
            np.testing.assert_allclose(state_block[key], expected, rtol=1e-6, atol=1e-9 * scale, err_msg=key)
        else:
            np.testing.assert_array_equal(state_block[key], expected, err_msg=key)


def test_the_walk_between_windows_apart_is_the_difference_of_their_means():
    """``T`` of two window means of a random walk: ``(a2 − b1) + (b1 − a1)/3 + (b2 − a2)/3``
    (two thirds of the span when adjacent), checked by Monte Carlo on a discretised walk."""
    rng = np.random.default_rng(0)
    dt, q = 0.01, 2.0
    steps = rng.normal(0.0, np.sqrt(q * dt), size=(20000, 1000))
    walk = np.cumsum(steps, axis=1)
    a1, b1, a2, b2 = 100, 300, 700, 1000  # sample indices
    difference = walk[:, a2 : b2 + 1].mean(axis=1) - walk[:, a1 : b1 + 1].mean(axis=1)
    T = (a2 - b1) * dt + ((b1 - a1) * dt + (b2 - a2) * dt) / 3.0
    # the sample variance of 20000 draws has a relative σ of √(2/20000) = 1 %: 4σ
    assert np.var(difference) == pytest.approx(q * T, rel=0.04)


def test_the_batch_counts_the_rows_each_observation_has_not_the_declared_rows():
    """A sample's tight observation through an outside instrument has the rows of the channels it
    saw (a points target: three), not the drive's six the filter is declared with. While the
    start-up batch gathers its samples it adopts the noise scale its post-fit residuals give, their
    degrees of freedom shared out by the batch's redundancy: on data of exactly the configured noise
    that scale is 1 when the redundancy counts three rows a sample (counted as six: 0.44, over 20
    seeds 0.36–0.48). 100 samples of three rows on four unknowns leave 296 degrees of freedom: the
    scale's σ is about √(2/296) ≈ 0.08 (0.07 measured over 20 seeds), 4σ allowed."""
    from stewart_calib.config import RobustConfig
    from stewart_calib.estimators.robust import RobustFilter
    from stewart_calib.model.unknowns import UnknownLayout

    rng = np.random.default_rng(29)
    n, rows, samples, sigma = 4, 3, 100, 0.01
    truth = rng.normal(0.0, 1.0, n)

    def observe(prepared, x):
        H, z = prepared[: rows * n].reshape(rows, n), prepared[rows * n :]
        return z - H @ x, H, sigma**2 * np.eye(rows)

    robust = RobustConfig(startup_samples=samples + 1)  # still gathering: the batch's own scale in use
    f = RobustFilter("toy", 10.0, 0.0, 0.9999, observe, robust, 6, layout=UnknownLayout(n_params=n))
    for k in range(samples):
        H = rng.normal(size=(rows, n))
        f.update(float(k), np.concatenate((H.ravel(), H @ truth + rng.normal(0.0, sigma, rows))))
    assert not f.started and f.measured_noise
    assert f.noise_scale2 == pytest.approx(1.0, abs=4 * np.sqrt(2 / (rows * samples - n)))


def test_the_walk_directions_of_the_unknowns_that_walk_are_the_general_ones():
    """The walk test's directions where ``W`` is the identity on some unknowns and 0 on the rest (the
    conditional of those that walk on the others) are those of the generalised eigenproblem of ``S``
    and ``W``: the same terms, ``λ`` and ``(gᵀ d)²``, in another order."""
    from stewart_calib.estimators.robust import _walk_directions

    rng = np.random.default_rng(3)
    root = rng.normal(size=(9, 9))
    spread, difference = root @ root.T, rng.normal(size=9)
    walks = np.array([True, True, False, True, True, True, False, True, True])
    subset = _walk_directions(spread, walks, difference)
    general = _walk_directions(spread, np.diag(walks.astype(float)), difference)
    for a, b in zip(subset[::2], general[::2], strict=True):
        np.testing.assert_allclose(np.sort(a), np.sort(b), rtol=1e-9, atol=1e-12)
    assert np.count_nonzero(subset[0]) == walks.sum()  # the directions that do not walk say nothing


def test_a_still_robot_has_the_configured_walk_lowered_to_what_its_data_allow(platform):
    """600 samples at 10 Hz of a robot standing still, the default config (a walk of 1 µm/√s): the
    window differences' likelihood lowers the rate to 0.2–1.6 % of the configured variance (seeds
    0–3). The χ² test of their plain sum it replaced, which most directions' scatter drowns, left
    1.4–27 % (on benchmarks.elastic's check: 100 %, and a payload step taken for the walk)."""
    config = EstimatorConfig()
    for seed in range(4):
        log, _, _ = _log(platform, seed, 1.0, 600)
        estimator = make_estimator("ekf", platform, config)
        feed(estimator, log)
        assert estimator.robust.walk_rate_mm2_per_s <= 0.03 * config.noise.random_walk_mm_per_sqrt_s**2


def test_the_window_contrasts_terms_are_those_of_their_pencil():
    """:func:`_contrast_terms` (successive differences, tridiagonal QL) gives, direction by direction, the
    terms of the contrasts ``y_{2…K} − y_1``: ``λ = 1/μ`` and ``z²/μ``, ``μ`` the eigenvalues of their walk
    covariance over their error covariance and ``z`` the white contrasts along the eigenvectors (the
    generalised ``eigh`` of the pencil); of windows at one instant, whose contrast no walk moves, a term
    ``λ = ∞`` where ``μ = 0``."""
    from stewart_calib.estimators.robust import _contrast_terms

    rng = np.random.default_rng(5)
    K, k = 9, 4
    for repeated in (None, 4):
        times = np.cumsum(rng.uniform(20.0, 30.0, K)) + 1e3
        if repeated is not None:
            times[repeated] = times[repeated - 1]
        variances, estimates = rng.uniform(1e-6, 1e-4, (K, k)), rng.normal(0.0, 1e-2, (K, k))
        lam, p = np.empty((k, K - 1)), np.empty((k, K - 1))
        assert _contrast_terms(times, variances, estimates, lam, p)
        start = times - times[0]
        C = start[np.minimum.outer(np.arange(K), np.arange(K))]  # a walk's covariance at the instants
        M = np.hstack([-np.ones((K - 1, 1)), np.eye(K - 1)])
        for i in range(k):
            L = np.linalg.cholesky(M @ np.diag(variances[:, i]) @ M.T)
            mu, U = np.linalg.eigh(np.linalg.solve(L, np.linalg.solve(L, M @ C @ M.T).T))
            z = U.T @ np.linalg.solve(L, M @ estimates[:, i])
            walking = mu > 1e-12 * mu.max()
            assert np.sum(np.isinf(lam[i])) == np.sum(~walking) == (repeated is not None)
            order, expected = np.argsort(lam[i])[: walking.sum()], np.argsort(1.0 / mu[walking])
            np.testing.assert_allclose(lam[i][order], (1.0 / mu[walking])[expected], rtol=1e-10)
            expected_p = (z[walking] ** 2 / mu[walking])[expected]
            np.testing.assert_allclose(p[i][order], expected_p, rtol=1e-8, atol=1e-12 * expected_p.sum())


def _misfit_filter(n: int, rows: int, sigma: float, kappa: float):
    from stewart_calib.config import RobustConfig
    from stewart_calib.estimators.robust import RobustFilter
    from stewart_calib.model.unknowns import UnknownLayout

    def observe(prepared, x):
        H, z = prepared[: rows * n].reshape(rows, n), prepared[rows * n :]
        return z - H @ x, H, sigma**2 * np.eye(rows)

    robust = RobustConfig(startup_samples=0, adapt_noise=False)  # the gated recursion from the first sample
    layout = UnknownLayout(n_params=n)
    return RobustFilter("toy", 1.0, 0.0, 0.0, observe, robust, rows, layout=layout, pose_misfit=(kappa, 1e-9))


def _misfit_poses(rng, n: int, rows: int, sigma: float, kappa: float, poses: int, per_pose: int):
    """``(t, prepared)`` of ``poses`` static poses of ``per_pose`` samples each (the first ``rows`` entries of a
    prepared sample, its pose's inputs, the same at one pose), their readings off by a misfit per pose and white
    noise, and each pose's ``(H, mean reading)``."""
    truth, samples, means = rng.normal(0.0, 1.0, n), [], []
    for pose in range(poses):
        H = rng.normal(size=(rows, n))
        misfit = rng.normal(0.0, np.sqrt(kappa) * sigma, rows)
        z = H @ truth + misfit + rng.normal(0.0, sigma, (per_pose, rows))
        samples += [(0.1 * (pose * per_pose + k), np.concatenate((H.ravel(), z[k]))) for k in range(per_pose)]
        means.append((H, z.mean(axis=0)))
    return samples, means


def test_a_static_poses_samples_count_as_their_mean_with_the_poses_misfit():
    """With ``pose_misfit`` (κ: a misfit N(0, κ R0) drawn afresh at each pose, the white noise R0 besides), the
    filter after ``p`` static poses of ``k`` samples is the posterior of the poses' mean readings, each of
    covariance ``(1/k + κ) R0``: the exact linear answer (before: the samples of a pose counted as ``k``
    independent readings, P ``k``-fold too small in the directions a pose sees, less its misfit)."""
    n, rows, sigma, kappa, per_pose = 5, 3, 0.01, 4.0, 8
    rng = np.random.default_rng(43)
    samples, means = _misfit_poses(rng, n, rows, sigma, kappa, poses=6, per_pose=per_pose)
    f = _misfit_filter(n, rows, sigma, kappa)
    for t_s, prepared in samples:
        f.update(t_s, prepared)
    information, weighted = np.eye(n), np.zeros(n)  # the prior N(0, I)
    for H, z in means:
        W = np.linalg.inv((1.0 / per_pose + kappa) * sigma**2 * np.eye(rows))
        information += H.T @ W @ H
        weighted += H.T @ W @ z
    P = np.linalg.inv(information)
    np.testing.assert_allclose(f.filter.P, P, rtol=1e-8, atol=1e-14)
    np.testing.assert_allclose(f.filter.x, P @ weighted, rtol=1e-8, atol=1e-12)


def test_a_pose_is_held_against_its_first_inputs_not_the_last_samples():
    """Inputs creeping by less than the tolerance a sample (a slow motion) leave the pose once they are beyond
    it from the pose's first sample: each sample against the one before it, the creep stayed one pose forever."""
    n, rows, sigma, kappa = 5, 3, 0.01, 4.0
    samples, _ = _misfit_poses(np.random.default_rng(11), n, rows, sigma, kappa, poses=1, per_pose=6)
    f = _misfit_filter(n, rows, sigma, kappa)
    firsts = []
    for k, (t_s, prepared) in enumerate(samples):
        prepared = prepared.copy()
        prepared[:rows] += 0.6e-9 * k  # the tolerance is 1e-9
        f.update(t_s, prepared)
        firsts.append(f._misfit.inputs.copy())
    starts = [samples[k][1][:rows] + 0.6e-9 * k for k in (0, 0, 2, 2, 4, 4)]
    for found, start in zip(firsts, starts, strict=True):
        np.testing.assert_array_equal(found, start)


def test_a_checkpoint_within_a_pose_keeps_its_misfit():
    """Resumed from a checkpoint taken within a pose, the filter goes on with that pose's misfit (not a new
    pose's): the same state as the filter that ran through."""
    n, rows, sigma, kappa = 5, 3, 0.01, 4.0
    samples, _ = _misfit_poses(np.random.default_rng(7), n, rows, sigma, kappa, poses=3, per_pose=6)
    through, resumed = _misfit_filter(n, rows, sigma, kappa), _misfit_filter(n, rows, sigma, kappa)
    for t_s, prepared in samples[:9]:  # half-way through the second pose
        through.update(t_s, prepared)
    resumed.import_state(through.export_state())
    for t_s, prepared in samples[9:]:
        through.update(t_s, prepared)
        resumed.update(t_s, prepared)
    np.testing.assert_array_equal(resumed.filter.x, through.filter.x)
    np.testing.assert_array_equal(resumed.filter.P, through.filter.P)
