"""Closed-form registration of the instrument: where the iterative fit starts (spec §7).

The fit is linear only near the answer; the instrument frame may be 100 mm and any rotation
away from its nominal value. Before iterating we solve, in closed form, for the instrument's
unknowns that best map the **nominal** forward-kinematics poses ``X_k`` onto what it measured:

* **pose** — the hand-eye problem ``X_k G = F M_k`` (AX = YB) for frame F and target G:
  the rotations from the linear system ``R_Xk R_G − R_F R_Mk = 0`` (null vector of the
  stacked 9N × 18 matrix, each 3 × 3 half projected onto SO(3)), then the translations from
  ``R_Xk t_G − t_F = R_F t_Mk − t_Xk`` by linear least squares;
* **points** — ``R_F m_kj + t_F − R_Xk p_j = t_Xk`` is linear in ``(R_F, t_F, p_j)`` with
  ``R_F`` taken as a free 3 × 3 matrix; solve, project ``R_F`` onto SO(3), solve again for
  ``t_F`` and ``p_j`` with it held.

:func:`refit_frame` fits the frame alone (the target(s) and the robot's model held), for
``validate --register-instrument``: Horn/Kabsch in closed form, then a few Gauss–Newton steps
on the whitened residual, as the two halves of a pose reading carry different noise.

A log that cannot register (fewer than 3 distinct poses, poses that do not rotate about two
axes) is refused with the reason: :class:`~stewart_calib.errors.CalibError`.
"""

from __future__ import annotations

import numpy as np

from ..errors import CalibError
from ..kinematics import pose_to_rt, transform_points
from . import lie
from .gauge import kabsch
from .points import PointsUnknowns
from .pose import PoseUnknowns

#: distinct poses needed: 2 leave the hand-eye rotation undetermined about their relative axis
MIN_DISTINCT_POSES = 3

#: poses closer than this many σ (position and orientation) count as one pose
DISTINCT_SIGMAS = 10.0

#: a direction of the linear system weaker than this fraction of the strongest is not determined
RELATIVE_RANK_TOLERANCE = 1e-9


def distinct_count(readings: np.ndarray, scale: np.ndarray, enough: int) -> int:
    """Number of distinct rows of ``readings`` ``(N, m)`` (NaN-aware), rows closer than ``scale``
    in every component counting as one (greedy clustering, order of the log), counted up to
    ``enough``: one pass over the log a distinct row (comparing each row with every distinct one
    ran over 10 minutes on 10⁵ varied poses, ``validate --register-instrument``)."""
    readings = np.asarray(readings, dtype=float)
    unclaimed = np.ones(len(readings), dtype=bool)  # rows close to no distinct row so far
    count = 0
    while count < enough and unclaimed.any():
        difference = readings - readings[np.argmax(unclaimed)]  # the first unclaimed row is the next distinct one
        unclaimed &= ~np.all((np.abs(difference) <= scale) | ~np.isfinite(difference), axis=1)
        count += 1
    return count


def _require_distinct(readings: np.ndarray, scale: np.ndarray, what: str) -> None:
    n = distinct_count(readings, DISTINCT_SIGMAS * scale, MIN_DISTINCT_POSES)
    if n < MIN_DISTINCT_POSES:
        raise CalibError(
            f"cannot register the {what}: the log has {n} distinct pose(s) (readings closer than {DISTINCT_SIGMAS:g} "
            f"σ count as one); expected at least {MIN_DISTINCT_POSES} that also rotate about two axes"
        )


def register_pose(
    R_X: np.ndarray, t_X: np.ndarray, R_M: np.ndarray, t_M: np.ndarray, sigmas: np.ndarray
) -> PoseUnknowns:
    """Frame F and target G with ``X_k G ≈ F M_k`` (hand-eye AX = YB), in closed form.

    Args:
        R_X, t_X: ``(N, 3, 3)``, ``(N, 3)`` platform poses (nominal FK of the strokes).
        R_M, t_M: the instrument's readings of {T} in {I}.
        sigmas: ``(6,)`` σ of a reading ``[rad ×3, mm ×3]`` (decides which poses are distinct).
    Raises:
        CalibError: fewer than 3 distinct poses, or rotations about fewer than two axes.
    """
    _require_distinct(
        np.concatenate([t_M, R_M.reshape(-1, 9)], axis=1), np.r_[sigmas[3:], np.full(9, sigmas[0])], "pose instrument"
    )
    n = len(R_X)
    eye = np.eye(3)
    # column-major vec: vec(A X) = (I ⊗ A) vec X, vec(X B) = (Bᵀ ⊗ I) vec X
    rows = np.concatenate(
        [np.stack([np.kron(eye, R_X[k]) for k in range(n)]), -np.stack([np.kron(R_M[k].T, eye) for k in range(n)])],
        axis=2,
    ).reshape(9 * n, 18)
    _, s, Vt = np.linalg.svd(rows, full_matrices=False)
    if s[-2] <= max(3.0 * s[-1], RELATIVE_RANK_TOLERANCE * s[0]):
        raise CalibError(
            "cannot register the pose instrument: the poses do not rotate about two different axes, so its "
            "frame's and its target's orientations cannot be told apart; expected poses with varied rotations"
        )
    v = Vt[-1]
    R_G, R_F = v[:9].reshape(3, 3).T, v[9:].reshape(3, 3).T
    if np.linalg.det(R_F) < 0:
        R_G, R_F = -R_G, -R_F
    R_G, R_F = lie.project_to_rotation(R_G), lie.project_to_rotation(R_F)
    A = np.concatenate([R_X, -np.broadcast_to(eye, (n, 3, 3))], axis=2).reshape(3 * n, 6)
    b = (np.einsum("ij,kj->ki", R_F, t_M) - t_X).reshape(-1)
    solution, *_ = np.linalg.lstsq(A, b, rcond=None)
    return PoseUnknowns(R_F, solution[3:], R_G, solution[:3])


