"""Central-difference Jacobians: the one numerical-derivative helper every Jacobian test uses.

GTSAM's Python module (4.3.0) exposes no ``numericalDerivative``; these play its part.

Step sizes. A central difference has truncation error ``≈ eps² |f'''| / 6`` and round-off
error ``≈ ε_mach |f| / eps`` (``ε_mach = 2.2e-16``); the best step balances the two,
``eps ≈ (3 ε_mach |f| / |f'''|)^(1/3)``. For a leg length (``|f| ≈ 1e3 mm``):

* with respect to a position [mm], ``|f'''| ≈ 1/L² ≈ 1e-6 mm⁻²`` → ``eps ≈ 9e-3 mm``;
  :data:`EPS_MM` = 1e-2 mm leaves an error ≈ 4e-11 on a derivative of order 1;
* with respect to a rotation [rad], ``|f'''| ≲ 1e3 mm`` (the joint lever arm) →
  ``eps ≈ 9e-6 rad``; :data:`EPS_RAD` = 1e-5 rad leaves an error ≈ 4e-8 mm/rad on a
  derivative of order 300 mm/rad.

Both are ≈ 1e-10 relative, four orders below the 1e-6 the tests ask for, so the tests have
room for f computed through an iterative solver (FK with ``tol_mm=1e-12`` adds
``1e-12 / (2 eps)`` ≈ 5e-11). A single step for mixed mm/rad arguments would be wrong for one
of them by ~100×; pass an ``(n,)`` array of steps (or ``(eps_rad, eps_mm)`` for poses).

Compare with :func:`relative_error` (Frobenius norm over the whole matrix): element-wise
ratios blow up on entries that are exactly zero analytically.

Pose tangent: ``ξ = [ω, v]`` (rotation first, body frame) as in ``gtsam.Pose3``.
:func:`numerical_pose_jacobian` perturbs with :func:`stewart_calib.model.kinematics.retract`
(``R Exp(ω)``, ``t + R v``); :func:`numerical_pose3_jacobian` with ``gtsam.Pose3.retract``,
which in gtsam 4.3.0 is the full SE(3) exponential (``t + R V(ω) v``). The two charts agree to
first order at ``ξ = 0``, so both give the same Jacobian (to O(eps²)).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from stewart_calib.model import kinematics as kin

EPS_MM = 1e-2
"""Central-difference step for arguments in mm (see module docstring) [mm]."""
EPS_RAD = 1e-5
"""Central-difference step for arguments in rad (see module docstring) [rad]."""


def numerical_jacobian(
    f: Callable[[np.ndarray], np.ndarray], x: np.ndarray, eps: float | np.ndarray = EPS_MM
) -> np.ndarray:
    """``∂f/∂x`` by central differences, shape ``f(x).shape + (n,)``.

    Args:
        f: function of a ``(n,)`` vector returning an array (any shape).
        x: ``(n,)`` point of evaluation.
        eps: scalar step or ``(n,)`` steps, in the units of ``x``.
    """
    x = np.asarray(x, dtype=float)
    steps = np.broadcast_to(np.asarray(eps, dtype=float), x.shape)
    columns = []
    for k in range(x.size):
        dx = np.zeros_like(x)
        dx[k] = steps[k]
        columns.append((np.asarray(f(x + dx)) - np.asarray(f(x - dx))) / (2.0 * steps[k]))
    return np.stack(columns, axis=-1)


def _pose_steps(eps: float | tuple[float, float] | np.ndarray) -> np.ndarray:
    eps = np.asarray(eps, dtype=float)
    if eps.shape == (2,):
        return np.repeat(eps, 3)
    return np.broadcast_to(eps, (6,))


def numerical_pose_jacobian(
    f: Callable[[np.ndarray, np.ndarray], np.ndarray],
    R: np.ndarray,
    t: np.ndarray,
    eps: float | tuple[float, float] | np.ndarray = (EPS_RAD, EPS_MM),
) -> np.ndarray:
    """``∂f(R Exp(ω), t + R v)/∂ξ`` at ``ξ = [ω, v] = 0``, shape ``f(R, t).shape + (6,)``.

    Args:
        f: function of ``(R (3, 3), t (3,) [mm])``.
        eps: ``(eps_rad, eps_mm)``, a ``(6,)`` array, or one scalar for all six.
    """
    return numerical_jacobian(lambda xi: f(*kin.retract(R, t, xi)), np.zeros(6), _pose_steps(eps))


def numerical_pose3_jacobian(
    f: Callable[[object], np.ndarray],
    pose3,
    eps: float | tuple[float, float] | np.ndarray = (EPS_RAD, EPS_MM),
) -> np.ndarray:
    """``∂f(pose3.retract(ξ))/∂ξ`` at ``ξ = 0`` for a ``gtsam.Pose3``, shape ``f(pose3).shape + (6,)``.

    The GTSAM convention for a factor's ``H``: ``ξ = [ω, v]``, rotation first, mm for ``v``.
    """
    return numerical_jacobian(lambda xi: f(pose3.retract(xi)), np.zeros(6), _pose_steps(eps))


def relative_error(analytic: np.ndarray, numeric: np.ndarray) -> float:
    """``‖analytic − numeric‖_F / ‖numeric‖_F`` (Frobenius over the whole array)."""
    analytic, numeric = np.asarray(analytic, dtype=float), np.asarray(numeric, dtype=float)
    return float(np.linalg.norm(analytic - numeric) / np.linalg.norm(numeric))
