"""Robustness and honesty of every method with the DEFAULT configuration.

**Robustness**: a synthetic log (random workspace poses, 10 Hz, true δM σ = 1 mm, noise as the
defaults assume) on the compact geometry — not the simulator's platform, whose numbers nothing
here is tuned to — with glitches: one ruler of a sample off by a size drawn uniformly in the
range, at a rate of the samples, either including the first two samples (*early*) or only in
the second half (*late*). Each method's parameter RMS error is compared with its own RMS on the
same log without glitches; the target is ≤ 1.5× for ``ekf`` and ``isam2``.

**Honesty**: the default configuration on logs whose noise differs from the default by a
factor (static parameters), and on drift logs (the parameters random-walk at 0.003 mm/√s, 3×
the default's walk), the log's noise also off. Reported: mean z² = mean over seeds and the 42
parameters of (error / reported σ)² (target [0.5, 2]) and the fraction of runs whose NEES lies
in the two-sided 95 % χ²(42) band (target ≥ 90 %), over 20 seeds: an honest estimator passes with
probability 0.92 (at most 2 of 20 out of the band).
"""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from benchmarks.common import GEOMETRIES, Row, Section
from stewart_calib.config import EstimatorConfig
from stewart_calib.errors import CalibError
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
HONESTY = ((0.2, 0.0), (0.5, 0.0), (2.0, 0.0), (5.0, 0.0), (0.3, 0.003), (3.0, 0.003))
HONESTY_METHODS = ("paper-ekf", "ekf", "isam2", "lm")
#: logs a honesty row is measured on (the module docstring: why not the glitch rows' 6)
HONESTY_SEEDS = 20
DEFAULT_READING_MM, DEFAULT_STROKE_MM = 0.002, 0.001


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
    return glitches + honesty


def run(quick: bool = False) -> Section:
    platform = GEOMETRIES[GEOMETRY]()
    n, seeds, honesty_seeds = (40, range(1), range(1)) if quick else (300, range(6), range(HONESTY_SEEDS))
    return Section(
        "Robustness and honesty (default configuration)",
        __doc__.split("\n\n", 1)[1].strip(),
        _robustness_rows(platform, n, seeds) + _honesty_rows(platform, n, honesty_seeds),
        {"geometry": GEOMETRY, "samples": n, "seeds": len(seeds), "honesty_seeds": len(honesty_seeds)},
    )


if __name__ == "__main__":
    import sys

    section = run("--quick" in sys.argv)
    for row in section.rows:
        print(
            f"| {row.name} | {row.value} | {row.target} | {'' if row.met is None else ('yes' if row.met else 'NO')} |",
            flush=True,
        )
