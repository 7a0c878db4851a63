"""Kinematics of a 6-6 Stewart platform: pure functions, vectorised over poses, mm and rad.

Conventions (spec §1, paper §3.1):

* A pose is the platform frame {D} in the base frame {J}: ``(R, t)`` with ``R`` of shape
  ``(..., 3, 3)`` and ``t`` of shape ``(..., 3)`` [mm], or a *pose6* vector
  ``[x, y, z [mm], roll, pitch, yaw [rad]]`` with ``R = Rz(yaw) Ry(pitch) Rx(roll)``
  (paper eq. 20–21).
* Pose perturbations for Jacobians, Newton steps and GTSAM are in the body-frame tangent
  ``ξ = [ω, v]`` (rotation first), ``R ← R Exp(ω)``, ``t ← t + R v`` — the same tangent and
  the same first derivative as ``gtsam.Pose3.retract`` (which in gtsam 4.3.0 is the full SE(3)
  exponential, ``t + R V(ω) v``: equal Jacobians at ξ = 0, different at second order).
* A leg between base joint ``b_i`` (in {J}) and platform joint ``p_i`` (in {D}) has length
  ``‖t + R p_i − b_i‖`` = ``initial_length_i + stroke_i`` (paper eq. 1, Table 2).

No I/O and no estimator state live here. The per-pose loops that numpy runs slowly (FK's
Newton iteration, the error Jacobian, the leg EKF's fused observation) are numba kernels
in :mod:`stewart_calib.model._kernels`; the functions here keep their numpy signatures.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..errors import CalibError, SampleRejected
from . import _kernels
from .rotations import (  # noqa: F401 -- the pose algebra is part of the kinematics API
    pose_error,
    pose_to_rt,
    retract,
    rotation_angle,
    rotation_to_rpy,
    rpy_to_rotation,
    rt_to_pose,
    skew,
    so3_exp,
    transform_points,
)

if TYPE_CHECKING:  # the annotations' type: platform.LegGeometry delegates its leg model to this module
    from .platform import LegGeometry

# ----------------------------------------------------------------------------- legs


def leg_vectors(legs: LegGeometry, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Closed-loop vectors ``l_i n_i = t + R p_i − b_i`` (paper eq. 1), ``(..., 6, 3)`` [mm]."""
    return transform_points(R, t, legs.platform_joints) - legs.base_joints


