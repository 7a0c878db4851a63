"""The Kalman recursion both EKFs share, written for speed.

Random-walk prediction (paper eq. 14–15: ``X`` unchanged, ``P ← P + Q``) and the update
(eq. 17–19) are fused into :func:`kalman_update`, because the prediction is only an
addition and fusing it saves a pass over the n×n covariance (42×42: the paper's δM). The
kernels are compiled with numba (on-disk cache, :func:`stewart_calib._jit.njit`): on arrays this
small numpy's per-call overhead costs ~10× the arithmetic (benchmarks/speed.py against numpy and
filterpy; BENCHMARKS.md).

One step of the recursion is defined once: :func:`fill_walk` (``Q = ρ²Δt · unit_Q``) and
:func:`filter_step` (``R = s² R0``, the finite check, the gated update, the variance components).
:class:`FilterState` takes every sample of both EKFs through it, and the robust filter
(:mod:`.robust`) its per-sample updates and batch passes. Where the instrument offers compiled
kernels (a leg set of known geometry: ``InstrumentModel.compiled_legs``), its observation is
compiled too (:func:`leg_set_observation`), and :func:`leg_set_filter_rows` runs the recursion over
rows of samples in one call: the same observation and step kernels; only its loop and bookkeeping
repeat the filter's Python, because a Python loop costs several µs a sample, more than the step.

Covariance update: ``P ← P⁻ − W Wᵀ`` with ``W = P⁻Hᵀ L⁻ᵀ`` and ``S = L Lᵀ`` (Cholesky), which
equals ``P⁻ − K S Kᵀ = (I − K H) P⁻`` (eq. 19). Only the upper triangle is computed and
then mirrored, so ``P`` is exactly symmetric after every update (the expanded Joseph form
drifts to ~1e-9 asymmetry, docs/measured-facts.md).

``fastmath`` allows reassociation and fused multiply-add (so the inner loops vectorise) but
not the no-NaN/no-Inf assumptions, so the positive-definiteness check of ``S`` still works.
"""

from __future__ import annotations

import math

import numpy as np

from .._jit import B_1, BOOL, F8_1, F8_2, FLOAT, I8_1, I8_2, INT, LEGS, Tuple, njit
from ..chi_square import chdtri  # chi2.ppf(p, m) is chdtri(m, 1 - p); scipy.special costs ~0.2 s of import
from ..errors import CalibError, SampleRejected, number
from ..estimate import Estimate
from ..model import _kernels
from ..model.unknowns import UnknownLayout, gauge_conditioned
from .base import checked_covariance, checked_time, state_array

_FAST = {"reassoc", "contract", "arcp", "nsz"}

#: the types of :func:`leg_set_observation`'s ``observation`` (:class:`~.measurement.LegSetPose` makes it):
#: drive legs, instrument legs, extension terms ``(starts, gains, factors, columns)``, variances, Newton's limits
OBSERVATION = Tuple((LEGS, LEGS, Tuple((I8_1, F8_1, F8_2, I8_2)), Tuple((FLOAT, FLOAT)), Tuple((FLOAT, INT))))
#: the types of :func:`leg_set_filter_rows`' arguments, as :meth:`~.measurement.LegSetPose.rows` passes them
_FILTER_ROWS_ENTRY = (
    *(F8_1, F8_2, F8_2, F8_2, F8_2),  # x, P, Q, unit_Q, S_last
    *(F8_1, F8_2, F8_2, B_1, FLOAT, OBSERVATION),  # t_s, prepared, poses, use, last_t, observation
    *(FLOAT, FLOAT, FLOAT, BOOL, F8_2, F8_1, BOOL),  # walk_rate, noise_scale2, gate_nis, skip, R_guess, t_guess, warm
    *(F8_1, F8_2, B_1, I8_1, INT, INT, F8_2, F8_1),  # the sample window, since_window, window, errors_out, components
)


