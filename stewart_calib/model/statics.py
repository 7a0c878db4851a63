"""Statics of the platform under gravity: masses → gravity wrench → axial leg forces, and their Jacobians.

One implementation for the simulator's load model (:mod:`stewart_calib.simulation.load`) and the
elastic drive model of the estimators (spec §10). Pure numpy, vectorised over the batch axes
``...`` of the poses.

Equilibrium (spec §10). The six legs are two-force members: leg i pushes the platform with
``f_i n_i`` (``n_i`` the unit vector of paper eq. 1, base → platform, so ``f_i > 0`` is
*compression*). Gravity (``g = 9.80665`` m/s² along the unit vector ``down`` of {J}: −z, spec §10, or
the direction a tilted mount gives, spec §17) acts on each mass ``m_k`` at its centre of mass ``c_k`` in
{D}. The forces balance it::

    Aᵀ f = −w,    column i of Aᵀ = [n_i; R d_i × n_i],    w = [Σ m_k g; Σ (R c_k) × m_k g],    g = 9.80665 down

in {J} about the platform origin ([N] and [N·mm]). Rotated into {D} and written rotation first,
the same equations read ``Jᵀ f = −w_D`` with ``J`` the leg-length pose Jacobian of
:func:`stewart_calib.model.kinematics.leg_pose_jacobian` (rows ``[d_i × u_i, u_i]``, ``u_i = Rᵀ n_i``)
and ``w_D = [Σ c_k × m_k g_D; Σ m_k g_D]``, ``g_D = Rᵀ g``: the virtual-work statement that leg
forces and platform wrench are dual through the leg-rate Jacobian. The Jacobians below are
derived in that form.

Gravity's direction is an input, ``down (..., 3)`` beside the poses (default :data:`DOWN`, −z): the
statics of a robot on a mount tilted by ``Q`` are those of the upright robot whose base joints,
pose and gravity are all turned by ``Qᵀ`` (tests/test_tilt.py checks that invariance). Only the
wrench sees it; ``down`` is taken as given — a unit vector, as the platform file's and the log's
readers (spec §17) normalise it — since a longer one is a heavier platform, not a tilt.

Derivatives. Perturbing ``J`` or ``w_D`` by ``δ``: ``δf = −J⁻ᵀ (δw_D + δJᵀ f)``. For the body
tangent ``ξ = [ω, v]`` (``R ← R Exp(ω)``, ``t ← t + R v``, as everywhere in the package):
``δg_D = [g_D]× ω``; the body-frame leg vector ``e_i = Rᵀ(t − j_i) + d_i`` moves by
``[e_i − d_i]× ω + v`` and ``u_i = e_i/‖e_i‖`` by ``(I − u_i u_iᵀ)/‖e_i‖`` times that. For leg i's
joints: ``δe_i = −Rᵀ δj_i + δd_i``, and the arm of ``J``'s row changes by ``δd_i × u_i``. The
initial length ``l_i`` does not enter the statics.
"""

from __future__ import annotations

import math

import numpy as np

from .._jit import F8_1, F8_2, FLOAT, RO_2, RO_3, njit
from ..errors import CalibError
from ._kernels import SINGULAR_RATIO, pose_gravity_forces
from .kinematics import leg_pose_jacobian, leg_unit_vectors, skew
from .platform import DOWN, G_N_PER_KG, N_LEGS, N_PARAMS, N_PARAMS_PER_LEG, LegGeometry


class SingularStatics(CalibError):
    """The statics matrix is singular at some pose: no leg forces balance the weight there.

    ``index`` is the flat index of the first such pose in the batch (0 for a single pose), ``ratio``
    its Hadamard ratio; :meth:`at` names the file and row a command read that pose from.
    """

    def __init__(self, message: str, index: int, ratio: float = math.nan):
        super().__init__(message)
        self.index = index
        self.ratio = ratio

    def at(self, where: str, row: int, ratio: float) -> CalibError:
        """The refusal of the pose of ``where`` (a file) at its 1-based line ``row``, of Hadamard ratio
        ``ratio`` there, instead of a pose's index in a batch, which names nothing a user can find."""
        return CalibError(f"{where}: row {row}: {_singular_reason(ratio)}")


