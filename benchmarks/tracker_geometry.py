"""The in-situ tracker's own geometry as an unknown: true closed-loop accuracy.

**Data.** The simulator's paper experiment (``configs/experiments/paper.toml``: nim-stewart, the
paper's Table 4 drive errors, ruler noise 0.5 µm, 50 nm quantum, the tracker's own geometry off
by i.i.d. 15 µm on its 42 values), reduced to one stage of static calibration poses with NO
load and the platform's own mass set to 0: the true drive is then pure geometry, the same at
every pose, so any error left is the estimators', not unmodelled sag. Each seed is the
experiment's seed (tracker residual, poses, noise; the drive errors are Table 4's).

**Fits.** ``ekf``, ``isam2`` and ``lm`` (``calibration.run_calibration``) on (a) the
platform as is — the tracker taken as exactly its nominal Table 2 geometry — and (b) the platform
with ``tracker_geometry_sigma_mm = 0.015`` — its 42 values identified with the drive under the
prior N(nominal, 15 µm²); (b) with ``lm`` is the joint maximum-likelihood fit of drive and
tracker that the target refers to. Noise model (``configs/estimators/in-situ-tracker.toml`` with
what this cell is known to be): no random walk and ``adapt_noise = false`` (constant geometry,
noise known), stroke σ 1 µm; reading σ 0.5 µm (the rulers) when the geometry is identified, and
the preset's effective 0.02 mm when it is fixed — the unmodelled 15 µm geometry error is then
part of every reading (the preset says so), and at 0.5 µm the χ² gate refuses clean samples.

**Metric: true closed-loop error.** For random workspace poses P (80 % of the ±200 mm / ±20°
box): strokes ``q = IK(identified drive, P)``, achieved pose ``FK(true drive, q)``; RMS of the
position error [µm] and of the orientation error [arcsec] against P. A pose is only meaningful
in a frame, and neither case observes where the frames {J} and {D} are; both define them by the
tracker's joints:

* (a) tracker fixed: the estimator takes the nominal tracker as exact, which makes {J} and {D}
  the frames where the tracker has its nominal geometry. The true tracker has that geometry in
  no frame; the closest are the frames where its joints best fit the nominal ones (Kabsch of
  its base joints, and of its platform joints, onto nominal), and the truth is compared there.
  The simulator's own frame differs from those by the rigid part of the 15 µm draws, which
  nothing can observe: compared in it, (a) would also be charged for that convention.
* (b) tracker identified: a rigid motion of all base joints of drive and tracker together (or of
  all platform joints) changes no reading or stroke — 12 gauge directions. The tracker holds
  them (``UnknownBlock.holds_gauge``): its joints' common rigid motion stays at nominal — to first
  order the same frames as (a)'s Kabsch fit, where the truth is compared.

Each method's error is the mean over seeds of its per-seed RMS; the target ratio (an
online method with the geometry identified within 1.25× the joint ``lm`` fit) is the ratio
of those means, with the per-seed range beside it.

**Why the tracker holds the gauge.** Table 4's drive errors carry a common rigid motion of
their joints of 0.2–1.8 mm. Held by the drive's joints instead (as the first version of this
feature did), the gauge pushed that rigid part into the tracker, millimetres away from its 15 µm
prior, and every fit with the geometry identified ended at 0.8–1.6 mm closed-loop error.

``python -m benchmarks.tracker_geometry [--seeds N] [--quick]`` prints the table.

**calibrate's own estimate** (:func:`honesty_section`, ``python -m benchmarks --only
tracker-geometry-honesty``): the README's quick experiment over 20 seeds, its tracker 15 µm off and
exact, through the CLI with the default config, which measures σ_g on the log: σ_g against the draw,
score's z² and the truth in calibrate's 90 % band (see :func:`honesty_note`).
"""

from __future__ import annotations

