"""What a calibration leaves where the robot works: the predicted closed-loop pose error, absolute in
{J} and of the motion from home.

After a calibration the controller commands the strokes that the **estimate** says reach a desired
pose X (inverse kinematics of ``M̂``, ``k̂``); the **true** robot moves them to
``FK(M, k; q)``. With the estimate's error ``e = θ̂ − θ`` over ``θ = x_drive = [δM (42), k (6)]``
(the drive model's unknowns, every term identified) the achieved pose misses X by, to first order
(the drive's FK Jacobian, :meth:`stewart_calib.model.drive.DriveModel.pose_jacobian`, at the nominal drive),

    δξ(X) = −∂ξ/∂θ (X) · e        (body tangent ``[ω, v]``: rotation, then position in {D})

so a covariance Σ of the estimate (the Cramér–Rao bound of a pose set, or a fit's own) predicts
at every workspace pose a Gaussian error ``N(0, D Σ Dᵀ)``. The instrument's own unknowns (frame,
targets) do not enter: the robot is driven without the instrument. Where the frame is unknown
its height trades against the leg lengths; that direction, poorly seen by poses that neither
tilt nor reach far, is a constant offset of every pose the robot reaches — invisible through the
calibrated frame (``validate``), obvious to anything the robot touches.

* :func:`predicted_error`: the **expected mean** position [mm] and orientation [deg] error over
  the workspace poses ``mean_X E‖δξ(X)‖`` — the quantity a simulated check measures as "mean
  closed-loop error" — from fixed standard normal draws (deterministic), and the band that holds
  the mean position error of 90 % of such calibrations. One calibration's error is one draw
  ``e``: where a few poorly seen directions dominate (poses that neither tilt nor reach far), its
  mean over the workspace is nearly ``|z|·c`` for a single standard normal z, so it lands within
  2× of any one number only ~85 % of the time (benchmarks/plan_poses.py's small workspace, 10 fits:
  the truth's quantile in the predicted distribution spread 0.10–0.93, all within the band);
* :func:`error_weight`: ``W = mean_X Dᵀ diag(L² I₃, I₃) D`` (rotation rows weighed by a length L,
  the platform joints' mean radius), so that ``tr(W Σ)`` is the mean squared displacement of a
  point at that radius — the linear (I-optimal) criterion that ``plan`` minimises.

Absolute against motion. The error at X holds a part common to every pose — above all what the
instrument's frame trades against (a near-rigid motion of the base joints), which a log through an
outside instrument barely sees. The **motion from home** H, the relative pose ``H⁻¹ X`` the robot
makes, loses that part: to first order (the chart of :func:`~stewart_calib.model.rotations.retract`)
its error is ``δξ(X) − M(X) δξ(H)`` with ``M = [[Rᵀ, 0], [−Rᵀ p^, Rᵀ]]`` for ``H⁻¹ X = (R, p)``, zero
for any constant pose offset in {J}. It is what the data can see and what a user checks with the
same instrument; the absolute error in {J} is what anything the robot touches meets, and the
principal axes of the error at home (:func:`limiting_directions`) say what limits it.

Registered. An outside instrument sees the robot through its frame ``F`` and target(s), fitted to
the readings (by the calibration, again by ``validate --register-instrument``): they absorb a common
rigid motion of {J} (the frame) and whatever the target(s) can take — a rigid motion of {D} for a
pose target, each point's own offset in {D} for 3-D targets (a rotation of {D} at home among them).
The error **as the instrument sees it after registration** is the readings' error ``H_X δξ(X)``
(the instrument model's Jacobians) with the least-squares effect of its unknowns ``H_u δu`` over
the evaluation poses taken out (whitened by the readings' σ, as the fits weigh them): what a check
through the same instrument measures beyond its noise, and less than the motion's error.

The frame of the error: {J} and {D} are the frames of the estimate's gauge (the in-situ tracker's,
or for an outside instrument where the joints best fit their nominal positions,
:mod:`stewart_calib.instruments.gauge`), the only frames in which any instrument sees the robot.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..errors import CalibError
from ..estimate import Estimate
from ..instruments.gauge import joint_columns
from ..instruments.registry import instrument_kind, outside_model
from ..model import kinematics as kin
from ..model import rotations
from ..model.drive import DriveModel, drive_model
from ..model.platform import Platform
from ..model.rotations import skew

#: Workspace poses the prediction averages over, drawn uniformly in the ``[workspace]`` box
#: (reachable within the stroke ranges) with a fixed seed, so that the same covariance always
#: gives the same prediction. The mean over 200 poses of a smooth error field is within ~2 % of
#: the box's mean (its pose-to-pose spread is < 30 % of the mean for every covariance tried).
EVALUATION_POSES = 200
EVALUATION_SEED = 20261125

#: Standard normal draws of the expectation ``E‖δξ‖`` (fixed): 1/√(2·512) ≈ 3 % relative error.
NORM_DRAWS = 512

#: Draws of the whole estimate error ``e ~ N(0, Σ)`` for the band of the mean position error
#: (fixed): the 5 % and 95 % quantiles of 20 000 draws sit within ±0.3 % in probability (two standard
#: errors). The same draws serve every covariance, so their error is every band's alike, not averaged
#: out over robots: with 1000 draws (±1.4 %) the absolute band held 877 of benchmarks.prediction_power's
#: 1000 laser-tracker robots, with 20 000 (two other seeds) 881 and 882.
BAND_DRAWS = 20_000
#: the draws one product of the band takes at a time (its ``(block, rows)`` array ~10 MB at 600 rows)
BAND_BLOCK = 2_000
#: The band's probability: its quantiles are (1 − p)/2 and (1 + p)/2.
BAND_PROBABILITY = 0.9

#: A prediction above this many times the noise floor warns. The floor is what the same noise
#: leaves with as many poses spread over the workspace box's extremes (``planning.noise_floor``);
#: measured (Cramér–Rao, 60 poses; nim-stewart with a laser tracker and with its in-situ tracker,
#: benchmarks.plan_poses' wide hexapod, the hobby's motion capture): ``plan``'s designs 0.65–1.04×
#: the floor, uniform random poses in the box 1.3–2.2×, 60 poses within ±20 mm / ±8° of the hobby
#: hexapod 3.9–4.1×; the hobby with a laser tracker (random poses against the box's corners, 400
#: each) puts random poses at 3.4–4.8×.
NOISE_FLOOR_FACTOR = 3.0

#: The words every command opens its predicted error with (calibrate, identifiability, plan, validate).
PREDICTION_HEAD = "predicted closed-loop pose error after calibration"

#: Candidate draws allowed per requested pose before giving up on a workspace whose box is
#: mostly outside the stroke or reading ranges.
MAX_DRAWS_PER_POSE = 50


def reachable_poses(
    platform: Platform,
    n: int,
    rng: np.random.Generator,
    face_bias_exponent: float = 1.0,
    ranges: str = "the stroke and reading ranges",
) -> np.ndarray:
    """``(n, 6)`` random poses in the workspace box with strokes and readings within range.

    Each coordinate is ``home + limit · sign(w)|w|^face_bias_exponent``, w uniform in [−1, 1]
    (1: uniform in the box; below 1: denser near its faces). ``ranges`` names the ranges in the
    refusal (a caller that narrowed them says how).

    Raises:
        CalibError: the platform has no ``[workspace]``, or almost no pose of the box is reachable.
    """
    ws = platform.workspace
    if ws is None:
        raise CalibError(f"{platform.source}: key 'workspace': expected a [workspace] table to draw poses from")
    half = np.r_[[ws.translation_limit] * 3, [ws.rotation_limit] * 3]
    if not half.any():
        raise CalibError(
            f"{platform.source}: key 'workspace': a box of zero size holds one pose only; expected "
            "translation_limit_mm or rotation_limit_deg > 0"
        )
    accepted: list[np.ndarray] = []
    count = draws = 0
    while count < n:
        if draws > MAX_DRAWS_PER_POSE * n:
            raise CalibError(
                f"{platform.source}: key 'workspace': expected a box whose poses mostly lie within {ranges}; "
                f"only {count} of {draws} random poses do"
            )
        w = rng.uniform(-1.0, 1.0, (n, 6))
        batch = ws.home + np.sign(w) * np.abs(w) ** face_bias_exponent * half
        draws += n
        accepted.append(batch[within_ranges(platform, batch)])
        count += len(accepted[-1])
    return np.concatenate(accepted)[:n]


def within_ranges(platform: Platform, poses: np.ndarray) -> np.ndarray:
    """``(N,)`` True where the nominal drive reaches ``poses`` (its inverse kinematics gives every leg
    a coordinate: a rotary drive's IK has none outside its angle range) and its strokes (and tracker
    readings, where the platform has a tracker with a reading range) lie within the platform's ranges."""
    R, t = kin.pose_to_rt(np.asarray(poses, dtype=float))
    strokes = drive_model(platform).inverse_kinematics(R, t)
    ok = np.all(np.isfinite(strokes), axis=1)
    if platform.stroke_range is not None:
        ok &= _within(strokes, platform.stroke_range)
    if platform.tracker is not None and platform.reading_range is not None:
        ok &= _within(kin.inverse_kinematics(platform.tracker, R, t), platform.reading_range)
    return ok


