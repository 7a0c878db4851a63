"""The 12 directions an instrument outside the robot cannot see, and how they are fixed.

Moving all six base joints ``j_i`` by one rigid motion changes the drive exactly as moving the
instrument frame {I} the other way: no measurement tells them apart (6 directions). The same
holds for the platform joints ``d_i`` and the measured target(s) in {D} (6 more). Spec §7 asks
the estimator to fix those 12 directions and say how. We hold the **rigid part of the joint
errors at zero**: ``δj`` carries no common translation and no common rotation about the joints'
centroid,

    Σ_i δj_i = 0,    Σ_i (j_i − c_j) × δj_i = 0        (and the same for δd_i about c_d),

so {J} stays the frame in which the base joints best fit (Kabsch) their nominal positions, {D}
likewise for the platform joints, and the instrument frame and target(s) take the rigid parts.
The joints are the leg model's :attr:`~stewart_calib.model.legs.LegModel.gauge_columns` (a
rotary drive's base-side points are its crank centres ``a_i``, spec §15).
:func:`free_basis` spans the directions of δM left free (42 − 12 = 30 prismatic, 66 − 12 = 54
rotary); :func:`to_gauge` moves a truth given in any frame into this gauge (for comparisons with
simulator truth).
"""

from __future__ import annotations

import numpy as np

from ..model import kinematics as kin
from ..model import rotations
from ..model.legs import LegModel

#: the base-side points whose rigid motion the gauge holds, by leg kind: ``(what they are, their symbol)``
BASE_POINTS = {"prismatic": ("base joints", "j"), "rotary": ("crank centres", "a")}


def gauge_statement(kind: str) -> str:
    """What every result that fixes the gauge this way states, in the base-side points of the leg
    kind ``kind`` (:attr:`LegModel.kind`, :data:`BASE_POINTS`; a rotary drive's crank centres ``a_i``,
    spec §15)."""
    points, symbol = BASE_POINTS[kind]
    return (
        f"12 gauge directions fixed: the {points}' and the platform joints' errors carry no common rigid "
        f"motion (sum of d{symbol}_i = 0 and sum of ({symbol}_i - centroid) x d{symbol}_i = 0; the same for "
        "d_i), so {J} and {D} are the frames where the joints best fit their nominal positions; the "
        "instrument frame and target(s) absorb the rigid parts"
    )


#: stated in every result of a prismatic drive that fixes the gauge this way
GAUGE_STATEMENT = gauge_statement("prismatic")


def joint_columns(legs: LegModel) -> tuple[np.ndarray, np.ndarray]:
    """``(base, platform)`` ``(3 n,)``: the entries of ``legs``' parameter vector that hold the base-side
    points and the platform joints ``d_i``, leg by leg, x y z (:attr:`LegModel.gauge_columns`)."""
    base, platform = legs.gauge_columns
    return np.asarray(base).reshape(-1), np.asarray(platform).reshape(-1)


def rigid_directions(points: np.ndarray) -> np.ndarray:
    """``(3 L, 6)``: the change of L points ``(L, 3)`` under a small translation (3) and rotation
    about their centroid (3), stacked point by point (``(18, 6)`` for six joints)."""
    centred = points - points.mean(axis=0)
    G = np.zeros((len(points), 3, 6))
    G[:, :, :3] = np.eye(3)
    G[:, :, 3:] = -kin.skew(centred)  # δp = ω × (p − c) = −[p − c]× ω
    return G.reshape(3 * len(points), 6)


def free_basis(nominal: LegModel) -> np.ndarray:
    """``(n_params, n_params − 12)`` orthonormal basis of the δM satisfying the gauge (see the module
    docstring): the null space of its 12 constraints (``(42, 30)`` prismatic, ``(66, 54)`` rotary)."""
    B = np.eye(nominal.n_params)
    keep = np.ones(nominal.n_params, dtype=bool)
    blocks = []
    values = nominal.as_vector()
    for columns in joint_columns(nominal):
        G = rigid_directions(values[columns].reshape(-1, 3))
        Q, _ = np.linalg.qr(G)
        free = len(G) - G.shape[1]  # the directions ⟂ the rigid ones: 12 of a leg set's 18 joint coordinates
        complement = np.linalg.svd(np.eye(len(G)) - Q @ Q.T)[0][:, :free]
        block = np.zeros((nominal.n_params, free))
        block[columns] = complement
        blocks.append(block)
        keep[columns] = False
    return np.hstack([B[:, keep], *blocks])


def kabsch(source: np.ndarray, destination: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` minimising ``Σ ‖R s_i + t − d_i‖²`` over rigid motions (Kabsch / Horn)."""
    cs, cd = source.mean(axis=0), destination.mean(axis=0)
    H = (destination - cd).T @ (source - cs)
    R = rotations.project_to_rotation(H)
    return R, cd - R @ cs


def best_fit_frames(nominal: LegModel, params: np.ndarray) -> tuple[tuple, tuple]:
    """``((R_J, t_J), (R_D, t_D))``: the rigid motions that best fit (Kabsch) the base-side points of the absolute
    parameters ``params`` of a leg set onto ``nominal``'s, and its platform joints likewise — the frames in which
    those joints' rigid part is nominal, which :func:`free_basis`'s constraints (and an in-situ tracker holding
    the gauge, ``UnknownBlock.holds_gauge``) keep to first order."""
    base_columns, platform_columns = nominal.gauge_columns
    values, params = nominal.as_vector(), np.asarray(params, dtype=float)
    base = kabsch(params[base_columns], values[base_columns])
    return base, kabsch(params[platform_columns], values[platform_columns])


def to_gauge(nominal: LegModel, params: np.ndarray) -> tuple[np.ndarray, tuple, tuple]:
    """Move true absolute parameters ``(n_params,)`` (``nominal.as_vector()`` + the true δM) into the gauge
    of :func:`free_basis`: the base side by the rigid motion that best fits (Kabsch) its points to the
    nominal ones, the platform joints likewise (a rotary base's crank axes and zero directions turn with
    it, :meth:`~stewart_calib.model.legs.LegModel.moved`).

    Returns:
        ``(params', (R_J, t_J), (R_D, t_D))``: the parameters in the gauge, and the rigid motions
        ``T_J'_J`` (new base frame from old) and ``T_D'_D``; a pose ``X = T_J_D`` becomes
        ``T_J'_J X T_D'_D⁻¹``, a frame ``F = T_J_I`` becomes ``T_J'_J F``, a target ``G = T_D_T``
        becomes ``T_D'_D G`` and target points ``p`` become ``R_D p + t_D``.
    """
    base, platform = best_fit_frames(nominal, params)
    return moved_into(nominal, params, base, platform), base, platform


def moved_into(nominal: LegModel, params: np.ndarray, base: tuple, platform: tuple) -> np.ndarray:
    """Absolute parameters ``params`` with the base side moved by the rigid motion ``base = (R, t)`` and the
    platform joints by ``platform`` (:meth:`~stewart_calib.model.legs.LegModel.moved`)."""
    values = nominal.as_vector()
    return values + nominal.moved(np.asarray(params, dtype=float) - values, base, platform)
