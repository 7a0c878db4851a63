"""Accuracy: Monte Carlo against the Cramér–Rao bound, filter consistency, convergence, drift.

**Monte Carlo** (per geometry, per seed), run as a sweep (``stewart-calib sweep``'s tasks on
an embedded Dask local cluster, one worker per core): a true δM (σ = 1 mm), random workspace
poses, one sample per pose at 10 Hz with exactly the estimators' noise model (reading σ_s,
stroke σ_q), constant parameters (random walk 0: the problem the bound is for). Every method
fits the same log. The bound is :func:`stewart_calib.analysis.identifiability.identifiability_report` on
the same poses (:mod:`stewart_calib.sweep.task` computes every per-run score).

* **RMS / CRB**: ``sqrt(mean over seeds and the 42 parameters of (error_p / crb_p)²)`` — 1 for
  an efficient estimator.
* **NEES**: ``eᵀ Σ⁻¹ e`` of the final estimate with its own covariance; a consistent estimator
  falls inside the two-sided 95 % χ²(42) band in 95 % of runs.
* **Convergence**: the first checkpoint n where the RMS / CRB of the estimate after n samples,
  taken against the bound of the *whole* log, is ≤ 2.

**Drift** (simulator, closed loop): the controller commands IK with the estimator's current
model; after a no-load stage a 40 kg payload is applied in one step. Reported: samples from the
step until the position error (mean over a sliding window) is back below 2× its no-load value.
"""

from __future__ import annotations

import dataclasses
import tempfile

import numpy as np
from scipy.stats import chi2

from benchmarks.common import COMPACT_RINGS, GEOMETRIES, ROOT, Row, Section, explain
from stewart_calib.config import EstimatorConfig, NoiseConfig, PaperEKFConfig
from stewart_calib.estimators import METHODS, fit_all, make_estimator, method_names
from stewart_calib.simulation import EstimatorController, FrozenController, load_experiment, run_experiment
from stewart_calib.simulation.experiment import Stage
from stewart_calib.sweep import SweepSpec, run_sweep
from stewart_calib.sweep.runner import default_workers
from stewart_calib.sweep.spec import FAMILY_DIMENSIONS, parse_spec

ONLINE = method_names(online=True)
CRB_TARGET = 1.2
CRB_TARGET_METHODS = ("ekf", "isam2", "lm")
NEES_TARGET_FRACTION = 0.90
CONVERGENCE_FACTOR = 2.0
DRIFT_FACTOR = 2.0
DRIFT_WINDOW_SAMPLES = 10
DRIFT_LOAD_KG = 40.0


#: The Monte Carlo as a sweep (stewart_calib.sweep): the two geometries of benchmarks.common,
#: compact-600/250 as a fixed ring family (every dimension a number, nothing drawn).
def monte_carlo_spec(seeds: int, n_samples: int, checkpoints: list[int]) -> SweepSpec:
    noise = NoiseConfig()
    doc = {
        "name": "benchmarks-accuracy",
        "methods": list(METHODS),
        "seeds": seeds,
        "checkpoints": checkpoints,
        "refit_at_checkpoints": ["ls"],  # cheap to refit on each prefix; lm is not, and is not online
        "grid": {
            "platform": list(GEOMETRIES),
            "samples": n_samples,
            "rate_hz": 10.0,
            "reading_sigma_mm": noise.reading_sigma_mm,
            "stroke_sigma_mm": noise.stroke_sigma_mm,
            "drift_mm_per_sqrt_s": 0.0,
        },
        "families": {"compact-600/250": dict(zip(FAMILY_DIMENSIONS, COMPACT_RINGS, strict=True))},
    }
    return parse_spec(doc, ROOT / "benchmarks" / "accuracy.toml")


def _rms(z) -> float:
    return float(np.sqrt(np.mean(np.square(z))))


