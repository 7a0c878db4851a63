"""Drive-leg factor: platform pose ↔ the drive model's unknowns (paper eq. 1).

Residual of drive leg i (:mod:`stewart_calib.model.drive`): the leg model's closure residual at the
leg's parameters ``nominal_i + δ_i``, for prismatic legs::

    r_i = ‖t + R d_i − j_i‖ − (l_i + e_i),    (j_i, d_i, l_i) = nominal_i + δ_i

with δ_i the leg's slice of δM (paper eq. 9: ``(δj_i, δd_i, δl_i)``) and ``e_i`` the drive model's
extension of the sample's inputs (the stroke ``(1 + k_i) q_i``), whose terms' values are the
nominal ones plus, where the drive identifies them, the unknown vector's errors
(``∂r_i/∂v_{b,i} = J_e,i g_b u_{b,i}``, prismatic ``J_e = −1``). Prismatic legs (``legs.compiled``)
are one compiled call; other leg kinds the drive model's numpy residual and Jacobians
(:func:`._kernels.drive_leg_rows_numpy`), the same rows. The factor's variables are the pose ``X_k`` (``gtsam.Pose3``)
and the unknown vector of the current parameter window (the drive's first); leg i's row touches
only its own parameters' columns and its terms' values. (One 42-vector variable is faster than six
7-vector variables; see :mod:`stewart_calib.estimators.isam2`.) One factor holds the six legs of
a sample (one Python callback per linearisation instead of six, and one Jacobian block for gtsam
to eliminate): with Gaussian noise the six rows are the six scalar factors exactly; a robust
kernel weighs a whole factor, so with one each leg gets a factor of its own.

Jacobians, body tangent ``ξ = [ω, v]`` (GTSAM order): with ``n`` the unit leg vector and
``n_b = Rᵀ n``, ``∂r/∂ξ = [(d × n_b)ᵀ, n_bᵀ]`` and ``∂r/∂(j, d, l) = [−nᵀ, n_bᵀ, −1]``
(the rows of paper eq. 8 in the leg-length form).

An unannounced payload (``[elastic] payload_sigma_kg``, spec §10; ``isam2`` only): the payload mass
``m`` [kg] is an entry of the unknown vector, and the leg forces are those under the sample's
``load_kg`` plus ``m`` times the forces per kg at ``[elastic] payload_com_mm`` (they are linear in
the masses), so ``∂r_i/∂m = −(∂e_i/∂f_i) f_{m,i} = c_i f_{m,i} / 1000`` — ekf's observation
(:mod:`stewart_calib.estimators.ekf`), the forces' own change with the pose left out as above.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import gtsam
import numpy as np

from ..model.drive import DriveModel
from . import pose_misfit
from ._kernels import drive_leg_rows, drive_leg_rows_numpy


@dataclass(frozen=True)
class DriveLegs:
    """What the factors of a set of drive legs share across samples (built once, not per sample).

    Attributes:
        legs: ``(k,)`` leg indices (0-based).
        nominal: ``(k, p)`` their nominal parameters, ``p`` a leg (prismatic ``[j_i | d_i | l_i]`` [mm]).
        columns: ``(k, p)`` their δ_i's columns in the unknown vector.
        terms: the drive's extension terms (:meth:`~stewart_calib.model.drive.DriveModel.kernel_terms`).
        elastic: the drive where its inputs hold leg forces (spec §10), else None: each evaluation
            then takes the forces at the pose and the geometry being evaluated, so the residual is
            exact wherever the solver goes; the Jacobians leave out the forces' own derivatives
            (``c·∂f/∂ξ`` and ``c·∂f/∂M`` are ~1e-3 of the rows they would join, see
            tests/test_elastic.py), which slows no convergence measurably.
        payload: the unannounced payload's column in the unknown vector (an elastic drive's, see the
            module docstring), else None.
        generic: the drive where its legs have no compiled kernels (``legs.compiled`` False): the
            rows are then its numpy residual and Jacobians; None: the compiled ones.
    """

    legs: np.ndarray
    nominal: np.ndarray
    columns: np.ndarray
    terms: tuple
    elastic: DriveModel | None = None
    payload: int | None = None
    generic: DriveModel | None = None

    @classmethod
    def of(cls, legs, drive: DriveModel, payload: int | None = None) -> DriveLegs:
        """Legs ``legs`` of ``drive``, whose ``x_drive`` opens the unknown vector (``payload``: the
        unannounced payload's column in it, or None)."""
        legs = np.asarray(legs, dtype=np.int64).reshape(-1)
        model = drive.legs
        params = model.as_vector().reshape(model.n_legs, -1)  # x_drive's first entries, leg by leg
        per_leg = params.shape[1]
        columns = per_leg * legs[:, None] + np.arange(per_leg)
        elastic = drive if drive.elastic is not None else None
        nominal = np.array(params[legs])
        if not model.compiled:
            return cls(legs, nominal, np.ascontiguousarray(columns), (), elastic, payload, drive)
        return cls(legs, nominal, np.ascontiguousarray(columns), drive.kernel_terms(), elastic, payload)

    def rows(self, pose: np.ndarray, unknowns: np.ndarray, inputs: np.ndarray):
        """``(r (k,), ∂r/∂ξ (k, 6), ∂r/∂unknowns (k, size))`` at ``pose`` ``(4, 4)`` and ``unknowns``."""
        if self.generic is not None:
            return drive_leg_rows_numpy(pose, unknowns, self.generic, self.legs, inputs)
        return drive_leg_rows(pose, unknowns, self.legs, self.nominal, self.columns, self.terms, inputs)


def _error(
    legs: DriveLegs,
    inputs: np.ndarray,
    channels,
    pose_key: int,
    params_key: int,
    this: gtsam.CustomFactor,
    values: gtsam.Values,
    H,
):
    pose, params = values.atPose3(pose_key).matrix(), values.atVector(params_key)
    elastic, dr_dm = legs.elastic, None
    if elastic is not None:  # the forces where this evaluation puts the platform and its legs
        inputs = elastic.reposed(inputs, channels, pose[:3, :3], pose[:3, 3], params)
        if legs.payload is not None:  # and the payload the unknown vector holds on top of the log's
            per_kg = elastic.payload_leg_forces(pose[:3, :3], pose[:3, 3], params, channels)
            inputs = elastic.loaded_inputs(inputs, per_kg, float(params[legs.payload]))
            dr_dm = -(elastic.force_gains(params) * per_kg)[legs.legs]
    r, H_pose, H_params = legs.rows(pose, params, inputs)
    if H is not None:
        if dr_dm is not None:
            H_params[:, legs.payload] = dr_dm
        H[0] = H_pose
        H[1] = H_params
    return r


def walk_covariance(legs: DriveLegs, pose: np.ndarray, unknowns: np.ndarray, inputs: np.ndarray, walks: np.ndarray):
    """``H_w H_wᵀ`` ``(k, k)``: the rows' covariance per unit walk variance of the unknowns ``walks``
    (bool, ``(size,)``), ``H_w`` the rows' Jacobian on them at ``pose`` (``(4, 4)``) and ``unknowns``
    (for a prismatic δM each leg's own ``[−nᵀ, n_bᵀ, −1]``: 3 on the diagonal, whatever the pose)."""
    _, _, H = legs.rows(pose, unknowns, inputs)
    H_walk = H[:, walks]
    return H_walk @ H_walk.T


def factor(
    pose_key: int,
    params_key: int,
    legs: DriveLegs,
    inputs: np.ndarray,
    noise: gtsam.noiseModel.Base,
    channels=None,
    misfit: tuple[int, np.ndarray] | None = None,
) -> gtsam.CustomFactor:
    """A ``CustomFactor`` on ``(Pose3 pose_key, unknown vector params_key)``: one row per leg of
    ``legs`` (all six in one factor unless a robust kernel weighs each alone).

    Args:
        inputs: the sample's drive inputs ``u`` (:meth:`~stewart_calib.model.drive.DriveModel.inputs`).
        channels: the sample's input channels (``Sample.inputs``): where the drive is elastic, the
            payload its leg forces carry (spec §10), taken again at each evaluation's pose.
        noise: of the ``k`` rows.
        misfit: ``(key, rows)``: a static pose's misfit variable and its rows of these legs, added to the
            residual (:mod:`.pose_misfit`); None: none.

    The residual and both Jacobians are one compiled call for prismatic legs (:func:`._kernels.drive_leg_rows`,
    on :func:`stewart_calib.model.kinematics.leg_residual`'s kernel), else the drive model's numpy rows.
    """
    u = np.array(inputs, dtype=float)
    error = partial(_error, legs, u, channels, pose_key, params_key)
    return pose_misfit.custom(noise, [pose_key, params_key], error, misfit)
