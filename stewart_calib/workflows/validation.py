"""How well a calibration result predicts a log (spec §7): the library under ``stewart-calib
validate`` and the residuals ``calibrate`` reports.

For every row: the platform pose from forward kinematics of the logged strokes with the
calibrated drive (``nominal + error`` and the values of the drive's blocks the result identified),
then what the instrument should have read — through the result's instrument frame and target(s),
or with ``register`` through a frame fitted again on the log (the instrument was moved between
sessions; the robot's model is not touched). For the in-situ tracker the prediction is its readings
at that pose, and the measured pose its own forward kinematics of the logged readings.
"""

from __future__ import annotations

import collections
import concurrent.futures
import math
import re
import statistics
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from .. import io
from ..errors import CalibError, number
from ..estimators import method_names
from ..instruments import instrument_kind
from ..io.platform_file import load_platform
from ..model import kinematics as kin
from ..model.drive import tracker_reading_residuals
from ..model.platform import LegGeometry, Platform
from ..samples import Log


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
    fk, _ = drive.settled_kinematics(log.strokes, log.inputs, strict=False)  # each row at its own payload
    if not np.all(fk.converged):
        k = int(np.flatnonzero(~fk.converged)[0])
        raise CalibError(
            f"{source}: sample {first_sample + k + 1} of the log (t_s = {number(log.t_s[k])}): forward kinematics "
            "of the calibrated model did not converge for its strokes"
        )
    return fk.R, fk.t


def _check_nominal(platform: Platform, result: dict, source: str) -> None:
    gap = io.nominal_gap(result, platform)  # in file units: a rotary drive's angles in degrees
    if gap > io.NOMINAL_TOLERANCE_MM:
        raise CalibError(
            f"{source}: key 'nominal': expected the nominal drive of platform '{platform.name}'; it differs by "
            f"{gap:.3g} {io.parameter_unit(platform.drive)}"
        )


def wrote_platform(platform: Platform, result: dict) -> bool:
    """Whether ``platform`` is the calibrated platform file that ``result`` wrote (spec §8): its
    legs are the result's estimate."""
    estimate = np.asarray(result["estimate"], dtype=float)
    drive = io.parameters_to_file(platform.drive.as_vector(), platform.drive)  # a result's units
    if estimate.shape != drive.shape or result.get("platform") != platform.name:
        return False
    return float(np.max(np.abs(estimate - drive))) <= io.NOMINAL_TOLERANCE_MM


def on_platform(platform: Platform, result: dict) -> dict:
    """``result`` as a result on ``platform``: itself, or where ``platform`` is the calibrated
    platform file that result wrote (:func:`wrote_platform`), the result with no error left on it —
    as ``compensate`` and ``export`` take it; the blocks as they are."""
    if not wrote_platform(platform, result):
        return result
    drive = io.parameters_to_file(platform.drive.as_vector(), platform.drive)
    return {**result, "nominal": drive.tolist(), "error": [0.0] * len(drive)}


#: how a calibrated platform file's ``description`` names its nominal platform (spec §8)
_NOMINAL_NAMED = re.compile(r"; nominal platform: (?P<name>.*) \((?P<file>.*)\)$")