import json
import math
import re
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from benchmarks.common import ROOT, Row, Section, explain, seeded_main
from benchmarks.prediction import _below as prediction_below
from benchmarks.prediction import _run, seeds_needed
from stewart_calib.config import load_estimator_config
from stewart_calib.instruments import gauge
from stewart_calib.io import read_log, read_truth
from stewart_calib.io.platform_file import load_platform
from stewart_calib.model import kinematics as kin
from stewart_calib.model.platform import LegGeometry, Platform
from stewart_calib.pipelines.score import scores
from stewart_calib.samples import Log
from stewart_calib.simulation import load_experiment, run_experiment
from stewart_calib.simulation.experiment import Stage
from stewart_calib.simulation.trajectories import random_static_poses
from stewart_calib.workflows.calibration import run_calibration
from stewart_calib.workflows.tracker_geometry import FALSE_ALARM, applies, estimate_tracker_geometry

METHODS = ("ekf", "isam2", "lm")
ONLINE_METHODS = ("ekf", "isam2")
REFERENCE = "lm"
RATIO_TARGET = 1.25
#: the tracker's own geometry error: the experiment's residual and the prior σ it is identified under [mm]
GEOMETRY_SIGMA_MM = 0.015
RULER_SIGMA_MM = 0.0005  # paper.toml [tracker] noise_mm
FIXED_READING_SIGMA_MM = 0.02  # in-situ-tracker.toml: a reading's effective error with the geometry fixed
WORKSPACE_FRACTION = 0.8
MARGIN_MM = 10.0
ARCSEC_PER_DEG = 3600.0
CASES = ("fixed", "identified")


@dataclass(frozen=True)
class Size:
    """Calibration poses, samples held per pose, validation poses."""

    calibration: int
    samples_per_pose: int
    validation: int


#: the paper's 60 calibration poses, each held 2 samples (the paper holds 8; at 0.5 µm of ruler
#: noise more samples of one pose add little); ~200 validation poses
FULL = Size(60, 2, 200)
QUICK = Size(24, 1, 40)


@dataclass(frozen=True)
class Cell:
    """One simulated calibration run and what the metric needs of its truth."""

    platform: Platform
    log: Log
    true_drive: np.ndarray  # (42,) absolute [mm], simulator frame
    true_tracker: LegGeometry
    validation: np.ndarray  # (n, 6) [mm, rad]


def simulate(seed: int, size: Size) -> Cell:
    """The paper experiment reduced as the module docstring says, and validation poses of its workspace."""
    paper = load_experiment("paper")
    experiment = replace(
        paper,
        seed=seed,
        load=replace(paper.load, platform_mass_kg=0.0),
        tracker=replace(paper.tracker, geometry_residual_mm=GEOMETRY_SIGMA_MM),
        poses=replace(paper.poses, calibration=size.calibration, validation=0, samples_per_pose=size.samples_per_pose),
        stages=(Stage("no-load", 0.0, 0.0, ("calibration",)),),
    )
    run = run_experiment(experiment)
    # a stream of its own: the experiment spawns its streams from the bare seed
    validation = random_static_poses(
        experiment.platform, size.validation, np.random.default_rng((seed, 1)), WORKSPACE_FRACTION, MARGIN_MM
    )
    return Cell(experiment.platform, run.log, run.robot.base_params, run.robot.tracker.geometry, validation)


def _moved(params: np.ndarray, base_frame: tuple, platform_frame: tuple) -> np.ndarray:
    """Drive parameters with the base joints moved by ``(R, t)`` of {J} and the platform joints by that of {D}."""
    legs = LegGeometry.from_params(params)
    (R_J, t_J), (R_D, t_D) = base_frame, platform_frame
    return LegGeometry(
        legs.base_joints @ R_J.T + t_J, legs.platform_joints @ R_D.T + t_D, legs.initial_lengths
    ).as_vector()


def true_drive_in_frame(cell: Cell) -> np.ndarray:
    """The true drive in the frames the estimates are written in: where the true tracker's joints
    best fit its nominal ones (module docstring)."""
    nominal = cell.platform.tracker
    return _moved(
        cell.true_drive,
        gauge.kabsch(cell.true_tracker.base_joints, nominal.base_joints),
        gauge.kabsch(cell.true_tracker.platform_joints, nominal.platform_joints),
    )


