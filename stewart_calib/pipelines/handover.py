"""What a calibration hands on (spec §8), shared by ``calibrate``, ``validate``, ``compensate`` and
``export``: the calibrated platform file and model, the result's optional fields, the residuals per
measured channel and the HTML report.
"""

from __future__ import annotations

import dataclasses
import math
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__, io
from ..config import EstimatorConfig
from ..errors import CalibError
from ..estimate import Estimate
from ..instruments import instrument_kind
from ..io.platform_file import platform_to_toml
from ..model.drive import COMPLIANCE, THERMAL, DriveModel, drive_model
from ..model.platform import Platform

REPORT_PAGE = "index.html"


def created_now() -> str:
    """The time now, ISO 8601 UTC to the second (``2026-11-23T02:40:00Z``)."""
    return datetime.now(UTC).isoformat(timespec="seconds").replace("+00:00", "Z")


def check_report_dir(directory: Path | None, option: str = "--report") -> None:
    """Refuse before any work a report directory that cannot be made, or a missing matplotlib."""
    if directory is None:
        return
    if directory.exists() and not directory.is_dir():
        raise CalibError(f"{option} {directory}: exists and is not a directory")
    io.check_writable_directory(directory if directory.exists() else directory.parent, f"{option} {directory}")
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise CalibError(f"{option}: the report needs matplotlib (pip install 'stewart-calib[report]')") from None


def write_report(directory: Path, page: str) -> Path:
    """``directory/index.html`` (the directory is made if missing); atomic like every output."""
    with io.output_directory(directory, "--report") as made:
        io.atomic_write_text(made / REPORT_PAGE, page)
    return made / REPORT_PAGE


# ----------------------------------------------------------------------------- calibrated platform


def calibrated_platform(platform: Platform, estimate: Estimate, method: str, log_name: str, created: str) -> Platform:
    """``platform`` with the drive replaced by the estimate ``nominal + δM`` — and, where the
    calibration identified them, the stroke scale and the instrument's frame and target(s) — and
    a description saying where it came from (spec §8); every command takes it as a nominal platform."""
    note = (
        f"calibrated by stewart-calib {__version__} ({method}) from {log_name} on {created}; "
        f"nominal platform: {platform.name} ({platform.source})"
    )
    platform = drive_model(platform).calibrated_by(estimate).onto(platform)
    changes: dict[str, Any] = {"description": note}
    theta = estimate.block_values("instrument")
    if theta is not None and instrument_kind(platform).outside:  # the file has no [tracker] unknowns to write
        from ..instruments import outside_model

        changes["instrument"] = outside_model(platform).instrument_at(theta)
    return dataclasses.replace(platform, **changes)


def calibrated_model(platform: Platform, result_path: str | None) -> DriveModel:
    """The calibrated robot's drive: the result's (``nominal + error``, the values of the blocks it
    identified) on its nominal platform; the platform's own without a result (a calibrated
    platform file, spec §8) — and also when the platform given is the calibrated one the result
    wrote (its legs are the result's estimate; the result's blocks are taken as they are).

    Raises:
        CalibError: a result made for another platform.
    """
    if result_path is None:
        return drive_model(platform)
    result = io.read_result(result_path)
    gap = np.max(
        np.abs(np.array(result["estimate"]) - io.parameters_to_file(platform.drive.as_vector(), platform.drive))
    )
    if gap <= io.NOMINAL_TOLERANCE_MM and result["platform"] == platform.name:
        return io.calibrated_drive(platform, {**result, "error": [0.0] * len(result["error"])}, str(result_path))
    return io.read_calibrated_drive(result_path, platform)


def calibrated_platform_text(platform: Platform, estimate: Estimate, method: str, log_name: str, created: str) -> str:
    return platform_to_toml(calibrated_platform(platform, estimate, method, log_name, created))


# ----------------------------------------------------------------------------- residuals


def residual_rms_field(residuals) -> dict:
    """The result's ``"residual_rms"`` (spec §8): ``{"channels", "before", "after"}`` in file units."""
    from ..viz.html_report import rms

    def numbers(values: np.ndarray) -> list:
        return [float(v) if math.isfinite(v) else None for v in values]

    return {
        "channels": list(residuals.channels),
        "before": numbers(rms(residuals.before)),
        "after": numbers(rms(residuals.after)),
    }


def config_field(config: EstimatorConfig) -> dict:
    """The estimator settings as JSON (an infinite value, which JSON cannot hold, as ``null``)."""

    def clean(value):
        if isinstance(value, dict):
            return {k: clean(v) for k, v in value.items()}
        if isinstance(value, float) and not math.isfinite(value):
            return None
        return value

    return clean(dataclasses.asdict(config))


