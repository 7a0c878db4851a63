"""numba kernels behind :mod:`stewart_calib.model.kinematics` and the EKFs' per-sample path.

Why numba: one 6-leg pose is ~100 flops, so numpy's 1–2 µs per small-array call dominates
(a warm numpy Newton solve costs 100–200 µs, docs/measured-facts.md); written as loops over the
six legs and compiled, the same solve takes a few µs. The public, vectorised functions of
:mod:`stewart_calib.model.kinematics` keep their numpy signatures and call these; nothing else
should import this module (but :mod:`stewart_calib.estimators.measurement`, for
``pose_difference`` and the sample check, ``LegGeometry.perturbed``,
:mod:`stewart_calib.analysis.identifiability` for the whitened rows,
:mod:`stewart_calib.estimators.kalman`, whose compiled filter pass observes through them, and
:mod:`stewart_calib.model.statics` and :mod:`stewart_calib.simulation.load`, whose robot settling under its
load is here, below the kinematics, so that the tracker residuals of an elastic drive settle with it).

Conventions (see :mod:`stewart_calib.model.kinematics`): mm and rad; a pose is ``(R, t)`` of the
platform frame {D} in the base frame {J}; pose Jacobians are in the body tangent
``ξ = [ω, v]`` (rotation first, GTSAM order), ``R ← R Exp(ω)``, ``t ← t + R v``.

The kernels Python calls are compiled ahead of time at installation, at the argument types their
``entry`` declares (:func:`stewart_calib._jit.njit`, as :mod:`stewart_calib.estimators.kalman`); where
that module is missing or stale, or a call passes other types, numba compiles on first use and caches on
disk. The wrappers pass C-contiguous float64 arrays, Python floats/ints and geometry read-only, so each
kernel has one signature (the rules that keep the compile small: :mod:`stewart_calib._jit`). No ``fastmath``:
the Newton tolerance (1e-9 mm on ~1000 mm lengths) sits a few ulps above rounding, and
the kernels must report NaN exactly as numpy would.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .._jit import BOOL, F8_1, F8_2, F8_3, FLOAT, I8_1, INT, RO_1, RO_2, RO_3, njit

# error_model="numpy": x / 0 gives inf/NaN as in numpy instead of raising ZeroDivisionError.
_JIT: dict[str, Any] = {"nogil": True, "error_model": "numpy"}

# Newton step cap (forward_kinematics): a poor guess can give wild steps that leave the basin.
_MAX_STEP_RAD = 0.2
_MAX_STEP_MM = 100.0


# ----------------------------------------------------------------------------- small helpers


@njit(**_JIT)
def _solve(A, B):
    """``A X = B`` for ``A (6, 6)``, ``B (6, m)``, by Gaussian elimination with partial pivoting.

    Overwrites both (``B`` becomes ``X``). Returns False on an exactly zero pivot, where
    LAPACK's ``getrf`` (``np.linalg.solve``) would raise ``LinAlgError``.
    """
    m = B.shape[1]
    for k in range(6):
        p = k
        for i in range(k + 1, 6):
            if abs(A[i, k]) > abs(A[p, k]):
                p = i
        if A[p, k] == 0.0:
            return False
        if p != k:
            for j in range(6):
                A[k, j], A[p, j] = A[p, j], A[k, j]
            for j in range(m):
                B[k, j], B[p, j] = B[p, j], B[k, j]
        for i in range(k + 1, 6):
            f = A[i, k] / A[k, k]
            for j in range(k + 1, 6):
                A[i, j] -= f * A[k, j]
            for j in range(m):
                B[i, j] -= f * B[k, j]
    for j in range(m):
        for i in range(5, -1, -1):
            s = B[i, j]
            for c in range(i + 1, 6):
                s -= A[i, c] * B[c, j]
            B[i, j] = s / A[i, i]
    return True


@njit(**_JIT)
def _unit_legs(base, plat, R, t, n, length):
    """``l_i n_i = t + R p_i − b_i`` (paper eq. 1): fills ``n (6, 3)`` and ``length (6,)``."""
    for i in range(6):
        norm2 = 0.0
        for a in range(3):
            v = t[a] + R[a, 0] * plat[i, 0] + R[a, 1] * plat[i, 1] + R[a, 2] * plat[i, 2] - base[i, a]
            n[i, a] = v
            norm2 += v * v
        length[i] = math.sqrt(norm2)
        for a in range(3):
            n[i, a] /= length[i]


@njit(**_JIT)
def _pose_jacobian(plat, R, n, J):
    """``∂ length_i / ∂ξ`` row ``[(p_i × Rᵀn_i)ᵀ, (Rᵀn_i)ᵀ]`` into ``J (6, 6)`` (kinematics.leg_pose_jacobian)."""
    for i in range(6):
        nb0 = R[0, 0] * n[i, 0] + R[1, 0] * n[i, 1] + R[2, 0] * n[i, 2]  # Rᵀ n_i
        nb1 = R[0, 1] * n[i, 0] + R[1, 1] * n[i, 1] + R[2, 1] * n[i, 2]
        nb2 = R[0, 2] * n[i, 0] + R[1, 2] * n[i, 1] + R[2, 2] * n[i, 2]
        J[i, 0] = plat[i, 1] * nb2 - plat[i, 2] * nb1
        J[i, 1] = plat[i, 2] * nb0 - plat[i, 0] * nb2
        J[i, 2] = plat[i, 0] * nb1 - plat[i, 1] * nb0
        J[i, 3], J[i, 4], J[i, 5] = nb0, nb1, nb2


@njit(**_JIT)
def _retract(R, t, w0, w1, w2, v0, v1, v2):
    """In place ``t ← t + R v``, ``R ← R Exp(ω)`` (Rodrigues, series below 1e-6 rad; kinematics.retract)."""
    for a in range(3):
        t[a] += R[a, 0] * v0 + R[a, 1] * v1 + R[a, 2] * v2
    theta2 = w0 * w0 + w1 * w1 + w2 * w2
    if theta2 < 1e-12:
        c1, c2 = 1.0 - theta2 / 6.0, 0.5 - theta2 / 24.0
    else:
        theta = math.sqrt(theta2)
        c1, c2 = math.sin(theta) / theta, (1.0 - math.cos(theta)) / theta2
    # Exp(ω) = I + c1 [ω]× + c2 [ω]×²,  [ω]×² = ω ωᵀ − θ² I; in scalars, as a Newton step's
    # one allocation would cost a tenth of the step
    diagonal = 1.0 - c2 * theta2
    e00, e01, e02 = c2 * w0 * w0 + diagonal, c2 * w0 * w1 - c1 * w2, c2 * w0 * w2 + c1 * w1
    e10, e11, e12 = c2 * w1 * w0 + c1 * w2, c2 * w1 * w1 + diagonal, c2 * w1 * w2 - c1 * w0
    e20, e21, e22 = c2 * w2 * w0 - c1 * w1, c2 * w2 * w1 + c1 * w0, c2 * w2 * w2 + diagonal
    for a in range(3):
        r0, r1, r2 = R[a, 0], R[a, 1], R[a, 2]
        R[a, 0] = r0 * e00 + r1 * e10 + r2 * e20
        R[a, 1] = r0 * e01 + r1 * e11 + r2 * e21
        R[a, 2] = r0 * e02 + r1 * e12 + r2 * e22


@njit(**_JIT)
def _rpy(R):
    """Roll, pitch, yaw of ``R = Rz(γ) Ry(β) Rx(α)`` (kinematics.rotation_to_rpy, paper eq. 20–21)."""
    return (
        math.atan2(R[2, 1], R[2, 2]),
        math.atan2(-R[2, 0], math.hypot(R[2, 1], R[2, 2])),
        math.atan2(R[1, 0], R[0, 0]),
    )


@njit(**_JIT)
def _rotation(pose6, R):
    """``R = Rz(γ) Ry(β) Rx(α)`` of ``pose6[3:6] = [α, β, γ]`` [rad] into ``R`` (rotations.rpy_to_rotation)."""
    ca, cb, cg = math.cos(pose6[3]), math.cos(pose6[4]), math.cos(pose6[5])
    sa, sb, sg = math.sin(pose6[3]), math.sin(pose6[4]), math.sin(pose6[5])
    R[0, 0] = cb * cg
    R[0, 1] = sa * sb * cg - sg * ca
    R[0, 2] = sb * ca * cg + sa * sg
    R[1, 0] = sg * cb
    R[1, 1] = sa * sb * sg + ca * cg
    R[1, 2] = sb * sg * ca - sa * cg
    R[2, 0] = -sb
    R[2, 1] = sa * cb
    R[2, 2] = ca * cb


@njit(**_JIT)
def _adjoint(R, t):
    """``Ad_T = [[R, 0], [t^ R, R]]`` (6, 6) in the ``[ω, v]`` order (model.rotations.adjoint)."""
    Ad = np.zeros((6, 6))
    for a in range(3):
        for b in range(3):
            Ad[a, b] = R[a, b]
            Ad[3 + a, 3 + b] = R[a, b]
    for b in range(3):  # t^ R: column b is t × R[:, b]
        Ad[3, b] = t[1] * R[2, b] - t[2] * R[1, b]
        Ad[4, b] = t[2] * R[0, b] - t[0] * R[2, b]
        Ad[5, b] = t[0] * R[1, b] - t[1] * R[0, b]
    return Ad


@njit(**_JIT)
def _tangent_from_pose6(pose6, R):
    """``(∂pose6/∂ξ)⁻¹ = [[0, Rᵀ T], [Rᵀ, 0]]`` (6, 6): the inverse of
    model.rotations.pose6_tangent_jacobian ``[[0, R], [T⁻¹ R, 0]]`` in closed form (``T`` of paper
    eq. 4–5 at the pose's pitch β and yaw γ)."""
    cb, sb = math.cos(pose6[4]), math.sin(pose6[4])
    cg, sg = math.cos(pose6[5]), math.sin(pose6[5])
    T = np.array([[cb * cg, -sg, 0.0], [cb * sg, cg, 0.0], [-sb, 0.0, 1.0]])
    out = np.zeros((6, 6))
    for a in range(3):
        for b in range(3):
            out[3 + a, b] = R[b, a]
            out[a, 3 + b] = R[0, a] * T[0, b] + R[1, a] * T[1, b] + R[2, a] * T[2, b]
    return out


@njit(**_JIT)
def pose_instrument_observation(z, theta, orientation_variance, position_variance):
    """The pose instrument's loose pose in one call (instruments.pose.PoseModel.pose): ``X = F M G⁻¹``
    of the reading ``M = z`` (pose6 [mm, rad]) with frame ``F = θ[:6]`` and target ``G = θ[6:12]``,
    the reading's covariance carried to X's tangent ``Ad_G N Ad_Gᵀ`` (``N`` = the orientation and
    position variances), and ``∂ξ/∂θ = [Ad_{G M⁻¹} (∂f/∂φ)⁻¹, −Ad_G (∂g/∂γ)⁻¹]`` (6, 12).

    Returns:
        ``(R_X, t_X, covariance, J_instrument)``.
    """
    R_F, R_M, R_G = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    _rotation(theta[0:6], R_F)
    _rotation(z, R_M)
    _rotation(theta[6:12], R_G)
    t_F, t_M, t_G = theta[0:3], z[0:3], theta[6:9]
    R_FM = R_F @ R_M
    t_FM = t_F + R_F @ t_M
    R_X = R_FM @ R_G.T
    t_X = t_FM - R_X @ t_G  # t_FM + R_FM (−R_Gᵀ t_G)
    Ad_G = _adjoint(R_G, t_G)
    noise = np.array([orientation_variance] * 3 + [position_variance] * 3)
    covariance = np.empty((6, 6))
    for a in range(6):
        for b in range(6):
            s = 0.0
            for c in range(6):
                s += Ad_G[a, c] * noise[c] * Ad_G[b, c]
            covariance[a, b] = s
    R_GMi = R_G @ R_M.T
    t_GMi = t_G - R_GMi @ t_M
    J = np.empty((6, 12))
    J[:, 0:6] = _adjoint(R_GMi, t_GMi) @ _tangent_from_pose6(theta[0:6], R_F)
    J[:, 6:12] = -(Ad_G @ _tangent_from_pose6(theta[6:12], R_G))
    return R_X, t_X, covariance, J


# ----------------------------------------------------------------------------- the drive's extensions


@njit(**_JIT)
def leg_extensions(starts, gains, factors, inputs, out):
    """``e_i = Σ_b factors[b, i] · gains[b] · inputs[starts[b] + i]`` into ``out (6,)``: a drive's leg
    extensions (drive.DriveModel.extensions, ``factors = o_b + v_b``) from one sample's inputs."""
    for i in range(6):
        e = factors[0, i] * (inputs[starts[0] + i] if gains[0] == 1.0 else gains[0] * inputs[starts[0] + i])
        for b in range(1, starts.shape[0]):
            e += factors[b, i] * (inputs[starts[b] + i] if gains[b] == 1.0 else gains[b] * inputs[starts[b] + i])
        out[i] = e


# ----------------------------------------------------------------------------- forward kinematics


@njit(**_JIT)
def _damped_step(J, target, length, A, step):
    """Least-squares Newton step for a singular ``J``: ``(JᵀJ + λI) ξ = Jᵀ e`` into ``step (6, 1)``.

    As λ → 0 this tends to the minimum-norm least-squares step (``np.linalg.lstsq``);
    ``λ = 1e-12 · tr(JᵀJ)`` only has to keep the null space of ``J`` out of the step. Written
    by hand because LAPACK's SVD in numba adds ~2.5 s to the kernel's first compile, for a
    case (e.g. all platform joints at one point) regular platforms never reach.
    """
    trace = 0.0
    for a in range(6):
        s = 0.0
        for i in range(6):
            s += J[i, a] * (target[i] - length[i])
        step[a, 0] = s
        for b in range(6):
            s = 0.0
            for i in range(6):
                s += J[i, a] * J[i, b]
            A[a, b] = s
        trace += A[a, a]
    for a in range(6):
        A[a, a] += 1e-12 * trace
    if not _solve(A, step):  # J = 0: no direction to step in
        step[:] = 0.0


@njit(**_JIT)
def _fk_work():
    """Scratch arrays of one pose's Newton solve (:func:`_newton`, :func:`_fk_single`): the unit
    legs, their lengths, the Jacobian, its factored copy, the step, the target lengths. A pass
    over many poses makes them once (an allocation costs about a Newton step's arithmetic)."""
    return np.empty((6, 3)), np.empty(6), np.empty((6, 6)), np.empty((6, 6)), np.empty((6, 1)), np.empty(6)


@njit(**_JIT)
def _newton(base, plat, target, R, t, tol_mm, max_iterations, work):
    """Newton–Raphson from ``(R, t)`` (overwritten) to the leg lengths ``target`` of one pose
    (see :func:`fk_newton`); ``work`` from :func:`_fk_work`. Returns ``(iterations, residual)``."""
    n_legs, length, J, A, err, _ = work
    iterations = 0
    while True:
        _unit_legs(base, plat, R, t, n_legs, length)
        worst = 0.0
        for i in range(6):
            err[i, 0] = target[i] - length[i]
            e = abs(err[i, 0])
            if e > worst or e != e:  # once NaN, stays NaN (e > NaN is False), as np.max reports it
                worst = e
        if not worst > tol_mm or iterations >= max_iterations:
            return iterations, worst
        _pose_jacobian(plat, R, n_legs, J)
        for i in range(6):
            for j in range(6):
                A[i, j] = J[i, j]
        if not _solve(A, err):  # singular Jacobian (degenerate pose): least-squares step
            _damped_step(J, target, length, A, err)
        xi = err[:, 0]
        norm_w = math.sqrt(xi[0] * xi[0] + xi[1] * xi[1] + xi[2] * xi[2])
        norm_v = math.sqrt(xi[3] * xi[3] + xi[4] * xi[4] + xi[5] * xi[5])
        scale = min(1.0, _MAX_STEP_RAD / max(norm_w, 1e-300), _MAX_STEP_MM / max(norm_v, 1e-300))
        _retract(R, t, scale * xi[0], scale * xi[1], scale * xi[2], scale * xi[3], scale * xi[4], scale * xi[5])
        iterations += 1


@njit(**_JIT)
def _finite_target(initial_lengths, strokes, target):
    """``target = initial_lengths + strokes``; False when a stroke is not finite."""
    finite = True
    for i in range(6):
        target[i] = initial_lengths[i] + strokes[i]
        finite = finite and math.isfinite(strokes[i])
    return finite


@njit(entry=(RO_3, RO_3, RO_2, F8_2, F8_3, F8_2, FLOAT, INT, BOOL, I8_1, F8_1), **_JIT)
def fk_newton(base, plat, initial_lengths, strokes, R, t, tol_mm, max_iterations, along, iterations, residual):
    """Newton–Raphson FK (paper §3.2 step 1) for ``n`` poses, in place.

    Args:
        base, plat, initial_lengths: ``(G, 6, 3)`` joints b_i in {J} and p_i in {D}, ``(G, 6)``
            lengths at zero stroke [mm]: ``G = 1``, one geometry for every pose, or ``G = n``,
            pose k solved with geometry k (e.g. the load-perturbed drive of the simulator).
        strokes: ``(n, 6)`` strokes or readings [mm]; the target lengths are
            ``initial_lengths + strokes``. A pose with a non-finite stroke is skipped
            (residual ``inf``, 0 iterations, guess untouched).
        R, t: ``(n, 3, 3)``, ``(n, 3)`` starting poses, overwritten with the solutions.
        tol_mm, max_iterations: stop once max |length error| ≤ ``tol_mm`` (a NaN residual
            also stops) or after ``max_iterations`` steps.
        along: the poses are a log's, in order: pose k > 0 starts from pose k − 1's solution where
            that converged (its solution standing only within one uncapped Newton step of it, as in
            :func:`tracker_reading_residuals`), else from the level guess (``R[k]``, ``t[k]`` unused).
        iterations, residual: ``(n,)`` outputs: steps taken, max |length error| [mm] at the
            returned pose.
    """
    work = _fk_work()
    for k in range(strokes.shape[0]):
        g = k if base.shape[0] > 1 else 0
        if not _finite_target(initial_lengths[g], strokes[k], work[5]):
            iterations[k], residual[k] = 0, np.inf
            continue
        if along and k >= 1:
            if residual[k - 1] <= tol_mm:
                copy_pose(R[k - 1], t[k - 1], R[k], t[k])
                iterations[k], residual[k] = _newton(
                    base[g], plat[g], work[5], R[k], t[k], tol_mm, max_iterations, work
                )
                if residual[k] <= tol_mm and _within_a_step(R[k - 1], t[k - 1], R[k], t[k]):
                    continue
            _level_guess(base[g], plat[g], work[5], R[k], t[k])
        iterations[k], residual[k] = _newton(base[g], plat[g], work[5], R[k], t[k], tol_mm, max_iterations, work)


@njit(entry=(RO_2, RO_2, RO_1, F8_1, F8_2, F8_1, BOOL, FLOAT, INT), **_JIT)
def fk_single(base, plat, initial_lengths, lengths, R, t, warm, tol_mm, max_iterations):
    """One pose's FK in one call (kinematics.solve_fk): Newton from ``(R, t)`` when ``warm``, then,
    if that does not converge, from the level cold guess of ``kinematics.default_guess``.

    Args:
        base, plat: ``(6, 3)`` joints; initial_lengths, lengths: ``(6,)`` [mm].
        R, t: ``(3, 3)``, ``(3,)`` the warm start, overwritten with the solution (C arrays).
    Returns:
        max |length error| [mm] at the returned pose (``> tol_mm``: neither start converged).
    """
    return _fk_single(base, plat, initial_lengths, lengths, R, t, warm, tol_mm, max_iterations, _fk_work())


@njit(**_JIT)
def _fk_single(base, plat, initial_lengths, lengths, R, t, warm, tol_mm, max_iterations, work):
    """:func:`fk_single` with the scratch arrays ``work`` of :func:`_fk_work`."""
    target = work[5]
    finite = _finite_target(initial_lengths, lengths, target)
    if warm and finite:
        residual = _newton(base, plat, target, R, t, tol_mm, max_iterations, work)[1]
        if residual <= tol_mm:
            return residual
    _level_guess(base, plat, target, R, t)
    return _newton(base, plat, target, R, t, tol_mm, max_iterations, work)[1] if finite else np.inf


@njit(**_JIT)
def _level_guess(base, plat, target, R, t):
    """``(R, t)`` = kinematics.default_guess for leg lengths ``target``: level, above the base centre,
    the mean leg length matched."""
    z = 0.0
    for i in range(6):
        dx = base[i, 0] - plat[i, 0]
        dy = base[i, 1] - plat[i, 1]
        z += math.sqrt(max(target[i] * target[i] - dx * dx - dy * dy, 1.0)) + base[i, 2] - plat[i, 2]
    R[:, :] = 0.0
    for i in range(3):
        R[i, i] = 1.0
        t[i] = 0.0
    t[2] = z / 6.0


@njit(**_JIT)
def _moved_pose(R_from, t_from, R_a, t_a, R_b, t_b, R, t):
    """``(R, t)``: the pose ``(R_from, t_from)`` moved as another went from ``(R_a, t_a)`` to
    ``(R_b, t_b)`` — ``R = R_from R_aᵀ R_b``, ``t = t_from − t_a + t_b`` (their offset held in the
    base frame) — a Newton start. ``R`` is made orthonormal again by a step of
    ``R ← R (3I − RᵀR) / 2``, so that rounding does not build up along a log."""
    for a in range(3):
        c0 = R_from[a, 0] * R_a[0, 0] + R_from[a, 1] * R_a[0, 1] + R_from[a, 2] * R_a[0, 2]  # row a of R_from R_aᵀ
        c1 = R_from[a, 0] * R_a[1, 0] + R_from[a, 1] * R_a[1, 1] + R_from[a, 2] * R_a[1, 2]
        c2 = R_from[a, 0] * R_a[2, 0] + R_from[a, 1] * R_a[2, 1] + R_from[a, 2] * R_a[2, 2]
        for b in range(3):
            R[a, b] = c0 * R_b[0, b] + c1 * R_b[1, b] + c2 * R_b[2, b]
        t[a] = t_from[a] - t_a[a] + t_b[a]
    s00 = R[0, 0] * R[0, 0] + R[1, 0] * R[1, 0] + R[2, 0] * R[2, 0]  # RᵀR
    s01 = R[0, 0] * R[0, 1] + R[1, 0] * R[1, 1] + R[2, 0] * R[2, 1]
    s02 = R[0, 0] * R[0, 2] + R[1, 0] * R[1, 2] + R[2, 0] * R[2, 2]
    s11 = R[0, 1] * R[0, 1] + R[1, 1] * R[1, 1] + R[2, 1] * R[2, 1]
    s12 = R[0, 1] * R[0, 2] + R[1, 1] * R[1, 2] + R[2, 1] * R[2, 2]
    s22 = R[0, 2] * R[0, 2] + R[1, 2] * R[1, 2] + R[2, 2] * R[2, 2]
    for a in range(3):
        r0, r1, r2 = R[a, 0], R[a, 1], R[a, 2]
        R[a, 0] = r0 * (1.5 - 0.5 * s00) - r1 * 0.5 * s01 - r2 * 0.5 * s02
        R[a, 1] = -r0 * 0.5 * s01 + r1 * (1.5 - 0.5 * s11) - r2 * 0.5 * s12
        R[a, 2] = -r0 * 0.5 * s02 - r1 * 0.5 * s12 + r2 * (1.5 - 0.5 * s22)


@njit(**_JIT)
def copy_pose(R_from, t_from, R, t):
    """``R[:, :] = R_from``, ``t[:] = t_from``, element by element: numba compiles an array-to-array slice
    assignment with its shape-mismatch error message, string formatting that costs a first compile seconds."""
    for a in range(3):
        t[a] = t_from[a]
        for b in range(3):
            R[a, b] = R_from[a, b]


@njit(**_JIT)
def _within_a_step(R_a, t_a, R_b, t_b):
    """Whether two poses are less than one uncapped Newton step apart (``_MAX_STEP_RAD``, ``_MAX_STEP_MM``)."""
    d2, trace = 0.0, 0.0
    for a in range(3):
        d2 += (t_b[a] - t_a[a]) ** 2
        for b in range(3):
            trace += R_a[a, b] * R_b[a, b]  # tr(R_aᵀ R_b) = 1 + 2 cos(angle)
    return d2 <= _MAX_STEP_MM**2 and (trace - 1.0) / 2.0 >= math.cos(_MAX_STEP_RAD)


# ----------------------------------------------------------------------------- a robot settling under its load

#: the statics matrix is refused as singular where ``|det|`` over the product of its column norms
#: (Hadamard's ratio, 1 for orthogonal columns, 0 at a singularity; the moment rows divided by the
#: platform's joint radius so that the ratio does not depend on the unit of length) falls below
#: this. The leg forces grow as the inverse of the smallest singular value: at 1e-6 they are of the
#: order of a million times the weight, no longer anything a leg carries.
SINGULAR_RATIO = 1e-6


@njit(**_JIT)
def pose_gravity_forces(base, plat, R, t, weights, down, coms, radius, A, w, forces):
    """One pose's ``Aᵀ`` (column i ``[n_i; R d_i × n_i]``), Hadamard's ratio of it with the moment rows
    over ``radius`` (returned), and ``f`` solving ``Aᵀ f = −w`` for weights ``(K,)`` [N] acting along the
    unit vector ``down (3,)`` in {J} at their centres ``coms (K, 3)`` in {D} into ``forces (6,)`` (left
    unset where the ratio is below :data:`SINGULAR_RATIO` or a pivot is zero); ``A (6, 6)``, ``w (6, 1)``:
    scratch (:mod:`stewart_calib.model.statics`, whose equations these are)."""
    for i in range(6):
        p0 = R[0, 0] * plat[i, 0] + R[0, 1] * plat[i, 1] + R[0, 2] * plat[i, 2]
        p1 = R[1, 0] * plat[i, 0] + R[1, 1] * plat[i, 1] + R[1, 2] * plat[i, 2]
        p2 = R[2, 0] * plat[i, 0] + R[2, 1] * plat[i, 1] + R[2, 2] * plat[i, 2]
        v0, v1, v2 = t[0] + p0 - base[i, 0], t[1] + p1 - base[i, 1], t[2] + p2 - base[i, 2]
        norm = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        n0, n1, n2 = v0 / norm, v1 / norm, v2 / norm
        A[0, i], A[1, i], A[2, i] = n0, n1, n2
        A[3, i], A[4, i], A[5, i] = p1 * n2 - p2 * n1, p2 * n0 - p0 * n2, p0 * n1 - p1 * n0
    # the weight W down at R c: force and moment about the platform origin, negated (for down = −z the
    # products are those of (0, 0, −W) exactly, so the forces are bit for bit those of gravity along −z)
    w[0, 0], w[1, 0], w[2, 0], w[3, 0], w[4, 0], w[5, 0] = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    for j in range(coms.shape[0]):
        g0, g1, g2 = weights[j] * down[0], weights[j] * down[1], weights[j] * down[2]
        c0 = R[0, 0] * coms[j, 0] + R[0, 1] * coms[j, 1] + R[0, 2] * coms[j, 2]
        c1 = R[1, 0] * coms[j, 0] + R[1, 1] * coms[j, 1] + R[1, 2] * coms[j, 2]
        c2 = R[2, 0] * coms[j, 0] + R[2, 1] * coms[j, 1] + R[2, 2] * coms[j, 2]
        w[0, 0] -= g0
        w[1, 0] -= g1
        w[2, 0] -= g2
        w[3, 0] -= c1 * g2 - c2 * g1
        w[4, 0] -= c2 * g0 - c0 * g2
        w[5, 0] -= c0 * g1 - c1 * g0
    product = 1.0  # of the column norms, moment rows over radius
    for i in range(6):
        column = A[0, i] * A[0, i] + A[1, i] * A[1, i] + A[2, i] * A[2, i]
        column += (A[3, i] * A[3, i] + A[4, i] * A[4, i] + A[5, i] * A[5, i]) / (radius * radius)
        product *= np.sqrt(column)
    if not _solve(A, w):  # A becomes U of its LU: |det| is the product of U's diagonal
        return 0.0
    determinant = 1.0
    for i in range(6):
        determinant *= A[i, i]
        forces[i] = w[i, 0]
    return abs(determinant) / radius**3 / product


@njit(**_JIT)
def pose_drift(base_params, R, t, forces, stiffness, params):
    """``params = M_base + δM`` of one pose from its leg forces [N] (:mod:`stewart_calib.simulation.load`,
    step 3): ``n_i`` on the base geometry ``base_params (42,)``; ``stiffness``
    ``[k_leg, k_base_joint, k_platform_joint, k_bending]`` [N/mm] (``inf``: that part rigid, no drift)."""
    k_leg, k_base, k_platform, k_bending = stiffness[0], stiffness[1], stiffness[2], stiffness[3]
    for i in range(len(forces)):  # seven parameters a leg, one force a leg
        o = 7 * i
        # the leg vector t + R d_i − j_i in scalars: an array a pose would cost as much as the rest
        v0 = t[0] + R[0, 0] * base_params[o + 3] + R[0, 1] * base_params[o + 4] + R[0, 2] * base_params[o + 5]
        v1 = t[1] + R[1, 0] * base_params[o + 3] + R[1, 1] * base_params[o + 4] + R[1, 2] * base_params[o + 5]
        v2 = t[2] + R[2, 0] * base_params[o + 3] + R[2, 1] * base_params[o + 4] + R[2, 2] * base_params[o + 5]
        v0, v1, v2 = v0 - base_params[o], v1 - base_params[o + 1], v2 - base_params[o + 2]
        norm = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        f = forces[i]
        v0, v1, v2 = v0 / norm * f, v1 / norm * f, v2 / norm * f  # the push of leg i on the platform, in {J} [N]
        params[o], params[o + 1], params[o + 2] = (
            base_params[o] - v0 / k_base,
            base_params[o + 1] - v1 / k_base,
            base_params[o + 2] - v2 / k_base,
        )
        for a in range(3):  # the same push in {D}: Rᵀ (n_i f_i)
            body = R[0, a] * v0 + R[1, a] * v1 + R[2, a] * v2
            sink = body / k_platform + body / k_bending if a == 2 else body / k_platform
            params[o + 3 + a] = base_params[o + 3 + a] + sink
        params[o + 6] = base_params[o + 6] - f / k_leg


@njit(**_JIT)
def split_params(params, base, plat, lengths):
    """``j_i`` into ``base (6, 3)``, ``d_i`` into ``plat (6, 3)``, ``l_i`` into ``lengths (6,)`` of a
    parameter vector ``(42,)`` (platform.vector_to_params), seven a leg."""
    for i in range(len(lengths)):
        for a in range(3):
            base[i, a] = params[7 * i + a]
            plat[i, a] = params[7 * i + 3 + a]
        lengths[i] = params[7 * i + 6]


@njit(**_JIT)
def settle_scratch():
    """Scratch arrays of :func:`settle_pose`: the statics' ``A``, ``w``, the loaded geometry's joints and
    lengths, the extensions, the target lengths of the pass before."""
    return (
        np.empty((6, 6)),
        np.empty((6, 1)),
        np.empty((6, 3)),
        np.empty((6, 3)),
        np.empty(6),
        np.empty(6),
        np.empty(6),
    )


@njit(**_JIT)
def settle_pose(legs, drift, load, terms, u, R, t, passes, settled_mm, tol_mm, max_iterations, work, scratch, forces):
    """Where a robot comes to rest under its load for drive inputs ``u``, from the pose ``(R, t)``
    (overwritten): passes of the leg forces at the pose (:func:`pose_gravity_forces` on the unloaded
    legs), the geometry they load (:func:`pose_drift`, where the joints give), the leg extensions
    (:func:`leg_extensions`, the forces written into ``u``'s force columns first), and Newton from the
    pose to those lengths — ``passes`` of them, or fewer once no target length moved more than
    ``settled_mm`` since the pass before (``settled_mm`` < 0: all of them). The simulator's truth
    (:mod:`stewart_calib.simulation.load`: compliant legs and joints, no force term) and the elastic
    drive model (:meth:`stewart_calib.model.drive.DriveModel.settled_kinematics`: rigid joints, the legs'
    compliance a term on the forces) are both this.

    Args:
        legs: ``(base (6, 3), plat (6, 3), initial_lengths (6,))`` the unloaded geometry.
        drift: ``(base_params (42,), stiffness (4,), params (42,) out)`` (:func:`pose_drift`;
            ``base_params`` the vector of ``legs``), or None: the geometry does not move (numba compiles
            that case without the drift, and Newton then runs on ``legs`` themselves).
        load: ``(weights (K,) [N], down (3,) the unit vector in {J} they act along, coms (K, 3) in {D} [mm],
            radius [mm])`` (:func:`pose_gravity_forces`).
        terms: ``(starts, gains, factors (b, 6), force_start)``: :func:`leg_extensions`' terms and the
            first of ``u``'s six force columns (−1: no term takes the forces).
        work, scratch: :func:`_fk_work`, :func:`settle_scratch`; forces: ``(6,)`` out [N].
    Returns:
        ``(the statics' last Hadamard ratio, Newton's last max |length error| [mm], its steps)``;
        the error is ``inf`` where the ratio fell below :data:`SINGULAR_RATIO` or a length is not finite.
    """
    base, plat, initial_lengths = legs
    weights, down, coms, radius = load
    starts, gains, factors, force_start = terms
    A, w, loaded_base, loaded_plat, lengths, extensions, previous = scratch
    target = work[5]
    ratio, residual, steps = 0.0, np.inf, 0
    for p in range(passes):
        ratio = pose_gravity_forces(base, plat, R, t, weights, down, coms, radius, A, w, forces)
        if not ratio >= SINGULAR_RATIO:
            return ratio, np.inf, steps
        if drift is not None:
            pose_drift(drift[0], R, t, forces, drift[1], drift[2])
            split_params(drift[2], loaded_base, loaded_plat, lengths)
        if force_start >= 0:
            for i in range(6):
                u[force_start + i] = forces[i]
        leg_extensions(starts, gains, factors, u, extensions)
        if drift is not None:
            finite = _finite_target(lengths, extensions, target)
        else:
            finite = _finite_target(initial_lengths, extensions, target)
        if not finite:
            return ratio, np.inf, steps
        moved = 0.0
        for i in range(6):
            moved = max(moved, abs(target[i] - previous[i]))
            previous[i] = target[i]
        if drift is not None:
            steps, residual = _newton(loaded_base, loaded_plat, target, R, t, tol_mm, max_iterations, work)
        else:
            steps, residual = _newton(base, plat, target, R, t, tol_mm, max_iterations, work)
        if p > 0 and moved <= settled_mm:
            break
    return ratio, residual, steps


@njit(
    entry=(RO_3, RO_3, RO_2, F8_3, RO_2, RO_2, RO_1, F8_2, FLOAT, INT, F8_3, F8_2)
    + (I8_1, F8_1, F8_3, INT, F8_2, F8_2, RO_2, F8_1, INT, FLOAT),
    **_JIT,
)
def tracker_reading_residuals(
    bases,
    plats,
    initial_lengths,
    inputs,
    tracker_base,
    tracker_plat,
    tracker_lengths,
    readings,
    tol_mm,
    max_iterations,
    residuals,
    fk_residual,
    starts,
    gains,
    factors,
    force_start,
    weights,
    downs,
    coms,
    radii,
    passes,
    settled_mm,
):
    """The tracker's readings minus what it reads at the FK pose of each of ``m`` drives, for ``n``
    consecutive samples (kinematics.tracker_reading_residuals), FK as :func:`fk_single` — or, with
    ``passes`` > 0, where each drive settles under its load (:func:`settle_pose`).

    Each Newton starts from a prediction (:func:`_moved_pose`): drive 0's pose extrapolated from
    its two samples before (a log moves smoothly; ~3 steps against ~5 from the level guess),
    drive j > 0's pose of the sample before moved as drive j − 1's moved since (models that
    differ by a calibration stay millimetres apart; ~2 steps). Its solution stands only within
    one uncapped Newton step of the known pose it was predicted from (drive 0's of the sample
    before, drive j − 1's of this sample), where no other FK solution lies; else, as when the
    known pose did not converge, the level cold guess decides, as :func:`fk_newton`'s callers do.

    Args:
        bases, plats: ``(m, 6, 3)`` joints; initial_lengths: ``(m, 6)``; inputs: ``(m, n, width)``
            each drive's inputs, whose extensions the terms ``starts (b,)``, ``gains (b,)``,
            ``factors (m, b, 6)`` give (:func:`leg_extensions`).
        tracker_base, tracker_plat: ``(6, 3)``; tracker_lengths: ``(6,)``; readings: ``(n, 6)`` [mm].
        residuals: ``(m, n, 6)`` out: ``s_i − (‖R p_i + t − b_i‖ − l_i)`` of the tracker [mm].
        fk_residual: ``(m, n)`` out: max |length error| of each FK [mm] (``> tol_mm``: not converged).
        force_start, weights ``(n, K)`` [N], downs ``(n, 3)``, coms ``(K, 3)``, radii ``(m,)``, passes,
            settled_mm: the load, as :func:`settle_pose` takes it (the joints rigid: an elastic drive's
            compliance is a term on the forces), sample k's ``weights[k]`` along its gravity's unit vector
            ``downs[k]`` in {J}; ``passes`` 0: no load (the others unused).
    """
    m = bases.shape[0]
    R, t = np.empty((m, 3, 3)), np.empty((m, 3))  # this sample's solutions
    R_1, t_1 = np.empty((m, 3, 3)), np.empty((m, 3))  # the sample before's
    R_2, t_2 = np.empty((3, 3)), np.empty(3)  # drive 0's two samples before
    work, scratch = _fk_work(), settle_scratch()
    extensions, forces = np.empty(6), np.empty(6)
    for k in range(readings.shape[0]):
        for j in range(m):
            Rj, tj = R[j], t[j]
            residual = np.inf
            if j == 0:
                R_known, t_known, known = R_1[0], t_1[0], k >= 1 and fk_residual[0, k - 1] <= tol_mm
                if known and k >= 2 and fk_residual[0, k - 2] <= tol_mm:
                    _moved_pose(R_1[0], t_1[0], R_2, t_2, R_1[0], t_1[0], Rj, tj)
                elif known:
                    copy_pose(R_1[0], t_1[0], Rj, tj)
            else:
                R_known, t_known, known = R[j - 1], t[j - 1], fk_residual[j - 1, k] <= tol_mm
                if known and k >= 1 and fk_residual[j, k - 1] <= tol_mm and fk_residual[j - 1, k - 1] <= tol_mm:
                    _moved_pose(R_1[j], t_1[j], R_1[j - 1], t_1[j - 1], R[j - 1], t[j - 1], Rj, tj)
                elif known:
                    copy_pose(R[j - 1], t[j - 1], Rj, tj)
            for cold in range(2):  # from the prediction where there is one, then from the level guess
                if cold == 0 and not known:
                    continue
                leg_extensions(starts, gains, factors[j], inputs[j, k], extensions)
                finite = _finite_target(initial_lengths[j], extensions, work[5])
                if cold == 1:
                    _level_guess(bases[j], plats[j], work[5], Rj, tj)
                if not finite:
                    residual = np.inf
                elif passes == 0:
                    residual = _newton(bases[j], plats[j], work[5], Rj, tj, tol_mm, max_iterations, work)[1]
                else:
                    residual = settle_pose(
                        (bases[j], plats[j], initial_lengths[j]),
                        None,
                        (weights[k], downs[k], coms, radii[j]),
                        (starts, gains, factors[j], force_start),
                        inputs[j, k],
                        Rj,
                        tj,
                        passes,
                        settled_mm,
                        tol_mm,
                        max_iterations,
                        work,
                        scratch,
                        forces,
                    )[1]
                if cold == 0 and not _within_a_step(R_known, t_known, Rj, tj):
                    residual = np.inf
                if residual <= tol_mm:
                    break
            fk_residual[j, k] = residual
            for i in range(6):  # inverse_kinematics: R p_i + t − b_i, its norm, less l_i
                norm2 = 0.0
                for a in range(3):
                    v = Rj[a, 0] * tracker_plat[i, 0] + Rj[a, 1] * tracker_plat[i, 1] + Rj[a, 2] * tracker_plat[i, 2]
                    v = v + tj[a] - tracker_base[i, a]
                    norm2 += v * v
                residuals[j, k, i] = readings[k, i] - (math.sqrt(norm2) - tracker_lengths[i])
        copy_pose(R_1[0], t_1[0], R_2, t_2)
        for j in range(m):
            copy_pose(R[j], t[j], R_1[j], t_1[j])


# ----------------------------------------------------------------------------- error models


@njit(entry=(RO_2, RO_2, F8_3, F8_2, F8_3), **_JIT)
def error_jacobian(base, plat, R, t, out):
    """Paper eq. 8–11 ``J_p = J_r J_s`` for ``n`` poses into ``out (n, 6, 42)`` (see kinematics.error_jacobian).

    ``J_r⁻¹`` row i is ``[n_iᵀ, (R d_i × n_i)ᵀ T]`` (eq. 10, ``T`` of eq. 4–5); ``J_s`` row i
    is ``[n_iᵀ, −n_iᵀ R, 1]`` on leg i's ``[j_i, d_i, l_i]`` (eq. 11), so column block i of
    ``J_p`` is column i of ``J_r`` times that row.
    """
    n_legs = np.empty((6, 3))
    length = np.empty(6)
    J_r = np.empty((6, 6))
    A = np.empty((6, 6))
    J_s = np.empty((6, 7))  # row i of J_s on leg i's seven parameters
    for k in range(R.shape[0]):
        Rk = R[k]
        _unit_legs(base, plat, Rk, t[k], n_legs, length)
        _, pitch, yaw = _rpy(Rk)
        cb, sb, cg, sg = math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
        for i in range(6):
            n0, n1, n2 = n_legs[i, 0], n_legs[i, 1], n_legs[i, 2]
            rd0 = Rk[0, 0] * plat[i, 0] + Rk[0, 1] * plat[i, 1] + Rk[0, 2] * plat[i, 2]  # R d_i
            rd1 = Rk[1, 0] * plat[i, 0] + Rk[1, 1] * plat[i, 1] + Rk[1, 2] * plat[i, 2]
            rd2 = Rk[2, 0] * plat[i, 0] + Rk[2, 1] * plat[i, 1] + Rk[2, 2] * plat[i, 2]
            c0, c1, c2 = rd1 * n2 - rd2 * n1, rd2 * n0 - rd0 * n2, rd0 * n1 - rd1 * n0  # (R d_i) × n_i
            A[i, 0], A[i, 1], A[i, 2] = n0, n1, n2
            # (R d_i × n_i)ᵀ T with T = [[cβcγ, −sγ, 0], [sγcβ, cγ, 0], [−sβ, 0, 1]] (eq. 5)
            A[i, 3] = c0 * cb * cg + c1 * sg * cb - c2 * sb
            A[i, 4] = -c0 * sg + c1 * cg
            A[i, 5] = c2
            for a in range(3):
                J_s[i, a] = n_legs[i, a]
                J_s[i, 3 + a] = -(n0 * Rk[0, a] + n1 * Rk[1, a] + n2 * Rk[2, a])
            J_s[i, 6] = 1.0
        J_r[:] = 0.0
        for i in range(6):
            J_r[i, i] = 1.0
        if not _solve(A, J_r):  # J_r = (J_r⁻¹)⁻¹ does not exist: NaN, never a wrong number
            J_r[:] = np.nan
        for i in range(6):
            for r in range(6):
                for c in range(7):
                    out[k, r, 7 * i + c] = J_r[r, i] * J_s[i, c]


@njit(entry=(F8_3, F8_2, F8_3, F8_2, F8_2), **_JIT)
def pose_difference(R_v, t_v, R_m, t_m, out):
    """``P_v − P_m`` as ``[δh, δθ]`` (paper eq. 9) for ``n`` pose pairs into ``out (n, 6)``; δθ wrapped to (−π, π]."""
    for k in range(R_v.shape[0]):
        rpy_v = _rpy(R_v[k])
        rpy_m = _rpy(R_m[k])
        for a in range(3):
            out[k, a] = t_v[k, a] - t_m[k, a]
            d = rpy_v[a] - rpy_m[a]
            out[k, 3 + a] = math.atan2(math.sin(d), math.cos(d))


@njit(entry=(RO_2, RO_2, RO_1, F8_1, F8_2, F8_1, F8_1, F8_2, FLOAT), **_JIT)
def leg_observation(base, plat, initial_lengths, x, R, t, strokes, pose_covariance, stroke_variance):
    """The leg-length EKF's observation at a measured pose ``(R, t)``, fused in one call.

    With drive parameters ``M + x``: ``M`` given as ``base (6, 3)``, ``plat (6, 3)``,
    ``initial_lengths (6,)`` (j_i, d_i, l_i) and ``x`` a 42-vector in the paper's order:

    * ``r_i = ‖t + R d_i − j_i‖ − (l_i + q_i)`` (kinematics.leg_residuals);
    * ``H = ∂r/∂M``, row i ``[−n_iᵀ, n_iᵀ R, −1]`` in columns 7i…7i+6 (leg_residual_jacobians);
    * ``R_meas = J_x Σ_x J_xᵀ + σ_q² I`` with ``J_x = ∂r/∂ξ`` and ``Σ_x`` the measured pose's
      covariance on the body tangent (the instrument model's loose pose).

    Returns:
        ``(r (6,), H (6, 42), R_meas (6, 6), J_x (6, 6))``.
    """
    j = np.empty((6, 3))
    d = np.empty((6, 3))
    for i in range(6):
        for a in range(3):
            j[i, a] = base[i, a] + x[7 * i + a]
            d[i, a] = plat[i, a] + x[7 * i + 3 + a]
    n_legs = np.empty((6, 3))
    length = np.empty(6)
    _unit_legs(j, d, R, t, n_legs, length)
    r = np.empty(6)
    H = np.zeros((6, 42))
    for i in range(6):
        r[i] = length[i] - (initial_lengths[i] + x[7 * i + 6] + strokes[i])
        for a in range(3):
            H[i, 7 * i + a] = -n_legs[i, a]
            H[i, 7 * i + 3 + a] = n_legs[i, 0] * R[0, a] + n_legs[i, 1] * R[1, a] + n_legs[i, 2] * R[2, a]
        H[i, 7 * i + 6] = -1.0
    J_x = np.empty((6, 6))
    _pose_jacobian(d, R, n_legs, J_x)
    B = np.zeros((6, 6))  # J_x Σ_x
    for a in range(6):
        for b in range(6):
            s = 0.0
            for c in range(6):
                s += J_x[a, c] * pose_covariance[c, b]
            B[a, b] = s
    R_meas = _symmetric_product(B, J_x, 1.0)
    for a in range(6):
        R_meas[a, a] += stroke_variance
    return r, H, R_meas, J_x


@njit(**_JIT)
def tracker_leg_observation(
    base,
    plat,
    initial_lengths,
    x,
    tracker_base,
    tracker_plat,
    tracker_lengths,
    readings,
    R,
    t,
    warm,
    tol_mm,
    max_iterations,
    strokes,
    reading_variance,
    stroke_variance,
    work,
):
    """:func:`fk_single` of the tracker readings (``R, t`` in/out; FK's scratch arrays ``work`` from
    :func:`_fk_work`, which a pass over many samples makes once), its pose covariance
    (:func:`pose_covariance`) and :func:`leg_observation` there, in one call.

    Returns:
        ``(FK residual [mm], r, H, R_meas, J_x)``; the last four are meaningless when the residual
        exceeds ``tol_mm`` (FK failed from both starts).
    """
    residual = _fk_single(
        tracker_base, tracker_plat, tracker_lengths, readings, R, t, warm, tol_mm, max_iterations, work
    )
    covariance = pose_covariance(tracker_base, tracker_plat, R, t, reading_variance)
    r, H, R_meas, J_x = leg_observation(base, plat, initial_lengths, x, R, t, strokes, covariance, stroke_variance)
    return residual, r, H, R_meas, J_x


@njit(**_JIT)
def _symmetric_product(A, B, scale):
    """``scale · A Bᵀ`` (6×6) for a product known to be symmetric: the upper triangle, mirrored,
    so the result is exactly symmetric."""
    out = np.empty((6, 6))
    for a in range(6):
        for b in range(a, 6):
            s = 0.0
            for c in range(6):
                s += A[a, c] * B[b, c]
            out[a, b] = scale * s
            out[b, a] = out[a, b]
    return out


@njit(entry=(RO_2, RO_2, F8_2, F8_1, FLOAT), **_JIT)
def pose_covariance(base, plat, R, t, variance):
    """``σ² (JᵀJ)⁻¹`` of one FK pose from i.i.d. length noise (kinematics.pose_covariance_from_legs),
    formed as ``σ² A Aᵀ`` with ``A = J⁻¹`` (one solve of ``J A = I``); NaN when ``J`` is singular."""
    n_legs = np.empty((6, 3))
    length = np.empty(6)
    _unit_legs(base, plat, R, t, n_legs, length)
    J = np.empty((6, 6))
    _pose_jacobian(plat, R, n_legs, J)
    A = np.eye(6)
    if not _solve(J, A):
        A[:] = np.nan
    return _symmetric_product(A, A, variance)


@njit(entry=(F8_2, F8_2, F8_1, F8_1, F8_1, F8_2, F8_2), **_JIT)
def leg_rows(legs, R, t, extensions, r, J_pose, J_leg):
    """``r_i = ‖t + R d_i − j_i‖ − (l_i + e_i)`` of ``k`` legs ``legs (k, 7)`` = ``[j_i | d_i | l_i]``
    with extensions ``e_i`` (strokes or readings), into ``r (k,)``, ``J_pose (k, 6)`` = ``∂r/∂ξ``
    (row ``[(d_i × Rᵀn_i)ᵀ, (Rᵀn_i)ᵀ]``) and ``J_leg (k, 7)`` = ``[−n_iᵀ, (Rᵀn_i)ᵀ, −1]``
    (kinematics.leg_residual: the factor graph's per-linearisation leg rows)."""
    for i in range(legs.shape[0]):
        v0 = t[0] - legs[i, 0] + R[0, 0] * legs[i, 3] + R[0, 1] * legs[i, 4] + R[0, 2] * legs[i, 5]
        v1 = t[1] - legs[i, 1] + R[1, 0] * legs[i, 3] + R[1, 1] * legs[i, 4] + R[1, 2] * legs[i, 5]
        v2 = t[2] - legs[i, 2] + R[2, 0] * legs[i, 3] + R[2, 1] * legs[i, 4] + R[2, 2] * legs[i, 5]
        length = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        r[i] = length - (legs[i, 6] + extensions[i])
        n0, n1, n2 = v0 / length, v1 / length, v2 / length
        nb0 = R[0, 0] * n0 + R[1, 0] * n1 + R[2, 0] * n2  # Rᵀ n_i
        nb1 = R[0, 1] * n0 + R[1, 1] * n1 + R[2, 1] * n2
        nb2 = R[0, 2] * n0 + R[1, 2] * n1 + R[2, 2] * n2
        J_pose[i, 0] = legs[i, 4] * nb2 - legs[i, 5] * nb1
        J_pose[i, 1] = legs[i, 5] * nb0 - legs[i, 3] * nb2
        J_pose[i, 2] = legs[i, 3] * nb1 - legs[i, 4] * nb0
        J_pose[i, 3], J_pose[i, 4], J_pose[i, 5] = nb0, nb1, nb2
        J_leg[i, 0], J_leg[i, 1], J_leg[i, 2] = -n0, -n1, -n2
        J_leg[i, 3], J_leg[i, 4], J_leg[i, 5] = nb0, nb1, nb2
        J_leg[i, 6] = -1.0


# ----------------------------------------------------------------------------- sample checks


@njit(entry=(F8_1, FLOAT, FLOAT), **_JIT)
def all_within(values, lower, upper):
    """True when every value is finite and in ``[lower, upper]`` (NaN fails): the fast path of
    check_sample and of forward_kinematics' convergence check."""
    for v in values:
        if not (math.isfinite(v) and lower <= v <= upper):
            return False
    return True


@njit(entry=(RO_2, RO_2, RO_1, F8_1), **_JIT)
def perturbed_legs(base, plat, initial_lengths, delta):
    """``M + δM`` as new ``(6, 3)``, ``(6, 3)``, ``(6,)`` arrays, δM a 42-vector in the paper's
    order (platform.LegGeometry.perturbed: three strided numpy sums cost ~2.4 µs)."""
    j = np.empty((6, 3))
    d = np.empty((6, 3))
    lengths = np.empty(6)
    for i in range(6):
        for a in range(3):
            j[i, a] = base[i, a] + delta[7 * i + a]
            d[i, a] = plat[i, a] + delta[7 * i + 3 + a]
        lengths[i] = initial_lengths[i] + delta[7 * i + 6]
    return j, d, lengths


# ----------------------------------------------------------------------------- identifiability


@njit(entry=(RO_2, RO_2, RO_1, RO_2, RO_2, F8_3, F8_2, FLOAT, FLOAT, F8_3), **_JIT)
def whitened_leg_rows(
    base, plat, initial_lengths, tracker_base, tracker_plat, R, t, reading_variance, stroke_variance, out
):
    """``C⁻½ ∂r/∂M`` of the leg-length form at ``n`` poses into ``out (n, 6, 42)``, at the nominal drive
    (identifiability.whitened_leg_jacobian): ``H`` and ``C = R_meas`` of :func:`leg_observation`
    with the tracker pose covariance ``σ_s² (J_tᵀ J_t)⁻¹`` (kinematics.pose_covariance_from_legs),
    ``C = L Lᵀ`` by Cholesky and ``L⁻¹ H`` by forward substitution. A pose whose ``C`` is not
    positive definite gets NaN rows (where ``np.linalg.cholesky`` would raise)."""
    zeros_42 = np.zeros(42)
    zeros_6 = np.zeros(6)
    n_legs = np.empty((6, 3))
    length = np.empty(6)
    J_t = np.empty((6, 6))
    L = np.empty((6, 6))
    for k in range(R.shape[0]):
        # Σ_x = σ_s² J_t⁻¹ J_t⁻ᵀ: solve J_t X = I, then X Xᵀ
        _unit_legs(tracker_base, tracker_plat, R[k], t[k], n_legs, length)
        _pose_jacobian(tracker_plat, R[k], n_legs, J_t)
        inverse = np.eye(6)
        singular = not _solve(J_t, inverse)
        pose_covariance = np.empty((6, 6))
        for a in range(6):
            for b in range(6):
                s = 0.0
                for c in range(6):
                    s += inverse[a, c] * inverse[b, c]
                pose_covariance[a, b] = reading_variance * s
        _, H, C, _ = leg_observation(
            base, plat, initial_lengths, zeros_42, R[k], t[k], zeros_6, pose_covariance, stroke_variance
        )
        positive = not singular
        for a in range(6):
            for b in range(a + 1):
                s = C[a, b]
                for c in range(b):
                    s -= L[a, c] * L[b, c]
                if a == b:
                    if not s > 0.0:
                        positive = False
                        s = 1.0
                    L[a, a] = math.sqrt(s)
                else:
                    L[a, b] = s / L[b, b]
        for col in range(42):
            for a in range(6):
                s = H[a, col]
                for c in range(a):
                    s -= L[a, c] * out[k, c, col]
                out[k, a, col] = s / L[a, a] if positive else np.nan