def gravity_wrench(R: np.ndarray, masses_kg: np.ndarray, coms_mm: np.ndarray, down: np.ndarray = DOWN) -> np.ndarray:
    """Gravity wrench ``w = [F [N], M [N·mm]]`` on the platform about its origin, in {J}.

    Args:
        R: ``(..., 3, 3)`` platform orientation.
        masses_kg: ``(..., K)`` masses [kg] (broadcast against the batch).
        coms_mm: ``(K, 3)`` their centres of mass in {D} [mm].
        down: ``(..., 3)`` the unit vector in {J} gravity acts along (default −z).
    Returns:
        ``(..., 6)``.
    """
    masses_kg = np.asarray(masses_kg, dtype=float)
    down = np.asarray(down, dtype=float)
    batch = np.broadcast_shapes(np.shape(R)[:-2], masses_kg.shape[:-1], down.shape[:-1])
    masses_kg = np.broadcast_to(masses_kg, batch + masses_kg.shape[-1:])
    weights = masses_kg[..., None] * (G_N_PER_KG * down)[..., None, :]  # (..., K, 3)
    arms = np.einsum("...ij,kj->...ki", R, np.asarray(coms_mm, dtype=float))  # (..., K, 3)
    return np.concatenate([weights.sum(axis=-2), np.cross(arms, weights).sum(axis=-2)], axis=-1)