@njit(fastmath=_FAST, nogil=True, error_model="numpy")
def kalman_update(
    x: np.ndarray,
    P: np.ndarray,
    H: np.ndarray,
    residual: np.ndarray,
    R: np.ndarray,
    Q: np.ndarray,
    gate_nis: float,
    work: np.ndarray | None = None,
) -> tuple[float, np.ndarray]:
    """Random-walk predict + Kalman update, in place (paper eq. 14–19).

    ``P⁻ = P + Q``; ``S = H P⁻ Hᵀ + R``; ``K = P⁻ Hᵀ S⁻¹``; ``x ← x + K ν``;
    ``P ← P⁻ − K S Kᵀ``. Solved through the Cholesky factor of ``S``, never an inverse.

    Args:
        x: ``(n,)`` state, updated in place.
        P: ``(n, n)`` symmetric covariance, updated in place.
        H: ``(m, n)`` observation Jacobian (paper ``J_k``).
        residual: ``(m,)`` innovation ``ν = z − h(x)`` (paper ``Y_k − J_k X_{k|k−1}``).
        R: ``(m, m)`` symmetric measurement covariance.
        Q: ``(n, n)`` symmetric process noise added before the update.
        gate_nis: χ² gate on ``NIS = νᵀ S⁻¹ ν``; above it nothing is changed (``inf`` = off).
        work: optional scratch of at least :func:`workspace_size` ``(n, m)`` floats, reused
            between calls (:class:`FilterState` holds one); allocated here when omitted.
    Returns:
        ``(nis, S)``: the normalised innovation squared and the innovation covariance
        ``S`` (``m × m``, a new array). ``nis > gate_nis`` means the sample was gated and
        ``x``, ``P`` are untouched; a ``nan`` NIS means ``S`` was not positive definite
        (also untouched).
    """
    n = x.shape[0]
    m = residual.shape[0]
    if work is None:
        work = np.empty(m * n + m * m + m)
    Wt = work[: m * n].reshape((m, n))  # (P⁻Hᵀ)ᵀ, then Wᵀ = L⁻¹ (P⁻Hᵀ)ᵀ
    L = work[m * n : m * n + m * m].reshape((m, m))  # S = L Lᵀ (lower triangle only)
    w = work[m * n + m * m : m * n + m * m + m]  # L⁻¹ ν
    # (P⁻Hᵀ)ᵀ row i by row i of P⁻ (P⁻ symmetric): dot products over contiguous rows,
    # three rows of H per pass so each row of P and Q is read twice, not m times. P + Q
    # is never stored, so a gated sample leaves P untouched.
    for i in range(n):
        k = 0
        while k + 3 <= m:
            s0 = 0.0
            s1 = 0.0
            s2 = 0.0
            for j in range(n):
                p = P[i, j] + Q[i, j]
                s0 += p * H[k, j]
                s1 += p * H[k + 1, j]
                s2 += p * H[k + 2, j]
            Wt[k, i] = s0
            Wt[k + 1, i] = s1
            Wt[k + 2, i] = s2
            k += 3
        while k < m:
            s0 = 0.0
            for j in range(n):
                s0 += (P[i, j] + Q[i, j]) * H[k, j]
            Wt[k, i] = s0
            k += 1
    S = np.empty((m, m))
    for a in range(m):
        for b in range(a, m):
            s = R[a, b]
            for j in range(n):
                s += H[a, j] * Wt[b, j]
            S[a, b] = s
            S[b, a] = s
    for a in range(m):
        for b in range(a + 1):
            s = S[a, b]
            for c in range(b):
                s -= L[a, c] * L[b, c]
            if a == b:
                if not s > 0.0:  # also catches NaN: fastmath here excludes the no-NaN flags
                    return math.nan, S
                L[a, a] = math.sqrt(s)
            else:
                L[a, b] = s / L[b, b]
    nis = 0.0  # NIS = ‖L⁻¹ ν‖²
    for a in range(m):
        s = residual[a]
        for c in range(a):
            s -= L[a, c] * w[c]
        w[a] = s / L[a, a]
        nis += w[a] * w[a]
    if not nis <= gate_nis:
        return nis, S
    for a in range(m):  # Wt ← L⁻¹ (P⁻Hᵀ)ᵀ = Wᵀ, forward substitution row by row
        for c in range(a):
            lac = L[a, c]
            for i in range(n):
                Wt[a, i] -= lac * Wt[c, i]
        inv = 1.0 / L[a, a]
        for i in range(n):
            Wt[a, i] *= inv
    for a in range(m):  # x += K ν = W w
        wa = w[a]
        for i in range(n):
            x[i] += Wt[a, i] * wa
    # P ← P + Q − W Wᵀ over whole rows (full-length contiguous loops vectorise; the upper
    # triangle alone, with its ragged row starts, measured slower), three columns of W per
    # pass, then the upper triangle is mirrored so P is exactly symmetric.
    for i in range(n):
        a = 0
        while a + 3 <= m:
            w0 = Wt[a, i]
            w1 = Wt[a + 1, i]
            w2 = Wt[a + 2, i]
            if a == 0:
                for j in range(n):
                    P[i, j] += Q[i, j] - (w0 * Wt[0, j] + w1 * Wt[1, j] + w2 * Wt[2, j])
            else:
                for j in range(n):
                    P[i, j] -= w0 * Wt[a, j] + w1 * Wt[a + 1, j] + w2 * Wt[a + 2, j]
            a += 3
        if m < 3:
            for j in range(n):
                P[i, j] += Q[i, j]
        while a < m:
            w0 = Wt[a, i]
            for j in range(n):
                P[i, j] -= w0 * Wt[a, j]
            a += 1
    for i in range(1, n):
        for j in range(i):
            P[i, j] = P[j, i]
    return nis, S