def nominal_platform_of(platform: Platform, result: dict) -> tuple[Platform | None, str]:
    """``(nominal, where)``: for the calibrated platform file ``result`` wrote, the nominal platform
    its ``description`` names ("…; nominal platform: NAME (FILE)", spec §8) — the file, else the
    shipped platform NAME — where it holds the result's nominal drive, and ``(None, what was
    looked for)`` where none does; for any other platform, ``(platform, "")``: its drive is the
    nominal one. The "before" of a comparison is this platform's: the calibrated file's own drive
    is the calibrated model."""
    if not wrote_platform(platform, result):
        return platform, ""
    named = _NOMINAL_NAMED.search(platform.description or "")
    if named is None:
        return None, "its description names no nominal platform"
    for where in (named["file"], named["name"]):
        try:
            candidate = load_platform(where)
        except CalibError:
            continue
        if candidate.name == result.get("platform") and io.nominal_gap(result, candidate) <= io.NOMINAL_TOLERANCE_MM:
            return candidate, where
    return None, f"the nominal platform it names ({named['file']}) is not found or holds another drive"


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
    legs = instrument_kind(platform).reading_legs(platform)
    if legs is not None:
        if register:
            raise CalibError(
                "--register-instrument: the in-situ tracker is part of the robot; "
                "it has no frame of its own to fit again"
            )
        predicted = kin.inverse_kinematics(legs, R_X, t_X)
        if not errors:
            return predicted, None, None
        seen = kin.forward_kinematics(legs, log.readings, guess=(R_X, t_X), strict=False)
        if not np.all(seen.converged):
            k = int(np.flatnonzero(~seen.converged)[0])
            raise CalibError(
                f"sample {first_sample + k + 1} (t_s = {number(log.t_s[k])}): tracker forward kinematics of its "
                "readings did not converge"
            )
        position, orientation = kin.pose_error(seen.R, seen.t, R_X, t_X)
        return predicted, position, orientation

    from ..instruments import outside_model

    model = outside_model(platform)
    values = _block(result, "instrument", model.unknown_names, result_source)
    unknowns = model.nominal_unknowns() if values is None else model.unknowns_from_file(values)
    if register:
        unknowns = model.refit_frame(unknowns, R_X, t_X, log.readings)
    return model.prediction_errors(unknowns, R_X, t_X, log.readings)


@dataclass(frozen=True)
class NoiseSquares:
    """What the noise alone adds to the mean square of a check's errors over its rows — position
    [mm²] or orientation [deg²] — and how it spreads: the mean square measured is ``B + mean``, ``B``
    the robot's own, with variance ``variance + cross · B`` (the noise's own square, then its product
    with the robot's error, spread evenly over the rows)."""

    mean: float
    variance: float
    cross: float

    @property
    def rms(self) -> float:
        """The RMS the noise alone leaves [mm or deg]."""
        return math.sqrt(self.mean)

    def beyond(self, rms: float, probability: float) -> tuple[float, tuple[float, float]]:
        """The robot's own RMS in a measured ``rms`` (in quadrature; 0 where the noise explains it all)
        and its two-sided ``probability`` interval from the noise's spread over the rows (normal in the
        mean square: many rows). A measured RMS below the noise's is read as the noise's: the interval's
        top is then what the noise's spread lets a robot of no error of its own hide, ``√(z σ₀)`` with
        ``σ₀² = variance`` — a measurement the noise happened to lower says nothing smaller of the robot."""
        own = rms**2 - self.mean
        # the standard library's normal quantile: calibrate imports this module, and keeps scipy.stats out of
        # its start-up (tests/test_scale.py)
        z = statistics.NormalDist().inv_cdf(0.5 + probability / 2)
        spread = lambda square: z * math.sqrt(self.variance + self.cross * square)  # noqa: E731
        seen = max(own, 0.0)
        return math.sqrt(seen), (math.sqrt(max(own - spread(seen), 0.0)), math.sqrt(seen + spread(seen)))


#: the rows of a log whose poses the noise's statistics are computed at (a long log's start stands for
#: it: they scale to its length)
NOISE_ROWS = 2000