def _within(values: np.ndarray, bounds: tuple[float, float]) -> np.ndarray:
    return np.all((values >= bounds[0]) & (values <= bounds[1]), axis=1)


def evaluation_poses(platform: Platform) -> np.ndarray:
    """The fixed workspace poses of the prediction (:data:`EVALUATION_POSES`, uniform, reachable)."""
    return reachable_poses(platform, EVALUATION_POSES, np.random.default_rng(EVALUATION_SEED))


def closed_loop_jacobian(platform: Platform, poses: np.ndarray) -> np.ndarray:
    """``D = ∂ξ/∂θ`` ``(V, 6, 48)`` at the nominal drive: how the pose the robot reaches for the
    commanded strokes of a desired pose moves with ``θ = x_drive`` (δM, then every term of the
    drive model: ``k``; body tangent ``[ω, v]``)."""
    R, t = kin.pose_to_rt(np.asarray(poses, dtype=float).reshape(-1, 6))
    drive = drive_model(platform).identifying()
    return drive.pose_jacobian(None, R, t, drive.inputs_near(drive.inverse_kinematics(R, t), None, (R, t)))


def rotation_length_mm(platform: Platform) -> float:
    """The length L [mm] a rotation error is weighed by in :func:`error_weight`: the platform
    joints' mean distance from {D}'s z axis (a rotation δφ moves them by about L·δφ)."""
    legs = platform.drive
    joints = legs.as_vector()[joint_columns(legs)[1]].reshape(legs.n_legs, 3)
    return float(np.mean(np.linalg.norm(joints[:, :2], axis=1)))


def error_weight(platform: Platform, poses: np.ndarray | None = None) -> np.ndarray:
    """``W = mean_X Dᵀ diag(L² I₃, I₃) D`` ``(48, 48)`` [mm²]: ``tr(W Σ)`` is the predicted mean
    squared closed-loop error (position, plus rotation × L) over ``poses`` (default
    :func:`evaluation_poses`)."""
    D = closed_loop_jacobian(platform, evaluation_poses(platform) if poses is None else poses)
    D = D * np.r_[[rotation_length_mm(platform)] * 3, [1.0] * 3][:, None]
    return np.einsum("vri,vrj->ij", D, D) / len(D)