@njit(fastmath=_FAST, nogil=True, error_model="numpy")
def variance_components(S: np.ndarray, residual: np.ndarray, R: np.ndarray) -> tuple[float, float]:
    """``(uᵀ R u, tr(S⁻¹ R))`` with ``u = S⁻¹ ν``: an update's post-fit residual ``e = R u`` and its
    expectation ``E[eᵀ R⁻¹ e] = tr(R S⁻¹)`` (variance-component estimation; ``S`` positive definite)."""
    # S⁻¹ by hand through its Cholesky factor: LAPACK's inverse in numba makes every kernel that
    # calls this one load ~0.5 s slower from the on-disk cache, for a matrix of at most ~9 × 9
    m = S.shape[0]
    L = np.zeros((m, m))
    for a in range(m):
        for b in range(a + 1):
            s = S[a, b]
            for c in range(b):
                s -= L[a, c] * L[b, c]
            L[a, b] = math.sqrt(s) if a == b else s / L[b, b]
    S_inv = np.zeros((m, m))
    for j in range(m):  # column j: L y = e_j, then Lᵀ x = y
        for a in range(m):
            s = 1.0 if a == j else 0.0
            for c in range(a):
                s -= L[a, c] * S_inv[c, j]
            S_inv[a, j] = s / L[a, a]
        for a in range(m - 1, -1, -1):
            s = S_inv[a, j]
            for c in range(a + 1, m):
                s -= L[c, a] * S_inv[c, j]
            S_inv[a, j] = s / L[a, a]
    # the products as loops: numba's @ and np.sum on these small arrays compile ~3 s of BLAS glue
    u = np.zeros(m)
    for a in range(m):
        for b in range(m):
            u[a] += S_inv[a, b] * residual[b]
    observed, expected = 0.0, 0.0
    for a in range(m):
        for b in range(m):
            observed += u[a] * R[a, b] * u[b]
            expected += S_inv[a, b] * R[a, b]
    return observed, expected


#: how :func:`filter_step` ended: the update taken, or refused with ``x`` and ``P`` untouched (a non-finite
#: observation, an innovation covariance not positive definite, the NIS above the gate).
STEP_TAKEN, STEP_NON_FINITE, STEP_NOT_POSITIVE_DEFINITE, STEP_GATED = 0, 1, 2, 3


@njit(entry=(F8_2, F8_2, FLOAT), nogil=True)
def fill_walk(Q: np.ndarray, unit_Q: np.ndarray, walk_step: float) -> None:
    """``Q = ρ²Δt · unit_Q`` in place (``walk_step = ρ²Δt``): the random walk's process noise over one step."""
    for i in range(Q.shape[0]):
        for j in range(Q.shape[1]):
            Q[i, j] = unit_Q[i, j] * walk_step


