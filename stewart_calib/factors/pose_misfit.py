"""The in-situ tracker's misfit at a static pose: one vector ``b`` a pose, added to its samples' rows.

The tracker's own geometry has a residual the model does not hold (``noise.pose_misfit_sigma_mm``): while
the platform holds a pose every sample's readings are off by the same amount, drawn afresh at the next
pose. ekf carries it beside its state (:meth:`~stewart_calib.estimators.robust.RobustFilter._misfit_step`:
``b ~ N(0, κ R0)`` on its leg-length observation, ``R0 = J_x Σ_x J_xᵀ + σ_q² I``). In the tight graph the
same misfit is one variable ``b`` per static pose with a row per measurement row of a sample — the
instrument's channels, then the drive's legs — prior ``N(0, κ R0)``, ``R0 = diag(σ_s², …, σ_q², …)`` the
rows' configured covariance, added to each row's residual::

    r'_k = r_k(X) + b[rows_k],    ∂r'_k/∂b = E_k  (the rows' selector)

Eliminating the pose (six readings fix it), ``J_x`` carries ``b``'s reading rows into ``κ J_x Σ_x J_xᵀ``
on the leg residuals and its leg rows add ``κ σ_q² I``: ekf's ``κ R0`` exactly. A pose's ``n`` samples so
weigh as their mean, ``(s²/n + κ) R0``, not as ``n`` independent readings.

Where isam2's snapshot of a parameter window (:class:`~stewart_calib.estimators.isam2.ISAM2Estimator`)
falls inside a pose, the pose's ``b`` enters the rebuilt smoother as ``b | p``, the Gaussian conditional
of the joint marginal: ``b − b̂ − K (p − p̂) ~ N(0, P_bb − K P_pb)``, ``K = P_bp P_pp⁺`` (:func:`conditional`).
"""

from __future__ import annotations

from functools import partial

import gtsam
import numpy as np


def misfit_key(j: int) -> int:
    """Key of the misfit variable of static pose j (0-based, counted over the log)."""
    return gtsam.symbol("b", j)


def residual(r: np.ndarray, b: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(r + b[rows], ∂/∂b)``: a factor's residual ``r`` ``(k,)`` with the misfit's ``rows`` ``(k,)`` added;
    the Jacobian on ``b`` ``(k, len(b))`` is the rows' selector."""
    E = np.zeros((len(rows), len(b)), order="F")
    E[np.arange(len(rows)), rows] = 1.0
    return r + b[rows], E


def _error(inner, rows: np.ndarray, key: int, index: int, this: gtsam.CustomFactor, values: gtsam.Values, H):
    r = inner(this, values, H)  # fills H[:index], the inner factor's keys (its own come first)
    e, E = residual(np.asarray(r, dtype=float), values.atVector(key), rows)
    if H is not None:
        H[index] = E
    return e


def custom(noise: gtsam.noiseModel.Base, keys: list[int], inner, misfit: tuple[int, np.ndarray] | None = None):
    """``gtsam.CustomFactor(noise, keys, inner)``; with ``misfit = (key, rows)`` the misfit variable ``key``'s
    ``rows`` added to its residual, the factor then on ``keys`` and ``key`` last."""
    if misfit is None:
        return gtsam.CustomFactor(noise, keys, inner)
    key, rows = misfit
    rows = np.asarray(rows, dtype=np.int64)
    return gtsam.CustomFactor(noise, [*keys, key], partial(_error, inner, rows, key, len(keys)))


def prior(key: int, sigmas: np.ndarray) -> gtsam.PriorFactorVector:
    """``b ~ N(0, diag(σ²))``: a new pose's misfit, σ per row [the rows' units]."""
    sigmas = np.asarray(sigmas, dtype=float)
    return gtsam.PriorFactorVector(key, np.zeros(len(sigmas)), gtsam.noiseModel.Diagonal.Sigmas(sigmas))


def conditional_residual(
    p: np.ndarray, b: np.ndarray, p_mean: np.ndarray, b_mean: np.ndarray, K: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(b − b̂ − K (p − p̂), ∂/∂p = −K, ∂/∂b = I)``."""
    return b - b_mean - K @ (p - p_mean), -K, np.eye(len(b))


def _conditional_error(p_mean, b_mean, K, p_key, b_key, this: gtsam.CustomFactor, values: gtsam.Values, H):
    e, H_p, H_b = conditional_residual(values.atVector(p_key), values.atVector(b_key), p_mean, b_mean, K)
    if H is not None:
        H[0] = np.asfortranarray(H_p)
        H[1] = H_b
    return e


def conditional(p_key: int, b_key: int, mean: np.ndarray, covariance: np.ndarray, n: int) -> gtsam.CustomFactor:
    """``b | p`` of the joint Gaussian ``N(mean, covariance)`` of ``[p; b]`` (``p`` its first ``n`` entries):
    with the marginal of ``p`` as its own prior, the joint exactly. ``P_pp`` may be singular along a gauge,
    where ``b`` does not follow ``p`` (its pseudo-inverse)."""
    P_pp, P_pb, P_bb = covariance[:n, :n], covariance[:n, n:], covariance[n:, n:]
    K = (np.linalg.pinv(P_pp, rcond=1e-10, hermitian=True) @ P_pb).T
    rest = P_bb - K @ P_pb
    noise = gtsam.noiseModel.Gaussian.Covariance(0.5 * (rest + rest.T))
    return gtsam.CustomFactor(
        noise,
        [p_key, b_key],
        partial(_conditional_error, mean[:n].copy(), mean[n:].copy(), np.ascontiguousarray(K), p_key, b_key),
    )
