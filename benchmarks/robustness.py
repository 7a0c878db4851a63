"""Robustness and honesty of every method with the DEFAULT configuration.

**Robustness**: a synthetic log (random workspace poses, 10 Hz, true δM σ = 1 mm, noise as the
defaults assume) on the compact geometry — not the simulator's platform, whose numbers nothing
here is tuned to — with glitches: one ruler of a sample off by a size drawn uniformly in the
range, at a rate of the samples, either including the first two samples (*early*) or only in
the second half (*late*). Each method's parameter RMS error is compared with its own RMS on the
same log without glitches; the target is ≤ 1.5× for ``ekf`` and ``isam2``.

**Honesty**: the default configuration on logs whose noise differs from the default by a
factor (static parameters), and on drift logs (the parameters random-walk at 0.3×, 1×, 3× and
10× the default's walk of 0.001 mm/√s: a robot drifting slower or faster than the configuration
says), the log's noise also off. Reported: mean z² = mean over seeds and the 42
parameters of (error / reported σ)² (target [0.5, 2]) and the fraction of runs whose NEES lies
in the two-sided 95 % χ²(42) band (target ≥ 90 %), over 20 seeds: an honest estimator passes with
probability 0.92 (at most 2 of 20 out of the band).

**A robot drifting faster than configured, along a smooth path**: nim-stewart along the 10 Hz
Lissajous path of ``benchmarks/fk_speed.py`` (a few seconds of it leave many directions open), the
tracker's readings at 1 µm, δM random-walking at 6.5× the default walk, 1 200 samples. Reported per
method over the seeds: the share of rows used (the rest refused or dropped by lock-out recoveries),
the parameter RMS error in units of the posterior bound (the information recursion with the true
walk from the estimators' prior) and the mean z²; targets ≥ 90 %, ≤ 2 and [0.5, 2] in every run.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from benchmarks.common import GEOMETRIES, Row, Section
from stewart_calib.config import EstimatorConfig
from stewart_calib.errors import CalibError, SampleRejected
from stewart_calib.estimators import fit_all, make_estimator
from stewart_calib.estimators.base import feed
from tests.synthetic import make_log, random_error, random_poses

GEOMETRY = "compact-600/250"
METHODS = ("ls", "paper-ekf", "ekf", "isam2", "lm")
TARGET_METHODS = ("ekf", "isam2")
RMS_RATIO_TARGET = 1.5
Z2_BAND = (0.5, 2.0)
NEES_FRACTION_TARGET = 0.9
#: (rate, smallest, largest [mm], early)
GLITCHES = ((0.02, 0.5, 2.0, True), (0.02, 50.0, 50.0, True), (0.05, 0.1, 50.0, False), (0.05, 0.1, 2.0, True))
#: (noise factor, walk [mm/√s])
HONESTY = (
    (0.2, 0.0),
    (0.5, 0.0),
    (2.0, 0.0),
    (5.0, 0.0),
    *((factor, walk) for walk in (0.0003, 0.001, 0.003, 0.01) for factor in (0.3, 3.0)),
)
HONESTY_METHODS = ("paper-ekf", "ekf", "isam2", "lm")
#: logs a honesty row is measured on (the module docstring: why not the glitch rows' 6)
HONESTY_SEEDS = 20
DEFAULT_READING_MM, DEFAULT_STROKE_MM = 0.002, 0.001
#: the smooth-path drift log (the module docstring): samples, rate [Hz], walk [mm/√s], readings' σ [mm]
DRIFT_LOG = (1200, 10.0, 0.0065, 0.001)
DRIFT_METHODS = ("ekf", "isam2")
DRIFT_SEEDS = 5
#: its targets: rows used, parameter RMS error / the bound, the band of the mean z²
DRIFT_ROWS_USED, DRIFT_ERROR_OVER_BOUND = 0.9, 2.0


def _log(platform, n: int, seed: int, noise_factor: float = 1.0, walk: float = 0.0, dt_s: float = 0.1):
    """A log and the true δM at its end."""
    rng = np.random.default_rng(seed)
    start = random_error(rng)
    errors = start
    if walk:
        steps = rng.normal(0.0, walk * np.sqrt(dt_s), (n, 42))
        steps[0] = 0.0
        errors = start + np.cumsum(steps, axis=0)
    log, _ = make_log(
        platform,
        errors,
        random_poses(platform, n, rng, fraction=0.8),
        rng,
        DEFAULT_READING_MM * noise_factor,
        DEFAULT_STROKE_MM * noise_factor,
        dt_s,
    )
    return log, (errors[-1] if walk else start), rng


def drifting_smooth_log(platform, seed: int, n: int = DRIFT_LOG[0]):
    """The smooth-path drift log (the module docstring) of ``n`` samples: ``(log, δM at its last sample,
    the posterior bound's σ of it)`` — the bound the information recursion
    ``J_k = (J_{k−1}⁻¹ + q Δt I)⁻¹ + A_kᵀ A_k`` over the whitened rows from the estimators' prior gives,
    with the true walk ``q`` (as ``stewart_calib.sweep.task.bound_stddev_mm`` does for a sweep's)."""
    from benchmarks.fk_speed import trajectory
    from stewart_calib.analysis.identifiability import whitened_leg_jacobian
    from stewart_calib.config import NoiseConfig

    _, rate_hz, walk, reading_mm = DRIFT_LOG
    rng = np.random.default_rng(seed)
    dt_s = 1.0 / rate_hz
    steps = rng.normal(0.0, walk * np.sqrt(dt_s), (n, 42))
    steps[0] = 0.0
    errors = random_error(rng) + np.cumsum(steps, axis=0)
    poses = trajectory(platform.workspace.home, n, rate_hz)
    log, _ = make_log(platform, errors, poses, rng, reading_mm, DEFAULT_STROKE_MM, dt_s)
    rows = whitened_leg_jacobian(platform, poses, NoiseConfig(reading_sigma_mm=reading_mm))
    covariance = np.eye(42) * NoiseConfig().prior_sigma_mm ** 2
    for k, A in enumerate(rows):
        predicted = covariance + np.eye(42) * (walk**2 * dt_s if k else 0.0)
        covariance = np.linalg.inv(np.linalg.inv(predicted) + A.T @ A)
    return log, errors[-1], np.sqrt(np.diag(covariance))


def drift_scores(platform, method: str, log, truth: np.ndarray, bound: np.ndarray) -> tuple[float, float, float]:
    """``(share of rows used, RMS error / bound, mean z²)`` of ``method`` on ``log``, default configuration."""
    from stewart_calib.estimators.base import accounted_estimate

    estimator = make_estimator(method, platform, EstimatorConfig())
    for sample in log:
        try:
            estimator.update(sample)
        except SampleRejected:
            pass
    estimate = accounted_estimate(estimator)
    e = estimate.error - truth
    return (
        estimate.samples_used / len(log),
        float(np.sqrt(np.mean((e / bound) ** 2))),
        float(np.mean(e**2 / np.diag(estimate.covariance))),
    )


def _drift_rows(platform, seeds, n: int) -> list[Row]:
    logs = [drifting_smooth_log(platform, seed, n) for seed in seeds]
    rows = []
    for method in DRIFT_METHODS:
        scores = np.array([drift_scores(platform, method, *data) for data in logs])
        used, ratio, z2 = scores.T
        met = bool(
            np.all(used >= DRIFT_ROWS_USED)
            and np.all(ratio <= DRIFT_ERROR_OVER_BOUND)
            and np.all((Z2_BAND[0] <= z2) & (z2 <= Z2_BAND[1]))
        )
        rows.append(
            Row(
                f"drift 6.5× the default walk, smooth path: {method}",
                f"rows used {used.min():.1%}–{used.max():.1%}, error/bound {ratio.min():.2f}–{ratio.max():.2f}, "
                f"mean z² {z2.min():.2f}–{z2.max():.2f} ({len(logs)} seeds)",
                f"≥ {DRIFT_ROWS_USED:.0%} rows, ≤ {DRIFT_ERROR_OVER_BOUND:g}× bound, "
                f"z² in [{Z2_BAND[0]}, {Z2_BAND[1]}]",
                met,
                {"rows_used": used.tolist(), "error_over_bound": ratio.tolist(), "z2": z2.tolist()},
            )
        )
    return rows


def _glitched(log, rng, rate: float, low: float, high: float, early: bool):
    n = len(log)
    count = max(2, round(rate * n))
    rows = rng.choice(np.arange(2, n) if early else np.arange(n // 2, n), count - 2 if early else count, replace=False)
    rows = np.r_[0, 1, rows] if early else rows  # early: the first two samples always
    bad = log.select(slice(None))
    bad.readings = log.readings.copy()
    bad.readings[rows, rng.integers(0, 6, len(rows))] += rng.uniform(low, high, len(rows)) * rng.choice(
        [-1, 1], len(rows)
    )
    return bad


def _estimate(platform, method: str, log):
    estimator = make_estimator(method, platform, EstimatorConfig())
    try:
        if hasattr(estimator, "fit"):
            return fit_all(estimator, list(log))
        feed(estimator, log)
        return estimator.estimate()
    except CalibError:
        return None


def _rms(estimate, truth) -> float:
    return float("nan") if estimate is None else float(np.sqrt(np.mean((estimate.error - truth) ** 2)))


def _robustness_rows(platform, n: int, seeds) -> list[Row]:
    rows = []
    for method in METHODS:
        clean = {seed: _log(platform, n, seed) for seed in seeds}
        clean_rms = np.array([_rms(_estimate(platform, method, log), truth) for log, truth, _ in clean.values()])
        for rate, low, high, early in GLITCHES:
            ratios = []
            for seed, (log, truth, _) in clean.items():
                bad = _glitched(log, np.random.default_rng(1000 + seed), rate, low, high, early)
                ratios.append(_rms(_estimate(platform, method, bad), truth))
            ratio = float(np.nanmax(np.array(ratios) / clean_rms)) if np.all(np.isfinite(ratios)) else float("nan")
            name = (
                f"glitches {rate:.0%} of {low:g}–{high:g} mm, {'first samples included' if early else 'late'}: {method}"
            )
            target = method in TARGET_METHODS
            rows.append(
                Row(
                    name,
                    f"RMS {np.nanmedian(ratios) * 1e3:.3g} µm, worst {ratio:.2f}× clean "
                    f"({np.nanmedian(clean_rms) * 1e3:.3g} µm)",
                    f"≤ {RMS_RATIO_TARGET}× clean" if target else "",
                    (ratio <= RMS_RATIO_TARGET) if target else None,
                    {"rms_mm": ratios, "clean_rms_mm": clean_rms.tolist(), "worst_ratio": ratio},
                )
            )
    return rows


def _honesty_rows(platform, n: int, seeds) -> list[Row]:
    band = chi2.ppf([0.025, 0.975], 42)
    rows = []
    for method in HONESTY_METHODS:
        for factor, walk in HONESTY:
            z2, in_band = [], []
            for seed in seeds:
                log, truth, _ = _log(platform, n, seed, factor, walk)
                estimate = _estimate(platform, method, log)
                if estimate is None or estimate.covariance is None:
                    continue
                e = estimate.error - truth
                z2.append(float(np.mean(e**2 / np.diag(estimate.covariance))))
                nees = float(e @ np.linalg.solve(estimate.covariance, e))
                in_band.append(band[0] <= nees <= band[1])
            mean_z2, fraction = float(np.mean(z2)), float(np.mean(in_band))
            target = method in TARGET_METHODS
            what = f"noise {factor:g}× the default" + (f", walk {walk:g} mm/√s" if walk else ", static")
            rows.append(
                Row(
                    f"honesty, {what}: {method}",
                    f"mean z² {mean_z2:.2f}, NEES in band {fraction:.0%}",
                    f"z² in [{Z2_BAND[0]}, {Z2_BAND[1]}], NEES ≥ {NEES_FRACTION_TARGET:.0%}" if target else "",
                    (Z2_BAND[0] <= mean_z2 <= Z2_BAND[1] and fraction >= NEES_FRACTION_TARGET) if target else None,
                    {"z2": z2, "nees_in_band": in_band},
                )
            )
    return rows


def row_names() -> list[str]:
    """The names of the rows :func:`run` writes, in order (the quick smoke test checks them)."""
    glitches = [
        f"glitches {rate:.0%} of {low:g}–{high:g} mm, {'first samples included' if early else 'late'}: {method}"
        for method in METHODS
        for rate, low, high, early in GLITCHES
    ]
    honesty = [
        f"honesty, noise {factor:g}× the default" + (f", walk {walk:g} mm/√s" if walk else ", static") + f": {method}"
        for method in HONESTY_METHODS
        for factor, walk in HONESTY
    ]
    drift = [f"drift 6.5× the default walk, smooth path: {method}" for method in DRIFT_METHODS]
    return glitches + honesty + drift


def run(quick: bool = False) -> Section:
    platform = GEOMETRIES[GEOMETRY]()
    n, seeds, honesty_seeds = (40, range(1), range(1)) if quick else (300, range(6), range(HONESTY_SEEDS))
    drift_n, drift_seeds = (60, range(1)) if quick else (DRIFT_LOG[0], range(DRIFT_SEEDS))
    rows = _robustness_rows(platform, n, seeds) + _honesty_rows(platform, n, honesty_seeds)
    rows += _drift_rows(GEOMETRIES["nim-stewart"](), drift_seeds, drift_n)
    return Section(
        "Robustness and honesty (default configuration)",
        __doc__.split("\n\n", 1)[1].strip(),
        rows,
        {
            "geometry": GEOMETRY,
            "samples": n,
            "seeds": len(seeds),
            "honesty_seeds": len(honesty_seeds),
            "drift_seeds": len(drift_seeds),
        },
    )


if __name__ == "__main__":
    import sys

    section = run("--quick" in sys.argv)
    for row in section.rows:
        print(
            f"| {row.name} | {row.value} | {row.target} | {'' if row.met is None else ('yes' if row.met else 'NO')} |",
            flush=True,
        )