@njit(
    entry=(F8_1, F8_2, F8_2, F8_2, F8_1, F8_2, FLOAT, FLOAT, F8_1, F8_1),
    fastmath=_FAST,
    nogil=True,
    error_model="numpy",
)
def filter_step(
    x: np.ndarray,
    P: np.ndarray,
    Q: np.ndarray,
    H: np.ndarray,
    nu: np.ndarray,
    R0: np.ndarray,
    noise_scale2: float,
    gate_nis: float,
    work: np.ndarray,
    components: np.ndarray,
) -> tuple[int, float, np.ndarray]:
    """One step of the filters' recursion, in place on ``(x, P)``: with ``R = s² R0``, refused when the
    observation is not finite, else :func:`kalman_update` with ``Q`` and the gate ``gate_nis``; a step
    taken adds its variance components (:func:`variance_components`) to ``components`` where that has
    two entries. The one definition of a step: :meth:`FilterState.update` (every sample of both EKFs),
    the robust filter's batch passes and its compiled recursion (:func:`leg_set_filter_rows`) take it.

    Returns:
        ``(status, NIS, S)``: :data:`STEP_TAKEN` or why nothing changed, the NIS (NaN where not
        computed) and the innovation covariance.
    """
    m = nu.shape[0]
    R = np.empty((m, m))
    for a in range(m):
        for b in range(m):
            R[a, b] = noise_scale2 * R0[a, b]
    if not all_finite(H, nu, R):
        return STEP_NON_FINITE, math.nan, R
    nis, S = kalman_update(x, P, H, nu, R, Q, gate_nis, work)
    if math.isnan(nis):
        return STEP_NOT_POSITIVE_DEFINITE, nis, S
    if not nis <= gate_nis:
        return STEP_GATED, nis, S
    if components.shape[0]:
        observed, expected = variance_components(S, nu, R)
        components[0] += observed
        components[1] += expected
    return STEP_TAKEN, nis, S


@njit(fastmath=_FAST, nogil=True, error_model="numpy")
def _leg_set_observation(x, row, observation, R_guess, t_guess, warm, scratch):
    """The EKF's observation of one prepared row ``[u | s]`` (the drive's inputs, then the readings ``s`` of
    an instrument that is a leg set of known geometry) at ``x``: FK of the readings from ``(R_guess,
    t_guess)`` into ``R_pose, t_pose`` and the drive's leg residuals there, ``ν = −r``, ``H = ∂r/∂x`` and
    ``R0 = R_meas``. ``observation = (drive legs, instrument legs, extension terms, variances, Newton's
    limits)`` as :func:`leg_set_filter_rows` takes them; ``scratch = (R_pose, t_pose, extensions, ν, FK's
    work, the terms' factors, H over the whole state)`` from :func:`_observation_scratch`. The drive's
    terms whose ``columns`` are ≥ 0 are unknowns of ``x``: their factors ``o_b + v_b`` take the state's
    value and their rows of ``H`` are ``∂r_i/∂v_b,i = −g_b u_b,i`` (as ``DriveModel.with_terms``).

    Returns:
        ``(FK's residual [mm] (above the tolerance: no pose, the rest meaningless), ν, H, R0)``.
    """
    drive, legs, extension_terms, variances, newton = observation
    R_pose, t_pose, extensions, nu, fk_work, factors, H_full = scratch
    starts, gains, base_factors, columns = extension_terms
    n_drive = drive[0].shape[0] * (drive[0].shape[1] + drive[1].shape[1] + 1)  # δM: the compiled (prismatic) leg layout
    for b in range(starts.shape[0]):
        for i in range(columns.shape[1]):
            c = columns[b, i]
            factors[b, i] = base_factors[b, i] + (x[c] if c >= 0 else 0.0)
    _kernels.copy_pose(R_guess, t_guess, R_pose, t_pose)
    _kernels.leg_extensions(starts, gains, factors, row, extensions)
    residual, r, H, R_meas, _ = _kernels.tracker_leg_observation(
        drive[0],
        drive[1],
        drive[2],
        x[:n_drive],
        legs[0],
        legs[1],
        legs[2],
        row[row.shape[0] - legs[2].shape[0] :],
        R_pose,
        t_pose,
        warm,
        newton[0],
        newton[1],
        extensions,
        variances[0],
        variances[1],
        fk_work,
    )
    for a in range(r.shape[0]):
        nu[a] = -r[a]
    if x.shape[0] == n_drive:
        return residual, nu, H, R_meas
    for a in range(H.shape[0]):
        for j in range(n_drive):
            H_full[a, j] = H[a, j]
        for j in range(n_drive, x.shape[0]):
            H_full[a, j] = 0.0
    for b in range(starts.shape[0]):
        for i in range(columns.shape[1]):
            if columns[b, i] >= 0:
                H_full[i, columns[b, i]] = -gains[b] * row[starts[b] + i]
    return residual, nu, H_full, R_meas


