"""``stewart-calib calibrate``: a measurement log → a calibration result (spec §6).

    stewart-calib calibrate --platform P.toml --log L.csv --method METHOD --out R.json
                            [--trace T.csv] [--rerun R.rrd] [--platform-out C.toml] [--report DIR]
                            [--skip-bad-rows]
                            [--config C.toml] [--set section.key=value ...]

Batch methods (those with ``fit``) see the whole log at once; online methods get
``update(sample)`` sample by sample, and the result holds their estimate at the last sample.
With an online method on the tracker and neither ``--rerun`` nor ``--report`` (which show every
sample), the log is streamed: read a block at a time, the trace written as it grows, so memory
does not grow with the log. Nothing is written unless the whole run succeeds.

``--platform-out`` writes the calibrated platform (spec §8: the drive replaced by the estimate),
which every command takes as a nominal platform; ``--report DIR`` a static HTML page
``DIR/index.html`` (residuals per channel before and after, δM ± σ, correlations, conditioning,
config, versions).
"""

from __future__ import annotations

import argparse
import sys
from contextlib import ExitStack
from functools import partial
from pathlib import Path

import numpy as np

from .. import __version__, estimators, io
from ..analysis.accuracy import (
    PredictedError,
    estimate_summary,
    given_log,
    relinearised_summary,
    verdict_line,
    worse_than_nominal_line,
)
from ..analysis.identifiability import (
    conditioning_summary,
    identifiability_report,
    instrument_conditioning,
    measured_samples,
    warning_line,
)
from ..analysis.plausibility import check_plausible, payload_walk_warning, prior_reach_warning
from ..config import load_estimator_config
from ..errors import CalibError, number
from ..estimate import Estimate
from ..estimators.base import (
    accounting_words,
    skipped_count,
)
from ..estimators.ls import outlier_warning
from ..instruments import instrument_kind, registered
from ..io.platform_file import load_platform
from ..memory import check_memory
from ..model import kinematics as kin
from ..model.drive import COMPLIANCE, THERMAL, drive_model, plain_drive
from ..model.platform import LegGeometry, Platform
from ..progress import MIN_LOG_ROWS
from ..samples import HELD_SAMPLES, Log
from ..workflows import calibration
from ..workflows.calibration import (
    Calibration,
    EvenlySpacedSamples,
    SampleSpool,
    Tally,
    run_calibration,
    stream_calibration,
)
from ..workflows.diagnosis import diagnose_log
from ..workflows.online import Rejections
from ..workflows.planning import noise_floor
from ..workflows.tracker_geometry import applies, estimate_samples, with_estimated_geometry
from ..workflows.validation import (
    measurement_residuals,
    nominal_residuals,
    pose_error_summary,
    streamed_residual_rms,
    unsupported_correction,
)
from . import add_config_arguments, add_tolerance_arguments, check_output_path, handover, run_command


def _with_measured_geometry(platform: Platform, method: str, config, unmeasured: list[str], log: Log):
    """``config`` with the tracker's geometry σ the log shows (:mod:`stewart_calib.workflows.tracker_geometry`),
    said on stderr where the log shows an error, and warned of where ``method`` cannot identify it; where the
    estimate applies but the log's head gives none, the warning is added to ``unmeasured`` (said once the log
    is known to be this robot's: a log of another one is refused for what it is)."""
    measured, estimate = with_estimated_geometry(platform, method, config, log)
    if estimate is None and applies(platform, config):
        picked = estimate_samples()
        picked.add(log.strokes)
        unmeasured.append(
            f"warning: the tracker's own geometry was not measured: the log's first {picked.seen} samples hold "
            f"{picked.poses} pose{'' if picked.poses == 1 else 's'} ({len(picked.indices)} read: at most "
            f"{HELD_SAMPLES} of one held pose), which give no drive fit to measure it against; it is taken as exact, "
            "and an error of it is missing from the σ and the predicted error"
        )
    if estimate is None or not estimate.detected:
        return measured
    found = (
        f"the tracker's own geometry is off its nominal by σ {estimate.sigma_mm:.2g} mm per value (measured on "
        f"{estimate.samples} samples beside {estimate.white_sigma_mm:.2g} mm of white reading noise; likelihood "
        f"ratio {estimate.likelihood_ratio:.3g} > {estimate.threshold:.3g})"
    )
    if measured is config:  # the method fits the drive to the measured pose alone
        print(
            f"stewart-calib calibrate: warning: {found}, which {method} cannot identify: its σ and predicted error "
            "leave out what that error does to the result; ekf, isam2 and lm identify it",
            file=sys.stderr,
        )
    else:
        print(
            f"stewart-calib calibrate: {found}: its 42 values are identified with the drive under that σ, the "
            "readings at the white σ (noise.tracker_geometry_sigma_mm, noise.reading_sigma_mm; --set "
            "noise.estimate_tracker_geometry=false takes the geometry as exact)",
            file=sys.stderr,
        )
    return measured