@dataclass(frozen=True)
class PredictedError:
    """The predicted closed-loop error over workspace poses (see the module docstring).

    Attributes:
        position_mm: expected mean absolute position error in {J} ``mean_X E‖δt(X)‖`` [mm].
        orientation_deg: expected mean absolute orientation error [deg].
        n_poses: the workspace poses averaged over.
        position_band_mm: ``(low, high)`` [mm], the mean absolute position error of
            :data:`BAND_PROBABILITY` of calibrations with this covariance lies between them (one
            calibration is one draw).
        workspace: True when they are the ``[workspace]`` box's, False when the platform has none
            and they are the measured poses themselves.
        motion_position_mm, motion_orientation_deg, motion_position_band_mm: the same of the
            motion from home (the error of ``H⁻¹ X``), what the data and the instrument see.
        limited_by: the principal axes of the absolute error at home, in words
            (:func:`limiting_directions`).
        registered_position_mm, registered_orientation_deg, registered_position_band_mm: the same as
            an outside instrument sees it after registration (:func:`registered_jacobian`), the
            position a point target's or the pose target's; NaN with the in-situ tracker (nothing to
            register) and the orientation NaN for points (they read none).
    """

    position_mm: float
    orientation_deg: float
    n_poses: int
    position_band_mm: tuple[float, float]
    workspace: bool = True
    motion_position_mm: float = float("nan")
    motion_orientation_deg: float = float("nan")
    motion_position_band_mm: tuple[float, float] = (float("nan"), float("nan"))
    limited_by: str = ""
    registered_position_mm: float = float("nan")
    registered_orientation_deg: float = float("nan")
    registered_position_band_mm: tuple[float, float] = (float("nan"), float("nan"))

    def to_dict(self) -> dict:
        return {
            "position_mm": self.position_mm,
            "orientation_deg": self.orientation_deg,
            "poses": self.n_poses,
            "over": "workspace" if self.workspace else "measured poses",
            "position_band_mm": list(self.position_band_mm),
            "motion_position_mm": self.motion_position_mm,
            "motion_orientation_deg": self.motion_orientation_deg,
            "motion_position_band_mm": list(self.motion_position_band_mm),
            "absolute_limited_by": self.limited_by,
            "registered_position_mm": _or_none(self.registered_position_mm),
            "registered_orientation_deg": _or_none(self.registered_orientation_deg),
            "registered_position_band_mm": [_or_none(value) for value in self.registered_position_band_mm],
        }

    @classmethod
    def from_dict(cls, field: object) -> PredictedError | None:
        """A result's ``"predicted_closed_loop"`` field read back; None where it holds no
        prediction (none available, or written without the motion from home)."""
        if not isinstance(field, dict) or field.get("available") is False or "motion_position_mm" not in field:
            return None
        return cls(
            float(field["position_mm"]),
            float(field["orientation_deg"]),
            int(field["poses"]),
            tuple(field["position_band_mm"]),
            field.get("over") == "workspace",
            float(field["motion_position_mm"]),
            float(field["motion_orientation_deg"]),
            tuple(field["motion_position_band_mm"]),
            str(field.get("absolute_limited_by", "")),
            _nan_if_none(field.get("registered_position_mm")),
            _nan_if_none(field.get("registered_orientation_deg")),
            _band_or_nan(field.get("registered_position_band_mm")),
        )

    def describe(self) -> str:
        """``"expected mean over 200 workspace poses (90% of such calibrations in each band): absolute place in
        {J} 0.0213 mm / 0.00141° (90%: 0.0101–0.0352 mm), motion from home 0.009 mm / 0.0011° (90%:
        0.004–0.016 mm); the absolute error limited by a constant z (σ 0.02 mm)"``: where the means are
        taken and what a band is, :meth:`expected_words`, and what limits the absolute error — the words
        every command's prediction prints."""
        where = "workspace poses" if self.workspace else "measured poses (no [workspace] in the platform file)"
        text = (
            f"expected mean over {self.n_poses} {where} ({BAND_PROBABILITY:.0%} of such calibrations in each band): "
            + self.expected_words()
        )
        if self.limited_by:
            text += f"; the absolute error limited by {self.limited_by}"
        return text

    def expected_words(self) -> str:
        """``"absolute place in {J} 0.0213 mm / 0.00141° (90%: 0.0101–0.0352 mm), motion from home 0.009 mm /
        0.0011° (90%: 0.004–0.016 mm)"``, then (an outside instrument) :meth:`registered_words`: the
        expected errors with their bands in the one order and the one set of words that the prediction
        lines (:meth:`describe`) and the verdict (:func:`verdict_line`) both print."""
        low, high = self.position_band_mm
        parts = [
            f"absolute place in {{J}} {self.position_mm:.3g} mm / {self.orientation_deg:.3g}° "
            f"({BAND_PROBABILITY:.0%}: {low:.3g}–{high:.3g} mm)"
        ]
        if np.isfinite(self.motion_position_mm):
            m_low, m_high = self.motion_position_band_mm
            parts.append(
                f"motion from home {self.motion_position_mm:.3g} mm / {self.motion_orientation_deg:.3g}° "
                f"({BAND_PROBABILITY:.0%}: {m_low:.3g}–{m_high:.3g} mm)"
            )
        if np.isfinite(self.registered_position_mm):
            parts.append(self.registered_words())
        return ", ".join(parts)

    def registered_words(self) -> str:
        """``"as the instrument sees it after registration 0.03 mm / 0.001° (90 %: 0.02–0.04 mm)"``
        (the orientation left out for points)."""
        low, high = self.registered_position_band_mm
        angle = f" / {self.registered_orientation_deg:.3g}°" if np.isfinite(self.registered_orientation_deg) else ""
        return (
            f"as the instrument sees it after registration {self.registered_position_mm:.3g} mm{angle} "
            f"({BAND_PROBABILITY:.0%}: {low:.3g}–{high:.3g} mm)"
        )


def _or_none(value: float) -> float | None:
    """NaN written as JSON null (a result holds no NaN)."""
    return float(value) if np.isfinite(value) else None


def _nan_if_none(value) -> float:
    return float("nan") if value is None else float(value)


def _band_or_nan(band) -> tuple[float, float]:
    """A band read back: NaN for a missing one (a result written before it) or its nulls."""
    low, high = (None, None) if band is None else band
    return _nan_if_none(low), _nan_if_none(high)


