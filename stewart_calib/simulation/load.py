"""Load model: payload + platform weight → static equilibrium → axial leg forces → compliance → δM.

One compiled pass over the poses (batch axes ``...``; :func:`_settle_poses`): the closed loop
settles an adaptive controller's samples one at a time, and in vectorised numpy this chain costs
~0.4 ms a sample there — a few seconds of every online run of ``reproduce``. The chain, for a pose
``(R, t)`` of {D} in {J} and the drive geometry in force:

1. **Gravity wrench** on the platform about its origin ``t`` (in {J}): each mass ``m_k`` [kg] at
   ``c_k`` in {D} contributes ``F = m_k g`` and ``M = (R c_k) × m_k g`` with ``g = 9.80665 down``
   N/kg — [N] and [N·mm] — ``down`` the unit vector in {J} gravity acts along: −z on a level mount
   (:attr:`LoadModel.gravity`), per pose on a tilting one (spec §17).
2. **Statics** (the transposed Jacobian; :mod:`stewart_calib.model.statics`, shared with the elastic
   drive model of the estimators; the compiled passes below are :func:`stewart_calib.model._kernels.settle_pose`,
   which the elastic drive's tracker residuals settle with too): the six legs are two-force members, leg i pushes the
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

from dataclasses import dataclass, field

import numpy as np

from .._jit import F8_1, F8_2, F8_3, FLOAT, I8_1, INT, RO_1, RO_2, njit
from ..model import kinematics as kin
from ..model._kernels import (
    SINGULAR_RATIO,
    _fk_work,
    pose_drift,
    pose_gravity_forces,
    settle_pose,
    settle_scratch,
    split_params,
)
from ..model.platform import DOWN, G_N_PER_KG, PARAMETER_FIELDS, Elastic, LegGeometry
from ..model.statics import SingularStatics, _singular_message, masses_and_centres, moment_radius


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
        gravity: ``(3,)`` the unit vector in {J} gravity acts along where a pose is given none of its
            own (a mount tilted once: ``[load] gravity`` of the experiment; default −z).
        tilt_axis: ``(3,)`` the unit axis in {J} a tilting mount turns about (the experiment's stages'
            ``tilt_deg``, :func:`~stewart_calib.simulation.experiment.tilted_gravity`).
    """

    platform_mass_kg: float
    platform_com_mm: np.ndarray
    payload_com_mm: np.ndarray
    leg_N_per_mm: float
    base_joint_N_per_mm: float
    platform_joint_N_per_mm: float
    bending_N_per_mm: float = float("inf")
    iterations: int = 2
    gravity: np.ndarray = field(default_factory=lambda: DOWN.copy())
    tilt_axis: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))


def elastic_of(load: LoadModel) -> Elastic | None:
    """The ``[elastic]`` table (spec §10) of a platform this load model acts on: its masses and
    centres of mass, the nominal compliance 0 (what a controller believes before calibration) and,
    as ``true_compliance_mm_per_kN``, the truth: the series axial compliance of leg and joints.

    Each joint's drift of step 3 lies along its leg, so it changes the leg length by ``−f_i / k``
    exactly as the leg's own compliance does: ``c_i = 1000 (1/k_leg + 1/k_base + 1/k_platform)``
    [mm/kN]. A finite plate bending moves the platform joints along z of {D}, not along the legs,
    and is not part of c. The mount's gravity is ``[elastic] gravity`` (spec §17). None for a massless
    platform (spec §10 needs a positive mass).
    """
    if not load.platform_mass_kg > 0:
        return None
    series = 1.0 / load.leg_N_per_mm + 1.0 / load.base_joint_N_per_mm + 1.0 / load.platform_joint_N_per_mm
    return Elastic(
        float(load.platform_mass_kg),
        np.array(load.platform_com_mm, dtype=float),
        np.array(load.payload_com_mm, dtype=float),
        true_compliance_mm_per_kN=np.full(6, 1000.0 * series),
        gravity=np.array(load.gravity, dtype=float),
    )


def _stiffness(load: LoadModel) -> np.ndarray:
    """``[k_leg, k_base_joint, k_platform_joint, k_bending]`` [N/mm] as the kernels take them."""
    return np.array(
        [load.leg_N_per_mm, load.base_joint_N_per_mm, load.platform_joint_N_per_mm, load.bending_N_per_mm], dtype=float
    )