def _summary(what: str, count: int, total: int, first: str) -> str:
    return f"stewart-calib calibrate: {what} {count} of {total} (first: {first})"


def _write_rerun(
    path: Path,
    platform: Platform,
    method: str,
    log: Log,
    run: Calibration,
    batch: bool,
    leg_forces: LegForceSeries | None = None,
    leg_temperatures: tuple[np.ndarray, np.ndarray] | None = None,
) -> None:
    """A rerun ``.rrd``: the platform geometry, the robot at each sample drawn with the calibrated
    legs (a rotary drive's crank → horn → rod, :func:`~stewart_calib.viz.recording.log_platform_pose`)
    at the instrument's pose where it fixes one (the tracker), else at the calibrated model's forward
    kinematics of the logged coordinates, the parameter errors δM over time with their ±σ bands in
    file units (mm; a servo's angles in degrees), and the method's diagnostics: drive-leg residuals
    after each sample and, for an online method, before it (the innovation), and the NIS of a Kalman
    method; with ``[thermal]`` each leg's temperature and growth over the log
    (:func:`handover.leg_temperatures`)."""
    from ..viz import recording as viz  # rerun is slow to import; only --rerun needs it

    nominal, trace = platform.drive.as_vector(), run.trace
    if trace is None:
        raise ValueError("--rerun draws the trace: run_calibration(..., diagnostics=True) keeps it")
    residual = innovation = None
    reading_legs = instrument_kind(platform).reading_legs(platform)
    if reading_legs is not None:  # the drive-leg residuals need the instrument's pose of each sample
        poses = kin.forward_kinematics(reading_legs, log.readings, strict=False)
        residual = _residuals_per_sample(platform, trace, poses.R, poses.t, log.strokes)
        if not batch:
            before = np.vstack([nominal, trace[:-1]])  # the model in force when each sample arrived
            innovation = _residuals_per_sample(platform, before, poses.R, poses.t, log.strokes)
    series = {"residual": residual, "innovation": innovation, "nis": run.nis}
    kinds = {kind for kind, values in series.items() if values is not None}
    fields = viz.parameter_fields(platform.drive.parameter_names, platform.drive.n_legs)
    calibrated = drive_model(platform).calibrated_by(run.estimate)
    if reading_legs is None:
        poses = calibrated.settled_kinematics(log.strokes, log.inputs, strict=False)[0]
    drawn = np.all(np.isfinite(poses.t), axis=1) & np.asarray(poses.converged)
    errors = io.parameters_to_file(trace - nominal, platform.drive)  # a servo's angles in degrees
    stddev = None if run.stddev is None else io.parameters_to_file(run.stddev, platform.drive)
    with io.atomic_path(path) as tmp, viz.open_recording(tmp) as rec:
        viz.log_platform_geometry(rec, platform)
        if drawn.any():
            samples = np.flatnonzero(drawn)
            R, t = poses.R[drawn], poses.t[drawn]
            viz.log_platform_pose(rec, platform, R, t, log.t_s[drawn], samples, drive_legs=calibrated.legs)
        viz.log_parameters(rec, method, errors, log.t_s, fields=fields)
        viz.log_parameter_band(rec, method, errors, stddev, log.t_s, fields=fields)
        viz.log_diagnostics(rec, method, log.t_s, residual, innovation, run.nis)
        if leg_forces is not None:  # an elastic platform's (_leg_forces): the legs' forces, and c ± σ
            forces, c, sigma = leg_forces
            viz.log_elastic(rec, method, forces, c, sigma, log.t_s)
        if leg_temperatures is not None:
            viz.log_thermal(rec, method, *leg_temperatures, log.t_s)
        views = viz.THERMAL_VIEWS if leg_temperatures is not None else ()
        viz.send_blueprint(rec, platform.drive.n_legs, [method], [], {method: kinds}, fields, views)