def _expected_norms(covariance: np.ndarray, mean: np.ndarray | None = None) -> np.ndarray:
    """``E‖x‖`` for ``x ~ N(mean, C)`` (``mean`` default 0), one per ``(..., 3, 3)`` covariance and
    ``(..., 3)`` mean, from fixed draws."""
    eigenvalues, eigenvectors = np.linalg.eigh(covariance)
    root = eigenvectors * np.sqrt(np.clip(eigenvalues, 0.0, None))[..., None, :]
    draws = np.random.default_rng(EVALUATION_SEED).standard_normal((NORM_DRAWS, 3))
    errors = np.einsum("...ij,sj->...si", root, draws)
    if mean is not None:
        errors = errors + mean[..., None, :]
    return np.mean(np.linalg.norm(errors, axis=-1), axis=-1)


def motion_jacobian(D: np.ndarray, poses: np.ndarray, home: np.ndarray, D_home: np.ndarray) -> np.ndarray:
    """``(V, 6, n)`` the error of the motion from ``home`` to each pose, ``D(X) − M(X) D(H)`` (the
    module docstring), from the absolute error Jacobians ``D (V, 6, n)`` at ``poses`` and
    ``D_home (6, n)`` at ``home``; body tangent ``[ω, v]``."""
    R_X, t_X = kin.pose_to_rt(np.asarray(poses, dtype=float).reshape(-1, 6))
    R_H, t_H = kin.pose_to_rt(np.asarray(home, dtype=float))
    R_rel = np.einsum("ji,njk->nik", R_H, R_X)
    p_rel = np.einsum("ji,nj->ni", R_H, t_X - t_H)
    Rt = np.swapaxes(R_rel, -1, -2)
    M = np.zeros((len(R_X), 6, 6))
    M[:, :3, :3] = Rt
    M[:, 3:, 3:] = Rt
    M[:, 3:, :3] = -Rt @ skew(p_rel)
    return D - M @ D_home