# base params, R, t, weights, downs, centres, radius, stiffness
_POSE_INPUTS = (RO_1, F8_3, F8_2, F8_2, F8_2, RO_2, FLOAT, F8_1)


@njit(entry=(*_POSE_INPUTS, F8_2, F8_2, F8_1), nogil=True, error_model="numpy")
def _loaded_params(base_params, R, t, weights, downs, coms, radius, stiffness, params, forces, ratios):
    """:func:`loaded_params` of every pose ``k`` (weights ``(n, 2)`` [N] along ``downs[k]``, unit vectors
    in {J}) into ``params[k]``, ``forces[k]``
    and the statics' Hadamard ratio ``ratios[k]`` (params and forces unset below
    :data:`~stewart_calib.model._kernels.SINGULAR_RATIO`)."""
    n_legs = len(base_params) // 7  # seven parameters a leg
    base, plat, lengths = np.empty((n_legs, 3)), np.empty((n_legs, 3)), np.empty(n_legs)
    split_params(base_params, base, plat, lengths)
    A, w = np.empty((6, 6)), np.empty((6, 1))
    for k in range(R.shape[0]):
        ratios[k] = pose_gravity_forces(base, plat, R[k], t[k], weights[k], downs[k], coms, radius, A, w, forces[k])
        if ratios[k] >= SINGULAR_RATIO:
            pose_drift(base_params, R[k], t[k], forces[k], stiffness, params[k])


@njit(entry=(*_POSE_INPUTS, F8_2, F8_2, INT, FLOAT, INT, F8_2, F8_2, F8_1, F8_1, I8_1), nogil=True, error_model="numpy")
def _settle_poses(
    base_params,
    R,
    t,
    weights,
    downs,
    coms,
    radius,
    stiffness,
    strokes,
    growth,
    iterations,
    tol_mm,
    max_iterations,
    params,
    forces,
    ratios,
    residual,
    newton_steps,
):
    """:func:`settle` of every pose ``k`` from its guess ``(R[k], t[k])`` (overwritten with where it
    rests): ``iterations`` passes of :func:`~stewart_calib.model._kernels.settle_pose` (the forces and
    ``params[k]`` at the pose, then FK of ``strokes[k]`` on ``params[k]``); ``ratios[k]`` the statics'
    last Hadamard ratio (below the bound: stopped there), ``residual[k]`` FK's last max |length error|
    [mm] (``inf`` for a non-finite stroke) after its ``newton_steps[k]`` Newton steps.

    ``growth[k]`` ``(6,)`` scales each leg joint to joint, ``(l'_i + q_i)(1 + s_i)`` with ``l'_i = l_i −
    f_i / k_leg`` the loaded leg's initial length (a warm leg's ``s_i = α_i ΔT_i · 1e-6``, :class:`Settling`):
    three terms of the extension on ``u = [q, s (l + q), f]``, ``q + s (l + q) − s f / k_leg``, the last on
    the forces the settling writes into ``u`` (0 where ``s`` is: the strokes alone, bit for bit)."""
    n_legs = len(base_params) // 7  # seven parameters a leg
    base, plat, lengths = np.empty((n_legs, 3)), np.empty((n_legs, 3)), np.empty(n_legs)
    split_params(base_params, base, plat, lengths)
    starts = np.array([0, n_legs, 2 * n_legs], dtype=np.int64)
    gains = np.array([1.0, 1.0, -1.0 / stiffness[0]])
    factors = np.ones((3, n_legs))
    terms = (starts, gains, factors, 2 * n_legs)
    u = np.zeros(3 * n_legs)
    work, scratch = _fk_work(), settle_scratch()
    for k in range(R.shape[0]):
        for i in range(n_legs):
            u[i] = strokes[k, i]
            u[n_legs + i] = growth[k, i] * (lengths[i] + strokes[k, i])
            factors[2, i] = growth[k, i]
        ratios[k], residual[k], newton_steps[k] = settle_pose(
            (base, plat, lengths),
            (base_params, stiffness, params[k]),
            (weights[k], downs[k], coms, radius),
            terms,
            u,
            R[k],
            t[k],
            iterations,
            -1.0,
            tol_mm,
            max_iterations,
            work,
            scratch,
            forces[k],
        )