def closed_loop_rms(model: LegGeometry, true_params: np.ndarray, poses: np.ndarray) -> tuple[float, float]:
    """RMS position [µm] and orientation [arcsec] error of ``FK(true, IK(model, P))`` against P."""
    R, t = kin.pose_to_rt(poses)
    achieved = kin.forward_kinematics(
        LegGeometry.from_params(true_params), kin.inverse_kinematics(model, R, t), guess=(R, t)
    )
    position_mm, orientation_deg = kin.pose_error(R, t, achieved.R, achieved.t)
    return float(np.sqrt(np.mean(position_mm**2)) * 1e3), float(np.sqrt(np.mean(orientation_deg**2)) * ARCSEC_PER_DEG)


def _config(case: str):
    reading_mm = RULER_SIGMA_MM if case == "identified" else FIXED_READING_SIGMA_MM
    return load_estimator_config(
        "in-situ-tracker",
        [
            f"noise.reading_sigma_mm={reading_mm}",
            "noise.random_walk_mm_per_sqrt_s=0",
            "robust.adapt_noise=false",
        ],
    )


def measure(seed: int, size: Size) -> dict:
    """``{case: {method: (position µm, orientation arcsec)}}`` and ``"nominal"``: the uncalibrated model's."""
    cell = simulate(seed, size)
    truth = true_drive_in_frame(cell)
    out = {"nominal": closed_loop_rms(cell.platform.drive, truth, cell.validation)}
    for case in CASES:
        platform = replace(cell.platform, tracker_geometry_sigma_mm=GEOMETRY_SIGMA_MM if case == "identified" else 0.0)
        config = _config(case)
        out[case] = {}
        for method in METHODS:
            estimate = run_calibration(platform, cell.log, method, config).estimate
            out[case][method] = closed_loop_rms(cell.platform.drive.perturbed(estimate.error), truth, cell.validation)
    return out


def _fmt(position_arcsec: np.ndarray) -> str:
    return f"{position_arcsec[0]:.1f} µm / {position_arcsec[1]:.2f}″"


def row_names() -> list[str]:
    """The names of the rows :func:`run` writes, in order (the quick test checks them)."""
    return (
        ["uncalibrated (nominal drive)"]
        + [f"{method}: tracker fixed → identified" for method in METHODS]
        + [f"{method} / {REFERENCE}-joint, tracker identified" for method in ONLINE_METHODS]
    )


def run(quick: bool = False, seeds: int | None = None) -> Section:
    size = QUICK if quick else FULL
    seeds = range(1 if quick else 5) if seeds is None else range(seeds)
    runs = [measure(seed, size) for seed in seeds]
    mean = {case: {m: np.mean([r[case][m] for r in runs], axis=0) for m in METHODS} for case in CASES}
    nominal = np.mean([r["nominal"] for r in runs], axis=0)
    rows = [Row("uncalibrated (nominal drive)", _fmt(nominal), raw={"per_seed": [r["nominal"] for r in runs]})]
    for method in METHODS:
        fixed, identified = mean["fixed"][method], mean["identified"][method]
        rows.append(
            Row(
                f"{method}: tracker fixed → identified",
                f"fixed {_fmt(fixed)}; identified {_fmt(identified)}",
                raw={case: [r[case][method] for r in runs] for case in CASES},
            )
        )
    reference = mean["identified"][REFERENCE][0]
    for method in ONLINE_METHODS:
        ratio = mean["identified"][method][0] / reference
        per_seed = [r["identified"][method][0] / r["identified"][REFERENCE][0] for r in runs]
        rows.append(
            Row(
                f"{method} / {REFERENCE}-joint, tracker identified",
                f"**{ratio:.2f}** ({mean['identified'][method][0]:.1f} vs {reference:.1f} µm; per seed "
                f"{min(per_seed):.2f}–{max(per_seed):.2f})",
                f"≤ {RATIO_TARGET}",
                bool(ratio <= RATIO_TARGET),
                {"ratio": ratio, "per_seed": per_seed},
            )
        )
    return Section("Tracker geometry", note(len(seeds), size), rows, {"size": size.__dict__, "seeds": list(seeds)})


