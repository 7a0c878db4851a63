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
import sys
from pathlib import Path

import numpy as np

from .. import io
from .. import kinematics as kin
from ..diagnosis import diagnose_log
from ..drive import drive_model
from ..errors import CalibError
from ..instruments import instrument_kind
from ..platform import Platform, load_platform
from ..progress import log_progress_bar
from ..samples import Log
from . import handover, run_command


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
    parser.set_defaults(func=run)


def _block(result: dict, key: str, expected_names, source: str) -> np.ndarray | None:
    block = result.get(key)
    if block is None:
        return None
    if list(block["names"]) != list(expected_names):
        raise CalibError(
            f"{source}: key '{key}.names': expected {', '.join(expected_names)} for this platform's instrument, "
            f"got {', '.join(block['names'])}"
        )
    return np.array(block["estimate"], dtype=float)


def _model_poses(platform: Platform, result: dict, log, source: str, first_sample: int = 0):
    """FK poses of the logged strokes with the calibrated drive model; ``log``'s samples are
    numbered from ``first_sample`` (a block of a longer log)."""
    drive = io.calibrated_drive(platform, result, source)
    fk, _ = drive.settled_kinematics(log.strokes, log.load_kg, strict=False)  # each row at its own payload
    if not np.all(fk.converged):
        k = int(np.flatnonzero(~fk.converged)[0])
        raise CalibError(
            f"{source}: sample {first_sample + k + 1} of the log (t_s = {log.t_s[k]!r}): forward kinematics of the "
            "calibrated model did not converge for its strokes"
        )
    return fk.R, fk.t


def _check_nominal(platform: Platform, result: dict, source: str) -> None:
    gap = float(np.max(np.abs(np.array(result["nominal"]) - platform.drive.as_vector())))
    if gap > io.NOMINAL_TOLERANCE_MM:
        raise CalibError(
            f"{source}: key 'nominal': expected the nominal drive of platform '{platform.name}'; it differs by "
            f"{gap:.3g} mm"
        )


def validate(
    platform: Platform,
    result: dict,
    log,
    register: bool,
    result_source: str = "result",
    errors: bool = True,
    first_sample: int = 0,
):
    """Predictions and errors of a held-out log.

    Args:
        errors: False: the predictions alone (position and orientation errors None); for the
            tracker that spares forward kinematics of the readings.
        first_sample: the number of samples before ``log``'s when it is a block of a longer log
            (refusals name the sample in the whole log).
    Returns:
        ``(predicted (N, m) code units, position_error_mm (N,), orientation_error_deg (N,) or None)``.
    Raises:
        CalibError: a result for another platform or instrument, FK failure, a log that cannot be
            registered (with ``register``).
    """
    _check_nominal(platform, result, result_source)
    R_X, t_X = _model_poses(platform, result, log, result_source, first_sample)
    reading_legs = instrument_kind(platform).reading_legs
    if reading_legs is not None:
        if register:
            raise CalibError(
                "--register-instrument: the in-situ tracker is part of the robot; "
                "it has no frame of its own to fit again"
            )
        legs = reading_legs(platform)
        predicted = kin.inverse_kinematics(legs, R_X, t_X)
        if not errors:
            return predicted, None, None
        seen = kin.forward_kinematics(legs, log.readings, guess=(R_X, t_X), strict=False)
        if not np.all(seen.converged):
            k = int(np.flatnonzero(~seen.converged)[0])
            raise CalibError(
                f"sample {first_sample + k + 1} (t_s = {log.t_s[k]!r}): tracker forward kinematics of its readings "
                "did not converge"
            )
        position, orientation = kin.pose_error(seen.R, seen.t, R_X, t_X)
        return predicted, position, orientation

    from ..instruments.external import model_for

    model = model_for(platform)
    values = _block(result, "instrument", model.unknown_names, result_source)
    unknowns = model.nominal_unknowns() if values is None else model.unknowns_from_file(values)
    if register:
        unknowns = model.refit_frame(unknowns, R_X, t_X, log.readings)
    return model.prediction_errors(unknowns, R_X, t_X, log.readings)