@njit(nogil=True)
def _observation_scratch(n, terms, legs):
    """The arrays :func:`_leg_set_observation` fills for ``n`` states, ``terms`` extension terms and
    ``legs`` legs: pose, the legs' extensions, innovation, FK's work, the terms' factors, ``H``."""
    return (
        np.empty((3, 3)),
        np.empty(3),
        np.empty(legs),
        np.empty(legs),
        _kernels._fk_work(),
        np.empty((terms, legs)),
        np.empty((legs, n)),
    )


@njit(entry=(F8_1, F8_1, OBSERVATION, F8_2, F8_1, BOOL), nogil=True)
def leg_set_observation(x, row, observation, R, t, warm):
    """:func:`_leg_set_observation` in fresh arrays, ``(R, t)`` the warm start, overwritten with the pose
    (the per-sample path: ``RobustFilter`` keeps a batch's observations). Returns its ``(FK residual, ν, H, R0)``."""
    scratch = _observation_scratch(x.shape[0], observation[2][0].shape[0], observation[0][2].shape[0])
    residual, nu, H, R0 = _leg_set_observation(x, row, observation, R, t, warm, scratch)
    _kernels.copy_pose(scratch[0], scratch[1], R, t)
    return residual, nu, H, R0


#: why :func:`leg_set_filter_rows` stopped: at the end of its rows; at a row the per-sample path must
#: take (it did not touch the state for it); after a row that made the window statistics due.
ROWS_DONE, ROWS_PER_SAMPLE, ROWS_WINDOW_DUE = 0, 1, 2