@dataclass(frozen=True)
class Settling:
    """A load model acting on one robot's unloaded drive, as the kernels take it: made once per robot,
    since per sample of the closed loop these conversions cost more than the kernels themselves.

    Attributes:
        base_params: ``(42,)`` true unloaded drive parameters [mm], read-only.
        centres: ``(2, 3)`` the platform's and the payload's centres of mass in {D} [mm], read-only.
        platform_mass_kg: the platform's own mass [kg].
        radius: the statics' moment radius (:func:`~stewart_calib.model.statics.moment_radius`) [mm].
        stiffness: as :func:`_stiffness`.
        iterations: FK ↔ compliance iterations of :meth:`settle`.
        gravity: ``(3,)`` the unit vector in {J} gravity acts along where a pose is given none.
    """

    base_params: np.ndarray
    centres: np.ndarray
    platform_mass_kg: float
    radius: float
    stiffness: np.ndarray
    iterations: int
    gravity: np.ndarray = field(default_factory=lambda: DOWN.copy())

    @classmethod
    def of(cls, load: LoadModel, base_params: np.ndarray) -> Settling:
        base = np.array(base_params, dtype=float)
        _, centres = masses_and_centres(load.platform_mass_kg, load.platform_com_mm, 0.0, load.payload_com_mm, ())
        centres = np.ascontiguousarray(centres, dtype=float)
        for array in (base, centres):
            array.setflags(write=False)
        radius = moment_radius(LegGeometry.from_params(base))
        gravity = np.array(load.gravity, dtype=float)
        return cls(base, centres, float(load.platform_mass_kg), radius, _stiffness(load), int(load.iterations), gravity)

    @property
    def n_legs(self) -> int:
        """The drive's legs: seven parameters each."""
        return self.base_params.size // len(PARAMETER_FIELDS)

    def _inputs(self, R: np.ndarray, t: np.ndarray, payload_kg, gravity=None) -> tuple[tuple, tuple]:
        """``(batch, the kernels' pose inputs)`` of poses ``(R, t)`` (copied: the kernels overwrite them)
        under gravity along ``gravity`` ``(..., 3)`` (None: :attr:`gravity`)."""
        down = self.gravity if gravity is None else np.asarray(gravity, dtype=float)
        batch = np.broadcast_shapes(np.shape(R)[:-2], np.shape(t)[:-1], np.shape(payload_kg), down.shape[:-1])
        R_flat = np.array(np.broadcast_to(R, (*batch, 3, 3)), dtype=float, order="C").reshape(-1, 3, 3)
        t_flat = np.array(np.broadcast_to(t, (*batch, 3)), dtype=float, order="C").reshape(-1, 3)
        masses = np.empty((len(R_flat), 2))
        masses[:, 0] = self.platform_mass_kg
        masses[:, 1] = np.broadcast_to(payload_kg, batch).reshape(-1)
        weights = masses * G_N_PER_KG
        downs = np.array(np.broadcast_to(down, (*batch, 3)), dtype=float, order="C").reshape(-1, 3)
        return batch, (self.base_params, R_flat, t_flat, weights, downs, self.centres, self.radius, self.stiffness)

    def loaded_params(self, R: np.ndarray, t: np.ndarray, payload_kg, gravity=None) -> tuple[np.ndarray, np.ndarray]:
        """:func:`loaded_params` on this robot."""
        batch, inputs = self._inputs(R, t, payload_kg, gravity)
        n = len(inputs[1])
        params, forces, ratios = np.empty((n, self.base_params.size)), np.empty((n, self.n_legs)), np.empty(n)
        _loaded_params(*inputs, params, forces, ratios)
        _refuse_singular(ratios)
        return params.reshape(batch + params.shape[1:]), forces.reshape(batch + forces.shape[1:])

    def settle(
        self, strokes: np.ndarray, payload_kg, guess: tuple[np.ndarray, np.ndarray], gravity=None, growth=None
    ) -> tuple[kin.FKSolution, np.ndarray]:
        """:func:`settle` on this robot, each leg joint to joint scaled by ``1 + growth`` (``(N, 6)``, a warm
        leg's ``α_i ΔT_i · 1e-6``; None: 0), ``(l_i + q_i − f_i / k_leg)(1 + s_i)``: the leg grows, loaded
        as it is, and its joints' give does not (the experiment's ``[thermal]``, spec §17)."""
        strokes = np.ascontiguousarray(strokes, dtype=float).reshape(-1, self.n_legs)
        n = len(strokes)
        down = self.gravity if gravity is None else gravity
        growth = np.zeros((n, self.n_legs)) if growth is None else np.ascontiguousarray(growth, dtype=float)
        growth = np.broadcast_to(growth, (n, self.n_legs)).copy()
        _, inputs = self._inputs(*guess, np.broadcast_to(payload_kg, n), np.broadcast_to(down, (n, 3)))
        params, forces = np.empty((n, self.base_params.size)), np.empty((n, self.n_legs))
        ratios, residual = np.empty(n), np.empty(n)
        steps = np.empty(n, dtype=np.int64)
        fk = (kin.FK_TOLERANCE_MM, kin.FK_MAX_ITERATIONS)
        _settle_poses(*inputs, strokes, growth, self.iterations, *fk, params, forces, ratios, residual, steps)
        _refuse_singular(ratios)
        converged = residual <= kin.FK_TOLERANCE_MM
        if not converged.all():
            first = int(np.flatnonzero(~converged)[0])
            finite = np.all(np.isfinite(strokes[first]))
            reason = f"residual {residual[first]:.3g} mm" if finite else "non-finite lengths"
            raise kin.FKError(
                f"forward kinematics did not converge (pose {first}): {reason}; the leg lengths may be unreachable"
            )
        return kin.FKSolution(inputs[1], inputs[2], steps, converged, residual), params


