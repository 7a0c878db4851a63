"""numba kernels behind the factors' ``gtsam.CustomFactor`` callbacks.

iSAM2 linearises every measurement factor about twice (when it enters and when its pose is
relinearised), two factors a sample: tens of thousands of callbacks a log. Written with numpy,
one callback made ~10 small arrays (fancy indexing, ``np.put``, ``np.zeros``, the rotation and
translation apart) around a compiled core. Here each callback is one compiled call from what
gtsam hands over (the pose as ``Pose3.matrix()``, the unknown vector) to the arrays it takes
back: a linearisation measured at 0.4× (drive legs) and 0.35× (tracker) the time, gtsam's own
part included. The arithmetic is :func:`stewart_calib.kinematics.leg_residual`'s (the same kernel,
:func:`stewart_calib._kernels.leg_rows`), so the numbers are bit for bit the same.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._jit import njit
from .._kernels import leg_rows

# as stewart_calib._kernels: x / 0 gives inf/NaN as numpy does
_JIT: dict[str, Any] = {"nogil": True, "error_model": "numpy"}


@njit(**_JIT)
def drive_leg_rows(pose, unknowns, legs_of, nominal, columns, terms, inputs):
    """Drive-leg residuals of ``k`` legs and their Jacobians on the pose and the unknown vector.

    Args:
        pose: ``(4, 4)`` homogeneous pose of {D} in {J} [mm] (``Pose3.matrix()``).
        unknowns: ``(size,)`` the unknown vector (the drive's ``x_drive`` first).
        legs_of: ``(k,)`` the rows' leg indices (0…5).
        nominal: ``(k, 7)`` nominal ``[j_i | d_i | l_i]`` [mm]; columns: ``(k, 7)`` their δ_i's
            columns in ``unknowns``.
        terms: the drive's extension terms ``(starts, gains, offsets, values (b, 6), columns (b, 6))``
            (:meth:`stewart_calib.drive.DriveModel.kernel_terms`; a column −1: the value is known).
        inputs: the sample's drive inputs ``u``.
    Returns:
        ``(r (k,), ∂r/∂ξ (k, 6), ∂r/∂unknowns (k, size))``.
    """
    starts, gains, offsets, values, term_columns = terms
    k = nominal.shape[0]
    legs = np.empty((k, 7))
    extensions = np.empty(k)
    gain = np.empty((starts.shape[0], k))  # ∂e_i/∂v_{b,i} = g_b u_{b,i}
    for i in range(k):
        leg = legs_of[i]
        for j in range(7):
            legs[i, j] = nominal[i, j] + unknowns[columns[i, j]]
        e = 0.0
        for b in range(starts.shape[0]):
            value = values[b, leg]
            if term_columns[b, leg] >= 0:
                value = values[b, leg] + unknowns[term_columns[b, leg]]
            u = inputs[starts[b] + leg]
            gain[b, i] = u if gains[b] == 1.0 else gains[b] * u
            part = (offsets[b] + value) * gain[b, i]
            e = part if b == 0 else e + part
        extensions[i] = e
    R = np.ascontiguousarray(pose[:3, :3])
    t = np.ascontiguousarray(pose[:3, 3])
    r, J_pose, J_legs = np.empty(k), np.empty((k, 6)), np.empty((k, 7))
    leg_rows(legs, R, t, extensions, r, J_pose, J_legs)
    H = np.zeros((k, unknowns.shape[0]))
    for i in range(k):
        for j in range(7):
            H[i, columns[i, j]] = J_legs[i, j]
        for b in range(starts.shape[0]):
            if term_columns[b, legs_of[i]] >= 0:
                H[i, term_columns[b, legs_of[i]]] = -gain[b, i]
    return r, J_pose, H


@njit(**_JIT)
def known_leg_rows(pose, legs, extensions):
    """Residuals of ``k`` legs of known geometry ``legs (k, 7)`` = ``[j_i | d_i | l_i]`` with
    extensions ``e_i`` (a tracker's rulers and their readings) at ``pose`` ``(4, 4)``, and their
    Jacobian on the pose: ``(r (k,), ∂r/∂ξ (k, 6))``."""
    k = legs.shape[0]
    R = np.ascontiguousarray(pose[:3, :3])
    t = np.ascontiguousarray(pose[:3, 3])
    r, J_pose, J_legs = np.empty(k), np.empty((k, 6)), np.empty((k, 7))
    leg_rows(legs, R, t, extensions, r, J_pose, J_legs)
    return r, J_pose