def noise_squares(
    platform: Platform,
    result: dict,
    log: Log,
    register: bool,
    rows: int,
    reading_sigma_mm: float,
    stroke_sigma_mm: float,
) -> tuple[NoiseSquares, NoiseSquares | None]:
    """What the noise alone adds to :func:`validate`'s mean squared position [mm²] and orientation
    [deg²] errors (None where the instrument gives none) over a log of ``rows`` rows whose first are
    ``log``'s, to first order.

    Through an outside instrument its readings' residual ``e = (I − H) n`` (``n`` the noise of σ_j a
    component, ``H`` the hat matrix of the frame fitted again with ``register``, else 0 — the frame the
    calibration fitted is the result's, its error part of the result's prediction): the mean square
    ``eᵀ W e`` (``W`` :meth:`~stewart_calib.instruments.external.OutsideModel.error_weights` over the
    rows) has mean ``tr((I − H) D)`` and variance ``2 tr(((I − H) D)²)``, ``D = diag(σ² W)``; the fit
    absorbs 6 of the noise's degrees of freedom, a share of each row's. Through the in-situ tracker
    each row's position (and orientation) noise is its forward kinematics' of readings of
    ``reading_sigma_mm`` beside the drive's of strokes of ``stroke_sigma_mm`` (a servo's angle noise is
    the drive model's own, spec §15): ``σ² (JᵀJ)⁻¹`` each, the 3 × 3 blocks ``P`` of a row, mean
    ``tr P``, variance ``2 tr P²``. The statistics are taken at the first :data:`NOISE_ROWS` rows'
    poses and scaled to ``rows`` (the fit's leverage ``H`` inversely with them).

    Raises:
        CalibError: as :func:`validate` (forward kinematics of the calibrated model).
    """
    sample = log.select(slice(0, NOISE_ROWS))
    n, scale = len(sample), len(sample) / rows  # ``scale``: a row's share of the log, against the sample's
    R_X, t_X = _model_poses(platform, result, sample, "result")
    legs = instrument_kind(platform).reading_legs(platform)
    if legs is not None:
        covariance = kin.pose_covariance_from_legs(legs, R_X, t_X, reading_sigma_mm)
        if isinstance(platform.drive, LegGeometry):
            covariance = covariance + kin.pose_covariance_from_legs(platform.drive, R_X, t_X, stroke_sigma_mm)
        blocks = (covariance[:, 3:, 3:], np.degrees(1.0) ** 2 * covariance[:, :3, :3])
        return tuple(  # type: ignore[return-value]
            NoiseSquares(
                float(np.mean(np.trace(P, axis1=-2, axis2=-1))),
                2.0 * scale * float(np.mean(np.einsum("nij,nji->n", P, P))) / n,
                4.0 * scale * float(np.mean(np.trace(P, axis1=-2, axis2=-1))) / (3.0 * n),
            )
            for P in blocks
        )

    from ..instruments import outside_model

    model = outside_model(platform)
    values = _block(result, "instrument", model.unknown_names, "result")
    unknowns = model.nominal_unknowns() if values is None else model.unknowns_from_file(values)
    e, _, H_u = model.readings_residual(unknowns, sample.readings, R_X, t_X, jacobians=register)
    seen = np.isfinite(e)
    sigma = np.broadcast_to(model.channel_sigma, e.shape)[seen]
    leverage = np.zeros_like(sigma)
    if register:  # the frame's hat matrix, its leverage on the whole log's rows a row's share of the sample's
        A = (H_u[..., :6] / model.channel_sigma[:, None])[seen]
        G_inv = np.linalg.inv(A.T @ A)
        leverage = scale * np.einsum("ji,ik,jk->j", A, G_inv, A)

    def squares(weights: np.ndarray) -> NoiseSquares:
        w = weights[seen] / n
        D = sigma**2 * w
        hat = 0.0
        if register:
            B = A.T @ (D[:, None] * A)
            hat = scale**2 * float(np.trace(G_inv @ B @ G_inv @ B))
        variance = 2.0 * (scale * np.sum(D**2) - 2.0 * scale * np.sum(leverage * D**2) + hat)
        return NoiseSquares(
            float(np.sum(D * (1.0 - leverage))),
            float(variance),
            4.0 * scale * float(np.sum(w**2 * sigma**2) / np.sum(w)),
        )

    position, orientation = model.error_weights(seen)
    return squares(position), None if orientation is None else squares(orientation)


def pose_errors(platform: Platform, result: dict, log, register: bool, source: str = "result") -> np.ndarray:
    """``(n, 4)``: each sample's measured minus predicted position ``x, y, z`` [mm] and the angle
    between the measured and predicted orientation [deg] (NaN for points, which give none); for
    the tracker in {J} (its forward kinematics of the readings against the model's of the
    strokes), for a pose in the instrument's axes, for points one row per target seen."""
    reading_legs = instrument_kind(platform).reading_legs(platform)
    if reading_legs is not None:
        R_X, t_X = _model_poses(platform, result, log, source)
        seen = kin.forward_kinematics(reading_legs, log.readings, guess=(R_X, t_X), strict=False)
        keep = seen.converged
        _, orientation = kin.pose_error(seen.R[keep], seen.t[keep], R_X[keep], t_X[keep])
        return np.column_stack([seen.t[keep] - t_X[keep], orientation])
    from ..instruments import outside_model

    predicted, _, orientation = validate(platform, result, log, register, source)
    difference = outside_model(platform).position_differences(log.readings, predicted)
    return np.column_stack([difference, np.full(len(difference), np.nan) if orientation is None else orientation])