def monte_carlo(seeds: int, n_samples: int) -> tuple[list[Row], dict]:
    checkpoints = sorted({n for n in (10, 20, 30, 40, 60, 80, 100, 150, 200, 300) if n < n_samples} | {n_samples})
    band = chi2.ppf([0.025, 0.975], 42)
    spec = monte_carlo_spec(seeds, n_samples, checkpoints)
    with tempfile.TemporaryDirectory() as out:
        report = run_sweep(spec, out, progress=False)
    columns = report.table.to_pydict()
    raw = {
        "seeds": seeds,
        "samples_per_run": n_samples,
        "checkpoints": checkpoints,
        "nees_band": band.tolist(),
        "sweep": {"tasks": report.tasks, "workers": default_workers(), "wall_seconds": report.seconds},
    }
    rows = []
    for geometry in GEOMETRIES:
        raw[geometry] = {}
        for method in METHODS:
            pick = [
                r
                for r, (g, m) in enumerate(zip(columns["platform"], columns["method"], strict=True))
                if g == geometry and m == method
            ]
            column = lambda name, pick=pick: np.array([columns[name][r] for r in pick], dtype=float)  # noqa: E731
            nees = column("nees")
            inside = float(np.mean((nees >= band[0]) & (nees <= band[1])))
            ratio = _rms(column("rms_over_crb"))  # every row's RMS is over the same 42 parameters
            per_checkpoint = [_rms(column(f"rms_over_crb_at_{n}")) for n in checkpoints]
            streamed = not np.all(np.isnan(per_checkpoint))
            converged_at = next(
                (n for n, r in zip(checkpoints, per_checkpoint, strict=True) if r <= CONVERGENCE_FACTOR), None
            )
            seconds = float(np.median(column("seconds")))
            raw[geometry][method] = {
                "rms_over_crb": ratio,
                "nees_median": float(np.nanmedian(nees)) if np.any(np.isfinite(nees)) else None,
                "nees_in_band_fraction": inside,
                "rms_over_crb_at_checkpoints": per_checkpoint if streamed else [],
                "samples_to_within_2x_crb": converged_at,
                "median_seconds_per_run": seconds,
            }
            met = ratio <= CRB_TARGET if method in CRB_TARGET_METHODS else None
            if not streamed:
                convergence = "batch only (not refitted per prefix)"
            elif converged_at is None:
                convergence = f"not within 2× in {n_samples} samples (RMS/CRB {per_checkpoint[-1]:.2f} at the end)"
            else:
                convergence = f"{converged_at} samples"
            rows.append(
                Row(
                    f"{geometry}: {method}",
                    f"RMS/CRB **{ratio:.2f}**; NEES in band {inside:.0%} (median "
                    f"{raw[geometry][method]['nees_median'] or float('nan'):.3g}); within 2× CRB: {convergence}; "
                    f"{seconds:.2f} s per run",
                    f"RMS/CRB ≤ {CRB_TARGET}; NEES in band ≥ {NEES_TARGET_FRACTION:.0%}"
                    if method in CRB_TARGET_METHODS
                    else "reported as is",
                    None if met is None else bool(met and inside >= NEES_TARGET_FRACTION),
                    raw[geometry][method],
                )
            )
    return rows, raw


def _drift_experiment(seed: int, stage_samples: int):
    """quick.toml's robot, load and tracker; a no-load stage, then a 40 kg step (ramp 0)."""
    base = load_experiment(ROOT / "configs" / "experiments" / "quick.toml")
    poses_per_stage = stage_samples // 2
    return dataclasses.replace(
        base,
        seed=seed,
        poses=dataclasses.replace(
            base.poses, calibration=poses_per_stage, validation=poses_per_stage, samples_per_pose=2
        ),
        stages=(
            Stage("no-load", 0.0, 0.0, ("calibration",)),
            Stage("40kg", DRIFT_LOAD_KG, 0.0, ("validation",)),
        ),
    )


#: Random walk of δM for the drift runs [mm/√s]: the 40 kg step moves the parameters by
#: ~0.1–0.2 mm within one sample, so the default 1e-3 mm/√s (slow thermal drift) would take
#: hours to follow it; 0.02 mm/√s lets ~0.2 mm through in ~10 s at 10 Hz.
DRIFT_RANDOM_WALK_MM_PER_SQRT_S = 0.02


#: The paper's filter with Q and R matched to this simulation instead of §4.1's values: Q per
#: update ≈ the ekf's walk over one 0.1 s sample (0.02² · 0.1 = 4e-5, rounded up for the step),
#: R ≈ the tracker's pose noise (~0.03 mm → 1e-3 mm²), orientation rows in degrees.
PAPER_EKF_MATCHED = "paper EKF, Q and R matched (Q 1e-4, R 1e-3)"
PAPER_EKF_MATCHED_CONFIG = {"process_noise": 1e-4, "measurement_noise": 1e-3, "angle_unit": "deg"}