def _refuse_singular(ratios: np.ndarray) -> None:
    bad = np.flatnonzero(~(ratios >= SINGULAR_RATIO))
    if bad.size:
        index = int(bad[0])
        raise SingularStatics(_singular_message(index, float(ratios[index])), index, float(ratios[index]))


def loaded_params(
    load: LoadModel, base_params: np.ndarray, R: np.ndarray, t: np.ndarray, payload_kg, gravity=None
) -> tuple[np.ndarray, np.ndarray]:
    """True drive parameters under load at pose ``(R, t)``: ``M_base + δM_load``.

    The forces are computed on the base geometry (the drift changes the moment arms by ~1e-3
    relative, a second-order effect on a ~1e-3 drift).

    Args:
        base_params: ``(42,)`` true unloaded drive parameters (nominal + manufacturing errors) [mm].
        payload_kg: scalar or ``(...)`` payload mass [kg].
        gravity: ``(..., 3)`` the unit vector in {J} gravity acts along at each pose (None: ``load.gravity``).
    Returns:
        ``((..., 42) params [mm], (..., 6) leg forces [N])``.
    Raises:
        SingularStatics: at a pose where the statics matrix is singular.
    """
    return Settling.of(load, base_params).loaded_params(R, t, payload_kg, gravity)


def settle(
    load: LoadModel,
    base_params: np.ndarray,
    strokes: np.ndarray,
    payload_kg,
    guess: tuple[np.ndarray, np.ndarray],
    gravity=None,
) -> tuple[kin.FKSolution, np.ndarray]:
    """Where the loaded robot comes to rest for executed strokes: FK ↔ compliance fixed point.

    Forces at the latest pose estimate; the last FK lands within ~1e-6 of the drift's own pose
    change of where those forces were taken, so two iterations (``load.iterations``) reach the
    nm level.

    Args:
        base_params: ``(42,)`` true unloaded drive parameters [mm].
        strokes: ``(N, 6)`` executed strokes q [mm].
        payload_kg: scalar or ``(N,)`` [kg].
        guess: ``(R (N, 3, 3), t (N, 3))`` start (e.g. the desired or previous pose).
        gravity: ``(3,)`` or ``(N, 3)`` the unit vector in {J} gravity acts along (None: ``load.gravity``).
    Returns:
        ``(FK solution of the final iteration, (N, 42) true params in force [mm])``.
    Raises:
        kinematics.FKError: some pose did not converge (unreachable strokes).
        SingularStatics: the statics matrix is singular at a pose on the way.
    """
    return Settling.of(load, base_params).settle(strokes, payload_kg, guess, gravity)
