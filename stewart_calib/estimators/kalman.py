"""The Kalman measurement update both EKFs share: one pure function, written for speed.

Random-walk prediction (paper eq. 14–15: ``X`` unchanged, ``P ← P + Q``) and the update
(eq. 17–19) are fused into :func:`kalman_update`, because the prediction is only an
addition and fusing it saves a pass over the 42×42 covariance. The kernel is compiled
with numba (on-disk cache, :func:`stewart_calib._jit.njit`). Measured at 42 states / 6 observations
on 2 cores: ~3.6 µs per call, against ~33 µs for the same algorithm in numpy (per-call overhead on small arrays)
and ~37 µs for filterpy's ``KalmanFilter.predict`` + ``update``.

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

from .. import _kernels
from .._jit import njit
from ..chi_square import chdtri  # chi2.ppf(p, m) is chdtri(m, 1 - p); scipy.special costs ~0.2 s of import
from ..errors import CalibError, SampleRejected
from ..estimate import Estimate
from ..unknowns import UnknownLayout, gauge_conditioned
from .base import checked_covariance, checked_time, state_array

_FAST = {"reassoc", "contract", "arcp", "nsz"}


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


@njit(fastmath=_FAST, nogil=True, error_model="numpy")
def _tracker_observation(
    x, row, drive, tracker, extension_terms, variances, newton, noise_scale2, R_guess, t_guess, warm, scratch
):
    """The EKF's observation of one prepared row ``[u | s (6)]`` (the drive's inputs, then the tracker's
    readings) of a tracker of known geometry
    at ``x`` (``LegEKF._observe``): FK of the readings from ``(R_guess, t_guess)`` into ``R_pose,
    t_pose``, ``ν = −r`` and ``R = s² R_meas`` into ``nu`` and ``R``, with ``scratch = (R_pose,
    t_pose, extensions, nu, R, FK's work, the terms' factors, H over the whole state)`` made once per
    pass (:func:`_observation_scratch`). The drive's terms whose ``columns`` are ≥ 0 are unknowns of
    ``x``: their factors ``o_b + v_b`` take the state's value and their rows of ``H`` are
    ``∂r_i/∂v_b,i = −g_b u_b,i`` (as ``DriveModel.with_terms``). Returns ``(FK converged, H)``."""
    R_pose, t_pose, extensions, nu, R, fk_work, factors, H_full = scratch
    starts, gains, base_factors, columns = extension_terms
    for b in range(starts.shape[0]):
        for i in range(6):
            c = columns[b, i]
            factors[b, i] = base_factors[b, i] + (x[c] if c >= 0 else 0.0)
    _kernels.copy_pose(R_guess, t_guess, R_pose, t_pose)
    _kernels.leg_extensions(starts, gains, factors, row, extensions)
    residual, r, H, R_meas, _ = _kernels.tracker_leg_observation_in(
        drive[0],
        drive[1],
        drive[2],
        x[:42],
        tracker[0],
        tracker[1],
        tracker[2],
        row[row.shape[0] - 6 :],
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
    for a in range(6):
        nu[a] = -r[a]
        for b in range(6):
            R[a, b] = noise_scale2 * R_meas[a, b]
    if x.shape[0] == 42:
        return residual <= newton[0], H
    for a in range(6):
        for j in range(42):
            H_full[a, j] = H[a, j]
        for j in range(42, x.shape[0]):
            H_full[a, j] = 0.0
    for b in range(starts.shape[0]):
        for i in range(6):
            if columns[b, i] >= 0:
                H_full[i, columns[b, i]] = -gains[b] * row[starts[b] + i]
    return residual <= newton[0], H_full


@njit(nogil=True)
def _observation_scratch(n, terms):
    """The arrays :func:`_tracker_observation` fills for ``n`` states and ``terms`` extension terms:
    pose, the legs' extensions, innovation, its covariance, FK's work, the terms' factors, ``H``."""
    return (
        np.empty((3, 3)),
        np.empty(3),
        np.empty(6),
        np.empty(6),
        np.empty((6, 6)),
        _kernels._fk_work(),
        np.empty((terms, 6)),
        np.empty((6, n)),
    )