@njit(entry=_FILTER_ROWS_ENTRY, fastmath=_FAST, nogil=True, error_model="numpy")
def leg_set_filter_rows(
    x,
    P,
    Q,
    unit_Q,
    S_last,
    t_s,
    prepared,
    poses,
    use,
    last_t,
    observation,
    walk_rate,
    noise_scale2,
    gate_nis,
    skip,
    R_guess,
    t_guess,
    warm,
    buffer_t,
    buffer_prepared,
    buffer_gated,
    span,
    since_window,
    window,
    errors_out,
    components,
) -> tuple[int, int, int, float, float, int, bool]:
    """``RobustFilter``'s recursion over rows of prepared samples of an instrument that is a leg set of
    known geometry, in one call: per row, the observation (:func:`_leg_set_observation`), ``Q = ρ²Δt ·
    unit_Q`` (:func:`fill_walk`) and :func:`filter_step` — what the filter does row by row in Python
    (``RobustFilter._step``, ``_observed_pass``), with the same kernels in the same order. This loop
    holds only the control flow: a Python loop over samples costs several µs a row, more than the step.

    Two uses:

    * the gated recursion (``skip`` false, ``RobustFilter.update_block``): stop at the first row that
      is not ``use``d (the caller's checks failed), goes back in time, has no pose or is refused by the
      step (:data:`ROWS_PER_SAMPLE`, nothing touched for it); each row taken moves the warm start to
      its pose, its ``S`` into ``S_last``, the row into the sample window (``_SampleWindow``'s arrays
      and ``span``, :func:`window_append`) and δM into ``errors_out[k]`` (when it has rows); after
      ``window`` rows since the last window statistics (``window`` > 0) stop with
      :data:`ROWS_WINDOW_DUE`;
    * a batch's pass (``skip`` true, gate ``inf``, ``RobustFilter._pass``): skip those rows instead,
      summing the variance components into ``components``; every pose found moves the warm start (as
      the per-sample observation does); empty window arrays.

    ``poses``: ``(K, 12)`` each row's pose ``[R row-major | t]`` where the caller has solved it already
    (an elastic drive's forces are taken there, ``EKF._prepared_rows``), Newton's start for that row
    (one step to confirm it, instead of ~4 from the row before on a log of scattered poses); ``(0, 12)``:
    each row starts from the warm start.

    Returns:
        ``(rows done, why it stopped, rows taken, last taken t_s, its NIS, since_window, warm)``.
    """
    n = x.shape[0]
    legs = observation[0][2].shape[0]
    work = np.empty(legs * n + legs * legs + legs)  # workspace_size
    scratch = _observation_scratch(n, observation[2][0].shape[0], legs)
    R_pose, t_pose = scratch[0], scratch[1]
    R_start, t_start = np.empty((3, 3)), np.empty(3)
    nis, nis_k, S = math.nan, math.nan, S_last
    filled = math.nan  # the walk step Q holds (none yet: the caller's Q may hold anything)
    taken = 0
    tolerance = observation[4][0]
    for k in range(t_s.shape[0]):
        status = STEP_NON_FINITE
        fk_residual = math.inf
        if use[k] and (skip or math.isnan(last_t) or t_s[k] >= last_t):
            R_from, t_from, from_warm = R_guess, t_guess, warm
            if poses.shape[0]:  # the pose the caller solved: Newton confirms it in one step
                _kernels.copy_pose(poses[k, :9].reshape((3, 3)), poses[k, 9:], R_start, t_start)
                R_from, t_from, from_warm = R_start, t_start, True
            fk_residual, nu, H, R0 = _leg_set_observation(
                x, prepared[k], observation, R_from, t_from, from_warm, scratch
            )
            if fk_residual <= tolerance:
                walk_step = 0.0 if math.isnan(last_t) else walk_rate * max(t_s[k] - last_t, 0.0)
                if walk_step != filled:  # at a steady rate Δt repeats: Q is already this one
                    fill_walk(Q, unit_Q, walk_step)
                    filled = walk_step
                status, nis_k, S = filter_step(x, P, Q, H, nu, R0, noise_scale2, gate_nis, work, components)
        # a row handed back is observed again by the caller, from the warm start before it
        if fk_residual <= tolerance and (skip or status == STEP_TAKEN):
            _kernels.copy_pose(R_pose, t_pose, R_guess, t_guess)
            warm = True
        if status != STEP_TAKEN:
            if skip:
                continue
            return k, ROWS_PER_SAMPLE, taken, last_t, nis, since_window, warm
        for a in range(S.shape[0]):
            for b in range(S.shape[1]):
                S_last[a, b] = S[a, b]
        nis = nis_k
        last_t = t_s[k]
        taken += 1
        if buffer_t.shape[0]:
            window_append(buffer_t, buffer_prepared, buffer_gated, span, t_s[k], prepared[k], np.bool_(False))
        for i in range(errors_out.shape[1] if errors_out.shape[0] else 0):
            errors_out[k, i] = x[i]
        since_window += 1
        if window > 0 and since_window >= window:
            return k + 1, ROWS_WINDOW_DUE, taken, last_t, nis, since_window, warm
    return t_s.shape[0], ROWS_DONE, taken, last_t, nis, since_window, warm