def _residuals_per_sample(platform: Platform, params: np.ndarray, R: np.ndarray, t: np.ndarray, strokes: np.ndarray):
    """``(N, legs)`` drive-leg residuals [mm] where sample k has its own absolute parameters ``params[k]``
    and pose ``(R[k], t[k])``, the strokes its legs' extensions: one compiled pass for the prismatic
    legs, else each sample's drive."""
    legs = platform.drive
    if type(legs) is LegGeometry:
        return kin.leg_residuals_per_sample(params, R, t, strokes)
    nominal = legs.as_vector()
    return np.array(
        [plain_drive(legs.perturbed(p - nominal)).residual(None, R[k], t[k], strokes[k]) for k, p in enumerate(params)]
    )


#: ``(forces (N, legs) [N], c (legs,) [mm/kN], σ of c or None)``: :func:`_leg_forces`
LegForceSeries = tuple[np.ndarray, np.ndarray, np.ndarray | None]


def _leg_forces(platform: Platform, estimate: Estimate, log: Log) -> LegForceSeries:
    """``(forces (N, legs) [N], c (legs,) [mm/kN], σ of c or None)`` of an elastic platform: the legs'
    forces at the calibrated model's settled poses of every sample (:func:`handover.leg_forces`), c the
    model's compliance (identified, or ``[elastic]``'s held value)."""
    drive = drive_model(platform).calibrated_by(estimate)
    block = estimate.block_results().get(COMPLIANCE, {})
    sigma = None if block.get("stddev") is None else np.asarray(block["stddev"])
    compliance = handover.term_values(drive, COMPLIANCE)
    assert compliance is not None  # an elastic platform's drive has the term
    return handover.leg_forces(drive, log), compliance, sigma


def nominal_poses(platform: Platform, log: Log) -> np.ndarray:
    """``(n, 6)`` the nominal drive's FK poses of a log's strokes (those that converge): where an
    outside instrument's log put the robot, for a platform without ``[workspace]``."""
    drive = drive_model(platform)
    fk, _ = drive.settled_kinematics(log.strokes, log.inputs, strict=False)
    return fk.pose6[fk.converged]


def outside_conditioning(platform: Platform, log: Log) -> tuple[dict, str | None]:
    """``(the "conditioning" section of a pose or points instrument's result, the expansion's trade-off
    line or None)``: what ``identifiability --log`` reports of these samples (the nominal drive with
    every term free, the instrument registered on them; :func:`handover.thermal_trade_off_line`)."""
    from ..estimators.batch import instrument_identifiability

    at_registration = registered(platform, log.strokes, log.readings)
    report = instrument_identifiability(at_registration, log.strokes, log.readings, log.inputs)
    drive = drive_model(platform).identifying()
    span = handover.temperature_span_K(log.inputs)
    line = handover.thermal_trade_off_line(drive, handover.outside_stddev(drive, report), span)
    return instrument_conditioning(report), line