@njit(fastmath=_FAST, nogil=True, error_model="numpy")
def tracker_filter_pass(
    x: np.ndarray,
    P: np.ndarray,
    t_s: np.ndarray,
    prepared: np.ndarray,
    use: np.ndarray,
    drive: tuple,
    tracker: tuple,
    extension_terms: tuple,
    variances: tuple,
    newton: tuple,
    walk_rate: float,
    noise_scale2: float,
    R_guess: np.ndarray,
    t_guess: np.ndarray,
    warm: bool,
    components: np.ndarray,
) -> tuple[int, float, bool]:
    """A random-walk filter pass, gate off, over leg-length observations of a tracker of known
    geometry, in place on ``(x, P)``: what ``RobustFilter``'s pass does sample by sample through
    the EKF's observation (``LegEKF._observe``), in one call.

    For each sample ``k`` in ``use``: FK of the readings (the last six of ``prepared[k]``)
    warm-started from ``(R_guess, t_guess)`` (updated in place on success; a sample whose FK fails
    is skipped), the observation at ``x`` with the drive's extensions of the inputs before them
    (:func:`~stewart_calib._kernels.tracker_leg_observation`), ``Q = ρ² Δt I``, the update with
    ``s² R_meas``, and the variance components (:func:`variance_components`) summed into
    ``components``.

    Args:
        drive, tracker: ``(base_joints, platform_joints, initial_lengths)`` of each leg set.
        extension_terms: the drive's ``(starts, gains, factors o_b + v_b at nominal, columns of the
            unknown ones in x (−1: known))`` (:meth:`stewart_calib.drive.DriveModel.kernel_terms`,
            :func:`~stewart_calib._kernels.leg_extensions`).
        variances: ``(σ_s², σ_q²)`` reading and stroke variance [mm²].
        newton: FK's ``(tolerance [mm], iteration cap)``.
    Returns:
        ``(samples used, t_s of the last one, whether (R_guess, t_guess) holds a pose)``.
    """
    m = 6
    n = x.shape[0]
    Q = np.zeros((n, n))
    work = np.empty(m * n + m * m + m)
    scratch = _observation_scratch(n, extension_terms[0].shape[0])
    R_pose, t_pose, _, nu, R, _, _, _ = scratch
    last_t = math.nan
    used = 0
    for k in range(t_s.shape[0]):
        if not use[k]:
            continue
        converged, H = _tracker_observation(
            x,
            prepared[k],
            drive,
            tracker,
            extension_terms,
            variances,
            newton,
            noise_scale2,
            R_guess,
            t_guess,
            warm,
            scratch,
        )
        if not converged:
            continue
        _kernels.copy_pose(R_pose, t_pose, R_guess, t_guess)
        warm = True
        step = 0.0 if math.isnan(last_t) else walk_rate * max(t_s[k] - last_t, 0.0)
        for i in range(n):
            Q[i, i] = step if i < 42 else 0.0  # δM walks; the drive's blocks are constant
        nis, S = kalman_update(x, P, H, nu, R, Q, math.inf, work)
        if math.isnan(nis):
            continue
        observed, expected = variance_components(S, nu, R)
        components[0] += observed
        components[1] += expected
        last_t = t_s[k]
        used += 1
    return used, last_t, warm


#: why :func:`tracker_filter_steps` stopped: at the end of its rows; at a row the per-sample
#: path must take (it did not touch the state for it); after a row that made the window statistics due.
STEPS_DONE, STEPS_PER_SAMPLE, STEPS_WINDOW_DUE = 0, 1, 2


@njit(fastmath=_FAST, nogil=True, error_model="numpy")
def tracker_filter_steps(
    x,
    P,
    Q,
    S_last,
    t_s,
    prepared,
    plain,
    last_t,
    drive,
    tracker,
    extension_terms,
    variances,
    newton,
    walk_rate,
    noise_scale2,
    gate_nis,
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
) -> tuple[int, int, float, float, int, bool]:
    """The gated recursion of ``RobustFilter`` after its start-up, over the EKF's observations of a
    tracker of known geometry, for as long as every row is an accepted sample — what
    ``RobustFilter.update`` does row by row, in one call (the same kernels, in the same order).

    For each row ``k``: stop (:data:`STEPS_PER_SAMPLE`, nothing touched for it) unless ``plain[k]``
    (the caller's checks passed), ``t_s[k] ≥ last_t``, FK converges, the observation is finite and the
    update passes the gate ``gate_nis`` with ``S`` positive definite; otherwise ``Q = ρ² Δt I`` into
    ``Q`` (the filter's, as ``_fill_Q``), the update in place on ``(x, P)``, its ``S`` into ``S_last``,
    the warm start ``(R_guess, t_guess)`` moved to the row's pose, the row appended to the sample
    window (``_SampleWindow``'s arrays and ``span = [start, end]``, in place) and δM into
    ``errors_out[k]`` (when it has rows). After ``window`` accepted rows since the last window
    statistics (``window`` > 0) it stops with :data:`STEPS_WINDOW_DUE`.

    Returns:
        ``(rows done, why it stopped, last accepted t_s, its NIS, since_window, warm)``.
    """
    m = 6
    n = x.shape[0]
    work = np.empty(m * n + m * m + m)
    scratch = _observation_scratch(n, extension_terms[0].shape[0])
    R_pose, t_pose, _, nu, R, _, _, _ = scratch
    capacity = buffer_t.shape[0] // 2
    nis = math.nan
    for k in range(t_s.shape[0]):
        if not (plain[k] and t_s[k] >= last_t):
            return k, STEPS_PER_SAMPLE, last_t, nis, since_window, warm
        converged, H = _tracker_observation(
            x,
            prepared[k],
            drive,
            tracker,
            extension_terms,
            variances,
            newton,
            noise_scale2,
            R_guess,
            t_guess,
            warm,
            scratch,
        )
        if not (converged and all_finite(H, nu, R)):
            return k, STEPS_PER_SAMPLE, last_t, nis, since_window, warm
        step = walk_rate * max(t_s[k] - last_t, 0.0)
        for i in range(n):
            Q[i, i] = step if i < 42 else 0.0  # δM walks; the drive's blocks are constant
        nis_k, S = kalman_update(x, P, H, nu, R, Q, gate_nis, work)
        if not nis_k <= gate_nis:  # gated, or S not positive definite: x and P untouched
            return k, STEPS_PER_SAMPLE, last_t, nis, since_window, warm
        _kernels.copy_pose(R_pose, t_pose, R_guess, t_guess)
        warm = True
        for a in range(m):
            for b in range(m):
                S_last[a, b] = S[a, b]
        nis = nis_k
        last_t = t_s[k]
        start, end = span[0], span[1]
        if end == buffer_t.shape[0]:  # slide the live rows to the front, as _SampleWindow.append
            for i in range(end - start):
                buffer_t[i] = buffer_t[start + i]
                for c in range(buffer_prepared.shape[1]):
                    buffer_prepared[i, c] = buffer_prepared[start + i, c]
                buffer_gated[i] = buffer_gated[start + i]
            start, end = 0, end - start
        buffer_t[end] = t_s[k]
        for c in range(buffer_prepared.shape[1]):
            buffer_prepared[end, c] = prepared[k, c]
        buffer_gated[end] = False
        end += 1
        if end - start > capacity:
            start += 1
        span[0], span[1] = start, end
        if errors_out.shape[0]:
            for i in range(42):
                errors_out[k, i] = x[i]
        since_window += 1
        if window > 0 and since_window >= window:
            return k + 1, STEPS_WINDOW_DUE, last_t, nis, since_window, warm
    return t_s.shape[0], STEPS_DONE, last_t, nis, since_window, warm


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


