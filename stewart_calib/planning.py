"""Which poses should a user measure? Optimal experimental design over random workspace poses.

Each candidate pose contributes a block of six rows ``U_k`` to the stacked identification
Jacobian (see :mod:`stewart_calib.identifiability`), so the information of a design is
``F = F₀ + Σ U_kᵀ U_k``. Criteria (bigger is better):

* ``A`` (default): ``−tr F⁻¹`` of the whitened leg-length form — minimises the sum of the 42
  predicted variances, i.e. the RMS predicted standard deviation a user sees in the report.
* ``D``: ``log det F`` of the whitened leg-length form — minimises the volume of the
  parameters' confidence ellipsoid (what ``ekf``/``isam2``/``lm`` identify).
* ``O1``: Borm & Menq's O1 of the paper's ``J_p`` form with scaled rotation rows (what ``ls`` and
  ``paper-ekf`` fit). For a fixed number of poses O1 = (det F)^(1/84)/√(6N), so it ranks
  designs as ``log det`` of that form does.
* ``E``: ``λmin(F)`` of the whitened leg-length form — the weakest direction's information.

Search: greedy by ``log det`` (``A`` and ``E`` are flat until 7 poses make F full rank, so its greedy
phase uses D too), then DETMAX-style exchanges (Mitchell 1974) by the chosen criterion: add the
best candidate, drop the design point whose removal costs least, until the one dropped is the
one just added. Adding or removing a six-row block changes ``log det`` by
``log det(I₆ ± U F⁻¹ Uᵀ)`` (matrix determinant lemma) and ``F⁻¹`` by a Woodbury update, so a
step costs one batched 6×6 determinant (``A``: a 6×6 solve) over the candidates instead of a
42×42 factorisation each. ``E`` needs 42×42 eigenvalues; an upper bound (the weakest
eigenvector's Rayleigh quotient) limits them to the few candidates that could win.

Cost: O(N·M) for N poses from M candidates — about 1.25 N steps (N greedy, then the
exchanges: 59 for N = 100, 253 for 1000, 515 for 2000), each ~2.3 µs of CPU a candidate
(``A``, nim-stewart, one core of a loaded machine). Linear in N at the default 2000
candidates (~5 ms a pose); quadratic when M grows with N (N = 2000 from 4000: 24 s; 10⁴ from
2·10⁴: over 300 s). The blocks hold 2 kB a candidate.
"""

from __future__ import annotations

import numpy as np

from . import kinematics as kin
from .config import NoiseConfig
from .errors import CalibError
from .identifiability import scaled_paper_jacobian, whitened_leg_jacobian
from .platform import Platform

CRITERIA = ("A", "D", "O1", "E")
DEFAULT_CRITERION = "A"

#: Ridge added to the information, relative to the mean per-pose information: it makes the
#: first greedy picks (fewer than 7 poses, singular F) well posed; at 1e-6 of one pose's
#: information it changes a 7-pose design's log det by < 1e-4.
RIDGE_REL = 1e-6

#: Candidates are drawn denser near the faces of the workspace box, where optimal designs put
#: their poses (the legs' directions spread most there); every candidate stays inside the box.
#: Measured on nim-stewart, 30 poses from 2000 candidates, criterion A: RMS predicted σ
#: 0.0139 mm with uniform candidates (exponent 1), 0.0123 with 1/2, 0.0116 with 0.3.
FACE_BIAS_EXPONENT = 0.3

#: Candidate draws allowed per requested candidate before giving up on a workspace whose box
#: is mostly outside the stroke or reading ranges.
MAX_DRAWS_PER_CANDIDATE = 50


def candidate_poses(platform: Platform, n: int, rng: np.random.Generator) -> np.ndarray:
    """``(n, 6)`` random poses in the workspace box with strokes and readings within range.

    Each coordinate is ``home + limit · sign(w)|w|^FACE_BIAS_EXPONENT``, w uniform in [−1, 1].

    Raises:
        CalibError: the platform has no ``[workspace]``, or almost no pose of the box is reachable.
    """
    ws = platform.workspace
    if ws is None:
        raise CalibError(f"{platform.source}: key 'workspace': expected a [workspace] table to draw poses from")
    half = np.r_[[ws.translation_limit] * 3, [ws.rotation_limit] * 3]
    accepted: list[np.ndarray] = []
    count = draws = 0
    while count < n:
        if draws > MAX_DRAWS_PER_CANDIDATE * n:
            raise CalibError(
                f"{platform.source}: key 'workspace': expected a box whose poses mostly lie within the "
                f"stroke and reading ranges; only {count} of {draws} random poses do"
            )
        w = rng.uniform(-1.0, 1.0, (n, 6))
        batch = ws.home + np.sign(w) * np.abs(w) ** FACE_BIAS_EXPONENT * half
        draws += n
        R, t = kin.pose_to_rt(batch)
        ok = np.ones(n, dtype=bool)
        for legs, bounds in ((platform.drive, platform.stroke_range), (platform.tracker, platform.reading_range)):
            if bounds is not None:
                lengths = kin.inverse_kinematics(legs, R, t)
                ok &= np.all((lengths >= bounds[0]) & (lengths <= bounds[1]), axis=1)
        accepted.append(batch[ok])
        count += int(ok.sum())
    return np.concatenate(accepted)[:n]