def pose_error_summary(platform: Platform, result: dict, sample, register: bool, n_rows: int, source) -> str | None:
    """:func:`pose_error_line` of the nominal and the calibrated model on ``sample`` (the log, or
    its first rows); None where a model cannot predict them (e.g. too few poses to fit a frame)."""
    compared = compared_pose_errors(platform, result, sample, register, n_rows, source)
    return None if compared is None else compared[0]


def compared_pose_errors(
    platform: Platform,
    result: dict,
    sample,
    register: bool,
    n_rows: int,
    source,
    held_out: bool = False,
    moved: bool = False,
) -> tuple[str, str | None] | None:
    """``(line, warning)``: :func:`pose_error_summary`'s line and, where the two models are compared
    alike (the in-situ tracker's absolute poses, or an outside instrument registered on ``sample`` for
    both) and the calibrated model predicts it worse, the loud line saying so (:func:`no_better_line`);
    None where a model cannot predict them. The line's "before" is the nominal model's plain
    registration; the test's, its σ-weighted one, as the calibrated model's.

    ``held_out``: ``sample`` is not the calibration's log, so without ``register`` the calibrated model
    reads it through the calibration's instrument frame and target(s) while the nominal model's are fitted
    to it — the line names each side's. ``moved``: that frame looks moved since the calibration
    (``validate``'s hint), its errors the move's: the line gives the nominal model's alone, not set beside
    them as a comparison."""
    outside = instrument_kind(platform).outside
    try:
        plain = registered_nominal_model(platform, sample)
        before = pose_errors(platform, plain, sample, False, "the nominal platform")
        after = pose_errors(platform, result, sample, register, str(source))
        # the paired test weighs both models' registrations alike: the calibrated model's is the σ-weighted one
        alike = registered_nominal_model(platform, sample, plain=False) if outside and register else None
        before_alike = before if alike is None else pose_errors(platform, alike, sample, False, "the nominal platform")
    except CalibError:
        return None
    rows = f" (first {len(sample)} rows)" if len(sample) < n_rows else ""
    through_calibration = held_out and outside and not register
    if through_calibration and moved:
        line = pose_error_line(
            before, None, f"nominal model{rows}, its instrument frame and target(s) fitted to this log"
        )
        return (
            line + "; not set beside the calibrated model's, which through the calibration's instrument frame "
            "measure that frame's move since (add --register-instrument to compare the two alike)",
            None,
        )
    sides = (
        " (nominal: instrument frame and target(s) fitted to this log; calibrated: through the calibration's)"
        if through_calibration
        else ""
    )
    line = pose_error_line(before, after, f"nominal → calibrated model{rows}{sides}")
    if outside and not register:  # the calibrated model through the calibration's frame: not alike
        return line, None
    return line, no_better_line(before_alike, after, outside, rows, before)


#: the one-sided tail of :func:`no_better_line`'s paired test: two models that predict a log
#: equally well are called one worse than the other in 1 % of logs
WORSE_TAIL = 0.01


def no_better_line(
    before: np.ndarray, after: np.ndarray, registered: bool, rows: str = "", shown: np.ndarray | None = None
) -> str | None:
    """The loud line when the calibrated model predicts a log worse than the nominal model, None
    otherwise: on data the fit never saw, a calibration that improves the robot fits better.

    Worse is a paired test over the rows of :func:`pose_errors` (the same poses, the same noise in
    both): each row's squared position error with the calibrated model less the nominal model's, their
    mean above zero by more than the :data:`WORSE_TAIL` quantile of its standard error. A log whose
    poses the two models predict alike within the noise (a nominal model already as good there) is
    no evidence either way: comparing the two RMS alone called such a calibration worse in half of
    such logs.

    ``before`` are the nominal model's errors the test takes (``registered``: through the instrument
    registered by its σ, as the calibrated model's); ``shown``, those of the pose error line
    (:func:`pose_error_line`, a plain registration; default ``before``), which the line quotes, so that
    the figures a user reads agree, and names the test that decided with its own figure."""
    squares = lambda v: np.sum(v[:, :3] ** 2, axis=1)  # noqa: E731
    difference = squares(after) - squares(before)
    difference = difference[np.isfinite(difference)]
    if difference.size < 2:
        return None
    margin = (
        statistics.NormalDist().inv_cdf(1 - WORSE_TAIL) * float(np.std(difference, ddof=1)) / math.sqrt(difference.size)
    )
    if not float(np.mean(difference)) > margin:
        return None
    rms = lambda v: float(np.sqrt(np.nanmean(squares(v))))  # noqa: E731
    shown = before if shown is None else shown
    alike = (
        f", both models through the instrument registered on this log by its σ (the nominal model's RMS so "
        f"{rms(before):.4g} mm)"
        if registered
        else ""
    )
    return (
        f"WARNING: the calibrated model predicts this log{rows} no better than the nominal model: position RMS "
        f"{rms(after):.4g} mm against the nominal model's {rms(shown):.4g} mm (the pose error line's); a paired test "
        f"of each row's squared position error{alike} finds the calibrated model's larger (one-sided, "
        f"{WORSE_TAIL:.0%}); the calibration likely left the robot worse: keep the nominal model, or calibrate again "
        "on poses that tilt and reach to the workspace's edges (stewart-calib plan)"
    )