def run(args: argparse.Namespace) -> int:
    report_dir = args.report and Path(args.report)
    handover.check_report_dir(report_dir)
    platform = load_platform(args.platform)
    result = io.read_result(args.result)
    columns = io.reading_columns(platform)
    header = ["t_s", *columns, *(f"pred_{name}" for name in columns), "position_error_mm"]
    if instrument_kind(platform).measures_orientation:
        header.append("orientation_error_deg")
    unseen = io.blank_reading_columns(columns)  # a target not seen: empty fields, read and predicted, and its error
    blank = (*(1 + j for j in unseen), *(1 + len(columns) + j for j in unseen), 1 + 2 * len(columns))
    page = moved = None
    with log_progress_bar(args.log, "validate") as bar:
        if report_dir or args.register_instrument:
            # the report plots, and the instrument frame is fitted to, the whole log
            log = _whole_log(platform, args.log, bar)
            diagnose_log(platform, log.strokes, log.readings, args.log, count=False)
            predicted, position, orientation = validate(
                platform, result, log, args.register_instrument, str(args.result)
            )
            if report_dir:
                page = _report_page(args, platform, result, log, predicted, position, orientation)
            io.write_csv_blocks(
                args.out, header, [_file_columns(log, predicted, position, orientation, columns)], blank
            )
        else:
            errors: list[tuple] = []
            first: list[Log] = []
            blocks = _validated_blocks(platform, result, args.log, str(args.result), bar, errors, first)
            io.write_csv_blocks(args.out, header, blocks, blank)
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
        print(f"stewart-calib validate: {_unseen_error_line(platform, result, position)}")
    sample = log if (report_dir or args.register_instrument) else first[0]
    pose_line = pose_error_summary(platform, result, sample, args.register_instrument, len(position), args.result)
    if pose_line:
        print(f"stewart-calib validate: {pose_line}", file=sys.stderr)
    if moved:
        print(f"stewart-calib validate: {moved}", file=sys.stderr)
    return 0


def _unseen_error_line(platform: Platform, result: dict, position_mm: np.ndarray) -> str:
    """What a check through an outside instrument's frame cannot see, beside what it saw: the
    frame (fitted with the drive, or again here) absorbs a constant pose error of the robot, so
    the robot's closed-loop (absolute) error is the result's prediction, not this RMS."""
    from ..accuracy import BAND_PROBABILITY, predicted_error

    seen_rms_mm = float(np.sqrt(np.nanmean(np.asarray(position_mm) ** 2)))
    head = (
        "a check through the instrument's calibrated frame cannot see the robot's closed-loop (absolute) "
        f"pose error (the frame absorbs a constant offset); position RMS here {seen_rms_mm:.4g} mm, "
    )
    predicted = result.get("predicted_closed_loop")
    if isinstance(predicted, dict) and predicted.get("available", True):
        band = predicted.get("position_band_mm")  # results written before the band have none
        return (
            head + f"the result predicts {predicted['position_mm']:.3g} mm / {predicted['orientation_deg']:.3g}° "
            f"where the robot works (expected mean over {predicted['poses']} {predicted['over']} poses"
            + (f"; {BAND_PROBABILITY:.0%} of such calibrations {band[0]:.3g}–{band[1]:.3g} mm)" if band else ")")
        )
    covariance = result.get("covariance")
    if covariance is None or platform.workspace is None:
        return head + "and the result holds no covariance to predict that error from"
    # the covariance's first rows: δM, then the drive's blocks the result has (spec §7, in the drive's order)
    n = len(result["error"]) + sum(
        len(result[term.key]["names"]) for term in drive_model(platform).terms if term.key in result
    )
    prediction = predicted_error(platform, np.asarray(covariance, dtype=float)[:n, :n])
    return head + f"the result's covariance predicts {prediction.describe()}"


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


