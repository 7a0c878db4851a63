"""``stewart-calib validate``: how well a calibration predicts a held-out log (spec §7).

    stewart-calib validate --platform P.toml --result R.json --log L.csv --out V.csv [--register-instrument]
                           [--report DIR]

For every row: the platform pose from forward kinematics of the logged strokes with the
calibrated drive (``nominal + error``, strokes scaled by ``1 + k_i`` where the result identified
the stroke scale), then what the instrument should have read — through the result's instrument
frame and target(s), or with ``--register-instrument`` through a frame fitted again on this log
(the instrument was moved between sessions; the robot's model is not touched). For the in-situ
tracker the prediction is its readings at that pose, and the measured pose its own forward
kinematics of the logged readings.

``V.csv``: ``t_s``, the log's measurement columns, the same columns predicted (prefix ``pred_``),
``position_error_mm`` and, for pose and tracker, ``orientation_error_deg``. One line on stdout
gives the RMS and maximum errors. ``--report DIR`` also writes ``DIR/index.html`` (spec §8): the
held-out errors and residuals per channel beside the calibration's parameters, correlations and
conditioning. Nothing is written unless the whole run succeeds.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

from .. import io
from ..analysis.accuracy import BAND_PROBABILITY, MeasuredError, PredictedError, predicted_error, verdict_line
from ..config import NoiseConfig
from ..errors import CalibError
from ..instruments import instrument_kind
from ..io.platform_file import load_platform
from ..model.drive import COMPLIANCE, drive_model
from ..model.platform import Platform
from ..progress import log_progress_bar
from ..samples import Log
from ..workflows.diagnosis import diagnose_log
from ..workflows.validation import (
    NoiseSquares,
    compared_pose_errors,
    measurement_residuals,
    noise_squares,
    nominal_platform_of,
    on_platform,
    validate,
)
from . import add_tolerance_arguments, handover, run_command


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "validate",
        description="Predict what the instrument should have read on a held-out log from the calibrated model; "
        "write V.csv with the predictions and errors and print their RMS and maximum.",
    )
    parser.add_argument("--platform", required=True, metavar="P.toml", help="platform file (spec §2, §7)")
    parser.add_argument("--result", required=True, metavar="R.json", help="calibration result (spec §5, §7)")
    parser.add_argument("--log", required=True, metavar="L.csv", help="held-out measurement log (spec §3, §7)")
    parser.add_argument("--out", required=True, metavar="V.csv", help="predictions and errors per row")
    parser.add_argument(
        "--register-instrument",
        action="store_true",
        help="fit the instrument frame again on this log (the instrument moved since the calibration)",
    )
    parser.add_argument("--report", metavar="DIR", help="also write a static HTML report DIR/index.html (spec §8)")
    add_tolerance_arguments(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    report_dir = args.report and Path(args.report)
    handover.check_report_dir(report_dir)
    platform = load_platform(args.platform)
    written = io.read_result(args.result)
    result = on_platform(platform, written)  # also on the calibrated platform it wrote
    # "before" is the nominal model's: on the calibrated platform file, its nominal platform's, with the result
    # as written (on any other platform ``result`` is ``written``)
    nominal, missing = nominal_platform_of(platform, written)
    compare = None if nominal is None else (nominal, written)
    columns = io.reading_columns(platform)
    header = ["t_s", *columns, *(f"pred_{name}" for name in columns), "position_error_mm"]
    if instrument_kind(platform).measures_orientation:
        header.append("orientation_error_deg")
    unseen = io.blank_reading_columns(platform)  # a target not seen: empty fields, read and predicted, and its error
    blank = (*(1 + j for j in unseen), *(1 + len(columns) + j for j in unseen), 1 + 2 * len(columns))
    page = moved = None
    log_digest = io.LogDigest()
    with log_progress_bar(args.log, "validate") as bar:
        if report_dir or args.register_instrument:
            # the report plots, and the instrument frame is fitted to, the whole log
            log = _whole_log(platform, args.log, bar, log_digest.update)
            in_sample = log_digest.is_of(written)
            diagnose_log(platform, log.strokes, log.readings, args.log, count=False)
            predicted, position, orientation = validate(
                platform, result, log, args.register_instrument, str(args.result)
            )
            if report_dir:
                if not args.register_instrument:  # through the calibration's frame, which may have moved
                    moved = _moved_frame_hint(platform, result, log, position, str(args.result))
                compared = _compared(args, compare, log, len(position), moved is not None)
                verdict = _verdict(
                    args, platform, result, position, orientation, log, compared, moved is not None, in_sample
                )[0]
                shown = " — ".join(text for text in (verdict, compared and compared[1]) if text)
                page = _report_page(args, platform, result, log, predicted, position, orientation, shown, compare)
            io.write_csv_blocks(
                args.out, header, [_file_columns(log, predicted, position, orientation, platform)], blank
            )
        else:
            errors: list[tuple] = []
            first: list[Log] = []
            blocks = _validated_blocks(
                platform, result, args.log, str(args.result), bar, errors, first, log_digest.update
            )
            io.write_csv_blocks(args.out, header, blocks, blank)
            in_sample = log_digest.is_of(written)
            position = np.concatenate([e[0] for e in errors])
            orientation = None if errors[0][1] is None else np.concatenate([e[1] for e in errors])
            sample_errors = np.concatenate([e[0] for e in errors])[: len(first[0])]
            moved = _moved_frame_hint(platform, result, first[0], sample_errors, str(args.result))
    if page is not None:
        handover.write_report(report_dir, page)
    print(
        f"stewart-calib validate: {_summary(position, orientation, len(position))}"
        + (" (instrument re-registered)" if args.register_instrument else "")
    )
    if instrument_kind(platform).outside:
        print(f"stewart-calib validate: {_unseen_error_line(platform, result, position, args.register_instrument)}")
    sample = log if (report_dir or args.register_instrument) else first[0]
    if not report_dir:
        compared = _compared(args, compare, sample, len(position), moved is not None)
    if compare is None:
        print(
            f"stewart-calib validate: no comparison with the nominal model: {args.platform} is the calibrated platform "
            f"file of {args.result}, and {missing}; give --platform the nominal platform file to compare",
            file=sys.stderr,
        )
    for line in compared or ():
        if line:  # the pose error line, then the loud one where the calibrated model is no better
            print(f"stewart-calib validate: {line}", file=sys.stderr)
    if moved:
        print(f"stewart-calib validate: {moved}", file=sys.stderr)
    if in_sample:
        print(f"stewart-calib validate: {IN_SAMPLE_LINE}", file=sys.stderr)
    verdict, over = _verdict(
        args, platform, result, position, orientation, sample, compared, moved is not None, in_sample
    )
    print(f"stewart-calib validate: {verdict}")
    return 1 if over and args.fail_over_tolerance else 0


def _compared(args, compare: tuple[Platform, dict] | None, sample: Log, rows: int, moved: bool):
    """:func:`compared_pose_errors` of the nominal platform and the result on it (``compare``) on this
    held-out log (``moved``: :func:`_moved_frame_hint` named a moved frame), or None where there is no
    nominal platform to compare with."""
    if compare is None:
        return None
    return compared_pose_errors(*compare, sample, args.register_instrument, rows, args.result, True, moved)


#: what ``validate`` says of a log whose bytes are those the result was calibrated from (its ``log_sha256``)
IN_SAMPLE_LINE = (
    "this log is the calibration's own (its bytes are those of the result's log_sha256): validate's errors on it "
    "are in-sample, how well the model fits the samples it was fitted to, not its accuracy on a held-out log"
)


def _verdict(
    args,
    platform: Platform,
    result: dict,
    position,
    orientation,
    sample: Log,
    compared=None,
    moved: bool = False,
    in_sample: bool = False,
) -> tuple[str, bool]:
    """The last line: what this check measured (and what the noise alone leaves in it, at the poses of
    ``sample``, the log or its first rows), with the result's expected errors, against the tolerance;
    ending with the nominal model's comparison where ``compared`` (:func:`compared_pose_errors`) warns.
    ``moved``: the instrument frame looks moved since the calibration (:func:`_moved_frame_hint`), so the
    errors through the calibration's frame measure the move, not the robot: not held against the
    prediction or the tolerance. ``in_sample``: the log is the calibration's own (:data:`IN_SAMPLE_LINE`), which
    the measured words say."""
    noise = result_noise(platform, result, sample, args.register_instrument, len(position))
    measured, beyond = _measured_words(platform, position, orientation, noise, args.register_instrument)
    if in_sample:
        measured += " on the calibration's own log (in-sample: the fit, not held-out accuracy)"
    if moved:
        measured += (
            "; these errors are through an instrument frame that looks moved since the calibration, not the robot's: "
            "add --register-instrument"
        )
    prediction = result_prediction(platform, result)
    if prediction is None:
        verdict, over = f"verdict: {measured}; the result holds no prediction of its error elsewhere", True
    else:
        # the robot's own; through a moved frame, the move's
        outside = instrument_kind(platform).outside
        verdict, over = verdict_line(
            prediction, args.tolerance_mm, args.tolerance_deg, measured, None if moved else beyond, outside,
            args.register_instrument,
        )  # fmt: skip
    if compared and compared[1]:
        verdict += "; on this log the calibrated model is no better than the nominal one"
    return verdict, over


def result_prediction(platform: Platform, result: dict) -> PredictedError | None:
    """The result's predicted error (its ``"predicted_closed_loop"`` field), or where it was written
    without the motion from home, that of its covariance over the workspace; None without either."""
    predicted = PredictedError.from_dict(result.get("predicted_closed_loop"))
    if predicted is not None:
        return predicted
    covariance = result.get("covariance")
    if covariance is None or platform.workspace is None:
        return None
    # the covariance's first rows: δM, then the drive's blocks the result has (spec §7, in the drive's order)
    n = len(result["error"]) + sum(
        len(result[term.key]["names"]) for term in drive_model(platform).terms if term.key in result
    )
    return predicted_error(platform, np.asarray(covariance, dtype=float)[:n, :n])


def _rms(values) -> float:
    return float(np.sqrt(np.nanmean(np.asarray(values) ** 2)))


def result_noise(
    platform: Platform, result: dict, sample: Log, register: bool, rows: int
) -> tuple[NoiseSquares, NoiseSquares | None]:
    """:func:`~stewart_calib.workflows.validation.noise_squares` of a check of ``rows`` rows, the
    in-situ tracker's readings and strokes of the result's ``[noise]`` σ (an outside instrument's
    are the platform file's)."""
    noise = {**dataclasses.asdict(NoiseConfig()), **result.get("config", {}).get("noise", {})}
    return noise_squares(platform, result, sample, register, rows, noise["reading_sigma_mm"], noise["stroke_sigma_mm"])


def _outside_check_words(register: bool) -> str:
    """What a check through an outside instrument measured: with ``--register-instrument`` (``register``),
    through its frame and target(s) fitted again to this log, the error as the instrument sees it after
    registration (the prediction's quantity, :mod:`stewart_calib.analysis.accuracy`); else through the
    calibration's frame and target(s), fitted to the calibration's log — their own error and any move of
    the instrument since are in the rows too."""
    if register:
        return "error as the instrument sees it after registration (its frame and target(s) fitted again to this log)"
    return "error as the instrument sees it through the calibration's frame and target(s) (not fitted to this log)"


def _measured_words(
    platform: Platform,
    position_mm: np.ndarray,
    orientation_deg,
    noise: tuple[NoiseSquares, NoiseSquares | None],
    register: bool,
) -> tuple[str, MeasuredError]:
    """What this check measured, named: through an outside instrument's frame and target(s) the error as
    the instrument sees it (:func:`_outside_check_words`: fitted again to this log with ``register``, else
    the calibration's; they absorb a rigid motion of {J} and the targets' places in {D}), through the
    in-situ tracker the absolute place: the rows' RMS and, beyond the noise (:func:`result_noise`), the
    robot's own with its 90 % interval from the noise's spread over the rows — which the verdict holds
    against the tolerance where an outside instrument measured it."""
    outside = instrument_kind(platform).outside
    what = _outside_check_words(register) if outside else "absolute place in {J}"
    text = f"validate measured the {what}: position RMS {_rms(position_mm):.3g} mm"
    if orientation_deg is not None:
        text += f" / {_rms(orientation_deg):.3g}°"
    position_noise, orientation_noise = noise
    own_mm, band_mm = position_noise.beyond(_rms(position_mm), BAND_PROBABILITY)
    beyond = f"{own_mm:.3g} mm ({BAND_PROBABILITY:.0%}: {band_mm[0]:.3g}–{band_mm[1]:.3g} mm)"
    own_deg = None
    if orientation_deg is not None and orientation_noise is not None:
        own_deg, band_deg = orientation_noise.beyond(_rms(orientation_deg), BAND_PROBABILITY)
        beyond += f" / {own_deg:.3g}° ({BAND_PROBABILITY:.0%}: {band_deg[0]:.3g}–{band_deg[1]:.3g}°)"
    noise_words = f"{position_noise.rms:.3g} mm"
    if orientation_deg is not None and orientation_noise is not None:
        noise_words += f" / {orientation_noise.rms:.3g}°"
    source = "instrument's" if outside else "tracker's and the strokes'"
    return (
        text + f" (the {source} noise alone leaves {noise_words}; beyond it {beyond})",
        MeasuredError(own_mm, band_mm, own_deg),
    )


def _unseen_error_line(platform: Platform, result: dict, position_mm: np.ndarray, register: bool) -> str:
    """What a check through an outside instrument's frame cannot see, beside what it saw: the
    frame and target(s) (fitted with the drive, the frame again here) absorb a rigid motion of {J}
    and the targets' places in {D}, so it measures the registered error, and the robot's closed-loop
    (absolute) error is the result's prediction — which the verdict gives (printed once, there), this
    line what limits it. ``register``: the frame and target(s) were fitted again to this log."""
    seen_rms_mm = _rms(position_mm)
    head = (
        f"validate measured the {_outside_check_words(register)}: a check through the "
        "instrument's fitted frame and target(s) cannot see the robot's closed-loop (absolute) pose error "
        "(they absorb a rigid motion of {J} and the targets' places in {D}); "
        f"position RMS here {seen_rms_mm:.4g} mm, "
    )
    prediction = result_prediction(platform, result)
    if prediction is None:
        return head + "and the result holds no covariance to predict that error from"
    limited = f", limited by {prediction.limited_by}" if prediction.limited_by else ""
    return head + f"the result's prediction of that error is the verdict's absolute place in {{J}}{limited}"


#: the held-out errors must exceed this many position σ of the instrument before a moved frame is suspected
MOVED_SIGMAS = 10.0
#: and fitting the frame again must cut them by this factor
MOVED_GAIN = 5.0


def _moved_frame_hint(platform: Platform, result: dict, block: Log, position: np.ndarray, source: str) -> str | None:
    """One line when an outside instrument's errors on the log's first block are far beyond its
    noise and a frame fitted again to that block explains them: the instrument moved since the
    calibration (cameras bumped, a tracker set up anew), not the robot."""
    if not instrument_kind(platform).outside or not len(block):
        return None
    rms = float(np.sqrt(np.nanmean(position**2)))
    if rms < MOVED_SIGMAS * platform.instrument.position_sigma_mm:
        return None
    try:
        refit = validate(platform, result, block, True, source)[1]
    except CalibError:
        return None
    refit_rms = float(np.sqrt(np.nanmean(refit**2)))
    if refit_rms * MOVED_GAIN > rms:
        return None
    return (
        f"the instrument frame looks moved since the calibration: position RMS {rms:.4g} mm through the "
        f"result's frame, {refit_rms:.4g} mm with the frame fitted to this log; add --register-instrument"
    )


def _file_columns(log: Log, predicted, position, orientation, platform: Platform) -> list[np.ndarray]:
    """V.csv's columns [file units] for the rows of ``log``."""
    return [
        log.t_s,
        *io.readings_in_file_units(log.readings, platform),
        *io.readings_in_file_units(predicted, platform),
        position,
        *([] if orientation is None else [orientation]),
    ]


def _whole_log(platform: Platform, path: str, bar, digest) -> Log:
    """The log's times, strokes, readings and input channels (all :func:`validate` and the report use:
    an elastic model predicts each row under its own load, a thermal one at its own temperatures), read
    a block at a time, the ``bar`` ticked per block, its bytes handed to ``digest``."""
    blocks = []
    for block in io.read_log_blocks(path, platform, digest=digest):
        blocks.append(Log(block.t_s, block.strokes, block.readings, inputs=block.inputs))
        bar.update(len(block))
    return Log.concatenate(blocks)


def _validated_blocks(
    platform: Platform, result: dict, path: str, result_source: str, bar, errors: list, first: list, digest
):
    """V.csv's columns a block of the log at a time (each row's prediction is its own), the ``bar``
    ticked per block; each block's ``(position, orientation)`` errors are appended to ``errors``
    and the blocks up to :data:`SAMPLE_ROWS` rows to ``first`` (then joined into one and diagnosed:
    :func:`~stewart_calib.workflows.diagnosis.diagnose_log`). A prediction refused is raised once the rest of
    the log is read, so that a bad row anywhere in it is refused first, as when the log was read whole.
    The log's bytes go to ``digest`` (:func:`stewart_calib.io.read_log`)."""
    blocks = io.read_log_blocks(path, platform, digest=digest)
    done = 0
    for block in blocks:
        bar.update(len(block))
        if not len(block):
            continue
        if done < SAMPLE_ROWS:
            first.append(block)  # with its payloads: an elastic model predicts each row under its own load
            if done + len(block) >= SAMPLE_ROWS:
                _diagnose_sample(platform, first, path)
        try:
            predicted, position, orientation = validate(
                platform, result, block, False, result_source, first_sample=done
            )
        except CalibError:
            for _ in blocks:
                pass
            raise
        errors.append((position, orientation))
        yield _file_columns(block, predicted, position, orientation, platform)
        done += len(block)
    if done < SAMPLE_ROWS:
        _diagnose_sample(platform, first, path)


#: the rows of a streamed log's start that the diagnosis, the moved-frame hint and the pose error
#: line look at (a log's start stands for it: the file written holds every row)
SAMPLE_ROWS = 2000


def _diagnose_sample(platform: Platform, first: list, path: str) -> None:
    sample = Log.concatenate(first)
    first[:] = [sample]
    diagnose_log(platform, sample.strokes, sample.readings, path, count=False)


def _report_page(
    args, platform: Platform, result: dict, log, predicted, position, orientation, verdict: str, compare
) -> str:
    """The ``--report`` page: the held-out errors and residuals per channel (before: the nominal platform's
    of ``compare``, else the calibrated platform file's own), then the calibration's own sections
    (parameters ± σ, correlations, conditioning, config, versions) from the result."""
    from ..viz.geometry import robot_at
    from ..viz.html_report import HeldOut, LegForces, LegTemperatures, report_html

    held = HeldOut(str(args.log), np.asarray(log.t_s), position, orientation, args.register_instrument)
    before_on, with_result = compare or (platform, result)
    residuals = measurement_residuals(before_on, log, with_result, predicted, "the held-out log")
    if compare is None:  # no nominal platform to be found: "before" is the calibrated file's own drive
        residuals = dataclasses.replace(
            residuals, before_model=f"{args.platform} itself (its nominal platform not found)"
        )
    inputs = {"platform file": str(args.platform), "result": str(args.result), "held-out log": str(args.log)}
    forces = None
    drive = handover.calibrated_model(platform, args.result)
    if platform.elastic is not None:
        compliance = handover.term_values(drive, COMPLIANCE)
        assert compliance is not None  # an elastic platform's drive has the term
        forces = LegForces(np.asarray(log.t_s), handover.leg_forces(drive, log), compliance)
    legs = handover.leg_temperatures(drive, log)  # the held-out log's temperatures, where [thermal] has them
    thermal = None if legs is None else LegTemperatures(np.asarray(log.t_s), *legs)
    title = f"Validation of {platform.name} ({result['method']}) on {Path(args.log).name}"
    robot = robot_at(platform, drive.legs)
    return report_html(title, result, residuals, held, inputs, forces, verdict, robot, thermal)


def _summary(position: np.ndarray, orientation: np.ndarray | None, n: int) -> str:
    rms = lambda v: float(np.sqrt(np.nanmean(np.asarray(v) ** 2)))  # noqa: E731
    text = f"{n} rows: position RMS {rms(position):.4g} mm, max {np.nanmax(position):.4g} mm"
    if orientation is not None:
        text += f"; orientation RMS {rms(orientation):.4g}°, max {np.nanmax(orientation):.4g}°"
    return text


def main(argv: list[str] | None = None) -> int:
    return run_command("validate", argv)