def pose_error_line(before: np.ndarray, after: np.ndarray | None, models: str) -> str:
    """One line: the RMS of :func:`pose_errors` per axis and of the rotation, before → after (``after``
    None: the one model's)."""
    rms = lambda v: float(np.sqrt(np.nanmean(v**2)))  # noqa: E731
    pair = lambda k: f"{rms(before[:, k]):.4g}" + ("" if after is None else f" → {rms(after[:, k]):.4g}")  # noqa: E731
    parts = [f"{axis} {pair(k)} mm" for k, axis in enumerate("xyz")]
    if np.isfinite(before[:, 3]).any():
        parts.append(f"rotation {pair(3)}°")
    return f"pose error RMS, {models}: {', '.join(parts)}"


def measurement_residuals(
    platform: Platform,
    log: Log,
    result: dict,
    predicted: np.ndarray | None = None,
    log_label: str = "the calibration log",
):
    """Measured minus predicted per measurement column of the log (file units), with the nominal
    model (an outside instrument's frame and target(s) at their best registration on the log) and
    with the calibration ``result`` — the predictions of ``validate`` (spec §7): the logged strokes
    through forward kinematics of the model, then what the instrument reads there
    (see :class:`~stewart_calib.viz.html_report.Residuals`). ``predicted``: the calibrated
    model's predictions [code units] when the caller has them (e.g. with a re-registered frame)."""
    from ..viz.html_report import Residuals  # matplotlib-free module, but only reports need it

    columns = io.reading_columns(platform)
    angles = io.angle_columns(platform)
    angle = np.array([name in angles for name in columns])

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
    # An outside instrument's frame and target(s) are rarely known to centimetres (spec §7): "before"
    # registers them on the log, as the calibration fits them, so that it measures the nominal robot,
    # not where the cameras happen to stand or where the rigid body's origin was put.
    if outside:
        nominal = registered_nominal_model(platform, log)
    before = residual_file_units(validate(platform, nominal, log, False, "the nominal platform", errors=False)[0])
    fitted = ", its instrument frame and target(s) fitted to this log" if outside else ""
    before_model = "the nominal platform" + fitted
    return Residuals(
        tuple(columns), np.asarray(log.t_s), before, residual_file_units(predicted), log_label, before_model
    )


def nominal_model(platform: Platform) -> dict:
    """The nominal platform as a calibration result (no error): what "before" predicts with."""
    nominal = io.parameters_to_file(platform.drive.as_vector(), platform.drive)  # a result's units
    return {"nominal": nominal.tolist(), "error": [0.0] * len(nominal)}


def registered_nominal_model(platform: Platform, log, plain: bool = True) -> dict:
    """:func:`nominal_model` with an outside instrument's frame and target(s) at their best
    registration on ``log`` (:meth:`~stewart_calib.instruments.OutsideModel.best_registration`): the
    nominal robot with the same instrument unknowns fitted as a calibration fits. ``plain``: by
    unweighted least squares in SI units, the "before" of every comparison a person reads (where
    the nominal model misses the rotations too, the σ-weighted registration trades them for a
    smaller position error than a user's own registration shows); else weighed by the instrument's
    σ, the optimum of the whitened residual that a χ² test compares with. A leg-set tracker has none: the nominal model
    itself.

    Raises:
        CalibError: the log cannot be registered, or the nominal model's FK fails for a sample.
    """
    nominal = nominal_model(platform)
    if not instrument_kind(platform).outside:
        return nominal
    from ..instruments import outside_model

    model = outside_model(platform)
    R_X, t_X = _model_poses(platform, nominal, log, "the nominal platform")
    unknowns = model.best_registration(R_X, t_X, log.readings, plain=plain)
    block = {"names": list(model.unknown_names), "estimate": model.file_values(unknowns).tolist()}
    return {**nominal, "instrument": block}