def note(seeds: int, size: Size) -> str:
    """The section's methods paragraph."""
    return (
        "The paper experiment's robot (Table 4 drive errors), no load and no platform mass, its in-situ tracker's "
        "own geometry off by i.i.d. 15 µm; `ekf`, `isam2` and `lm` fitted with the tracker fixed at nominal and "
        "with its 42 values identified (`[tracker] geometry_sigma_mm = 0.015`; `lm` then is the joint "
        f"maximum-likelihood fit, the peer). {seeds} seed(s), {size.calibration} calibration poses × "
        f"{size.samples_per_pose} samples. Metric: strokes = IK(identified drive, P) for {size.validation} random "
        "workspace poses P, achieved pose = FK(true drive, strokes), RMS position / orientation error against P, "
        "with the truth in the frames both fits define; mean over seeds. Target: the online methods within "
        f"{RATIO_TARGET}× the joint fit's position error. Times are not part of this table."
    )


# --- calibrate's own estimate of the geometry error, against the truth -------------------------------------------

HONESTY_SEEDS, HONESTY_QUICK_SEEDS = 20, 2
#: the quick experiment's tracker: its geometry off by i.i.d. 15 µm (its default), and exact (the control)
HONESTY_CASES = {"off by 15 µm": GEOMETRY_SIGMA_MM, "exact": 0.0}
QUICK_EXPERIMENT = ROOT / "configs" / "experiments" / "quick.toml"


def quick_experiment_text(seed: int, residual_mm: float) -> str:
    """configs/experiments/quick.toml at ``seed`` with the tracker's geometry off by i.i.d. ``residual_mm``."""
    text = re.sub(r"(?m)^seed = .*$", f"seed = {seed}", QUICK_EXPERIMENT.read_text(encoding="utf-8"))
    return f"{text}\n[tracker]\ngeometry_residual_mm = {residual_mm!r}\n"


def geometry_rms_mm(platform: Platform, truth) -> float:
    """The RMS over its 42 values of the simulated tracker's geometry error (the draw's realised σ; 0 where the
    truth gives none: the nominal geometry) [mm]."""
    if truth.instrument is None:
        return 0.0
    nominal = platform.required_tracker("the tracker's geometry error")
    return float(np.sqrt(np.mean((truth.instrument[1] - nominal.as_vector()) ** 2)))


def calibrate_and_score(seed: int, residual_mm: float, work: Path) -> dict:
    """One seed of the quick experiment: ``calibrate --method M`` of each method (default config), then
    ``score``'s numbers against the truth and the prediction's band."""
    (work / "e.toml").write_text(quick_experiment_text(seed, residual_mm), encoding="utf-8")
    sim = work / "sim"
    _run(["simulate", "--experiment", work / "e.toml", "--out", sim])
    platform = load_platform(sim / "platform.toml")
    truth = read_truth(sim / "truth.csv", platform)
    log = read_log(sim / "log.csv", platform)
    config = load_estimator_config()
    estimate = estimate_tracker_geometry(platform, log, config) if applies(platform, config) else None
    out: dict = {
        "seed": seed,
        "rows": len(log),
        "geometry_rms_mm": geometry_rms_mm(platform, truth),
        "sigma_g_mm": None if estimate is None else estimate.sigma_mm,
        "sigma_w_mm": None if estimate is None else estimate.white_sigma_mm,
        "detected": bool(estimate is not None and estimate.detected),
    }
    for method in METHODS:
        result_path = work / f"{method}.json"
        _run(
            ["calibrate", "--platform", sim / "platform.toml", "--log", sim / "log.csv", "--method", method]
            + ["--out", result_path]
        )
        result = json.loads(result_path.read_text(encoding="utf-8"))
        scored = scores(platform, result, truth)
        # the truth in the simulator's own frames, off those the calibration holds by the draw's rigid part
        unmoved = scores(platform, result, replace(truth, instrument=None))
        predicted = result["predicted_closed_loop"]
        low, high = predicted["position_band_mm"]
        out[method] = {
            "z2": scored["z2"],
            "z2_simulator_frames": unmoved["z2"],
            "z2_honest_variance": z2_honest_variance(result),
            "truth_mm": scored["closed_loop_mm"],
            "predicted_mm": predicted["position_mm"],
            "band_mm": [low, high],
            "in_band": bool(low <= scored["closed_loop_mm"] <= high),
            "rows_dropped": len(log) - int(result["samples_used"]),
            "rejected": result["samples_rejected"]["by_reason"],
        }
    return out