class FilterState:
    """The state both EKFs carry: ``X = δM``, ``P``, the gate, and the bookkeeping.

    A thin wrapper over :func:`kalman_update` that turns a gated or degenerate update into
    :class:`~stewart_calib.errors.SampleRejected` (state untouched) and builds the
    :class:`~stewart_calib.estimators.base.Estimate` (``covariance = P``).

    Args:
        method: the estimator's name, for the estimate and messages.
        prior_sigma_mm: σ of δM's prior [mm]; initial ``P = σ² I`` on δM.
        gate_probability: χ² gate probability with ``m`` degrees of freedom, 0 = off.
        m: observation size.
        layout: the unknown vector (default: δM alone); its blocks start from their own prior
            σ, and ``P`` is conditioned on the gauge constraints ``C`` (``C x = 0`` then holds
            for every state; the caller conditions its process noise the same way).
        C: the gauge rows (:meth:`~stewart_calib.unknowns.UnknownLayout.gauge_rows`), or None.
    """

    def __init__(
        self,
        method: str,
        prior_sigma_mm: float,
        gate_probability: float,
        m: int = 6,
        layout: UnknownLayout | None = None,
        C: np.ndarray | None = None,
    ):
        if not 0.0 <= gate_probability < 1.0:
            raise CalibError(f"{method}: gate_probability must lie in [0, 1), got {gate_probability}")
        if not prior_sigma_mm > 0.0:
            raise CalibError(f"{method}: noise.prior_sigma_mm must be positive, got {prior_sigma_mm}")
        self.method = method
        self.layout = layout or UnknownLayout()
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

    def update(self, H: np.ndarray, residual: np.ndarray, R: np.ndarray, t_s: float, gated: bool = True) -> None:
        """:func:`kalman_update` with ``self.Q``; counts the sample or raises ``SampleRejected``
        (``gated`` false: whatever its NIS, a sample a test of its own has taken)."""
        if not all_finite(H, residual, R):  # compiled: three np.isfinite passes cost ~5 µs
            raise SampleRejected(
                f"{self.method}: sample at t = {t_s} s gives a non-finite observation", SampleRejected.NON_FINITE
            )
        m = len(residual)
        gate_nis = math.inf if not gated else self.gate_nis if m == self._m else self._gate(m)  # another size
        if self._work.size < workspace_size(len(self.x), m):
            self._work = np.empty(workspace_size(len(self.x), m))
        nis, S = kalman_update(self.x, self.P, H, residual, R, self.Q, gate_nis, self._work)
        if math.isnan(nis):
            raise SampleRejected(
                f"{self.method}: sample at t = {t_s} s: innovation covariance not positive definite",
                SampleRejected.NOT_POSITIVE_DEFINITE,
            )
        if nis > gate_nis:
            raise SampleRejected(
                f"{self.method}: sample at t = {t_s} s gated: NIS {nis:.3g} > χ² bound {gate_nis:.3g}",
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