#: the tail of the χ² test of :func:`unsupported_correction`: a right nominal model is called
#: unsupported by its log in 1 % of logs
NO_EVIDENCE_TAIL = 0.01


def _whitened_squares(platform: Platform, result: dict, log, source: str) -> tuple[float, int]:
    """The sum of squares of an outside instrument's whitened residuals (its model's: rotation
    vectors, not Euler differences) with ``result``'s drive and instrument, and their number."""
    from ..instruments import outside_model

    model = outside_model(platform)
    R_X, t_X = _model_poses(platform, result, log, source)
    values = _block(result, "instrument", model.unknown_names, source)
    unknowns = model.nominal_unknowns() if values is None else model.unknowns_from_file(values)
    e = model.readings_residual(unknowns, log.readings, R_X, t_X)[0] / model.channel_sigma
    finite = np.isfinite(e)
    return float(np.sum(e[finite] ** 2)), int(finite.sum())


def unsupported_correction(
    platform: Platform, result: dict, log, rank: int, correction_mm: float
) -> tuple[str, str] | None:
    """``(the loud line, the verdict's words)`` when an outside instrument's log gives no evidence that
    the nominal model is wrong, None otherwise (or for a leg-set tracker).

    The calibration fits ``rank`` unknowns where the nominal model's σ-weighted registration
    (:func:`registered_nominal_model`) fits the instrument's alone; were the nominal model right, the
    fall of the whitened sum of squares, over the calibrated fit's own noise scale
    ``s² = SS_after / (rows − rank)``, is χ² with as many degrees of freedom as the drive's share.
    Below its :data:`NO_EVIDENCE_TAIL` quantile the calibration's ``correction_mm`` (how far it
    moves the robot) rests on noise: the calibrated robot is likely further from its poses than
    the nominal one. Below zero the calibrated model fits its own log worse than the nominal one
    registered to it: that is no verdict on the nominal model but on the estimate, which stopped
    short of the log's optimum (an online filter's single pass linearised far from it).
    """
    if not instrument_kind(platform).outside:
        return None
    from ..chi_square import chdtri
    from ..instruments import outside_model

    dof = rank - len(outside_model(platform).unknown_names)
    try:
        nominal = registered_nominal_model(platform, log, plain=False)
        before, _ = _whitened_squares(platform, nominal, log, "the nominal platform")
        after, rows = _whitened_squares(platform, result, log, "the result")
    except CalibError:
        return None
    if dof <= 0 or rows <= rank or not after > 0:
        return None
    fall = (before - after) / (after / (rows - rank))
    threshold = chdtri(dof, NO_EVIDENCE_TAIL)
    if fall >= threshold:
        return None
    if fall < 0.0:
        method = result.get("method", "")
        remedy = (
            "check that the log is this robot's (its platform file, the strokes' zeros and units)"
            if method in method_names(online=False)
            else "calibrate this log with --method ls, which iterates to its optimum"
        )
        return (
            f"WARNING: the calibrated model fits its own log worse than the nominal model registered to it "
            f"(the sum of squares of its σ-weighted residuals is {after / before:.3g}× the nominal model's): the "
            f"{method} estimate stopped short of the log's optimum and moves "
            f"the robot by {correction_mm:.3g} mm that the log does not support, so it is likely worse than the "
            f"nominal one; {remedy}",
            "the calibrated model fits its own log worse than the nominal one",
        )
    return (
        f"WARNING: the log gives no evidence that the nominal model is wrong — fitting the drive's {dof} "
        f"unknowns lowers the residuals by χ² {fall:.3g}, where a right nominal model's fall below "
        f"{threshold:.3g} in {1 - NO_EVIDENCE_TAIL:.0%} of logs; the calibrated model moves the robot by "
        f"{correction_mm:.3g} mm on noise and is likely worse than the nominal one: keep the nominal model, "
        "or log poses whose errors the instrument can see beyond its noise",
        "the log gives no evidence the calibration improves on the nominal model",
    )