def z2_honest_variance(result: dict) -> float:
    """The variance of ``score``'s z² (the mean of ``(e_i / σ_i)²`` over the drive's parameters) were the
    result's covariance ``C`` the truth's: ``e ~ N(0, C)`` gives ``2 tr(ρ²) / n²`` with ``ρ`` the
    parameters' correlation matrix (``n`` independent ones: ``2 / n``, the χ²ₙ/n spread)."""
    stddev = np.asarray(result["stddev"], dtype=float)
    n = len(stddev)
    correlation = np.asarray(result["covariance"], dtype=float)[:n, :n] / np.outer(stddev, stddev)
    return float(2.0 * np.sum(correlation**2) / n**2)


def honesty_rows(case: str, runs: list[dict]) -> list[Row]:
    """The rows of one geometry case: σ_g against the draw's, each method's z² and band, rows dropped."""
    n = len(runs)
    rows = []
    if case != "exact":
        measured = np.array([r["sigma_g_mm"] or 0.0 for r in runs]) * 1e3
        realised = np.array([r["geometry_rms_mm"] for r in runs]) * 1e3
        ratio = measured / realised
        rows.append(
            Row(
                f"{case}: σ_g measured against the draw's RMS of its 42 values",
                f"median {np.median(measured):.1f} µm (range {measured.min():.1f}–{measured.max():.1f}) against "
                f"{np.median(realised):.1f} µm ({realised.min():.1f}–{realised.max():.1f}); ratio median "
                f"{np.median(ratio):.2f} (range {ratio.min():.2f}–{ratio.max():.2f}); detected in "
                f"{sum(r['detected'] for r in runs)}/{n}",
                raw={"measured_um": measured.tolist(), "realised_um": realised.tolist()},
            )
        )
    else:
        detected = sum(r["detected"] for r in runs)
        rows.append(
            Row(
                f"{case}: a geometry error detected (test of size {FALSE_ALARM:g})",
                f"{detected}/{n}",
                f"≤ {_most_false_alarms(n)}/{n}",
                bool(detected <= _most_false_alarms(n)),
            )
        )
    need = seeds_needed(n)
    for method in METHODS:
        z2 = np.array([r[method]["z2"] for r in runs])
        unmoved = np.mean([r[method]["z2_simulator_frames"] for r in runs])
        # the mean over seeds of an honest result's z²: 1 within two of its standard errors
        spread = 2.0 * np.sqrt(np.sum([r[method]["z2_honest_variance"] for r in runs])) / n
        rows.append(
            Row(
                f"{case}: {method}'s z² (score's, the drive's parameters against their σ), mean over seeds",
                f"**{z2.mean():.2f}** (median {np.median(z2):.2f}, range {z2.min():.2f}–{z2.max():.2f}; the truth "
                f"in the simulator's frames: {unmoved:.2f})",
                f"1 ± {spread:.2f} (two standard errors of the mean of an honest result's z²)",
                bool(abs(z2.mean() - 1.0) <= spread),
                {"z2": z2.tolist()},
            )
        )
        hits = sum(r[method]["in_band"] for r in runs)
        ratio = np.array([r[method]["truth_mm"] / r[method]["predicted_mm"] for r in runs])
        above = sum(r[method]["truth_mm"] > r[method]["band_mm"][1] for r in runs)
        rows.append(
            Row(
                f"{case}: the truth's closed-loop position error in {method}'s 90 % band",
                f"{hits}/{n} ({above} above; truth ÷ predicted mean median {np.median(ratio):.2f}, range "
                f"{ratio.min():.2f}–{ratio.max():.2f})",
                f"≥ {need}/{n} (an honest band falls below with probability {prediction_below(n, need):.2f})",
                bool(hits >= need),
                {"truth_over_predicted": ratio.tolist()},
            )
        )
    dropped = {method: [r[method]["rows_dropped"] for r in runs] for method in METHODS}
    rows.append(
        Row(
            f"{case}: rows dropped or rejected (ekf / isam2 / lm, over all seeds)",
            " / ".join(f"{sum(dropped[m])} of {sum(r['rows'] for r in runs)}" for m in METHODS),
            "0",
            bool(all(sum(d) == 0 for d in dropped.values())),
            {"per_seed": dropped, "rejected": {m: [r[m]["rejected"] for r in runs] for m in METHODS}},
        )
    )
    return rows