def statics_matrix(legs: LegGeometry, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``Aᵀ`` with column i ``[n_i; R d_i × n_i]`` — leg forces → wrench about ``t``, ``(..., 6, 6)``."""
    n = leg_unit_vectors(legs, R, t)
    arms = np.einsum("...ij,kj->...ki", R, legs.platform_joints)
    return np.swapaxes(np.concatenate([n, np.cross(arms, n)], axis=-1), -1, -2)


def moment_radius(legs: LegGeometry) -> float:
    """The platform joints' RMS distance from {D}'s origin [mm] (1 if 0): the length that makes the moment
    rows of ``Aᵀ`` comparable with its force rows in Hadamard's ratio (:data:`SINGULAR_RATIO`)."""
    return float(np.sqrt(np.mean(np.sum(legs.platform_joints**2, axis=-1)))) or 1.0


def statics_ratios(legs: LegGeometry, statics: np.ndarray) -> np.ndarray:
    """Hadamard's ratio ``|det| / Π‖column‖`` of statics matrices ``(..., 6, 6)``, their moment rows over
    :func:`moment_radius`: 1 for orthogonal columns, 0 at a singular pose (:data:`SINGULAR_RATIO`)."""
    scaled = np.array(statics, dtype=float)
    scaled[..., 3:, :] /= moment_radius(legs)
    return np.abs(np.linalg.det(scaled)) / np.prod(np.linalg.norm(scaled, axis=-2), axis=-1)


def check_not_singular(legs: LegGeometry, statics: np.ndarray) -> None:
    """Refuse (:class:`SingularStatics`, one line) a batch of statics matrices ``(..., 6, 6)`` with
    a singular one (:data:`SINGULAR_RATIO`)."""
    ratio = np.reshape(statics_ratios(legs, statics), -1)
    bad = np.flatnonzero(~(ratio >= SINGULAR_RATIO))
    if bad.size:
        index = int(bad[0])
        raise SingularStatics(_singular_message(index, float(ratio[index])), index, float(ratio[index]))


def _singular_reason(ratio: float) -> str:
    return (
        f"the statics matrix Aᵀ is singular (Hadamard ratio {ratio:.2g} < {SINGULAR_RATIO:g}): "
        "no leg forces balance the weight there"
    )


def _singular_message(index: int, ratio: float) -> str:
    return f"pose {index + 1}: {_singular_reason(ratio)}"


def leg_forces(legs: LegGeometry, R: np.ndarray, t: np.ndarray, wrench: np.ndarray) -> np.ndarray:
    """Axial leg forces balancing an external wrench: ``Aᵀ f = −w``; ``(..., 6)`` [N], compression > 0.

    Raises:
        SingularStatics: at a pose where ``Aᵀ`` is singular.
    """
    A_T = statics_matrix(legs, R, t)
    check_not_singular(legs, A_T)
    return np.linalg.solve(A_T, -np.asarray(wrench)[..., None])[..., 0]


def gravity_leg_forces(
    legs: LegGeometry,
    R: np.ndarray,
    t: np.ndarray,
    masses_kg: np.ndarray,
    coms_mm: np.ndarray,
    down: np.ndarray = DOWN,
) -> np.ndarray:
    """Leg forces [N] holding masses ``(..., K)`` [kg] at centres ``(K, 3)`` in {D} [mm] at poses
    ``(R, t)`` under gravity along the unit vectors ``down (..., 3)`` in {J} (default −z), ``(..., 6)``:
    :func:`leg_forces` of :func:`gravity_wrench` in one compiled pass (an order of magnitude faster
    than the vectorised numpy on small batches, equal to it to rounding).

    Raises:
        SingularStatics: as :func:`leg_forces` (the same ratio).
    """
    c = np.ascontiguousarray
    coms_mm = np.asarray(coms_mm, dtype=float)
    batch = np.broadcast_shapes(np.shape(R)[:-2], np.shape(t)[:-1], np.shape(masses_kg)[:-1], np.shape(down)[:-1])
    R = c(np.broadcast_to(R, (*batch, 3, 3)), dtype=float).reshape(-1, 3, 3)
    t = c(np.broadcast_to(t, (*batch, 3)), dtype=float).reshape(-1, 3)
    masses = c(np.broadcast_to(np.asarray(masses_kg, dtype=float), (*batch, len(coms_mm)))).reshape(len(R), -1)
    downs = np.array(np.broadcast_to(np.asarray(down, dtype=float), (*batch, 3)), order="C").reshape(
        -1, 3
    )  # writable, C
    forces, ratios = np.empty((len(R), 6)), np.empty(len(R))
    radius = moment_radius(legs)
    weights = masses * G_N_PER_KG
    _gravity_forces(legs.base_joints, legs.platform_joints, R, t, weights, downs, c(coms_mm), radius, forces, ratios)
    bad = np.flatnonzero(~(ratios >= SINGULAR_RATIO))
    if bad.size:
        index = int(bad[0])
        raise SingularStatics(_singular_message(index, float(ratios[index])), index, float(ratios[index]))
    return forces.reshape(*batch, 6)


@njit(entry=(RO_2, RO_2, RO_3, RO_2, RO_2, F8_2, RO_2, FLOAT, F8_2, F8_1), nogil=True, error_model="numpy")
def _gravity_forces(base, plat, R, t, weights, downs, coms, radius, forces, ratios):
    """:func:`~stewart_calib.model._kernels.pose_gravity_forces` of every pose ``k`` (weights ``(n, K)`` [N]
    along ``downs[k]``, ``(n, 3)`` unit vectors in {J}) into ``forces[k]`` and ``ratios[k]``."""
    A = np.empty((6, 6))
    w = np.empty((6, 1))
    for k in range(R.shape[0]):
        ratios[k] = pose_gravity_forces(base, plat, R[k], t[k], weights[k], downs[k], coms, radius, A, w, forces[k])


def masses_and_centres(
    platform_mass_kg: float, platform_com_mm: np.ndarray, payload_kg, payload_com_mm: np.ndarray, batch: tuple
) -> tuple[np.ndarray, np.ndarray]:
    """The platform's and the payload's masses ``(batch + (2,))`` [kg] and centres ``(2, 3)`` [mm]."""
    masses = np.stack(
        np.broadcast_arrays(np.full(batch, float(platform_mass_kg)), np.asarray(payload_kg, dtype=float)), axis=-1
    )
    return masses, np.stack([np.asarray(platform_com_mm, dtype=float), np.asarray(payload_com_mm, dtype=float)])


def leg_force_jacobians(
    legs: LegGeometry,
    R: np.ndarray,
    t: np.ndarray,
    forces_N: np.ndarray,
    masses_kg: np.ndarray,
    coms_mm: np.ndarray,
    down: np.ndarray = DOWN,
) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians of :func:`gravity_leg_forces` at its solution ``forces_N``: ``(∂f/∂ξ, ∂f/∂M)``.

    Args:
        forces_N: ``(..., 6)`` the forces at ``(R, t)`` [N].
        masses_kg, coms_mm, down: as :func:`gravity_leg_forces`.
    Returns:
        ``(..., 6, 6)`` [N per rad, N/mm] for the body tangent ``ξ = [ω, v]``, and ``(..., 6, 42)``
        [N/mm] on the drive parameters in the paper's order (zero on every ``l_i``).
    """
    J = leg_pose_jacobian(legs, R, t)  # rows [d_i × u_i, u_i]
    u = J[..., 3:]  # (..., 6, 3) Rᵀ n_i
    vec = np.einsum("...ji,...kj->...ki", R, (t[..., None, :] - legs.base_joints)) + legs.platform_joints
    length = np.linalg.norm(vec, axis=-1)[..., None, None]
    # ∂u_i/∂e_i = (I − u uᵀ)/‖e‖
    du_de = (np.eye(3) - u[..., :, None] * u[..., None, :]) / length  # (..., 6, 3, 3)
    arms = skew(legs.platform_joints)  # (6, 3, 3): [d_i]×

    # the gravity wrench's change with the orientation: δg_D = [g_D]× ω
    g_D = np.einsum("...ji,...j->...i", R, G_N_PER_KG * np.asarray(down, dtype=float))
    dg = skew(g_D)  # (..., 3, 3)
    masses_kg = np.broadcast_to(
        np.asarray(masses_kg, dtype=float),
        (
            *np.shape(forces_N)[:-1],
            len(coms_mm),
        ),
    )
    total = masses_kg.sum(axis=-1)[..., None, None]
    first_moment = np.einsum("...k,kj->...j", masses_kg, np.asarray(coms_mm, dtype=float))
    dw = np.zeros((*np.shape(forces_N)[:-1], 6, 6))
    dw[..., 0:3, 0:3] = skew(first_moment) @ dg
    dw[..., 3:6, 0:3] = total * dg

    # δJᵀ f = Σ_i f_i [d_i × δu_i; δu_i], δu_i = du_de_i ([e_i − d_i]× ω + v)
    de_dxi = np.concatenate([skew(vec - legs.platform_joints), _eye_legs(vec)], axis=-1)
    du_dxi = du_de @ de_dxi  # (..., 6, 3, 6)
    weighted = forces_N[..., None, None] * du_dxi
    dJf = np.concatenate([np.einsum("iab,...ibc->...ac", arms, weighted), weighted.sum(axis=-3)], axis=-2)
    J_inv_T = np.linalg.inv(np.swapaxes(J, -1, -2))
    df_dxi = -J_inv_T @ (dw + dJf)

    # leg i's joints: δe_i = −Rᵀ δj_i + δd_i; row i of J gains [δd_i × u_i + d_i × δu_i, δu_i]
    de_dparams = np.concatenate([-np.swapaxes(R, -1, -2)[..., None, :, :].repeat(N_LEGS, axis=-3), _eye_legs(vec)], -1)
    du_dparams = du_de @ de_dparams  # (..., 6, 3, 6) on (j_i, d_i)
    arm_change = np.concatenate([np.zeros((*vec.shape, 3)), -skew(u)], axis=-1)  # δd_i × u_i = −[u_i]× δd_i
    row_change = np.concatenate([arm_change + arms @ du_dparams, du_dparams], axis=-2)  # (..., 6, 6, 6)
    df_djd = -np.einsum("...ab,...ibc->...aic", J_inv_T, forces_N[..., :, None, None] * row_change)
    df_dM = np.zeros((*np.shape(forces_N)[:-1], N_LEGS, N_LEGS, N_PARAMS_PER_LEG))
    df_dM[..., :6] = df_djd
    return df_dxi, df_dM.reshape((*np.shape(forces_N)[:-1], N_LEGS, N_PARAMS))


def _eye_legs(vec: np.ndarray) -> np.ndarray:
    return np.broadcast_to(np.eye(3), (*vec.shape, 3))