def drift(seeds: int, stage_samples: int) -> tuple[list[Row], dict]:
    config = EstimatorConfig(noise=NoiseConfig(random_walk_mm_per_sqrt_s=DRIFT_RANDOM_WALK_MM_PER_SQRT_S))
    configs = {PAPER_EKF_MATCHED: dataclasses.replace(config, paper_ekf=PaperEKFConfig(**PAPER_EKF_MATCHED_CONFIG))}
    estimator_of = {PAPER_EKF_MATCHED: "paper-ekf"}
    results: dict[str, list] = {m: [] for m in ("ls", *ONLINE, PAPER_EKF_MATCHED)}
    for seed in range(seeds):
        experiment = _drift_experiment(seed, stage_samples)
        platform = experiment.platform
        for method in results:
            if method == "ls":  # batch: fitted on the no-load stage, then frozen
                no_load = run_experiment(experiment)
                mask = np.asarray(no_load.stages) == "no-load"
                fit = fit_all(make_estimator("ls", platform, config), list(no_load.log.select(mask)))
                result = run_experiment(experiment, FrozenController(platform.drive.perturbed(fit.error)))
            else:
                estimator = make_estimator(estimator_of.get(method, method), platform, configs.get(method, config))
                result = run_experiment(experiment, EstimatorController(estimator, platform))
            position_mm, _ = result.pose_errors()
            step = int(np.argmax(np.asarray(result.stages) == "40kg"))
            no_load_mm = float(np.mean(position_mm[step // 2 : step]))  # second half: converged
            window = np.convolve(position_mm[step:], np.ones(DRIFT_WINDOW_SAMPLES) / DRIFT_WINDOW_SAMPLES, mode="valid")
            below = np.flatnonzero(window < DRIFT_FACTOR * no_load_mm)
            results[method].append(
                {
                    "seed": seed,
                    "no_load_mm": no_load_mm,
                    "right_after_step_mm": float(position_mm[step]),
                    "end_mm": float(np.mean(position_mm[-DRIFT_WINDOW_SAMPLES:])),
                    "samples_to_recover": int(below[0] + DRIFT_WINDOW_SAMPLES) if below.size else None,
                }
            )
    rows = []
    for method, runs in results.items():
        counts = [r["samples_to_recover"] for r in runs]
        recovered = [c for c in counts if c is not None]
        med = lambda key, runs=runs: float(np.median([r[key] for r in runs]))  # noqa: E731
        if len(recovered) == len(counts):
            value = f"median **{np.median(recovered):.0f}** samples (range {min(recovered)}–{max(recovered)})"
        elif recovered:
            value = f"{len(recovered)}/{len(counts)} runs recover, median {np.median(recovered):.0f} samples"
        else:
            value = f"**never** within the {stage_samples} loaded samples"
        rows.append(
            Row(
                f"drift: {method}" + (" (batch, frozen after the no-load stage)" if method == "ls" else ""),
                f"{value}; error no-load {med('no_load_mm'):.3f} mm, right after the step "
                f"{med('right_after_step_mm'):.3f} mm, at the end {med('end_mm'):.3f} mm",
                "recovers" if method != "ls" else "— (batch: never, by design)",
                (len(recovered) == len(counts)) if method != "ls" else None,
                {"runs": runs},
            )
        )
    raw = {
        "seeds": seeds,
        "stage_samples": stage_samples,
        "random_walk_mm_per_sqrt_s": DRIFT_RANDOM_WALK_MM_PER_SQRT_S,
        "methods": results,
    }
    return rows, raw


def run(quick: bool) -> Section:
    seeds, n_samples = (2, 20) if quick else (50, 200)
    mc_rows, mc_raw = monte_carlo(seeds, n_samples)
    drift_seeds, stage_samples = (1, 30) if quick else (10, 300)
    drift_rows, drift_raw = drift(drift_seeds, stage_samples)
    band = mc_raw["nees_band"]
    note = (
        f"Monte Carlo: {seeds} seeds per geometry, {n_samples} random workspace poses per run (one sample each, 10 "
        f"Hz), true δM ~ N(0, 1 mm²), reading σ {NoiseConfig.reading_sigma_mm} mm, stroke σ "
        f"{NoiseConfig.stroke_sigma_mm} mm, constant parameters (random walk 0). NEES band for χ²(42): "
        f"[{band[0]:.1f}, {band[1]:.1f}]. Drift: {drift_seeds} seeds, closed loop on nim-stewart "
        f"(configs/experiments/quick.toml's robot and load), {stage_samples} samples no-load then a {DRIFT_LOAD_KG:g} "
        f"kg step held for {stage_samples} samples; random walk {DRIFT_RANDOM_WALK_MM_PER_SQRT_S} mm/√s for ekf and "
        "isam2, the paper's Q and R for paper-ekf, and paper-ekf again with Q and R matched to this simulation "
        f"({PAPER_EKF_MATCHED}); recovery = {DRIFT_WINDOW_SAMPLES}-sample mean position error below {DRIFT_FACTOR:g}× "
        "its no-load value. The peer is the Cramér–Rao bound (RMS/CRB) and, for the drift, the batch `ls` frozen "
        "after the no-load stage. Targets: RMS/CRB ≤ 1.2 and NEES in band in ≥ 90 % of the runs for ekf, isam2 and "
        "lm; every online run recovers after the step."
    )
    section = Section("Accuracy", note, mc_rows + drift_rows, raw={"monte_carlo": mc_raw, "drift": drift_raw})
    return explain(section, WHY)


#: why a target may not be met (a row not met carries its sentence)
RIGID_STEP = (
    "the rigid model cannot take up the payload's pose-dependent sag, so its error plateaus near 2× the no-load "
    "level and a run counts as recovered only where a 10-sample mean dips under it by chance; with `[elastic]` "
    "the step is taken within 10 samples (The elastic robot, table 3)."
)
WHY = {"drift: ": RIGID_STEP}