def _most_false_alarms(n: int) -> int:
    """The detections of ``n`` exact trackers a test of size :data:`FALSE_ALARM` exceeds with probability < 1 %."""
    k = 0
    while 1.0 - sum(math.comb(n, j) * FALSE_ALARM**j * (1 - FALSE_ALARM) ** (n - j) for j in range(k + 1)) > 0.01:
        k += 1
    return k


#: why a row of the exact tracker may miss its target (measured aside over seeds 1–10 of the same experiment)
HONESTY_WHY = {
    prefix: (
        "with the tracker exact nothing is estimated and the default config runs as it is: ekf's and isam2's "
        "covariances come out larger than their errors (every band miss below the band) — conservative, not "
        "over-confident; measured aside over seeds 1–10, neither their random walk (off: z² 0.51 / 0.50) nor the "
        "readings' σ (the simulated 0.5 µm, strokes 0.1 µm: 0.65 / 0.58) is the cause, and lm's on the same logs "
        "is honest."
    )
    for prefix in ("exact: ekf's", "exact: isam2's", "exact: the truth's closed-loop position error in isam2's")
}


def honesty_section(quick: bool = False, seeds: int | None = None) -> Section:
    """calibrate's estimate of the tracker's geometry error and its prediction against the truth (see
    :func:`honesty_note`)."""
    seeds = seeds or (HONESTY_QUICK_SEEDS if quick else HONESTY_SEEDS)
    runs: dict[str, list[dict]] = {}
    for case, residual_mm in HONESTY_CASES.items():
        for seed in range(1, seeds + 1):
            with tempfile.TemporaryDirectory() as directory:
                runs.setdefault(case, []).append(calibrate_and_score(seed, residual_mm, Path(directory)))
    rows = [row for case, group in runs.items() for row in honesty_rows(case, group)]
    section = Section(
        "The tracker's geometry error measured by calibrate", honesty_note(seeds), rows, {"runs": runs, "seeds": seeds}
    )
    return explain(section, HONESTY_WHY)


def honesty_note(seeds: int) -> str:
    """The section's methods paragraph."""
    return (
        "The README's quick experiment (nim-stewart, a 15 kg platform, 120 rows over a 0 and a 40 kg stage) at "
        f"seeds 1–{seeds}, its in-situ tracker's own geometry off by i.i.d. 15 µm on its 42 "
        "values, and exact (the control). Per seed, in this process through the CLI: `simulate`, then `calibrate "
        "--method M` with the default config (the geometry estimated on the log and, where detected, identified "
        "under the σ_g measured, the readings at the σ_w measured) for ekf, isam2 and lm, and `score`'s numbers "
        "against the truth — in the frames the true tracker's joints define (where they best fit their nominal "
        "ones: the frames the calibration holds; the simulator's differ by the rigid part of the draw, which no "
        "reading shows). σ_g is set against the RMS of the 42 values the simulator drew. z² is score's: the "
        "mean over the 42 drive parameters of (estimate − truth)² / σ², 1 on average where the result's covariance "
        "is honest; its target is 1 within two standard errors of the mean over the seeds, each seed's variance "
        "2 tr(ρ²)/42² from the result's own correlations ρ (what an honest result's z² spreads by). The band: "
        "calibrate's 90 % band of the mean closed-loop position error over the workspace against the truth's (score's "
        "closed loop); its target the binomial rule of the prediction section (the most hits an honest band falls "
        "below with probability ≤ 0.1). Rows dropped: the log's rows not among the samples used."
    )


def main(argv: list[str] | None = None) -> int:
    return seeded_main("tracker_geometry", __doc__, run, 5, argv)


if __name__ == "__main__":
    raise SystemExit(main())
