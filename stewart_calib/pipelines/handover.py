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
from ..samples import TEMPERATURE_C

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


def term_values(drive: DriveModel, key: str) -> np.ndarray | None:
    """``(legs,)`` the values of the drive's term ``key`` (the compliance c_i [mm/kN], the expansion α_i
    [ppm/K]): identified, or the platform's held value; None where the drive has no such term."""
    rows = [row for row, term in enumerate(drive.terms) if term.key == key]
    return drive.term_values()[rows[0]] if rows else None


def leg_temperatures(drive: DriveModel, log) -> tuple[np.ndarray, np.ndarray] | None:
    """``(temperatures (N, legs) [°C], growth (N, legs) [µm])`` of a thermal drive over a log: each leg's
    temperature and what it grew by there, the expansion term's part of its extension, ``α_i (T_i −
    T_ref) · 1e-6 · L_i`` (spec §17, the drive's α: identified, or ``[thermal]``'s held value) — what the
    report and the rerun recording show; None without ``[thermal]`` or without the log's temperatures."""
    rows = [row for row, term in enumerate(drive.terms) if term.key == THERMAL]
    temperatures = log.inputs.get(TEMPERATURE_C)
    if not rows or temperatures is None:
        return None
    term, alpha = drive.terms[rows[0]], drive.term_values()[rows[0]]
    inputs = drive.inputs_near(log.strokes, log.inputs)  # the growth needs no pose (the forces' columns do)
    growth_mm = alpha * term.gain * inputs[..., term.input_start : term.input_start + drive.rows]
    return np.asarray(temperatures, dtype=float), growth_mm * 1e3


# ----------------------------------------------------------------------------- the expansion against the legs


def trade_off_drive(drive: DriveModel) -> DriveModel | None:
    """``drive`` with every term an unknown (the stroke scale k_i too), where its expansion α_i is an
    unknown block (spec §17): at one temperature each leg's growth ``α_i ΔT (l_i + q_i)`` is a
    combination of the columns of ``l_i`` and ``k_i``, so the Cramér–Rao σ of α with ``k`` free is
    what the log's temperatures themselves tell of it (:func:`thermal_trade_off_line`); None
    without that block."""
    if not any(block.key == THERMAL for block in drive.blocks):
        return None
    return drive.identifying()


def temperature_span_K(channels) -> np.ndarray | None:
    """``(legs,)`` each leg's temperature span over the samples' channels (max − min) [K], or None
    where they carry no temperature."""
    temperatures = (channels or {}).get(TEMPERATURE_C)
    if temperatures is None or not len(temperatures):
        return None
    return np.ptp(np.asarray(temperatures, dtype=float), axis=0)


def thermal_trade_off_line(drive: DriveModel, stddev: dict, span_K: np.ndarray | None) -> str | None:
    """One warning line where the log's temperatures do not separate the legs' expansion from their
    lengths and stroke scale, else None.

    ``stddev``: the Cramér–Rao σ [ppm/K] of ``alpha1 …`` by name from the data alone with ``l_i`` and
    ``k_i`` free (:func:`trade_off_drive`; None or inf: not identified; a name absent: not judged). A
    leg's α is not separated where that σ exceeds the prior σ of ``[thermal]
    expansion_sigma_ppm_per_K``: the log then tells α less than the prior does (its information
    ``1/σ²`` below the prior's), and a calibration keeps it near the nominal — the threshold is the
    data's information against the prior's, which a log that spans (nearly) one temperature does
    not reach."""
    term = next((term for term in drive.terms if term.key == THERMAL and term.prior_sigma is not None), None)
    if term is None:
        return None
    prior = float(term.prior_sigma or 0.0)  # a held term (None) is no block: not reached
    judged = np.array([name in stddev for name in term.names])
    sigma = np.array([np.inf if stddev.get(name) is None else float(stddev[name]) for name in term.names])
    weak = judged & ~(sigma <= prior)
    if not weak.any():
        return None
    names = [name for name, w in zip(term.names, weak, strict=True) if w]
    shown = f"{names[0]}…{names[-1]}" if len(names) == len(term.names) else ", ".join(names)
    span = "no temperatures" if span_K is None else f"{float(np.max(span_K[weak])):.3g} K"
    seen = sigma[weak][np.isfinite(sigma[weak])]
    told = (
        "not identified by the data"
        if not seen.size
        else f"Cramér–Rao σ {float(np.min(seen)):.3g}–{float(np.max(seen)):.3g} ppm/K from the data"
    )
    return (
        f"warning: {shown} not separable from l_i and k_i: the log spans {span} (at one temperature "
        f"α_i ΔT (l_i + q_i) is a combination of l_i and k_i; {told}, above the prior σ {prior:g} ppm/K): "
        "the calibration keeps them near [thermal] expansion_ppm_per_K; a log over a warm-up separates them"
    )


def outside_stddev(drive, report: dict) -> dict:
    """An outside instrument's Cramér–Rao σ by name
    (:func:`~stewart_calib.estimators.batch.instrument_identifiability`), with the expansion's inf
    where its block is not identified (every σ is None where the rank is short, the block's own
    verdict then says whether it is among what the poses leave out)."""
    stddev = dict(report["predicted_stddev"])
    if report.get(f"{THERMAL}_identifiable") is not False:
        return {name: value for name, value in stddev.items() if value is not None}
    names = [name for term in drive.terms if term.key == THERMAL for name in term.names]
    return {**stddev, **{name: float("inf") for name in names}}


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