def tracker_trade_off_line(platform: Platform, drive, report, poses, strokes, channels, noise) -> str | None:
    """:func:`handover.thermal_trade_off_line` of the tracker's samples: their expansion's Cramér–Rao σ
    with every term of the drive free (``report`` itself where they already are)."""
    separating = handover.trade_off_drive(drive)
    if separating is None:
        return None
    if separating.size != drive.size:
        report = identifiability_report(platform, poses, noise, False, separating, strokes, channels)
    names, stddev = report.block_stddev[THERMAL]
    span = handover.temperature_span_K(channels)
    return handover.thermal_trade_off_line(drive, dict(zip(names, stddev.tolist(), strict=True)), span)


def run(args: argparse.Namespace) -> int:
    if args.method not in estimators.METHODS:
        raise CalibError(f"--method: unknown method '{args.method}'; expected one of {', '.join(estimators.METHODS)}")
    out, trace_path, rerun_path = Path(args.out), args.trace and Path(args.trace), args.rerun and Path(args.rerun)
    platform_out, report_dir = args.platform_out and Path(args.platform_out), args.report and Path(args.report)
    for path, option in (
        (out, "--out"),
        (trace_path, "--trace"),
        (rerun_path, "--rerun"),
        (platform_out, "--platform-out"),
    ):
        check_output_path(path, option)
    handover.check_report_dir(report_dir)
    platform = load_platform(args.platform)
    config = load_estimator_config(args.config, args.set)
    # a leg set's readings stream (no registration, residuals per leg); an outside instrument's log is read whole
    outside = instrument_kind(platform).outside
    streamed = not outside and estimators.method_spec(args.method).online and not (rerun_path or report_dir)
    if not streamed:  # what a method holding the whole log will need, before it reads a row
        need = check_memory(args.method, estimators.method_spec(args.method).bytes_per_sample, args.log)
        if need:
            print(f"stewart-calib calibrate: {need}", file=sys.stderr)

    # Everything is rendered (so validated) before anything is written; a streamed trace goes to
    # a temporary that becomes the file only when the stack closes without error.
    with ExitStack() as stack:
        skipped = Tally()
        residuals = None
        log_digest = io.LogDigest()  # of the log's bytes as read (standard input's too): validate knows its own log
        unmeasured: list[str] = []  # the tracker geometry's warning where the log's head gives no estimate
        if streamed:
            trace_file = None
            if trace_path:
                trace_file = stack.enter_context(
                    open(stack.enter_context(io.atomic_path(trace_path)), "w", encoding="utf-8", newline="")
                )
            spool = SampleSpool(out.parent)
            stack.callback(spool.close)
            # the tracker's geometry measured on the log's head, which the stream reads first (diagnosed)
            measure = applies(platform, config)
            head = estimate_samples()
            measured = partial(_with_measured_geometry, platform, args.method, config, unmeasured)
            configure = (lambda block: head.add(block.strokes), measured)
            streaming = stream_calibration(
                platform,
                args.log,
                args.method,
                config,
                args.skip_bad_rows,
                trace_file,
                lambda block: spool.add(block, nominal_residuals(platform, block)),
                log_digest.update,
                configure if measure else None,
            )
            config = streaming.config or config
            estimate, n_samples, skipped = streaming.estimate, streaming.samples, streaming.skipped
            rejections, first_rejected_t_s = streaming.rejections, streaming.first_rejected_t_s
            noise_scale = streaming.noise_scale
            checked = streaming.checked.log
        else:
            log = io.read_log(args.log, platform, skip_bad_rows=args.skip_bad_rows, digest=log_digest.update)
            skipped.add(log.skipped)
            diagnose_log(platform, log.strokes, log.readings, args.log)
            config = _with_measured_geometry(platform, args.method, config, unmeasured, log)
            # isam2 costs milliseconds a sample (a pose instrument's whole session in the smoother: ~15 ms),
            # so a few hundred samples take seconds: its bar shows whatever the log's length
            progress = sys.stderr.isatty() and (len(log) >= MIN_LOG_ROWS or args.method == "isam2")
            # a filter linearises each sample once, along its way: with an outside instrument, whose frame and
            # encoder zeros it finds over the log, its covariance is asked again at its estimate
            result = run_calibration(
                platform, log, args.method, config, bool(trace_path), progress, bool(rerun_path), outside
            )
            estimate, n_samples, noise_scale = result.estimate, len(log), result.noise_scale
            rejections = Rejections.of(err for _, err in result.rejected)
            first_rejected_t_s = float(log.t_s[result.rejected[0][0]]) if result.rejected else None
            sample = EvenlySpacedSamples(calibration.CHECKED_SAMPLES)
            sample.add(log)
            checked = sample.log
        if skipped.count:
            line, reason = skipped.first
            print(
                _summary("skipped bad log rows:", skipped.count, n_samples + skipped.count, f"row {line}: {reason}"),
                file=sys.stderr,
            )
        # the leg residual it checks is the leg set's; an outside instrument's fit reports its own residuals
        check_plausible(
            platform,
            estimate.error,
            config.noise,
            np.zeros((0, 6)) if outside else checked.strokes,
            np.zeros((0, 6)) if outside else checked.readings,
            args.method,
            noise_scale,
        )
        for text in (
            *unmeasured,
            prior_reach_warning(platform, estimate.error, config.noise, args.method),
            payload_walk_warning(platform.elastic, estimate),
        ):
            if text:
                print(f"stewart-calib calibrate: {text}", file=sys.stderr)
        rejected = rejections.in_result(estimate)  # those the method took back in are among the used
        if rejected["count"]:
            print(
                _summary(
                    f"{args.method} rejected samples:",
                    rejected["count"],
                    n_samples,
                    f"t_s={number(first_rejected_t_s)}: {rejections.first}",
                ),
                file=sys.stderr,
            )

        extra: dict[str, object] = {"samples_rejected": rejected, **log_digest.field()}
        warning = None
        if not outside:  # the leg set's FK gives the poses to assess
            poses, strokes, channels = measured_samples(platform, checked)
            drive = drive_model(platform, config.noise)  # its unknown blocks too, as the estimators identify them
            report = identifiability_report(platform, poses, config.noise, False, drive, strokes, channels)
            warning = warning_line(report)
            extra["conditioning"] = conditioning_summary(report)
            thermal_line = tracker_trade_off_line(platform, drive, report, poses, strokes, channels, config.noise)
        else:
            poses = nominal_poses(platform, checked)
            conditioning, thermal_line = outside_conditioning(platform, checked)
            extra["conditioning"] = conditioning
            warning = outside_warning_line(conditioning)
        # the tracker's methods carry a random walk and the paper's forms: their covariances are not the
        # static Cramér–Rao bound the noise floor is, so only an outside instrument's is compared with it
        floor = noise_floor(platform, estimate.samples_used, config.noise) if outside else None
        predicted, line, warns = estimate_summary(platform, estimate, floor, poses)
        prediction = PredictedError.from_dict(predicted)
        overconfident = None
        optimum = None if streamed else result.relinearised
        judged = None if optimum is None else given_log(estimate, optimum)
        if optimum is not None and judged is not None and prediction is not None:
            # the prediction, the verdict and the covariance written are of the estimate's error given the
            # log, not of the filter's own claim (which the field keeps)
            predicted, line, warns = estimate_summary(platform, estimate, floor, poses, optimum)
            own, prediction = prediction, PredictedError.from_dict(predicted)
            if prediction is not None:
                predicted["relinearised"], overconfident = relinearised_summary(
                    platform, args.method, own, prediction, optimum, poses
                )
                estimate = judged
        extra["predicted_closed_loop"] = predicted
        if warning and warns:  # one warning line: the poses' conditioning, then what it leaves
            print(f"stewart-calib calibrate: {warning}; {line.removeprefix('warning: ')}", file=sys.stderr)
        else:
            for text in (warning, line):
                if text:
                    print(f"stewart-calib calibrate: {text}", file=sys.stderr)
        if thermal_line:
            print(f"stewart-calib calibrate: {thermal_line}", file=sys.stderr)
        outliers = (estimate.details or {}).get("outliers")
        if outliers:  # ls takes every sample in (the paper's baseline): it says when some are gross errors
            print(f"stewart-calib calibrate: {outlier_warning(outliers)}", file=sys.stderr)

        samples_skipped = skipped_count(skipped.count, rejections.count, estimate)
        created = handover.created_now()
        extra.update(
            {
                "covariance": handover.covariance_field(estimate, platform.drive),
                "config": handover.config_field(config),
                "version": __version__,
                "created": created,
            }
        )
        result_data = io.result_dict(estimate, platform, samples_skipped, extra)
        if streamed:
            result_data["residual_rms"] = streamed_residual_rms(
                platform, spool.blocks(), result_data, streaming.rejected
            )
        else:
            used = np.ones(len(log), dtype=bool)
            used[[k for k, _ in result.rejected]] = False  # e.g. readings the tracker's FK cannot solve
            residuals = measurement_residuals(platform, log.select(used), result_data)
            result_data["residual_rms"] = handover.residual_rms_field(residuals)
        result_json = io.result_text(result_data, str(out))
        pose_line = _pose_error_line(platform, result_data, checked, n_samples)
        unsupported = None  # the χ² test's (loud line, the verdict's words)
        if outside and predicted.get("available", True):
            rank = int(conditioning["rank"])
            unsupported = unsupported_correction(platform, result_data, checked, rank, predicted["correction_mm"])
        verdict, over = (
            verdict_line(prediction, args.tolerance_mm, args.tolerance_deg)
            if prediction is not None
            else ("verdict: none — the estimate has no covariance to predict its error from", True)
        )
        # the χ² test's line already says the calibrated model is likely worse: one loud line
        worse = (
            None
            if unsupported or prediction is None
            else worse_than_nominal_line(prediction, predicted["correction_mm"], predicted["motion_correction_mm"])
        )
        if unsupported:
            verdict = f"{verdict}; {unsupported[1]}"
        elif worse:
            verdict = f"{verdict}; the calibrated model is likely worse than the nominal one"
        if overconfident:
            verdict = f"{verdict}; {args.method} stopped short of the log's optimum (warned above)"
        loud = [text for text in (unsupported[0] if unsupported else worse, overconfident) if text]
        trace_csv = None
        if trace_path and not streamed and result.trace is not None:
            trace = io.parameters_to_file(result.trace, platform.drive)  # a rotary drive's angles in degrees
            trace_csv = io.trace_text(log.t_s, trace, names=platform.drive.parameter_names)
        platform_toml = (
            handover.calibrated_platform_text(platform, estimate, args.method, Path(args.log).name, created)
            if platform_out
            else None
        )
        page = None
        # the whole log settled once at the calibrated model, for the report and the recording alike
        leg_forces = (
            _leg_forces(platform, estimate, log)
            if platform.elastic is not None and (report_dir or rerun_path)
            else None
        )
        leg_temperatures = (
            handover.leg_temperatures(drive_model(platform).calibrated_by(estimate), log)
            if platform.thermal is not None and (report_dir or rerun_path)
            else None
        )
        if report_dir:
            from ..viz.geometry import robot_at
            from ..viz.html_report import LegForces, LegTemperatures, report_html

            inputs = {"platform file": str(args.platform), "log": str(args.log)}
            forces = None if leg_forces is None else LegForces(np.asarray(log.t_s), *leg_forces[:2])
            title = f"Calibration of {platform.name} with {args.method}"
            shown = " — ".join((verdict, *loud))
            robot = robot_at(platform, drive_model(platform).calibrated_by(estimate).legs)
            thermal = None if leg_temperatures is None else LegTemperatures(np.asarray(log.t_s), *leg_temperatures)
            page = report_html(title, result_data, residuals, None, inputs, forces, shown, robot, thermal)
        if rerun_path:
            batch = not estimators.method_spec(args.method).online
            _write_rerun(rerun_path, platform, args.method, log, result, batch, leg_forces, leg_temperatures)
    if trace_csv is not None:
        io.atomic_write_text(trace_path, trace_csv)
    if platform_toml is not None:
        io.atomic_write_text(platform_out, platform_toml)
    if page is not None:
        handover.write_report(report_dir, page)
    io.atomic_write_text(out, result_json)
    if pose_line:
        print(f"stewart-calib calibrate: {pose_line}", file=sys.stderr)
    for text in loud:
        print(f"stewart-calib calibrate: {text}", file=sys.stderr)
    print(
        f"stewart-calib calibrate: wrote {out} ({args.method}: {estimate.samples_used} samples used, "
        f"{samples_skipped} skipped{accounting_words(estimate.details or {})}, of {n_samples + skipped.count} rows)",
        file=sys.stderr,
    )
    print(f"stewart-calib calibrate: {verdict}", file=sys.stderr)
    return 1 if over and args.fail_over_tolerance else 0