def _blocks(platform: Platform, poses: np.ndarray, criterion: str, noise: NoiseConfig) -> np.ndarray:
    """Six-row information blocks ``U_k`` ``(M, 6, 42)`` for the criterion's Jacobian form."""
    if criterion == "O1":
        return scaled_paper_jacobian(platform, poses)
    return whitened_leg_jacobian(platform, poses, noise)


def _logdet_change(cov: np.ndarray, U: np.ndarray, sign: float) -> np.ndarray:
    """``log det(F ± UᵀU) − log det F = log det(I₆ ± U F⁻¹ Uᵀ)`` per block ``(K,)``."""
    S = np.eye(U.shape[1]) + sign * (U @ cov) @ np.swapaxes(U, -1, -2)
    if sign > 0:  # S is then positive definite: Cholesky is ~10× cheaper than slogdet
        return 2.0 * np.sum(np.log(np.diagonal(np.linalg.cholesky(S), axis1=-2, axis2=-1)), axis=-1)
    sign_det, logdet = np.linalg.slogdet(S)
    # Removing a block that carries all the information in some direction makes S singular.
    return np.where(sign_det > 0, logdet, -np.inf)


def _trace_change(cov: np.ndarray, U: np.ndarray, sign: float) -> np.ndarray:
    """``tr (F ± UᵀU)⁻¹ − tr F⁻¹ = ∓ tr(S⁻¹ U F⁻² Uᵀ)`` with ``S = I₆ ± U F⁻¹ Uᵀ``, per block."""
    UC = U @ cov
    S = np.eye(U.shape[1]) + sign * UC @ np.swapaxes(U, -1, -2)
    change = -sign * np.trace(np.linalg.solve(S, UC @ np.swapaxes(UC, -1, -2)), axis1=-2, axis2=-1)
    if sign > 0:
        return change
    sign_det, _ = np.linalg.slogdet(S)
    return np.where(sign_det > 0, change, np.inf)


def _woodbury(cov: np.ndarray, U: np.ndarray, sign: float) -> np.ndarray:
    """``(F ± UᵀU)⁻¹`` from ``cov = F⁻¹``: ``cov ∓ cov Uᵀ (I ± U cov Uᵀ)⁻¹ U cov``."""
    CU = cov @ U.T
    S = np.eye(U.shape[0]) + sign * U @ CU
    updated = cov - sign * CU @ np.linalg.solve(S, CU.T)
    return 0.5 * (updated + updated.T)  # round-off asymmetry would grow over many updates


def _best_lambda_min(info: np.ndarray, U: np.ndarray, allowed: np.ndarray, chunk: int = 64) -> int:
    """Index of the allowed block maximising ``λmin(F + UᵀU)``, exactly, by branch and bound.

    ``λmin(F + UᵀU) ≤ vᵀ(F + UᵀU)v = λmin(F) + ‖U v‖²`` for F's weakest eigenvector v, so
    candidates are evaluated (42×42 eigenvalues, the costly part) in order of that bound
    until the best value found beats every remaining bound.
    """
    eigenvalues, eigenvectors = np.linalg.eigh(info)
    bound = np.where(allowed, eigenvalues[0] + np.sum((U @ eigenvectors[:, 0]) ** 2, axis=-1), -np.inf)
    order = np.argsort(-bound)
    best, best_value = -1, -np.inf
    for start in range(0, int(allowed.sum()), chunk):
        if best_value >= bound[order[start]]:
            break
        idx = order[start : start + chunk]
        idx = idx[allowed[idx]]
        values = np.linalg.eigvalsh(info + np.swapaxes(U[idx], -1, -2) @ U[idx])[:, 0]
        if values.max() > best_value:
            best, best_value = int(idx[np.argmax(values)]), float(values.max())
    return best