def pose_errors(platform: Platform, result: dict, log, register: bool, source: str = "result") -> np.ndarray:
    """``(n, 4)``: each sample's measured minus predicted position ``x, y, z`` [mm] and the angle
    between the measured and predicted orientation [deg] (NaN for points, which give none); for
    the tracker in {J} (its forward kinematics of the readings against the model's of the
    strokes), for a pose in the instrument's axes, for points one row per target seen."""
    reading_legs = instrument_kind(platform).reading_legs
    if reading_legs is not None:
        R_X, t_X = _model_poses(platform, result, log, source)
        seen = kin.forward_kinematics(reading_legs(platform), log.readings, guess=(R_X, t_X), strict=False)
        keep = seen.converged
        _, orientation = kin.pose_error(seen.R[keep], seen.t[keep], R_X[keep], t_X[keep])
        return np.column_stack([seen.t[keep] - t_X[keep], orientation])
    from ..instruments.external import model_for

    predicted, _, orientation = validate(platform, result, log, register, source)
    difference = model_for(platform).position_differences(log.readings, predicted)
    return np.column_stack([difference, np.full(len(difference), np.nan) if orientation is None else orientation])


def pose_error_summary(platform: Platform, result: dict, sample, register: bool, n_rows: int, source) -> str | None:
    """:func:`pose_error_line` of the nominal and the calibrated model on ``sample`` (the log, or
    its first rows); None where a model cannot predict them (e.g. too few poses to fit a frame)."""
    try:
        outside = instrument_kind(platform).outside
        before = pose_errors(platform, nominal_model(platform), sample, outside, "the nominal platform")
        after = pose_errors(platform, result, sample, register, str(source))
    except CalibError:
        return None
    rows = f" (first {len(sample)} rows)" if len(sample) < n_rows else ""
    return pose_error_line(before, after, f"nominal → calibrated model{rows}")


def pose_error_line(before: np.ndarray, after: np.ndarray, models: str) -> str:
    """One line: the RMS of :func:`pose_errors` per axis and of the rotation, before → after."""
    rms = lambda v: float(np.sqrt(np.nanmean(v**2)))  # noqa: E731
    parts = [f"{axis} {rms(before[:, k]):.4g} → {rms(after[:, k]):.4g} mm" for k, axis in enumerate("xyz")]
    if np.isfinite(before[:, 3]).any():
        parts.append(f"rotation {rms(before[:, 3]):.4g} → {rms(after[:, 3]):.4g}°")
    return f"pose error RMS, {models}: {', '.join(parts)}"


def _file_columns(log: Log, predicted, position, orientation, columns) -> list[np.ndarray]:
    """V.csv's columns [file units] for the rows of ``log``."""
    return [
        log.t_s,
        *io.readings_in_file_units(log.readings, columns),
        *io.readings_in_file_units(predicted, columns),
        position,
        *([] if orientation is None else [orientation]),
    ]


def _whole_log(platform: Platform, path: str, bar) -> Log:
    """The log's times, strokes and readings (all :func:`validate` and the report use), read a
    block at a time, the ``bar`` ticked per block."""
    blocks = []
    for block in io.read_log_blocks(path, platform):
        blocks.append(Log(block.t_s, block.strokes, block.readings))
        bar.update(len(block))
    return Log.concatenate(blocks)


def _validated_blocks(platform: Platform, result: dict, path: str, result_source: str, bar, errors: list, first: list):
    """V.csv's columns a block of the log at a time (each row's prediction is its own), the ``bar``
    ticked per block; each block's ``(position, orientation)`` errors are appended to ``errors``
    and the blocks up to :data:`SAMPLE_ROWS` rows to ``first`` (then joined into one and diagnosed:
    :func:`~stewart_calib.diagnosis.diagnose_log`). A prediction refused is raised once the rest of
    the log is read, so that a bad row anywhere in it is refused first, as when the log was read whole."""
    blocks = io.read_log_blocks(path, platform)
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
        yield _file_columns(block, predicted, position, orientation, io.reading_columns(platform))
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