@njit(entry=(F8_1, F8_2, B_1, I8_1, FLOAT, F8_1, BOOL), nogil=True)
def window_append(t, prepared, gated, span, t_s, row, gated_row) -> None:
    """Append one sample to a window of the last ``len(t) // 2`` samples, in place: the live rows are
    ``[span[0], span[1])`` of the arrays, slid back to the front when the end is reached (amortised
    O(1)); the oldest is dropped beyond the capacity (``_SampleWindow``, and the compiled recursion)."""
    start, end = span[0], span[1]
    if end == t.shape[0]:
        for i in range(end - start):
            t[i] = t[start + i]
            for c in range(prepared.shape[1]):
                prepared[i, c] = prepared[start + i, c]
            gated[i] = gated[start + i]
        start, end = 0, end - start
    t[end] = t_s
    for c in range(prepared.shape[1]):
        prepared[end, c] = row[c]
    gated[end] = gated_row
    end += 1
    if end - start > t.shape[0] // 2:
        start += 1
    span[0], span[1] = start, end


def workspace_size(n: int, m: int) -> int:
    """Floats of scratch :func:`kalman_update` needs for ``n`` states and ``m`` observations."""
    return m * n + m * m + m


@njit(nogil=True)
def all_finite(H: np.ndarray, residual: np.ndarray, R: np.ndarray) -> bool:
    """True when every entry of the three arrays is finite (one compiled pass, no temporaries)."""
    for v in H.flat:
        if not math.isfinite(v):
            return False
    for v in residual.flat:
        if not math.isfinite(v):
            return False
    for v in R.flat:
        if not math.isfinite(v):
            return False
    return True


#: :func:`filter_step`'s ``components`` where none are summed.
NO_COMPONENTS = np.zeros(0)
#: :func:`leg_set_filter_rows`' ``poses`` where no row's pose is known ahead.
NO_POSES = np.zeros((0, 12))