def covariance_field(estimate: Estimate, legs) -> list | None:
    """The covariance of every identified unknown in file units, in the order of ``parameter_names``
    then the blocks' names (spec §8; the compliance last, §10), or None when the method gives none;
    ``legs``: the drive's nominal leg model, which says which of its parameters files give in degrees."""
    drive_scale = io.parameter_file_scale(legs)  # a rotary drive's angles in degrees (spec §15)
    if estimate.full_covariance is None:
        if estimate.covariance is None:
            return None
        return (np.asarray(estimate.covariance, dtype=float) * np.outer(drive_scale, drive_scale)).tolist()
    scale = np.concatenate([drive_scale, *(block.file_scale for block in estimate.layout.blocks)])
    covariance = np.asarray(estimate.full_covariance, dtype=float) * np.outer(scale, scale)
    # spec §10, §17: the compliance after the other blocks, the expansion after it (the unknown vector
    # keeps the drive's blocks together)
    last = [np.r_[span] for span in (estimate.layout.slice(COMPLIANCE), estimate.layout.slice(THERMAL)) if span]
    if last:
        moved = np.concatenate(last)
        order = np.r_[np.delete(np.arange(len(covariance)), moved), moved]
        covariance = covariance[np.ix_(order, order)]
    return covariance.tolist()


def leg_forces(drive: DriveModel, log) -> np.ndarray:
    """``(N, legs)`` an elastic drive's axial leg forces [N] at its settled poses of a log's strokes, each
    row under its own input channels (compression > 0): what the report and the rerun recording show."""
    _, inputs = drive.settled_kinematics(log.strokes, log.inputs, strict=False)
    return inputs[:, drive.force_columns()]


# ----------------------------------------------------------------------------- singular statics


def singular_statics_row(err, platform_path: str, path: str, is_log: bool, skip_bad_rows: bool = False) -> CalibError:
    """A :class:`~stewart_calib.model.statics.SingularStatics` refusal naming the file and row of its pose.

    The estimators, the diagnosis and compensation meet the pose in a batch of their own (a block,
    evenly spaced samples), whose index names nothing a user can find: on this refusal alone the file
    is read again for the first row whose statics are singular — a log's at the instrument's pose
    (a tracker's forward kinematics of the readings) and at the rigid drive's forward kinematics of
    the strokes, a pose list's at its poses. Without such a row (standard input, or a pose off the
    nominal only) the refusal names the file."""
    from ..io.platform_file import load_platform
    from ..model import kinematics as kin
    from ..model.statics import SINGULAR_RATIO, statics_matrix, statics_ratios

    if path == "-":
        return CalibError(f"standard input: {err}")
    try:
        platform = load_platform(platform_path)
        legs = platform.prismatic_drive("the statics check")
        ratios = lambda R, t: statics_ratios(legs, statics_matrix(legs, R, t))  # noqa: E731
        if not is_log:
            done = 0
            for poses in io.read_pose_list_blocks(path):
                ratio = ratios(*kin.pose_to_rt(poses))
                bad = np.flatnonzero(~(ratio >= SINGULAR_RATIO))
                if bad.size:
                    return err.at(path, done + int(bad[0]) + 2, float(ratio[bad[0]]))  # the header is row 1
                done += len(poses)
            return CalibError(f"{path}: {err}")
        rigid = drive_model(dataclasses.replace(platform, elastic=None))
        reading_legs = instrument_kind(platform).reading_legs(platform)
        line = 1  # the header
        for block in io.read_log_blocks(path, platform, skip_bad_rows=skip_bad_rows):
            skipped = {row for row, _ in block.skipped}
            fits = [rigid.settled_kinematics(block.strokes, strict=False)[0]]
            if reading_legs is not None:
                fits.append(kin.forward_kinematics(reading_legs, block.readings, strict=False))
            ratio = np.full(len(block), np.inf)
            for fk in fits:  # the lower of the two poses' ratios, where their FK converged
                ratio[fk.converged] = np.minimum(ratio[fk.converged], ratios(fk.R[fk.converged], fk.t[fk.converged]))
            for k in range(len(block)):
                line += 1
                while line in skipped:
                    line += 1
                if ratio[k] < SINGULAR_RATIO:
                    return err.at(path, line, float(ratio[k]))
            line = max([line, *skipped])
    except CalibError:
        pass
    return CalibError(f"{path}: {err}")