def register_points(R_X: np.ndarray, t_X: np.ndarray, measured: np.ndarray, sigma_mm: float) -> PointsUnknowns:
    """Frame F and targets ``p_j`` in {D} with ``F⁻¹ X_k p_j ≈ m_kj``, in closed form.

    Args:
        measured: ``(N, 3K)`` readings [mm], NaN where a target was not seen.
    Raises:
        CalibError: fewer than 3 distinct poses, or poses too poor to fix the frame and targets.
    """
    n = len(R_X)
    m = np.asarray(measured, dtype=float).reshape(n, -1, 3)
    K = m.shape[1]
    _require_distinct(m.reshape(n, -1), np.full(3 * K, sigma_mm), "points instrument")
    seen = np.all(np.isfinite(m), axis=2)
    poses, targets = np.nonzero(seen)
    for k in range(K):
        if distinct_count(m[seen[:, k], k], np.full(3, DISTINCT_SIGMAS * sigma_mm), 2) < 2:
            raise CalibError(
                f"cannot register the points instrument: target {k + 1} is seen at fewer than 2 distinct poses"
            )
    eqs = len(poses)

    def system(R_F: np.ndarray | None):
        """Rows of ``R_F m + t_F − R_X p_j = t_X`` (3 per seen target); R_F unknown when None."""
        width = (9 if R_F is None else 0) + 3 + 3 * K
        A = np.zeros((eqs, 3, width))
        col = 0
        if R_F is None:
            A[:, :, :9] = np.einsum("ea,ij->eija", m[poses, targets], np.eye(3)).reshape(eqs, 3, 9)
            col = 9
        A[:, :, col : col + 3] = np.eye(3)
        for j in range(K):
            mine = targets == j
            A[mine, :, col + 3 + 3 * j : col + 6 + 3 * j] = -R_X[poses[mine]]
        b = t_X[poses] if R_F is None else t_X[poses] - m[poses, targets] @ R_F.T
        return A.reshape(3 * eqs, width), b.reshape(-1)

    A, b = system(None)
    solution, _, rank, _ = np.linalg.lstsq(A, b, rcond=None)
    if rank < A.shape[1]:
        raise CalibError(
            f"cannot register the points instrument: its {A.shape[1]} linear unknowns have rank {rank} over these "
            "poses; expected poses that translate and rotate the targets in three dimensions"
        )
    R_F = lie.project_to_rotation(solution[:9].reshape(3, 3))  # row-major: R_F[i, a] at 3i + a
    A, b = system(R_F)
    solution, *_ = np.linalg.lstsq(A, b, rcond=None)
    return PointsUnknowns(R_F, solution[:3], solution[3:].reshape(K, 3))


#: Gauss–Newton steps of :func:`refit_frame` after the closed form (it converges in 2–3)
REFIT_ITERATIONS = 10


def refit_frame(model, unknowns, measured: np.ndarray, R_X: np.ndarray, t_X: np.ndarray, sigmas: np.ndarray):
    """The instrument frame fitted again to a log, everything else held (``validate
    --register-instrument``): closed form, then Gauss–Newton on the whitened residual.

    Args:
        model: :mod:`~stewart_calib.instruments.pose` or :mod:`~stewart_calib.instruments.points`.
        unknowns: the calibrated instrument unknowns (their target(s) are kept).
        measured: ``(N, m)`` readings (code units; NaN where a point target was not seen).
        sigmas: ``(m,)`` σ of a reading's components.
    Raises:
        CalibError: fewer than 3 distinct poses.
    """
    n = len(R_X)
    if isinstance(unknowns, PoseUnknowns):
        R_M, t_M = pose_to_rt(measured)
        _require_distinct(measured, np.r_[np.full(3, sigmas[3]), np.full(3, sigmas[0])], "pose instrument")
        R_P, t_P = lie.compose(R_X, t_X, unknowns.R_target, unknowns.t_target)  # X G = F M
        R_F = lie.project_to_rotation(np.einsum("kij,klj->il", R_P, R_M))
        t_F = np.mean(t_P - np.einsum("ij,kj->ki", R_F, t_M), axis=0)
        current: PoseUnknowns | PointsUnknowns = PoseUnknowns(R_F, t_F, unknowns.R_target, unknowns.t_target)
    else:
        m = np.asarray(measured, dtype=float).reshape(n, -1, 3)
        _require_distinct(m.reshape(n, -1), np.full(m.shape[1] * 3, sigmas[0]), "points instrument")
        in_base = transform_points(R_X, t_X, unknowns.targets)
        seen = np.all(np.isfinite(m), axis=2)
        R_F, t_F = kabsch(m[seen], in_base[seen])  # y = R_F m + t_F
        current = PointsUnknowns(R_F, t_F, unknowns.targets)
    for _ in range(REFIT_ITERATIONS):
        e, _, H_u = model.residual(current, measured, R_X, t_X, jacobians=True)
        rows = np.isfinite(e)
        step, *_ = np.linalg.lstsq((H_u[..., :6] / sigmas[:, None])[rows], -(e / sigmas)[rows], rcond=None)
        current = current.retract(np.r_[step, np.zeros(current.size - 6)])
        if np.max(np.abs(step)) < 1e-12:
            break
    return current