def _best_addition(criterion: str, info: np.ndarray, cov: np.ndarray, U: np.ndarray, free: np.ndarray) -> int:
    """The free candidate whose block improves the criterion most."""
    if criterion == "E":
        return _best_lambda_min(info, U, free)
    gain = -_trace_change(cov, U, +1.0) if criterion == "A" else _logdet_change(cov, U, +1.0)
    return int(np.argmax(np.where(free, gain, -np.inf)))


def _cheapest_removal(criterion: str, info: np.ndarray, cov: np.ndarray, U: np.ndarray) -> int:
    """Position (in ``U``) of the design block whose removal costs the criterion least."""
    if criterion == "E":
        kept = np.linalg.eigvalsh(info - np.swapaxes(U, -1, -2) @ U)[:, 0]
    elif criterion == "A":
        kept = -_trace_change(cov, U, -1.0)
    else:
        kept = _logdet_change(cov, U, -1.0)
    return int(np.argmax(kept))


def select_poses(
    blocks: np.ndarray, n: int, criterion: str = DEFAULT_CRITERION, max_exchanges: int | None = None
) -> np.ndarray:
    """Indices of ``n`` distinct candidates maximising the criterion (greedy, then exchanges).

    Args:
        blocks: ``(M, 6, 42)`` each candidate's rows of the stacked identification Jacobian.
        n: poses to pick (≤ M).
        criterion: ``A`` (−trace of its inverse), ``D``/``O1`` (log det of the blocks'
            information) or ``E`` (its λmin).
        max_exchanges: cap on accepted exchanges (default ``10 n``); each strictly improves
            the criterion, so the cap only guards against cycling on exact ties.
    Returns:
        ``(n,)`` candidate indices in the order of the final design.
    """
    M, _, n_params = blocks.shape
    gram = np.einsum("kri,krj->ij", blocks, blocks) / M
    info = RIDGE_REL * np.trace(gram) / n_params * np.eye(n_params)
    cov = np.linalg.inv(info)
    chosen: list[int] = []
    free = np.ones(M, dtype=bool)
    for _ in range(n):
        k = _best_addition("D", info, cov, blocks, free)
        chosen.append(k)
        free[k] = False
        info += blocks[k].T @ blocks[k]
        cov = _woodbury(cov, blocks[k], +1.0)

    for _ in range(10 * n if max_exchanges is None else max_exchanges):
        k = _best_addition(criterion, info, cov, blocks, free)
        info_plus = info + blocks[k].T @ blocks[k]
        cov_plus = _woodbury(cov, blocks[k], +1.0)
        members = np.array(chosen + [k])
        drop = int(members[_cheapest_removal(criterion, info_plus, cov_plus, blocks[members])])
        if drop == k:
            break
        chosen[chosen.index(drop)] = k
        free[k], free[drop] = False, True
        info = info_plus - blocks[drop].T @ blocks[drop]
        cov = _woodbury(cov_plus, blocks[drop], -1.0)
    return np.array(chosen)


def plan_poses(
    platform: Platform,
    n: int,
    criterion: str = DEFAULT_CRITERION,
    rng: np.random.Generator | None = None,
    n_candidates: int = 2000,
    noise: NoiseConfig | None = None,
) -> np.ndarray:
    """Pick ``n`` calibration poses from ``n_candidates`` random reachable workspace poses.

    Args:
        platform: nominal geometry with a ``[workspace]``.
        n: poses to plan (≥ 1, ≤ ``n_candidates``).
        criterion: one of :data:`CRITERIA`.
        rng: randomness of the candidates (default ``np.random.default_rng()``).
        n_candidates: random candidate poses to choose from.
        noise: weights of the leg-length form (default :class:`NoiseConfig`).
    Returns:
        ``(n, 6)`` desired poses ``[mm, rad]``, in the order drawn (a usable driving order).
    Raises:
        CalibError: a bad ``n``, criterion or candidate count, or no workspace.
    """
    if criterion not in CRITERIA:
        raise CalibError(f"criterion: expected one of {', '.join(CRITERIA)}, got {criterion!r}")
    if n < 1 or n_candidates < n:
        raise CalibError(f"n = {n}, candidates = {n_candidates}: expected 1 ≤ n ≤ candidates")
    rng = np.random.default_rng() if rng is None else rng
    candidates = candidate_poses(platform, n_candidates, rng)
    blocks = _blocks(platform, candidates, criterion, noise or NoiseConfig())
    return candidates[np.sort(select_poses(blocks, n, criterion))]
