"""``stewart-calib calibrate``: a measurement log → a calibration result (spec §6).

    stewart-calib calibrate --platform P.toml --log L.csv --method METHOD --out R.json
                            [--trace T.csv] [--rerun R.rrd] [--platform-out C.toml] [--report DIR]
                            [--skip-bad-rows]
                            [--config C.toml] [--set section.key=value ...]

Batch methods (those with ``fit``) see the whole log at once; online methods get
``update(sample)`` sample by sample, and the result holds their estimate at the last sample.
Nothing is written unless the whole run succeeds.

``--platform-out`` writes the calibrated platform (spec §8: the drive replaced by the estimate),
which every command takes as a nominal platform; ``--report DIR`` a static HTML page
``DIR/index.html`` (residuals per channel before and after, δM ± σ, correlations, conditioning,
config, versions).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from . import add_config_arguments, handover, run_command
from .validate import measurement_residuals
from .. import __version__, estimators, io
from ..errors import CalibError, SampleRejected
from ..config import EstimatorConfig, load_estimator_config
from ..estimate import Estimate
from .. import kinematics as kin
from ..estimators import BatchEstimator
from ..estimators.base import late_index, take_late_rejections
from ..estimators.ekf import LegEKF
from ..estimators.paper_ekf import PaperEKF
from ..online import Rejections
from ..identifiability import conditioning_summary, identifiability_report, measured_poses, warning_line
from ..plausibility import check_plausible
from ..platform import Platform, load_platform
from ..samples import Log

#: logs at least this long get a progress bar (when stderr is a terminal).
PROGRESS_MIN_SAMPLES = 1000
#: the result's conditioning section looks at most this many poses, evenly spaced over the log.
CONDITIONING_MAX_POSES = 2000


@dataclass(frozen=True)
class Calibration:
    """One estimator run over a log.

    Attributes:
        estimate: at the last sample (online) or the fit to the whole log (batch).
        trace: ``(N, 42)`` estimated absolute parameters [mm] after each sample, or None.
        rejected: ``(sample index, SampleRejected)`` of samples the estimator refused.
        stddev: ``(N, 42)`` σ of the parameters after each sample [mm] (NaN: no covariance), or None.
        nis: ``(N,)`` normalised innovation squared of each sample (Kalman methods; NaN where
            refused), or None.
        noise_scale: the estimator's measurement noise estimated from the data, as a multiple
            of the configured σ (None when it does not estimate it).
    """

    estimate: Estimate
    trace: np.ndarray | None
    rejected: list[tuple[int, SampleRejected]]
    stddev: np.ndarray | None = None
    nis: np.ndarray | None = None
    noise_scale: float | None = None


def run_calibration(
    platform: Platform, log: Log, method: str, config: EstimatorConfig | None = None, trace: bool = False,
    progress: bool = False, diagnostics: bool = False,
) -> Calibration:
    """Run ``method`` over ``log``; see :class:`Calibration`. ``diagnostics`` (implies ``trace``)
    also keeps σ and the NIS per sample — the covariance costs isam2 ~0.3 ms a sample.

    Raises:
        CalibError: an unknown method, or a method that rejected every sample.
    """
    if platform.instrument.kind != "tracker":  # an outside instrument's frame may be anywhere: start from its registration
        from ..instruments.external import registered_platform

        platform = registered_platform(platform, log.strokes, log.readings)
    estimator = estimators.make_estimator(method, platform, config)
    nominal = platform.drive.as_vector()
    if isinstance(estimator, BatchEstimator):
        estimate = estimator.fit(list(log))
        rejected = list(estimator.rejected)
        # a batch fit holds for the whole log: one constant row per sample time
        rows = np.tile(nominal + estimate.error, (len(log), 1)) if trace or diagnostics else None
        _refuse_if_all_rejected(method, rejected, len(log))
        sigma = np.tile(_stddev_or_nan(estimate), (len(log), 1)) if diagnostics else None
        return Calibration(estimate, rows, rejected, sigma)
    rows = np.empty((len(log), len(nominal))) if trace or diagnostics else None
    sigma = np.empty_like(rows) if diagnostics else None
    kalman = isinstance(estimator, (LegEKF, PaperEKF))
    nis = np.full(len(log), np.nan) if diagnostics and kalman else None
    rejected = []
    bar = tqdm(log, desc=method, unit="sample", file=sys.stderr, disable=not progress, leave=False)
    for k, sample in enumerate(bar):
        try:
            estimator.update(sample)
            if nis is not None:
                nis[k] = estimator.filter.nis
        except SampleRejected as err:
            rejected.append((k, err))
        for err in take_late_rejections(estimator):  # a robust start-up batch left it out
            rejected.append((late_index(log.t_s[: k + 1].tolist(), err.t_s), err))
        if sigma is not None:
            now = estimator.estimate()
            rows[k], sigma[k] = nominal + now.error, _stddev_or_nan(now)
        elif rows is not None:
            rows[k] = nominal + estimator.current_error()  # a rejected sample leaves the estimate in force
    _refuse_if_all_rejected(method, rejected, len(log))
    return Calibration(estimator.estimate(), rows, rejected, sigma, nis, getattr(estimator, "noise_scale", lambda: None)())


def _stddev_or_nan(estimate: Estimate) -> np.ndarray:
    return np.full(len(estimate.error), np.nan) if estimate.stddev is None else estimate.stddev


def _refuse_if_all_rejected(method: str, rejected: list[tuple[int, SampleRejected]], n_samples: int) -> None:
    if rejected and len(rejected) == n_samples:
        raise CalibError(f"{method} rejected all {n_samples} samples (first: {rejected[0][1]})")


def calibrate(
    platform: Platform, log: Log, method: str, config: EstimatorConfig | None = None, trace: bool = False
) -> tuple[Estimate, np.ndarray | None, int]:
    """``(estimate, trace (N, 42) [mm] or None, samples rejected)`` of ``method`` on ``log``."""
    run = run_calibration(platform, log, method, config, trace)
    return run.estimate, run.trace, len(run.rejected)


def _check_writable_dir(path: Path | None, option: str) -> None:
    """Fail before a long run, not after it, when an output cannot be placed."""
    if path is not None and not path.parent.is_dir():
        raise CalibError(f"{option} {path}: directory {path.parent} does not exist")


def _summary(what: str, count: int, total: int, first: str) -> str:
    return f"stewart-calib calibrate: {what} {count} of {total} (first: {first})"


def _write_rerun(path: Path, platform: Platform, method: str, log: Log, run: Calibration, batch: bool) -> None:
    """A rerun ``.rrd``: the platform geometry, the parameter errors δM over time with their ±σ
    bands [mm], and the method's diagnostics: drive-leg residuals after each sample and, for an
    online method, before it (the innovation), and the NIS of a Kalman method."""
    from ..viz import recording as viz  # rerun is slow to import; only --rerun needs it

    nominal = platform.drive.as_vector()
    residual = innovation = None
    if platform.instrument.kind == "tracker":  # the drive-leg residuals need the tracker's pose of each sample
        poses = kin.forward_kinematics(platform.tracker, log.readings, strict=False)
        residual = kin.leg_residuals_per_sample(run.trace, poses.R, poses.t, log.strokes)
        if not batch:
            before = np.vstack([nominal, run.trace[:-1]])  # the model in force when each sample arrived
            innovation = kin.leg_residuals_per_sample(before, poses.R, poses.t, log.strokes)
    series = {"residual": residual, "innovation": innovation, "nis": run.nis}
    kinds = {kind for kind, values in series.items() if values is not None}
    with io.atomic_path(path) as tmp, viz.open_recording(tmp) as rec:
        viz.log_platform_geometry(rec, platform)
        viz.log_parameters(rec, method, run.trace - nominal, log.t_s)
        viz.log_parameter_band(rec, method, run.trace - nominal, run.stddev, log.t_s)
        viz.log_diagnostics(rec, method, log.t_s, residual, innovation, run.nis)
        viz.send_blueprint(rec, [method], [], {method: kinds})


def run(args: argparse.Namespace) -> int:
    if args.method not in estimators.METHODS:
        raise CalibError(f"--method: unknown method '{args.method}'; expected one of {', '.join(estimators.METHODS)}")
    out, trace_path, rerun_path = Path(args.out), args.trace and Path(args.trace), args.rerun and Path(args.rerun)
    platform_out, report_dir = args.platform_out and Path(args.platform_out), args.report and Path(args.report)
    for path, option in ((out, "--out"), (trace_path, "--trace"), (rerun_path, "--rerun"), (platform_out, "--platform-out")):
        _check_writable_dir(path, option)
    handover.check_report_dir(report_dir)
    platform = load_platform(args.platform)
    config = load_estimator_config(args.config, args.set)
    log = io.read_log(args.log, platform, skip_bad_rows=args.skip_bad_rows)
    total = len(log) + len(log.skipped)
    if log.skipped:
        line, reason = log.skipped[0]
        print(_summary("skipped bad log rows:", len(log.skipped), total, f"row {line}: {reason}"), file=sys.stderr)

    progress = sys.stderr.isatty() and len(log) >= PROGRESS_MIN_SAMPLES
    result = run_calibration(platform, log, args.method, config, bool(trace_path), progress, bool(rerun_path))
    # the leg residual it checks is the tracker's; an outside instrument's fit reports its own residuals
    tracker = platform.instrument.kind == "tracker"
    check_plausible(platform, result.estimate.error, config.noise, log.strokes if tracker else np.zeros((0, 6)),
                    log.readings if tracker else np.zeros((0, 6)), args.method, result.noise_scale)
    if result.rejected:
        k, reason = result.rejected[0]
        print(_summary(f"{args.method} rejected samples:", len(result.rejected), len(log),
                       f"t_s={float(log.t_s[k])!r}: {reason}"), file=sys.stderr)

    extra = {"samples_rejected": Rejections.of(err for _, err in result.rejected).summary()}
    if platform.instrument.kind == "tracker":  # the tracker's FK gives the poses to assess
        report = identifiability_report(platform, measured_poses(platform, log, CONDITIONING_MAX_POSES), config.noise)
        warning = warning_line(report)
        if warning:
            print(f"stewart-calib calibrate: {warning}", file=sys.stderr)
        extra["conditioning"] = conditioning_summary(report)

    # Render (and so validate) everything before writing anything.
    samples_skipped = len(log.skipped) + len(result.rejected)
    created = handover.created_now()
    extra.update({
        "covariance": handover.covariance_field(result.estimate),
        "config": handover.config_field(config),
        "version": __version__,
        "created": created,
    })
    result_data = io.result_dict(result.estimate, platform, samples_skipped, extra)
    used = np.ones(len(log), dtype=bool)
    used[[k for k, _ in result.rejected]] = False  # e.g. readings the tracker's FK cannot solve
    residuals = measurement_residuals(platform, log.select(used), result_data)
    result_data["residual_rms"] = handover.residual_rms_field(residuals)
    result_json = io.result_text(result_data, str(out))
    trace_csv = io.trace_text(log.t_s, result.trace) if trace_path else None
    platform_toml = (
        handover.calibrated_platform_text(platform, result.estimate, args.method, Path(args.log).name, created)
        if platform_out else None
    )
    page = None
    if report_dir:
        from ..viz.html_report import report_html

        inputs = {"platform file": str(args.platform), "log": str(args.log)}
        page = report_html(f"Calibration of {platform.name} with {args.method}", result_data, residuals, None, inputs)
    if rerun_path:
        _write_rerun(rerun_path, platform, args.method, log, result, not estimators.method_spec(args.method).online)
    if trace_csv is not None:
        io.atomic_write_text(trace_path, trace_csv)
    if platform_toml is not None:
        io.atomic_write_text(platform_out, platform_toml)
    if page is not None:
        handover.write_report(report_dir, page)
    io.atomic_write_text(out, result_json)
    print(
        f"stewart-calib calibrate: wrote {out} ({args.method}: {result.estimate.samples_used} samples used, "
        f"{samples_skipped} skipped)",
        file=sys.stderr,
    )
    return 0


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "calibrate",
        help="identify the 42 drive parameters from a measurement log",
        description="Read a platform file and a measurement log, run one estimator, write a result JSON (spec §5).",
    )
    parser.add_argument("--platform", required=True, metavar="P.toml", help="platform file (spec §2)")
    parser.add_argument("--log", required=True, metavar="L.csv", help="measurement log (spec §3)")
    # Checked in run() rather than by argparse choices, so the message is ours and names the methods.
    parser.add_argument("--method", required=True, metavar="METHOD", help=f"one of {', '.join(estimators.METHODS)}")
    parser.add_argument("--out", required=True, metavar="R.json", help="result file (spec §5)")
    parser.add_argument("--trace", metavar="T.csv", help="also write t_s + the 42 estimated parameters per sample")
    parser.add_argument("--rerun", metavar="R.rrd", help="also write a rerun recording of the parameter errors over time")
    parser.add_argument("--platform-out", metavar="C.toml", help="also write the calibrated platform (a nominal platform for every command)")
    parser.add_argument("--report", metavar="DIR", help="also write a static HTML report DIR/index.html")
    parser.add_argument("--skip-bad-rows", action="store_true", help="skip bad log rows (reported) instead of refusing the log")
    add_config_arguments(parser)
    parser.set_defaults(func=run)


def main(argv: list[str] | None = None) -> int:
    return run_command("calibrate", argv)