def tracker_residuals(platform: Platform, log: Log, models: list[tuple[dict, str]]) -> np.ndarray | None:
    """The tracker's readings minus its readings predicted by each ``(result, source)`` model, as
    :func:`validate`'s predictions (within FK's tolerance; an elastic drive settled under each row's
    input channels) in one compiled pass over the log: ``(len(models), N, rulers)`` [mm], or None when
    a model's FK does not converge for a sample."""
    for result, source in models:
        _check_nominal(platform, result, source)
    drives = [io.calibrated_drive(platform, result, source) for result, source in models]
    tracker = platform.required_tracker("the tracker residuals")
    residuals, converged = tracker_reading_residuals(drives, tracker, log.strokes, log.readings, log.inputs)
    return residuals if converged.all() else None


def nominal_residuals(platform: Platform, block: Log) -> np.ndarray:
    """``(len(block), rulers)`` the tracker's readings minus what the nominal model predicts [mm], NaN
    where its FK fails: the residual RMS "before", which needs no estimate, so is spooled with the
    samples on the first pass (on the read-ahead thread) and only the calibrated model's is left
    for the second."""
    before = tracker_residuals(platform, block, [(nominal_model(platform), "the nominal platform")])
    return np.full(block.readings.shape, np.nan) if before is None else before[0]


#: blocks whose residuals :func:`streamed_residual_rms` computes at a time (on as many threads)
RESIDUAL_THREADS = 2

T = TypeVar("T")
U = TypeVar("U")


def in_order(
    pool: concurrent.futures.Executor, function: Callable[[T], U], items: Iterable[T], ahead: int
) -> Iterator[U]:
    """``function`` of each item, in order, computed by ``pool`` with at most ``ahead`` items in flight
    (``pool.map`` would take every item at once: a whole log's blocks in memory)."""
    pending: collections.deque = collections.deque()
    for item in items:
        pending.append(pool.submit(function, item))
        if len(pending) >= ahead:
            yield pending.popleft().result()
    while pending:
        yield pending.popleft().result()


def streamed_residual_rms(
    platform: Platform, spooled: Iterable[tuple[Log, np.ndarray]], result: dict, rejected: list[int]
) -> dict:
    """The result's ``"residual_rms"`` field (:func:`~stewart_calib.pipelines.handover.residual_rms_field`)
    of a streamed tracker log without its ``rejected`` samples, from the ``(block, before)`` pairs of
    its :class:`~stewart_calib.workflows.calibration.SampleSpool` (``before``: the :func:`nominal_residuals` of
    each sample): the calibrated model's residuals are computed here, and the per-channel sums of
    squares add up over the blocks.
    """
    sums, counts = {"before": 0.0, "after": 0.0}, {"before": 0, "after": 0}
    left_out = np.asarray(rejected, dtype=np.int64)

    def used_rows() -> Iterator[tuple[Log, np.ndarray]]:
        k = 0
        for block, before in spooled:
            used = ~np.isin(k + np.arange(len(block)), left_out)
            k += len(block)
            if used.any():
                yield block.select(used), before[used]

    def residuals(used: tuple[Log, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        block, before = used
        after = tracker_residuals(platform, block, [(result, "the result")])
        if after is None or np.isnan(before).any():  # an FK failed: validate's path words it
            residuals = measurement_residuals(platform, block, result)
            return residuals.before, residuals.after
        return before, after[0]

    # two blocks at a time: their FK is compiled code that lets go of the GIL, so a second core halves it
    with concurrent.futures.ThreadPoolExecutor(RESIDUAL_THREADS) as pool:
        for before, after in in_order(pool, residuals, used_rows(), RESIDUAL_THREADS):
            for when, values in (("before", before), ("after", after)):
                finite = np.isfinite(values)
                sums[when] = sums[when] + np.sum(np.where(finite, values, 0.0) ** 2, axis=0)
                counts[when] = counts[when] + finite.sum(axis=0)
    field: dict[str, list] = {"channels": list(io.reading_columns(platform))}
    for when in ("before", "after"):
        with np.errstate(invalid="ignore", divide="ignore"):
            rms = np.sqrt(sums[when] / counts[when])
        field[when] = [float(v) if math.isfinite(v) else None for v in rms]
    return field