def registered_jacobian(platform: Platform, D: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The error an outside instrument sees after registration (the module docstring) at ``poses``:
    ``(V, m, n)`` over the estimate's error, the readings' rows (code units: rad, mm), and ``(V, m)``
    True where a row is read; from the absolute error Jacobians ``D (V, 6, n)``.

    Each pose's readings error ``H_X D`` is stacked, whitened by the readings' σ, and projected onto
    the complement of the span of ``H_u`` (the frame's and the target(s)' columns, at their nominal
    values): ``(I − Q Qᵀ)`` with Q an orthonormal basis of the whitened ``H_u``, rows not read left out.
    """
    model = outside_model(platform)
    unknowns = model.nominal_unknowns()
    R, t = kin.pose_to_rt(poses)
    readings = model.predicted_readings(unknowns, R, t)
    _, H_X, H_u = model.readings_residual(unknowns, readings, R, t, jacobians=True)
    read = model.seen_channels(R, t)
    weight = np.where(read, 1.0 / model.channel_sigma, 0.0)[..., None]  # unread rows: out of the fit
    A = (weight * (H_X @ D)).reshape(-1, D.shape[-1])
    G = (weight * H_u).reshape(-1, H_u.shape[-1])
    U, singular, _ = np.linalg.svd(G, full_matrices=False)
    Q = U[:, singular > singular[0] * 1e-10]
    projected = (A - Q @ (Q.T @ A)).reshape(len(poses), -1, D.shape[-1])
    return np.where(read[..., None], projected / np.where(weight > 0, weight, 1.0), 0.0), read


def _registered_prediction(
    platform: Platform, D: np.ndarray, poses: np.ndarray, covariance: np.ndarray, mean: np.ndarray
) -> tuple[float, float, tuple[float, float]]:
    """``(position [mm], orientation [deg] or NaN, position band [mm])`` of :func:`registered_jacobian`:
    a pose reading's position and rotation rows, or each 3-D target's position (its mean over the
    targets read), for an error ``N(mean, covariance)``."""
    nan = float("nan")
    if not instrument_kind(platform).outside:
        return nan, nan, (nan, nan)
    D_seen, channels_read = registered_jacobian(platform, D, poses)
    rows = D_seen.reshape(len(D_seen), -1, 3, D_seen.shape[-1])  # pose: [rotation, position]; points: a target each
    read = np.all(channels_read.reshape(len(D_seen), -1, 3), axis=-1)
    orientation = nan
    if instrument_kind(platform).measures_orientation:
        rotation, rows, read = rows[:, 0], rows[:, 1:], read[:, 1:]
        rotation_covariance = rotation @ covariance @ np.swapaxes(rotation, -1, -2)
        orientation = float(np.degrees(np.mean(_expected_norms(rotation_covariance, rotation @ mean))))
    position = rows[read]
    position_covariance = position @ covariance @ np.swapaxes(position, -1, -2)
    return (
        float(np.mean(_expected_norms(position_covariance, position @ mean))),
        orientation,
        _position_band(position, covariance, mean),
    )


#: A principal axis of the error at home is named when it holds this share of the largest one's σ.
LIMITING_SHARE = 0.5

_AXIS_NAMES = ("rotation about x", "rotation about y", "rotation about z", "x", "y", "z")


def limiting_directions(platform: Platform, home_covariance: np.ndarray) -> str:
    """The principal axes of the absolute error at home (``(6, 6)`` covariance of ``[ω, v]``),
    rotations weighed by :func:`rotation_length_mm`: each axis within :data:`LIMITING_SHARE` of the
    largest (two at most), as ``"a constant z + 0.4 rotation about x (σ 0.61 mm)"`` — its components
    of at least 0.3 (relative to the largest), and its σ in mm at that length."""
    L = rotation_length_mm(platform)
    scale = np.r_[[L] * 3, [1.0] * 3]
    values, vectors = np.linalg.eigh(scale[:, None] * home_covariance * scale[None, :])
    values = np.clip(values, 0.0, None)[::-1]
    vectors = vectors[:, ::-1]
    if not values[0] > 0:
        return ""
    parts: list[str] = []
    for value, vector in zip(values, vectors.T, strict=True):
        if np.sqrt(value) < LIMITING_SHARE * np.sqrt(values[0]) or len(parts) == 2:
            break
        lead = int(np.argmax(np.abs(vector)))
        words = _AXIS_NAMES[lead]
        for k in np.argsort(-np.abs(vector)):
            ratio = vector[k] / vector[lead]
            if k != lead and abs(vector[k]) >= 0.3:
                words += f" {'+' if ratio > 0 else '−'} {abs(ratio):.2g} {_AXIS_NAMES[k]}"
        parts.append(f"a constant {words} (σ {np.sqrt(value):.3g} mm)")
    return " and ".join(parts)


def predicted_error(
    platform: Platform,
    covariance: np.ndarray,
    poses: np.ndarray | None = None,
    home: np.ndarray | None = None,
    mean: np.ndarray | None = None,
) -> PredictedError:
    """The expected mean closed-loop error left by an estimate whose error has covariance ``covariance``
    (and mean ``mean``, default 0).

    Args:
        covariance: ``(42, 42)`` over δM [mm²] (the stroke scale then exact) or ``(≥ 48, ≥ 48)``
            whose first 48 rows are ``[δM, k]``; further rows (instrument unknowns) do not enter.
        poses: ``(V, 6)`` the poses to average over (default :func:`evaluation_poses`).
        home: ``(6,)`` where the motion starts (default the ``[workspace]`` home, else the first of
            ``poses``).
        mean: the error's mean over the same unknowns as ``covariance`` (an estimate off the log's
            optimum by a known step, :func:`estimate_summary`'s ``optimum``); its limiting directions are
            those of the second moment.
    """
    covariance = np.asarray(covariance, dtype=float)
    workspace = poses is None
    poses = evaluation_poses(platform) if poses is None else np.asarray(poses, dtype=float).reshape(-1, 6)
    if home is None:
        home = platform.workspace.home if platform.workspace is not None else poses[0]
    D = closed_loop_jacobian(platform, np.vstack([poses, home]))
    n = min(len(covariance), D.shape[-1])
    D, D_home = D[:-1, :, :n], D[-1, :, :n]
    covariance = covariance[:n, :n]
    mean = np.zeros(n) if mean is None else np.asarray(mean, dtype=float)[:n]
    pose_covariance, pose_mean = D @ covariance @ np.swapaxes(D, -1, -2), D @ mean
    D_motion = motion_jacobian(D, poses, home, D_home)
    motion_covariance, motion_mean = D_motion @ covariance @ np.swapaxes(D_motion, -1, -2), D_motion @ mean
    return PredictedError(
        float(np.mean(_expected_norms(pose_covariance[:, 3:, 3:], pose_mean[:, 3:]))),
        float(np.degrees(np.mean(_expected_norms(pose_covariance[:, :3, :3], pose_mean[:, :3])))),
        len(D),
        _position_band(D[:, 3:, :], covariance, mean),
        workspace,
        float(np.mean(_expected_norms(motion_covariance[:, 3:, 3:], motion_mean[:, 3:]))),
        float(np.degrees(np.mean(_expected_norms(motion_covariance[:, :3, :3], motion_mean[:, :3])))),
        _position_band(D_motion[:, 3:, :], covariance, mean),
        limiting_directions(platform, D_home @ (covariance + np.outer(mean, mean)) @ D_home.T),
        *_registered_prediction(platform, D, poses, covariance, mean),
    )


def _position_band(
    D_position: np.ndarray, covariance: np.ndarray, mean: np.ndarray | None = None
) -> tuple[float, float]:
    """The :data:`BAND_PROBABILITY` band ``(low, high)`` [mm] of ``mean_X ‖D_t(X) e‖`` for
    ``e ~ N(mean, covariance)`` (``mean`` default 0), from fixed draws: the mean over the poses of one
    estimate's error."""
    eigenvalues, eigenvectors = np.linalg.eigh(0.5 * (covariance + covariance.T))
    root = eigenvectors * np.sqrt(np.clip(eigenvalues, 0.0, None))
    flat = D_position.reshape(-1, D_position.shape[-1])
    rows = flat @ root  # a standard normal draw's error at each pose
    offset = np.zeros(len(flat)) if mean is None else flat @ mean
    means = []
    for block in np.split(_band_draws(len(root)), range(BAND_BLOCK, BAND_DRAWS, BAND_BLOCK)):
        errors = (block @ rows.T + offset).reshape(len(block), len(D_position), 3)
        means.append(np.mean(np.sqrt(np.einsum("spr,spr->sp", errors, errors)), axis=1))
    low, high = np.quantile(np.concatenate(means), [(1.0 - BAND_PROBABILITY) / 2, (1.0 + BAND_PROBABILITY) / 2])
    return float(low), float(high)


@functools.lru_cache(maxsize=4)
def _band_draws(n: int) -> np.ndarray:
    """The band's fixed ``(BAND_DRAWS, n)`` standard normal draws (read-only: shared by every call)."""
    draws = np.random.default_rng(EVALUATION_SEED).standard_normal((BAND_DRAWS, n))
    draws.flags.writeable = False
    return draws


def correction_size(platform: Platform, estimate: DriveModel, poses: np.ndarray | None = None) -> float:
    """Mean position change [mm] over the workspace poses (or ``poses``) that the estimated drive
    (:meth:`~stewart_calib.model.drive.DriveModel.calibrated`) makes to where the robot goes:
    ``‖FK(estimate, IK(nominal, X)) − X‖`` — the uncalibrated robot's closed-loop error if the
    estimate were the truth."""
    poses = evaluation_poses(platform) if poses is None else np.asarray(poses, dtype=float).reshape(-1, 6)
    R, t = kin.pose_to_rt(poses)
    drive = drive_model(platform)
    reached, _ = estimate.settled_kinematics(drive.inverse_kinematics(R, t), guess=(R, t), strict=False)
    position_mm, _ = kin.pose_error(R, t, reached.R, reached.t)
    return float(np.mean(position_mm[reached.converged])) if reached.converged.any() else float("inf")


def motion_correction_size(
    platform: Platform, estimate: DriveModel, poses: np.ndarray | None = None, home: np.ndarray | None = None
) -> float:
    """Mean position change [mm] of the motion from ``home`` (default the ``[workspace]`` home, else the
    first of ``poses``) to each pose that the estimated drive makes: ``‖p(FK(H')⁻¹ FK(X')) − p(H⁻¹ X)‖``
    with ``X' = (estimate, IK(nominal, X))`` — the uncalibrated robot's error of motion if the estimate
    were the truth; a constant offset of every pose (what an outside instrument's frame trades
    against) moves no motion."""
    poses = evaluation_poses(platform) if poses is None else np.asarray(poses, dtype=float).reshape(-1, 6)
    if home is None:
        home = platform.workspace.home if platform.workspace is not None else poses[0]
    R, t = kin.pose_to_rt(np.vstack([poses, home]))
    drive = drive_model(platform)
    reached, _ = estimate.settled_kinematics(drive.inverse_kinematics(R, t), guess=(R, t), strict=False)
    if not reached.converged[-1]:
        return float("inf")
    R_h, t_h = rotations.inverse(reached.R[-1], reached.t[-1])
    _, moved = rotations.compose(R_h, t_h, reached.R[:-1], reached.t[:-1])
    R_d, t_d = rotations.inverse(R[-1], t[-1])
    _, desired = rotations.compose(R_d, t_d, R[:-1], t[:-1])
    change = np.linalg.norm(moved - desired, axis=1)[reached.converged[:-1]]
    return float(np.mean(change)) if change.size else float("inf")


def summary_line(
    prediction: PredictedError,
    noise_floor: PredictedError | None,
    correction_mm: float | None = None,
    what: str = PREDICTION_HEAD,
) -> tuple[str, bool]:
    """The one line ``calibrate`` and ``identifiability`` print (``what`` its head), and whether it is a warning.

    A warning when the predicted position error exceeds :data:`NOISE_FLOOR_FACTOR` × the noise
    floor (None: not compared), or (with an estimate) the correction the calibration makes: the
    estimate's change to where the robot goes is then within its own uncertainty, and the
    calibrated robot may be further from its poses than the uncalibrated one.
    """
    head = f"{what}: {prediction.describe()}"
    reasons = []
    if noise_floor is not None and prediction.position_mm > NOISE_FLOOR_FACTOR * noise_floor.position_mm:
        reasons.append(
            f"{prediction.position_mm / noise_floor.position_mm:.3g}× the {noise_floor.position_mm:.3g} mm the "
            f"instrument's noise leaves with as many poses at the workspace's extremes (warned above "
            f"{NOISE_FLOOR_FACTOR:g}×): the poses leave some direction poorly seen — poses that tilt and reach "
            "to the workspace's edges (stewart-calib plan) see it"
        )
    if correction_mm is not None and prediction.position_mm > correction_mm:
        reasons.append(
            f"more than the {correction_mm:.3g} mm the calibration changes where the robot goes: "
            "the calibrated robot may be worse than the uncalibrated one"
        )
    if reasons:
        return "warning: " + head + "; " + "; ".join(reasons), True
    return head, False


def worse_than_nominal_line(
    prediction: PredictedError, correction_mm: float | None, motion_correction_mm: float | None
) -> str | None:
    """The loud line when a calibration moves the robot by less than its own expected error, both in
    absolute place (``correction_mm``, :func:`correction_size`) and in the motion from home
    (``motion_correction_mm``, :func:`motion_correction_size`), None otherwise: the nominal model then
    lies within the estimate's uncertainty of it even where the log sees best, and were the nominal
    model right, the calibrated robot would miss its poses by the whole move.

    Both must fall short: an outside instrument's frame trades against a near-rigid motion of the
    joints, so the absolute correction of a robot the calibration does improve can lie within its
    uncertainty too; the motion, which the log sees, then still moves by more than its own.
    """
    if correction_mm is None or motion_correction_mm is None:
        return None
    if not (prediction.position_mm > correction_mm and prediction.motion_position_mm > motion_correction_mm):
        return None
    low, high = prediction.position_band_mm
    m_low, m_high = prediction.motion_position_band_mm
    limited = f"; the absolute error limited by {prediction.limited_by}" if prediction.limited_by else ""
    return (
        f"WARNING: the calibrated model is likely worse than the nominal one: it moves the robot by "
        f"{correction_mm:.3g} mm and its motion from home by {motion_correction_mm:.3g} mm, each less than its own "
        f"expected error ({prediction.position_mm:.3g} mm, {BAND_PROBABILITY:.0%}: {low:.3g}–{high:.3g} mm; motion "
        f"{prediction.motion_position_mm:.3g} mm, {BAND_PROBABILITY:.0%}: {m_low:.3g}–{m_high:.3g} mm), so the log "
        f"does not support the move{limited}: keep the nominal model, or log poses that tilt and reach to the "
        "workspace's edges (stewart-calib plan)"
    )


def _offset(estimate: Estimate, optimum: Estimate) -> np.ndarray:
    """``estimate − optimum`` over their whole unknown vector ``[δM | blocks]``."""
    return np.concatenate((estimate.error - optimum.error, estimate.block_error - optimum.block_error))


def given_log(estimate: Estimate, optimum: Estimate) -> Estimate | None:
    """``estimate`` with the covariance of its error given the log, ``optimum`` the log's MAP found from it
    (:class:`~stewart_calib.estimators.Relinearising`); None where the optimum has no covariance.

    A filter's estimate and covariance sum each sample's information at the state it stood at when the sample
    came; where that state moved by millimetres over the log (an outside instrument's frame and the encoder
    zeros, found along the way), its covariance is not the information the log holds, nor its state the log's
    optimum. Given the log, the truth is ``N(x̂, P̂)`` about the optimum (Laplace), so the estimate's error
    ``x − x_true`` has the second moment ``P̂ + d dᵀ``, ``d = x − x̂``: the covariance every prediction of the
    estimate takes, equal to the method's own where its recursion is the batch's (one linearisation point: an
    honest run differs by the model's curvature, a few per cent)."""
    if optimum.full_covariance is None:
        return None
    offset = _offset(estimate, optimum)
    second = optimum.full_covariance + np.outer(offset, offset)
    n = optimum.layout.n_params
    return dataclasses.replace(estimate, covariance=second[:n, :n], full_covariance=second)


def relinearised_summary(
    platform: Platform,
    method: str,
    own: PredictedError,
    judged: PredictedError,
    optimum: Estimate,
    measured_poses: np.ndarray,
) -> tuple[dict, str | None]:
    """An online ``method``'s own prediction ``own`` against ``judged``, that of its estimate given the log
    (:func:`given_log`), ``optimum`` the log's MAP: ``(the result's "relinearised" field, the loud line or
    None)``.

    The line is written where the expected mean given the log (absolute place or motion from home) lies above
    the top of the method's own band — beyond what :data:`BAND_PROBABILITY` of calibrations with its covariance
    would show: the method stopped short of the log's optimum, and its own covariance does not describe its
    error. One-sided: a filter less sure than the log (a walk) misleads no one."""
    covariance = estimate_drive_covariance(optimum, drive_model(platform))
    if covariance is None or not np.all(np.isfinite(covariance)):
        return {"available": False}, None
    best = predicted_error(platform, covariance, None if platform.workspace is not None else measured_poses)
    field = {
        "position_mm": judged.position_mm,
        "motion_position_mm": judged.motion_position_mm,
        "filter_position_mm": own.position_mm,
        "filter_position_band_mm": list(own.position_band_mm),
        "filter_motion_position_mm": own.motion_position_mm,
        "filter_motion_position_band_mm": list(own.motion_position_band_mm),
        "optimum_position_mm": best.position_mm,
        "optimum_motion_position_mm": best.motion_position_mm,
    }
    beyond = [
        f"{what} {theirs:.3g} mm where its own covariance claims {mine:.3g} mm ({BAND_PROBABILITY:.0%}: "
        f"{band[0]:.3g}–{band[1]:.3g} mm)"
        for what, theirs, mine, band in (
            ("absolute place in {J}", judged.position_mm, own.position_mm, own.position_band_mm),
            ("motion from home", judged.motion_position_mm, own.motion_position_mm, own.motion_position_band_mm),
        )
        if theirs > band[1]
    ]
    if not beyond:
        return field, None
    return field, (
        f"WARNING: {method} stopped short of the log's optimum: the optimum (Gauss–Newton from {method}'s estimate "
        f"over the samples it used) expects of {method}'s estimate {'; '.join(beyond)}, beyond its own band. It "
        f"took each sample's information at the state it stood at when the sample came, and here that state moved "
        f"far over the log (the instrument's frame and the encoder zeros, found along the way): the prediction "
        f"above is the log's, not its own; for a log measured whole, calibrate with --method ls or lm (the "
        f"optimum's expected error: absolute {best.position_mm:.3g} mm, motion {best.motion_position_mm:.3g} mm)"
    )


def _against(band_mm: tuple[float, float], orientation_deg: float, tolerance_mm, tolerance_deg) -> str:
    """``"within"``, ``"over"`` or ``"not sure"`` (the tolerance inside the 90 % band) of one error."""
    words = []
    if tolerance_mm is not None:
        low, high = band_mm
        words.append("within" if high <= tolerance_mm else "over" if low > tolerance_mm else "not sure")
    if tolerance_deg is not None:
        words.append("within" if orientation_deg <= tolerance_deg else "over")
    return "over" if "over" in words else "not sure" if "not sure" in words else "within"


class MeasuredError(NamedTuple):
    """What a check measured of the robot's own error, beyond its instrument's noise: the position RMS
    [mm] with its 90 % interval from the noise's spread over the rows, and the orientation RMS [deg]
    (None where the instrument gives none)."""

    position_mm: float
    position_band_mm: tuple[float, float]
    orientation_deg: float | None


def verdict_line(
    prediction: PredictedError,
    tolerance_mm: float | None = None,
    tolerance_deg: float | None = None,
    measured: str | None = None,
    measured_error: MeasuredError | None = None,
    registered: bool = False,
    refitted: bool = False,
) -> tuple[str, bool]:
    """The last line of ``calibrate`` and ``validate`` (and the top of their report): the expected
    error of the absolute place in {J} and of the motion from home over the workspace with their
    90 % bands (:meth:`PredictedError.expected_words`, the prediction lines' words), each against the
    tolerance where given; ``(line, over)`` with ``over`` True where either is over the tolerance or not
    surely within it.

    Args:
        measured: what a check measured, named in the line (``validate``).
        measured_error: what a check measured of the robot's own error, beyond the instrument's noise, set
            beside its prediction's band (the line says whether the two intervals meet): through the in-situ
            tracker the absolute place in {J}; through an outside instrument's fitted frame and target(s)
            (``registered``) the error as the instrument sees it after registration. Surely over the
            tolerance (its interval's bottom above it), registered, the motion is over it: the frame and
            target(s) absorb a rigid motion of {J} and the targets' places in {D} (a rotation of {D} at home
            among them, which turns the motion's position ``T_home⁻¹ T``), so the registered error is only
            part of the motion's (benchmarks.prediction). The absolute place is over it too, through the
            tracker and where the frame was fitted to the check's own rows (``refitted``): the error in {J}
            at those poses is no smaller than what the best frame and target(s) leave (through the
            calibration's frame it may be: that frame's own error is in the rows). Otherwise the
            prediction's words stand: the check's poses are not the workspace's.
    """
    where = "workspace" if prediction.workspace else "measured poses"
    line = f"verdict: expected mean error over the {where}: {prediction.expected_words()}"
    if measured:
        line += f"; {measured}"
    predicted_band, what = (
        (prediction.registered_position_band_mm, "registered error")
        if registered
        else (prediction.position_band_mm, "absolute place")
    )
    place = None
    if measured_error is not None and np.all(np.isfinite(predicted_band)):
        p_low, p_high = predicted_band
        seen_low, seen_high = measured_error.position_band_mm
        place = (
            "its interval meets"
            if seen_low <= p_high and seen_high >= p_low
            else "above"
            if seen_low > p_high
            else "below"
        )
        line += f", {place} the predicted {what}'s {BAND_PROBABILITY:.0%} band"
    if place == "above":  # more poses would not help: what the check meets is not the result's error
        line += (
            ": the robot or the instrument is not as it was calibrated (loaded, worn, set up anew, another robot), "
            "or the calibration's log held errors its model lacks; calibrate again on a log like this one"
        )
    if tolerance_mm is None and tolerance_deg is None:
        return line + "; give --tolerance-mm / --tolerance-deg to compare", False
    motion_word = _against(
        prediction.motion_position_band_mm, prediction.motion_orientation_deg, tolerance_mm, tolerance_deg
    )
    absolute_word = _against(prediction.position_band_mm, prediction.orientation_deg, tolerance_mm, tolerance_deg)
    if measured_error is not None:
        rms_deg = measured_error.orientation_deg
        seen = _against(
            measured_error.position_band_mm, rms_deg if rms_deg is not None else 0.0, tolerance_mm, tolerance_deg
        )
        if seen == "over":
            motion_word = "over" if registered else motion_word
            absolute_word = "over" if refitted or not registered else absolute_word
    tolerance = " / ".join(
        text
        for text in (
            None if tolerance_mm is None else f"{tolerance_mm:g} mm",
            None if tolerance_deg is None else f"{tolerance_deg:g}°",
        )
        if text
    )
    line += f"; against {tolerance}: motion {motion_word}, absolute place {absolute_word}"
    if place == "above":
        return line, motion_word != "within" or absolute_word != "within"
    if absolute_word != "within" and prediction.limited_by:
        line += f" (limited by {prediction.limited_by}: poses that tilt and reach to the workspace's edges see it)"
    if motion_word != "within":
        line += (
            "; more poses, spread to the workspace's edges, or a less noisy instrument lower both (stewart-calib plan)"
        )
    return line, motion_word != "within" or absolute_word != "within"


def _drive_index(estimate: Estimate, drive: DriveModel) -> np.ndarray:
    """Where each of ``drive``'s unknowns as :func:`predicted_error` takes them sits in the estimate's
    unknown vector: δM, then each term of the drive up to the last the estimate identified (−1 for a term
    it did not identify before that one: known exactly)."""
    spans = [estimate.layout.slice(term.key) for term in drive.terms]
    identified = [k for k, span in enumerate(spans) if span is not None]
    return np.concatenate(
        [np.arange(drive.n_params)]
        + [
            np.arange(s.start, s.stop) if s is not None else np.full(drive.rows, -1)
            for s in spans[: identified[-1] + 1 if identified else 0]
        ]
    )


def estimate_drive_covariance(estimate: Estimate, drive: DriveModel) -> np.ndarray | None:
    """The covariance of an estimate over ``drive``'s unknowns as :func:`predicted_error` takes
    them (:func:`_drive_index`; a term not identified: zero rows, known exactly). None when the estimate
    has none (a rank-deficient fit)."""
    index = _drive_index(estimate, drive)
    if len(index) == drive.n_params or estimate.full_covariance is None:
        return estimate.covariance
    covariance = estimate.full_covariance[np.ix_(index, index)]
    missing = index < 0
    covariance[missing, :] = covariance[:, missing] = 0.0
    return covariance


def _drive_offset(estimate: Estimate, optimum: Estimate, drive: DriveModel) -> np.ndarray:
    """``estimate − optimum`` over ``drive``'s unknowns as :func:`estimate_drive_covariance` takes them."""
    offset = _offset(estimate, optimum)
    index = _drive_index(optimum, drive)
    return np.where(index >= 0, offset[np.maximum(index, 0)], 0.0)


def estimate_summary(
    platform: Platform,
    estimate: Estimate,
    noise_floor: PredictedError | None,
    measured_poses: np.ndarray,
    optimum: Estimate | None = None,
) -> tuple[dict, str, bool]:
    """The prediction of a calibration result: ``(result field, one line, is a warning)``.

    Over the workspace box, or where the platform has no ``[workspace]`` over ``measured_poses``
    (the log's). The field is :meth:`PredictedError.to_dict` with the noise floor's and the
    correction's position error and the warning (``"warning": line or null``); without a
    covariance, ``{"available": false}`` and a line saying why. ``optimum``: the log's MAP found from
    ``estimate`` (:func:`given_log`), whose covariance about it the truth has: the estimate's error is then
    ``N(estimate − optimum, optimum's covariance)``.
    """
    drive = drive_model(platform)
    covariance = estimate_drive_covariance(estimate if optimum is None else optimum, drive)
    if covariance is None or not np.all(np.isfinite(covariance)):
        line = "warning: no predicted closed-loop pose error: the estimate has no covariance (rank-deficient fit)"
        return {"available": False, "warning": line}, line, True
    poses = None if platform.workspace is not None else measured_poses
    mean = None if optimum is None else _drive_offset(estimate, optimum, drive)
    prediction = predicted_error(platform, covariance, poses, mean=mean)
    correction = correction_size(platform, drive.calibrated_by(estimate), poses)
    line, warn = summary_line(prediction, noise_floor, correction)
    field = {
        **prediction.to_dict(),
        "noise_floor_mm": None if noise_floor is None else noise_floor.position_mm,
        "correction_mm": correction,
        "motion_correction_mm": motion_correction_size(platform, drive.calibrated_by(estimate), poses),
        "warning": line if warn else None,
    }
    return field, line, warn
