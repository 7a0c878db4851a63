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

:func:`refine` fits the frame alone (the target(s) and the robot's model held), for
``validate --register-instrument``, or the frame and the target(s) together, for the nominal
model's registrations: after the closed form, a few Gauss–Newton steps on the residual weighed
per channel — by the instrument's σ (the maximum-likelihood registration: the two halves of a pose
reading carry different noise and the closed forms do not weigh them), or unweighted in SI units
(:data:`SI_SCALE`: the plain registration, the "before" every command reports).

Each kind's closed forms are its model's (:meth:`~.pose.PoseModel.register`,
:meth:`~.points.PointsModel.register`, ``refit_frame``); what they share is here.

A log that cannot register (fewer than 3 distinct poses, poses that do not rotate about two
axes) is refused with the reason: :class:`~stewart_calib.errors.CalibError`.
"""

from __future__ import annotations

import numpy as np

from ..errors import CalibError

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


def require_distinct(readings: np.ndarray, scale: np.ndarray, what: str) -> None:
    n = distinct_count(readings, DISTINCT_SIGMAS * scale, MIN_DISTINCT_POSES)
    if n < MIN_DISTINCT_POSES:
        raise CalibError(
            f"cannot register the {what}: the log has {n} distinct pose(s) (readings closer than {DISTINCT_SIGMAS:g} "
            f"σ count as one); expected at least {MIN_DISTINCT_POSES} that also rotate about two axes"
        )


#: Gauss–Newton steps of :func:`refine` after the closed form (it converges in 2–4)
REFIT_ITERATIONS = 20


#: Each noise channel's length in SI units, by the unit its name ends in: the plain registration's
#: weights (position [m], rotation [rad]: a radian weighs as a metre, 1000 mm/rad).
SI_SCALE = {"mm": 1000.0, "rad": 1.0}


def si_scale(model) -> np.ndarray:
    """``(m,)`` each component of ``model``'s reading divided by it is in SI units (:data:`SI_SCALE`)."""
    per_channel = np.array([SI_SCALE[name.rsplit("_", 1)[1]] for name in model.noise_channel_names])
    return per_channel[model.noise_channels]


def refine(
    model,
    current,
    measured: np.ndarray,
    R_X: np.ndarray,
    t_X: np.ndarray,
    frame_only: bool = True,
    scale: np.ndarray | None = None,
):
    """Gauss–Newton on the residual of ``model`` (an :class:`~.external.OutsideModel`) over the
    frame alone (``frame_only``, the target(s) held) or over the frame and the target(s), from
    ``current`` (a closed-form start): least squares, no robust kernel, each component divided by
    ``scale`` (``(m,)``; default the instrument's σ, the whitened residual)."""
    sigmas = model.channel_sigma if scale is None else scale
    for _ in range(REFIT_ITERATIONS):
        e, _, H_u = model.readings_residual(current, measured, R_X, t_X, jacobians=True)
        rows = np.isfinite(e)
        H = H_u[..., :6] if frame_only else H_u
        step, *_ = np.linalg.lstsq((H / sigmas[:, None])[rows], -(e / sigmas)[rows], rcond=None)
        current = current.retract(np.r_[step, np.zeros(current.size - step.size)])
        if np.max(np.abs(step)) < 1e-12:
            break
    return current