class FilterState:
    """The state both EKFs carry: ``X = δM``, ``P``, the gate, and the bookkeeping.

    A thin wrapper over :func:`filter_step` that turns a gated or degenerate update into
    :class:`~stewart_calib.errors.SampleRejected` (state untouched) and builds the
    :class:`~stewart_calib.estimators.base.Estimate` (``covariance = P``).

    Args:
        method: the estimator's name, for the estimate and messages.
        prior_sigma_mm: σ of δM's prior [code units], one for all entries or ``(n_params,)`` entry by
            entry (the drive's :meth:`~stewart_calib.model.drive.DriveModel.prior_sigmas`); initial
            ``P = diag(σ²)`` on δM.
        gate_probability: χ² gate probability with ``m`` degrees of freedom, 0 = off.
        m: observation size the gate is set for: rows of a sample as the caller's model declares them
            (the drive's legs, :attr:`~stewart_calib.model.drive.DriveModel.rows`; the pose6 difference of
            the paper's EKF); an observation of another size is gated at its own.
        layout: the unknown vector (δM alone: ``UnknownLayout(n_params=…)``); its blocks start from
            their own prior σ, and ``P`` is conditioned on the gauge constraints ``C`` (``C x = 0`` then holds
            for every state; the caller conditions its process noise the same way).
        C: the gauge rows (:meth:`~stewart_calib.model.unknowns.UnknownLayout.gauge_rows`), or None.
    """

    def __init__(
        self,
        method: str,
        prior_sigma_mm: float | np.ndarray,
        gate_probability: float,
        m: int,
        layout: UnknownLayout,
        C: np.ndarray | None = None,
    ):
        if not 0.0 <= gate_probability < 1.0:
            raise CalibError(f"{method}: gate_probability must lie in [0, 1), got {gate_probability}")
        if not np.all(np.asarray(prior_sigma_mm) > 0.0):
            raise CalibError(f"{method}: noise.prior_sigma_mm must be positive, got {prior_sigma_mm}")
        self.method = method
        self.layout = layout
        n = self.layout.size
        self.x = np.zeros(n)
        prior = np.diag(self.layout.prior_sigma(prior_sigma_mm) ** 2)
        self.P = prior if C is None else gauge_conditioned(prior, C)
        self.Q = np.zeros((n, n))
        self.gate_probability = gate_probability
        self.gate_nis = self._gate(m)
        self.samples_used = 0
        self.t_s = math.nan
        #: NIS and innovation covariance ``S`` of the last accepted update.
        self.nis = math.nan
        self.S: np.ndarray | None = None
        self._m = m
        self._work = np.empty(workspace_size(n, m))  # kalman_update's scratch, reused every call

    def _gate(self, m: int) -> float:
        """The χ² bound on the NIS of an ``m``-observation (``inf`` with the gate off)."""
        return float(chdtri(m, 1.0 - self.gate_probability)) if self.gate_probability > 0.0 else math.inf

    def workspace(self, m: int) -> np.ndarray:
        """:func:`kalman_update`'s scratch for ``m`` observations, reused from call to call."""
        if self._work.size < workspace_size(len(self.x), m):
            self._work = np.empty(workspace_size(len(self.x), m))
        return self._work

    def update(
        self, H: np.ndarray, residual: np.ndarray, R0: np.ndarray, t_s: float, gated: bool = True, noise_scale2=1.0
    ) -> None:
        """:func:`filter_step` with ``self.Q`` and ``R = noise_scale2 · R0``; counts the sample or raises
        ``SampleRejected`` (``gated`` false: whatever its NIS, a sample a test of its own has taken)."""
        m = len(residual)
        gate_nis = self.gate_for(m) if gated else math.inf
        status, nis, S = filter_step(
            self.x, self.P, self.Q, H, residual, R0, noise_scale2, gate_nis, self.workspace(m), NO_COMPONENTS
        )
        self.count_step(status, nis, S, t_s, gate_nis)

    def gate_for(self, m: int) -> float:
        """The gate's NIS bound on an ``m``-row observation (the configured size's, or another's)."""
        return self.gate_nis if m == self._m else self._gate(m)

    def count_step(self, status: int, nis: float, S: np.ndarray, t_s: float, gate_nis: float) -> None:
        """Counts a step :func:`filter_step` took at ``t_s`` [s] (its NIS and ``S`` the last ones) or raises
        ``SampleRejected`` with why it did not (the state as it was)."""
        if status == STEP_NON_FINITE:
            raise SampleRejected(
                f"{self.method}: sample at t = {number(t_s)} s gives a non-finite observation",
                SampleRejected.NON_FINITE,
            )
        if status == STEP_NOT_POSITIVE_DEFINITE:
            raise SampleRejected(
                f"{self.method}: sample at t = {number(t_s)} s: innovation covariance not positive definite",
                SampleRejected.NOT_POSITIVE_DEFINITE,
            )
        if status == STEP_GATED:
            raise SampleRejected(
                f"{self.method}: sample at t = {number(t_s)} s gated: NIS {nis:.3g} > χ² bound {gate_nis:.3g}",
                SampleRejected.GATED,
            )
        self.nis, self.S = nis, S
        self.samples_used += 1
        self.t_s = t_s

    def estimate(self) -> Estimate:
        return Estimate.of_state(self.x, self.P, self.layout, self.method, self.samples_used, self.t_s)

    def export_state(self) -> dict:
        """Everything :meth:`update` reads or writes, as arrays (checkpoints)."""
        state = {
            "x": self.x.copy(),
            "P": self.P.copy(),
            "Q": self.Q.copy(),
            "samples_used": np.int64(self.samples_used),
            "t_s": np.float64(self.t_s),
            "nis": np.float64(self.nis),
        }
        if self.S is not None:
            state["S"] = self.S.copy()
        return state

    def import_state(self, state: dict) -> None:
        """Restore :meth:`export_state` (the gate comes from the config, not the state).

        Raises:
            CalibError: a missing key or a wrong shape.
        """
        n = len(self.x)
        self.x = state_array(state, "x", (n,))
        if not np.all(np.isfinite(self.x)):
            raise CalibError("estimator state: key 'x': values not finite")
        self.P = checked_covariance(state_array(state, "P", (n, n)), "P")
        self.Q = checked_covariance(state_array(state, "Q", (n, n)), "Q")
        self.samples_used = int(state_array(state, "samples_used", ()))
        if self.samples_used < 0:
            raise CalibError("estimator state: key 'samples_used': expected a count ≥ 0")
        self.t_s = checked_time(float(state_array(state, "t_s", ())), "t_s")
        self.nis = float(state_array(state, "nis", ()))
        m = len(state["S"]) if "S" in state else 0  # the last observation's size
        self.S = state_array(state, "S", (m, m)) if "S" in state else None