def measurement_residuals(
    platform: Platform,
    log: Log,
    result: dict,
    predicted: np.ndarray | None = None,
    log_label: str = "the calibration log",
):
    """Measured minus predicted per measurement column of the log (file units), with the nominal
    model (an outside instrument's frame registered on the log) and with the calibration ``result``
    — the predictions of ``validate`` (spec §7): the logged strokes through forward kinematics of the
    model, then what the instrument reads there
    (see :class:`~stewart_calib.viz.html_report.Residuals`). ``predicted``: the calibrated
    model's predictions [code units] when the caller has them (e.g. with a re-registered frame)."""
    from ..viz.html_report import Residuals  # matplotlib-free module, but only reports need it

    columns = io.reading_columns(platform)
    angle = np.array([name in io.MEASURED_ANGLE_COLUMNS for name in columns])

    def residual_file_units(predicted_code: np.ndarray) -> np.ndarray:
        difference = log.readings - predicted_code
        wrapped = np.where(angle, (difference + np.pi) % (2 * np.pi) - np.pi, difference)  # 359° off is 1° off
        return wrapped * np.where(angle, 180.0 / np.pi, 1.0)

    nominal = nominal_model(platform)
    outside = instrument_kind(platform).outside
    if predicted is None and not outside:
        residuals = tracker_residuals(platform, log, [(nominal, "the nominal platform"), (result, "the result")])
        if residuals is not None:  # else an FK failed: validate() below words it
            before, after = residuals
            return Residuals(tuple(columns), np.asarray(log.t_s), before, after, log_label, "the nominal platform")
    if predicted is None:
        predicted = validate(platform, result, log, False, "the result", errors=False)[0]
    # An outside instrument's frame is rarely known to centimetres (spec §7): "before" registers it
    # on the log, so that it measures the nominal robot, not where the cameras happen to stand.
    before = residual_file_units(validate(platform, nominal, log, outside, "the nominal platform", errors=False)[0])
    before_model = "the nominal platform" + (", its instrument frame fitted to this log" if outside else "")
    return Residuals(
        tuple(columns), np.asarray(log.t_s), before, residual_file_units(predicted), log_label, before_model
    )


def nominal_model(platform: Platform) -> dict:
    """The nominal platform as a calibration result (no error): what "before" predicts with."""
    return {"nominal": platform.drive.as_vector().tolist(), "error": [0.0] * len(platform.drive.as_vector())}


def tracker_residuals(platform: Platform, log: Log, models: list[tuple[dict, str]]) -> np.ndarray | None:
    """The tracker's readings minus its readings predicted by each ``(result, source)`` model, as
    :func:`validate`'s predictions (within FK's tolerance) in one compiled pass over the log:
    ``(len(models), N, 6)`` [mm], or None when a model's FK does not converge for a sample or the
    drive is elastic."""
    for result, source in models:
        _check_nominal(platform, result, source)
    drives = [io.calibrated_drive(platform, result, source) for result, source in models]
    if any(drive.elastic is not None for drive in drives):
        return None  # the forces need the pose first: validate()'s settled kinematics
    extensions = [drive.extensions(drive.inputs(log.strokes)) for drive in drives]
    residuals, converged = kin.tracker_reading_residuals(
        platform.required_tracker("the tracker residuals"), log.readings, [drive.legs for drive in drives], extensions
    )
    return residuals if converged.all() else None


def _report_page(args, platform: Platform, result: dict, log, predicted, position, orientation) -> str:
    """The ``--report`` page: the held-out errors and residuals per channel, then the calibration's own
    sections (parameters ± σ, correlations, conditioning, config, versions) from the result."""
    from ..viz.html_report import HeldOut, report_html

    held = HeldOut(str(args.log), np.asarray(log.t_s), position, orientation, args.register_instrument)
    residuals = measurement_residuals(platform, log, result, predicted, "the held-out log")
    inputs = {"platform file": str(args.platform), "result": str(args.result), "held-out log": str(args.log)}
    return report_html(
        f"Validation of {platform.name} ({result['method']}) on {Path(args.log).name}", result, residuals, held, inputs
    )


def _summary(position: np.ndarray, orientation: np.ndarray | None, n: int) -> str:
    rms = lambda v: float(np.sqrt(np.nanmean(np.asarray(v) ** 2)))  # noqa: E731
    text = f"{n} rows: position RMS {rms(position):.4g} mm, max {np.nanmax(position):.4g} mm"
    if orientation is not None:
        text += f"; orientation RMS {rms(orientation):.4g}°, max {np.nanmax(orientation):.4g}°"
    return text


def main(argv: list[str] | None = None) -> int:
    return run_command("validate", argv)