def outside_warning_line(conditioning: dict) -> str | None:
    """The warning ``identifiability --log`` gives of an outside instrument's poses, in its words:
    its verdict on the equilibrated condition number
    (:data:`~stewart_calib.analysis.identifiability.CONDITION_POOR`)."""
    from ..analysis.identifiability import CONDITION_POOR

    verdict = conditioning.get("verdict")
    if verdict == "rank-deficient":
        return (
            f"warning: the poses do not identify all {conditioning['unknowns']} unknowns (rank "
            f"{conditioning['rank']}): {'; '.join(conditioning['null_space'][:3])}"
        )
    if verdict == "poorly conditioned":
        return (
            f"warning: poorly conditioned (condition number {conditioning['condition_number_equilibrated']:.3g} "
            f"with unit columns > {CONDITION_POOR:g}); weakest direction {conditioning['weakest_directions'][0]}"
        )
    return None


def _pose_error_line(platform: Platform, result: dict, checked: Log, n_samples: int) -> str | None:
    """What an engineer looks for first: the pose error before (nominal model; an outside
    instrument's frame and target(s) at their best registration on the log) and after (the
    calibration), per axis and rotation, over the evenly spaced samples the conditioning uses."""
    line = pose_error_summary(platform, result, checked, False, n_samples, "the result")
    return line and line.replace(f"(first {len(checked)} rows)", f"({len(checked)} evenly spaced samples)")


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "calibrate",
        description="Read a platform file and a measurement log, run one estimator, write a result JSON (spec §5).",
    )
    parser.add_argument("--platform", required=True, metavar="P.toml", help="platform file (spec §2)")
    parser.add_argument("--log", required=True, metavar="L.csv", help="measurement log (spec §3)")
    # Checked in run() rather than by argparse choices, so the message is ours and names the methods.
    parser.add_argument("--method", required=True, metavar="METHOD", help=f"one of {', '.join(estimators.METHODS)}")
    parser.add_argument("--out", required=True, metavar="R.json", help="result file (spec §5)")
    parser.add_argument("--trace", metavar="T.csv", help="also write t_s + the 42 estimated parameters per sample")
    parser.add_argument(
        "--rerun", metavar="R.rrd", help="also write a rerun recording of the parameter errors over time"
    )
    parser.add_argument(
        "--platform-out",
        metavar="C.toml",
        help="also write the calibrated platform (a nominal platform for every command)",
    )
    parser.add_argument("--report", metavar="DIR", help="also write a static HTML report DIR/index.html")
    parser.add_argument(
        "--skip-bad-rows", action="store_true", help="skip bad log rows (reported) instead of refusing the log"
    )
    add_config_arguments(parser)
    add_tolerance_arguments(parser)
    parser.set_defaults(func=run)


def main(argv: list[str] | None = None) -> int:
    return run_command("calibrate", argv)
