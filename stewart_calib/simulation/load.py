"""Load model: payload + platform weight → static equilibrium → axial leg forces → compliance → δM.

Pure, vectorised numpy (batch axes ``...`` over poses). The chain, for a pose ``(R, t)`` of
{D} in {J} and the drive geometry in force:

1. **Gravity wrench** on the platform about its origin ``t`` (in {J}): each mass ``m_k`` [kg] at
   ``c_k`` in {D} contributes ``F = m_k g`` and ``M = (R c_k) × m_k g`` with
   ``g = [0, 0, −9.80665]`` N/kg — [N] and [N·mm].
2. **Statics** (the transposed Jacobian; :mod:`stewart_calib.statics`, shared with the elastic
   drive model of the estimators): the six legs are two-force members, leg i pushes the
   platform with ``f_i n_i`` (``n_i`` the unit vector of paper eq. 1, base → platform, so
   ``f_i > 0`` is *compression*). Equilibrium ``Σ f_i n_i + F = 0``,
   ``Σ (R d_i) × f_i n_i + M = 0``, i.e. ``Aᵀ f = −w`` with ``Aᵀ`` the 6×6 matrix whose
   column i is ``[n_i; R d_i × n_i]`` — the transpose of the leg-rate Jacobian.
3. **Compliance** turns the forces into parameter changes (paper §4.2, the load-induced "shape
   errors"), each one shortening the effective leg under compression:

   * leg: ``δl_i = −f_i / k_leg`` (the leg shrinks along its axis);
   * base joint: ``δj_i = −n_i f_i / k_base_joint`` (the leg end sinks into the base);
   * platform joint: ``δd_i = Rᵀ n_i f_i / k_platform_joint`` (the leg end sinks into the
     platform, expressed in {D});
   * platform bending (optional): the plate sags between its joints, lumped as an extra
     ``δd_iz = (Rᵀ n_i f_i)_z / k_bending`` (a joint moves up relative to the {D} origin at the
     plate's centre when its leg pushes up).

The drift depends on the pose (through ``n_i`` and the moment arms) and on the load, as on the
real machine. Because the forces depend on the pose that the drifted geometry produces,
:func:`settle` iterates FK ↔ compliance to a fixed point (the drift is ~1e-3 of the geometry,
so each iteration gains ~3 orders of magnitude; two are plenty).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import kinematics as kin
from ..platform import Elastic, LegGeometry, vector_to_params
from ..statics import gravity_leg_forces, masses_and_centres


@dataclass(frozen=True)
class LoadModel:
    """Masses and stiffnesses of the load model (all config, see ``configs/experiments/``).

    Attributes:
        platform_mass_kg: the moving platform's own mass [kg] (always loads the legs).
        platform_com_mm: ``(3,)`` its centre of mass in {D} [mm].
        payload_com_mm: ``(3,)`` the payload's centre of mass in {D} [mm].
        leg_N_per_mm: axial stiffness of a drive leg [N/mm].
        base_joint_N_per_mm: axial stiffness of a base (lower Hooke) joint [N/mm].
        platform_joint_N_per_mm: axial stiffness of a platform (upper Hooke) joint [N/mm].
        bending_N_per_mm: plate bending stiffness at a joint [N/mm]; ``inf`` = rigid plate.
        iterations: FK ↔ compliance fixed-point iterations in :func:`settle`.
    """

    platform_mass_kg: float
    platform_com_mm: np.ndarray
    payload_com_mm: np.ndarray
    leg_N_per_mm: float
    base_joint_N_per_mm: float
    platform_joint_N_per_mm: float
    bending_N_per_mm: float = float("inf")
    iterations: int = 2


def elastic_of(load: LoadModel) -> Elastic | None:
    """The ``[elastic]`` table (spec §10) of a platform this load model acts on: its masses and
    centres of mass, the nominal compliance 0 (what a controller believes before calibration) and,
    as ``true_compliance_mm_per_kN``, the truth: the series axial compliance of leg and joints.

    Each joint's drift of step 3 lies along its leg, so it changes the leg length by ``−f_i / k``
    exactly as the leg's own compliance does: ``c_i = 1000 (1/k_leg + 1/k_base + 1/k_platform)``
    [mm/kN]. A finite plate bending moves the platform joints along z of {D}, not along the legs,
    and is not part of c. None for a massless platform (spec §10 needs a positive mass).
    """
    if not load.platform_mass_kg > 0:
        return None
    series = 1.0 / load.leg_N_per_mm + 1.0 / load.base_joint_N_per_mm + 1.0 / load.platform_joint_N_per_mm
    return Elastic(
        float(load.platform_mass_kg),
        np.array(load.platform_com_mm, dtype=float),
        np.array(load.payload_com_mm, dtype=float),
        true_compliance_mm_per_kN=np.full(6, 1000.0 * series),
    )


def compliance_drift(
    load: LoadModel, legs: LegGeometry, R: np.ndarray, t: np.ndarray, forces_N: np.ndarray
) -> np.ndarray:
    """Parameter change δM from axial forces (step 3 of the module docstring), ``(..., 6, 7)`` [mm]."""
    n = kin.leg_unit_vectors(legs, R, t)
    push = n * forces_N[..., None]  # force of leg i on the platform, in {J} [N]
    push_body = np.einsum("...ji,...kj->...ki", R, push)  # the same in {D}
    d_platform = push_body / load.platform_joint_N_per_mm
    d_platform[..., 2] += push_body[..., 2] / load.bending_N_per_mm
    return np.concatenate(
        [-push / load.base_joint_N_per_mm, d_platform, (-forces_N / load.leg_N_per_mm)[..., None]], axis=-1
    )


def loaded_params(
    load: LoadModel, base_params: np.ndarray, R: np.ndarray, t: np.ndarray, payload_kg
) -> tuple[np.ndarray, np.ndarray]:
    """True drive parameters under load at pose ``(R, t)``: ``M_base + δM_load``.

    The forces are computed on the base geometry (the drift changes the moment arms by ~1e-3
    relative, a second-order effect on a ~1e-3 drift).

    Args:
        base_params: ``(42,)`` true unloaded drive parameters (nominal + manufacturing errors) [mm].
        payload_kg: scalar or ``(...)`` payload mass [kg].
    Returns:
        ``((..., 42) params [mm], (..., 6) leg forces [N])``.
    """
    legs = LegGeometry.from_params(base_params)
    batch = np.shape(t)[:-1]
    masses, coms = masses_and_centres(
        load.platform_mass_kg, load.platform_com_mm, payload_kg, load.payload_com_mm, batch
    )
    forces = gravity_leg_forces(legs, R, t, masses, coms)
    drift = compliance_drift(load, legs, R, t, forces)
    return np.asarray(base_params) + drift.reshape(batch + (42,)), forces


def settle(
    load: LoadModel, base_params: np.ndarray, strokes: np.ndarray, payload_kg, guess: tuple[np.ndarray, np.ndarray]
) -> tuple[kin.FKSolution, np.ndarray]:
    """Where the loaded robot comes to rest for executed strokes: FK ↔ compliance fixed point.

    Args:
        base_params: ``(42,)`` true unloaded drive parameters [mm].
        strokes: ``(N, 6)`` executed strokes q [mm].
        payload_kg: scalar or ``(N,)`` [kg].
        guess: ``(R (N, 3, 3), t (N, 3))`` start (e.g. the desired or previous pose).
    Returns:
        ``(FK solution of the final iteration, (N, 42) true params in force [mm])``.
    Raises:
        kinematics.FKError: some pose did not converge (unreachable strokes).
    """
    R, t = guess
    for _ in range(load.iterations):
        # Forces at the latest pose estimate; the last FK lands within ~1e-6 of the drift's own
        # pose change of where those forces were taken, so two iterations reach the nm level.
        params, _ = loaded_params(load, base_params, R, t, payload_kg)
        p = vector_to_params(params)  # (N, 6, 7): every pose has its own drive geometry
        sol = kin.forward_kinematics_per_pose(p[..., 0:3], p[..., 3:6], p[..., 6], strokes, (R, t))
        R, t = sol.R, sol.t
    return sol, params