def leg_lengths(legs: LegGeometry, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``‖t + R p_i − b_i‖`` for the six legs, ``(..., 6)`` [mm]."""
    return np.linalg.norm(leg_vectors(legs, R, t), axis=-1)


def inverse_kinematics(legs: LegGeometry, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Strokes (drive ``q_i``) or readings (tracker ``s_i``) that put the platform at ``(R, t)``.

    Returns:
        ``(..., 6)`` ``‖t + R p_i − b_i‖ − initial_length_i`` [mm].
    """
    return leg_lengths(legs, R, t) - legs.initial_lengths


def leg_pose_jacobian(legs: LegGeometry, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``∂ length_i / ∂ξ`` for the body tangent ``ξ = [ω, v]`` (GTSAM order), ``(..., 6, 6)``.

    With ``p = t + R p_i``, ``δp = −R[p_i]× ω + R v``, so the row of leg i is
    ``[ (p_i × Rᵀn_i)ᵀ, (Rᵀn_i)ᵀ ]`` with ``n_i`` the unit leg vector.
    """
    vec = leg_vectors(legs, R, t)
    n = vec / np.linalg.norm(vec, axis=-1, keepdims=True)
    n_body = np.einsum("...ji,...kj->...ki", R, n)  # Rᵀ n_i per leg
    return np.concatenate([np.cross(legs.platform_joints, n_body), n_body], axis=-1)


@dataclass(frozen=True)
class FKSolution:
    """Result of :func:`forward_kinematics`.

    Attributes:
        R: ``(..., 3, 3)`` platform orientation.
        t: ``(..., 3)`` platform position [mm].
        iterations: ``(...)`` Newton iterations used per pose.
        converged: ``(...)`` whether the length residual fell below the tolerance.
        residual_mm: ``(...)`` max |length error| at the returned pose [mm].
    """

    R: np.ndarray
    t: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    residual_mm: np.ndarray

    @property
    def pose6(self) -> np.ndarray:
        return rt_to_pose(self.R, self.t)


class FKError(CalibError):
    """Forward kinematics did not converge or the leg lengths are unreachable."""


#: Newton's tolerance on the leg lengths [mm] and its iteration cap, for every FK entry point.
FK_TOLERANCE_MM = 1e-9
FK_MAX_ITERATIONS = 30


def default_guess(legs: LegGeometry, strokes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A level pose above the base centre whose mean leg length matches the mean of ``strokes``."""
    target = np.asarray(strokes, dtype=float) + legs.initial_lengths
    radial = legs.base_joints[:, :2] - legs.platform_joints[:, :2]
    dz = np.sqrt(np.maximum(target**2 - np.sum(radial**2, axis=-1), 1.0))
    z = np.mean(dz + legs.base_joints[:, 2] - legs.platform_joints[:, 2], axis=-1)
    t = np.zeros(target.shape[:-1] + (3,))
    t[..., 2] = z
    return np.broadcast_to(np.eye(3), target.shape[:-1] + (3, 3)).copy(), t


def forward_kinematics(
    legs: LegGeometry,
    strokes: np.ndarray,
    guess: tuple[np.ndarray, np.ndarray] | None = None,
    tol_mm: float = FK_TOLERANCE_MM,
    max_iterations: int = FK_MAX_ITERATIONS,
    strict: bool = True,
    along: bool = False,
) -> FKSolution:
    """Forward kinematics by Newton–Raphson on the leg lengths (paper §3.2, step 1).

    Solves ``‖t + R p_i − b_i‖ = initial_length_i + stroke_i`` for ``(R, t)``, stepping in the
    body tangent ``ξ = [ω, v]`` with the leg Jacobian of :func:`leg_pose_jacobian`. Each pose
    of a batch iterates until its own residual is below ``tol_mm``; steps are capped at
    0.2 rad / 100 mm so a poor guess stays in Newton's basin, and a singular Jacobian gets
    the least-squares step. One compiled loop (:func:`stewart_calib.model._kernels.fk_newton`)
    serves single poses, batches, and (:func:`forward_kinematics_per_pose`) batches where
    every pose has its own geometry.

    Args:
        legs: drive or tracker geometry.
        strokes: ``(..., 6)`` strokes q_i or readings s_i [mm].
        guess: starting ``(R, t)`` broadcastable to the batch (warm start from the previous
            pose); default: a level pose from :func:`default_guess`.
        tol_mm: convergence tolerance on max |length residual| [mm].
        max_iterations: iteration cap.
        strict: raise :class:`FKError` if any pose fails; otherwise report it in ``converged``.
        along: ``strokes (N, 6)`` are a log's samples in order: each pose after the first starts
            from the one before where that converged (~3 Newton steps against ~5 from the level guess;
            within FK's tolerance of the same solutions, see :func:`stewart_calib.model._kernels.fk_newton`).
    Raises:
        FKError: lengths unreachable (no pose fits them) or no convergence within the cap.
    """
    strokes = np.ascontiguousarray(strokes, dtype=float)
    if guess is None:
        guess = default_guess(legs, strokes)
    # (1, 6, 3) / (1, 6) views: one geometry for the whole batch. LegGeometry's arrays are
    # read-only C arrays, so the kernel sees the same types as from the per-pose path.
    return _newton_fk(
        legs.base_joints[None],
        legs.platform_joints[None],
        legs.initial_lengths[None],
        strokes,
        guess,
        tol_mm,
        max_iterations,
        strict,
        along,
    )


def forward_kinematics_per_pose(
    base_joints: np.ndarray,
    platform_joints: np.ndarray,
    initial_lengths: np.ndarray,
    strokes: np.ndarray,
    guess: tuple[np.ndarray, np.ndarray],
    tol_mm: float = FK_TOLERANCE_MM,
    max_iterations: int = FK_MAX_ITERATIONS,
    strict: bool = True,
) -> FKSolution:
    """:func:`forward_kinematics` where pose k has its own geometry (e.g. a drive deformed by
    the load at that pose): same Newton solve, same compiled loop, same result fields.

    Args:
        base_joints, platform_joints: ``(..., 6, 3)`` b_i in {J} and p_i in {D} per pose [mm].
        initial_lengths: ``(..., 6)`` lengths at zero stroke per pose [mm].
        strokes: ``(..., 6)`` strokes or readings [mm]; ``...`` is the batch of all four.
        guess: starting ``(R, t)`` broadcastable to the batch (no default: a per-pose
            geometry has no single level pose).
        tol_mm, max_iterations, strict: as :func:`forward_kinematics`.
    Raises:
        ValueError: a geometry array's shape is not the batch's.
        FKError: as :func:`forward_kinematics`.
    """
    strokes = np.ascontiguousarray(strokes, dtype=float)
    batch = strokes.shape[:-1]
    geometry: list[np.ndarray] = []
    for name, value, shape in (
        ("base_joints", base_joints, (6, 3)),
        ("platform_joints", platform_joints, (6, 3)),
        ("initial_lengths", initial_lengths, (6,)),
    ):
        value = np.ascontiguousarray(value, dtype=float)
        if value.shape != batch + shape:
            raise ValueError(
                f"{name} must have shape {batch + shape} to match strokes {strokes.shape}, got {value.shape}"
            )
        view = value.reshape((-1,) + shape)  # a new view: read-only like LegGeometry's, caller's array untouched
        view.setflags(write=False)
        geometry.append(view)
    base, plat, lengths = geometry
    return _newton_fk(base, plat, lengths, strokes, guess, tol_mm, max_iterations, strict)


def _newton_fk(
    base, plat, lengths, strokes: np.ndarray, guess, tol_mm: float, max_iterations: int, strict: bool, along=False
) -> FKSolution:
    """The FK entry points' one body: ``base, plat, lengths`` read-only C ``(G, 6, 3), (G, 6, 3),
    (G, 6)`` with ``G`` 1 or the flat batch size, ``strokes`` C ``(..., 6)``."""
    batch = strokes.shape[:-1]
    flat = strokes.reshape(-1, 6)
    R_start, t_start = np.empty(batch + (3, 3)), np.empty(batch + (3,))  # fresh C arrays: the kernel overwrites them
    R_start[...], t_start[...] = guess
    R, t = R_start.reshape(-1, 3, 3), t_start.reshape(-1, 3)
    iterations = np.empty(len(flat), dtype=np.int64)
    residual = np.empty(len(flat))
    _kernels.fk_newton(
        base, plat, lengths, flat, R, t, float(tol_mm), int(max_iterations), bool(along), iterations, residual
    )

    # The compiled check first: `residual <= tol_mm` and `.all()` cost a sizeable share of a solve.
    converged = (
        np.ones(len(flat), dtype=bool) if _kernels.all_within(residual, -np.inf, float(tol_mm)) else residual <= tol_mm
    )
    return fk_solution(
        R, t, iterations, residual, converged, flat, batch, strict, "forward kinematics", "lengths", "leg lengths"
    )


def fk_solution(
    R: np.ndarray,
    t: np.ndarray,
    iterations: np.ndarray,
    residual: np.ndarray,
    converged: np.ndarray,
    coordinates: np.ndarray,
    batch: tuple[int, ...],
    strict: bool,
    what: str,
    coordinate_name: str,
    reach_name: str,
) -> FKSolution:
    """The :class:`FKSolution` of a flat batch of Newton solves (``R (n, 3, 3)``, ``t (n, 3)``, their
    ``iterations``, ``residual`` [mm] and ``converged``, from ``coordinates (n, 6)``) shaped as
    ``batch``; every leg model's FK ends here.

    Raises:
        FKError: ``strict`` and a pose did not converge; it names ``what`` solved, the first such pose
            as non-finite ``coordinate_name``, or the ``reach_name`` unreachable.
    """
    if strict and not converged.all():
        first = int(np.flatnonzero(~converged)[0])
        where = f" (pose {tuple(int(i) for i in np.unravel_index(first, batch))})" if batch else ""
        finite = np.all(np.isfinite(coordinates[first]))
        reason = f"residual {residual[first]:.3g} mm" if finite else f"non-finite {coordinate_name}"
        raise FKError(
            f"{what} did not converge{where}: {reason} after {iterations[first]} "
            f"Newton iterations; the {reach_name} may be unreachable"
        )
    return FKSolution(
        R.reshape(batch + (3, 3)),
        t.reshape(batch + (3,)),
        iterations.reshape(batch),
        converged.reshape(batch),
        residual.reshape(batch),
    )


# ----------------------------------------------------------------------------- error model


def leg_unit_vectors(legs: LegGeometry, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``n_i`` of paper eq. 1, ``(..., 6, 3)``."""
    vec = leg_vectors(legs, R, t)
    return vec / np.linalg.norm(vec, axis=-1, keepdims=True)


def error_jacobian(legs: LegGeometry, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The paper's error Jacobian ``J_p = J_r J_s`` (eq. 8–11), ``(..., 6, 42)``.

    ``δE = J_p δM`` with ``δE = [δh, δθ]`` (position [mm], roll-pitch-yaw [rad]) the change of
    the pose reached with fixed strokes when the parameters change by δM (paper order).
    ``J_r⁻¹`` has rows ``[n_iᵀ, (R d_i × n_i)ᵀ T]`` (eq. 10); ``J_s`` is block-diagonal with
    rows ``[n_iᵀ, −n_iᵀ R, 1]`` on ``[δj_i, δd_i, δl_i]`` (eq. 11).
    """
    R_flat, t_flat, batch = _flat_poses(R, t)
    J_p = np.empty((len(R_flat), 6, legs.n_params))
    _kernels.error_jacobian(legs.base_joints, legs.platform_joints, R_flat, t_flat, J_p)
    return J_p.reshape(batch + (6, legs.n_params))


def _flat_poses(R: np.ndarray, t: np.ndarray, batch: tuple[int, ...] | None = None):
    """``(R, t)`` broadcast to ``batch`` (default: their own), as C-contiguous ``(n, 3, 3)``,
    ``(n, 3)`` copies for the kernels, and the batch shape."""
    if batch is None:
        batch = np.broadcast_shapes(np.shape(R)[:-2], np.shape(t)[:-1])
    R_flat, t_flat = np.empty(batch + (3, 3)), np.empty(batch + (3,))
    R_flat[...], t_flat[...] = R, t
    return R_flat.reshape(-1, 3, 3), t_flat.reshape(-1, 3), batch


def leg_residuals(legs: LegGeometry, R: np.ndarray, t: np.ndarray, strokes: np.ndarray) -> np.ndarray:
    """Leg-length model ``r_i = ‖t + R d_i − j_i‖ − (l_i + q_i)``, ``(..., 6)`` [mm]."""
    return leg_lengths(legs, R, t) - legs.initial_lengths - np.asarray(strokes, dtype=float)


def leg_residuals_per_sample(params_mm: np.ndarray, R: np.ndarray, t: np.ndarray, strokes_mm: np.ndarray) -> np.ndarray:
    """``(N, 6)`` drive-leg residuals ``‖t + R d_i − j_i‖ − (l_i + q_i)`` [mm] where sample k has its
    own parameters ``params_mm[k]`` (absolute 42-vector, paper order) and pose ``(R[k], t[k])``."""
    p = np.reshape(params_mm, (len(params_mm), np.shape(strokes_mm)[-1], -1))  # (N, legs, [j | d | l])
    joints = t[:, None, :] + np.einsum("nij,nkj->nki", R, p[:, :, 3:6]) - p[:, :, 0:3]
    return np.linalg.norm(joints, axis=-1) - (p[:, :, 6] + strokes_mm)


def leg_residual_param_jacobian(legs: LegGeometry, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``∂r_i/∂(j_i, d_i, l_i)`` = ``[−n_iᵀ, n_iᵀ R, −1]`` for each leg, ``(..., 6, 7)``.

    Leg i's residual depends only on leg i's seven parameters; :func:`block_diagonal_params`
    spreads these rows into the full ``(..., 6, 42)`` Jacobian.
    """
    n = leg_unit_vectors(legs, R, t)
    return np.concatenate([-n, np.einsum("...ki,...ij->...kj", n, R), -np.ones(n.shape[:-1] + (1,))], axis=-1)


def block_diagonal_params(per_leg: np.ndarray) -> np.ndarray:
    """``(..., 6, 7)`` per-leg rows → ``(..., 6, 42)`` with leg i's row in columns 7i…7i+6."""
    legs, width = per_leg.shape[-2:]
    out = np.zeros(per_leg.shape[:-1] + (legs * width,))
    for i in range(legs):
        out[..., i, width * i : width * (i + 1)] = per_leg[..., i, :]
    return out


def leg_residual_jacobians(legs: LegGeometry, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians of :func:`leg_residuals`: ``(∂r/∂ξ (..., 6, 6), ∂r/∂M (..., 6, 42))``.

    The pose Jacobian is in the body tangent ``ξ = [ω, v]`` (see :func:`leg_pose_jacobian`).
    """
    return leg_pose_jacobian(legs, R, t), block_diagonal_params(leg_residual_param_jacobian(legs, R, t))


def pose_covariance_from_legs(legs: LegGeometry, R: np.ndarray, t: np.ndarray, sigma_mm: float) -> np.ndarray:
    """Covariance of an FK pose in the body tangent ``[ω, v]`` from i.i.d. length noise σ [mm].

    First-order propagation ``Σ_ξ = σ² (JᵀJ)⁻¹`` with ``J`` = :func:`leg_pose_jacobian`; this is
    the *loose* tracker measurement's covariance. ``(..., 6, 6)`` [rad², rad·mm, mm²]. One pose
    goes through a compiled kernel (it is computed once per sample online).
    """
    if np.ndim(R) == 2:
        c = np.ascontiguousarray
        return _kernels.pose_covariance(
            legs.base_joints, legs.platform_joints, c(R, dtype=float), c(t, dtype=float), float(sigma_mm) ** 2
        )
    J = leg_pose_jacobian(legs, R, t)
    J_inv = np.linalg.inv(J)
    return sigma_mm**2 * J_inv @ np.swapaxes(J_inv, -1, -2)


def leg_ekf_observation(
    drive: LegGeometry,
    delta: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    strokes: np.ndarray,
    pose_covariance: np.ndarray,
    stroke_sigma_mm: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The leg-length EKF's whole observation at one measured pose, in one compiled call.

    For the drive ``M + δM`` (``drive`` and the 42-vector ``delta``) at the pose ``(R, t)`` an
    instrument measured with covariance ``Σ_x`` (body tangent), equal to (up to rounding)::

        r = leg_residuals(M + δM, R, t, strokes)
        J_x, H = leg_residual_jacobians(M + δM, R, t)
        R_meas = J_x @ Σ_x @ J_x.T + σ_q² I

    Returns:
        ``(r (6,) [mm], H (6, 42), R_meas (6, 6) [mm²], J_x (6, 6))``; NaN in ``R_meas`` if
        ``Σ_x`` holds NaN (a singular tracker Jacobian).
    """
    c = np.ascontiguousarray  # one array layout, so one compiled signature
    return _kernels.leg_observation(
        drive.base_joints,
        drive.platform_joints,
        drive.initial_lengths,
        c(delta, dtype=float),
        c(R, dtype=float),
        c(t, dtype=float),
        c(strokes, dtype=float),
        c(pose_covariance, dtype=float),
        float(stroke_sigma_mm) ** 2,
    )


def leg_residual(
    R: np.ndarray, t: np.ndarray, legs: np.ndarray, extensions_mm: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``‖t + R d_i − j_i‖ − (l_i + e_i)`` of ``k`` legs ``[j_i | d_i | l_i]`` with their
    Jacobians, in one compiled call (a factor linearises it thousands of times a second).

    Shared by the drive legs (extension = stroke q_i) and the tracker's rulers (reading s_i).

    Args:
        R, t: platform pose ``(3, 3)``, ``(3,)`` [mm].
        legs: ``(k, 7)`` geometry rows ``[j_x j_y j_z d_x d_y d_z l]`` [mm].
        extensions_mm: ``(k,)`` strokes or readings [mm].
    Returns:
        ``(r (k,) [mm], ∂r/∂ξ (k, 6) on ξ = [ω, v], ∂r/∂leg (k, 7))``, row i
        ``[(d_i × Rᵀn_i)ᵀ, (Rᵀn_i)ᵀ]`` and ``[−n_iᵀ, (Rᵀn_i)ᵀ, −1]``.
    """
    c = np.ascontiguousarray  # one array layout, so one compiled signature
    legs, extensions = c(legs, dtype=float), c(extensions_mm, dtype=float)
    k = len(extensions)
    r, J_pose, J_leg = np.empty(k), np.empty((k, 6)), np.empty(legs.shape)
    _kernels.leg_rows(legs, c(R, dtype=float), c(t, dtype=float), extensions, r, J_pose, J_leg)
    return r, J_pose, J_leg


def solve_fk(
    legs: LegGeometry,
    lengths: np.ndarray,
    guess: tuple[np.ndarray, np.ndarray] | None,
    what: str,
    tol_mm: float = FK_TOLERANCE_MM,
) -> tuple[np.ndarray, np.ndarray]:
    """FK from ``guess`` (the previous pose), then from the default cold guess: a jump between
    samples can leave the old pose outside Newton's basin.

    Raises:
        SampleRejected: neither start converges; ``what`` names the leg set.
    """
    R, t = start_pose(guess)
    # one compiled call for both starts: forward_kinematics' batch wrapper costs more a pose than the solve
    residual = _kernels.fk_single(
        legs.base_joints,
        legs.platform_joints,
        legs.initial_lengths,
        np.ascontiguousarray(lengths, dtype=float),
        R,
        t,
        guess is not None,
        float(tol_mm),
        FK_MAX_ITERATIONS,
    )
    if residual <= tol_mm:
        return R, t
    raise fk_failed(what, residual)


def tracker_reading_residuals(
    tracker: LegGeometry,
    readings: np.ndarray,
    drives: list[LegGeometry],
    inputs: list[np.ndarray],
    terms: tuple | None = None,
    load: tuple | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The tracker's ``readings`` minus what it reads where each drive puts the platform, for a
    log's samples in order, in one compiled pass: ``readings − inverse_kinematics(tracker,
    forward_kinematics(drives[j], extensions[j]))``, within FK's tolerance of that batch solve
    (each Newton starts from a neighbouring solution, see
    :func:`stewart_calib.model._kernels.tracker_reading_residuals`, instead of the level guess).

    Args:
        readings: ``(N, 6)`` tracker readings s_i [mm].
        drives: ``m`` drive geometries, e.g. the nominal and a calibrated one.
        inputs: ``m`` arrays ``(N, width)``, each drive's inputs: its extensions [mm] (e.g. strokes scaled
            by its stroke scale) where ``terms`` is None.
        terms: ``(starts (b,), gains (b,), factors (m, b, 6))``: the extensions as
            :func:`stewart_calib.model._kernels.leg_extensions` makes them of the inputs.
        load: ``(force_start, weights (N, K) [N], downs (N, 3), centres (K, 3) [mm], radii (m,), passes,
            settled_mm)``, ``downs`` each sample's unit vector of gravity in {J}: the drives settle under
            it, their joints rigid (:func:`stewart_calib.model._kernels.settle_pose`); None: they are rigid.
    Returns:
        ``(residuals (m, N, 6) [mm], converged (m, N))``: a sample's residuals are meaningless
        where its FK did not converge.
    """
    c = np.ascontiguousarray
    readings = c(readings, dtype=float)
    residuals, fk_residual = np.empty((len(drives),) + readings.shape), np.empty((len(drives), len(readings)))
    u = np.array(inputs, dtype=float)  # a copy: a settling drive's force columns are written into it
    if terms is None:  # the inputs are the extensions: one term of gain 1
        terms = (np.zeros(1, dtype=np.int64), np.ones(1), np.ones((len(drives), 1, len(drives[0].initial_lengths))))
    if load is None:
        load = (
            -1,
            np.empty((len(readings), 0)),
            np.empty((len(readings), 3)),
            np.empty((0, 3)),
            np.ones(len(drives)),
            0,
            0.0,
        )
    force_start, weights, downs, centres, radii, passes, settled_mm = load
    starts, gains, factors = terms
    _kernels.tracker_reading_residuals(
        _readonly(c([d.base_joints for d in drives])),  # as LegGeometry's: the FK kernels compile once
        _readonly(c([d.platform_joints for d in drives])),
        _readonly(c([d.initial_lengths for d in drives])),
        u,
        tracker.base_joints,
        tracker.platform_joints,
        tracker.initial_lengths,
        readings,
        FK_TOLERANCE_MM,
        FK_MAX_ITERATIONS,
        residuals,
        fk_residual,
        c(starts, dtype=np.int64),
        c(gains, dtype=float),
        c(factors, dtype=float),
        int(force_start),
        c(weights, dtype=float),
        np.array(np.broadcast_to(downs, (len(readings), 3)), dtype=float, order="C"),  # a writable copy: one signature
        _readonly(c(centres, dtype=float)),
        c(radii, dtype=float),
        int(passes),
        float(settled_mm),
    )
    return residuals, fk_residual <= FK_TOLERANCE_MM


def _readonly(array: np.ndarray) -> np.ndarray:
    """A read-only view of ``array``. The kernels take geometry read-only (as :class:`LegGeometry` holds it):
    numba compiles a kernel once per array mutability, so a writable copy would compile the FK twice."""
    view = array.view()
    view.setflags(write=False)
    return view


def start_pose(guess: tuple[np.ndarray, np.ndarray] | None) -> tuple[np.ndarray, np.ndarray]:
    """Fresh C arrays ``(R, t)`` for a compiled FK to overwrite: a copy of ``guess`` (the warm start),
    or placeholders when there is none (the kernel then starts cold)."""
    if guess is None:
        return np.eye(3), np.zeros(3)
    return np.array(guess[0], dtype=float), np.array(guess[1], dtype=float)


def fk_failed(what: str, residual_mm: float) -> SampleRejected:
    """The refusal of a sample whose ``what`` leg set's FK converged from no start."""
    return SampleRejected(
        f"{what} forward kinematics did not converge (residual {residual_mm:.3g} mm): the lengths may be unreachable",
        SampleRejected.FK_FAILED,
    )
