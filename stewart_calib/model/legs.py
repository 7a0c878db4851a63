"""The leg-model protocol: what a set of legs between the base {J} and the platform {D} is (spec §15).

A leg model owns a parameter vector ``M`` (its layout and names, leg by leg) and per leg a closure
residual ``r_i(pose; M, e_i) = 0`` in one coordinate ``e_i`` per leg — a prismatic leg's extension
[mm], a rotary leg's crank angle before its zero offset [rad] — with its Jacobians, forward and
inverse kinematics, the direction its force acts along and the columns of ``M`` that hold an
outside instrument's gauge. Each closure is a joint-to-joint distance less the leg's length, so a
growth of the whole leg (its temperature, spec §17) is the optional ``lengthening`` ``Δℓ (..., n)``
[mm] of every kinematic method, ``∂r_i/∂Δℓ_i = −1``: where the coordinate is itself a length
(:attr:`LegModel.coordinate_is_length`, prismatic) it adds to ``e``, elsewhere to the fixed length
(a rotary leg's rod). :class:`~stewart_calib.model.drive.DriveModel` and every estimator reach the
legs through it alone; compiled fast paths are taken only where :attr:`LegModel.compiled`.

A new leg kind is one module implementing :class:`LegModel` and one line of :data:`LEG_KINDS`.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from .kinematics import FK_TOLERANCE_MM, FKSolution
from .platform import LegGeometry
from .rotary import RotaryLegs


class LegModel(Protocol):
    """What a set of legs between base {J} and platform {D} is: a parameter vector M, and per leg a
    closure residual ``r_i(pose; M, e_i) = 0`` in one coordinate ``e_i`` per leg (a prismatic leg's
    extension [mm], a rotary leg's crank angle before its zero offset [rad]).

    Attributes:
        kind: ``"prismatic"`` | ``"rotary"``: the platform file's ``[drive] kind``.
        n_legs: legs of the set (6).
        n_params: entries of M, leg by leg (42 | 66; spec §5, §15 order).
        parameter_names: their names (``j1x … l6`` | ``a1x a1y a1z d1x d1y d1z h1 r1 o1 tu1 tw1 … tw6``).
        parameter_degrees: ``(n_params,)`` bool, True where files give the entry in degrees (code: rad).
        coordinate_unit: ``"mm"`` | ``"deg"``: the unit of the log's drive columns ``q{i}_{unit}``.
        coordinate_is_length: whether ``e_i`` adds to the leg's joint-to-joint length (a prismatic
            leg's extension), so that a lengthening ``Δℓ`` is the same as ``e + Δℓ``; False for a
            rotary leg, whose rod takes it.
        gauge_columns: ``((n, 3), (n, 3))`` int columns in M of the base-side points (prismatic
            ``j_i``, rotary crank centres ``a_i``) and of the platform joints ``d_i``: an outside
            instrument's gauge holds their mean rigid motion at nominal (spec §7, §15).
        compiled: the prismatic numba kernels apply (:class:`~stewart_calib.model.platform.LegGeometry` only).
    """

    @property
    def kind(self) -> str: ...

    @property
    def n_legs(self) -> int: ...

    @property
    def n_params(self) -> int: ...

    @property
    def parameter_names(self) -> tuple[str, ...]: ...

    @property
    def parameter_degrees(self) -> np.ndarray: ...

    @property
    def coordinate_unit(self) -> str: ...

    @property
    def coordinate_is_length(self) -> bool: ...

    @property
    def gauge_columns(self) -> tuple[np.ndarray, np.ndarray]: ...

    @property
    def compiled(self) -> bool: ...

    def as_vector(self) -> np.ndarray:
        """``(n_params,)`` M in code units (mm, rad)."""
        ...

    def perturbed(self, delta: np.ndarray) -> LegModel:
        """``M + δM``, the same kind."""
        ...

    def residuals(
        self, R: np.ndarray, t: np.ndarray, e: np.ndarray, *, lengthening: np.ndarray | None = None
    ) -> np.ndarray:
        """``(..., n_legs)`` closure residuals [mm] at poses ``(R, t)`` with coordinates ``e``, each leg
        longer by ``lengthening`` ``(..., n)`` [mm] (None: 0)."""
        ...

    def residual_jacobians(
        self, R: np.ndarray, t: np.ndarray, e: np.ndarray, *, lengthening: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(J_pose (..., n, 6), J_M (..., n, n_params), J_e (..., n))``: the body tangent
        ``ξ = [ω, v]`` rotation first (``R ← R Exp(ω)``, ``t ← t + R v``), and ``J_e,i = ∂r_i/∂e_i``
        (prismatic: −1); ``∂r_i/∂Δℓ_i = −1`` needs no array."""
        ...

    def moved(self, delta: np.ndarray, base: tuple, platform: tuple) -> np.ndarray:
        """``δM'`` such that ``self.perturbed(δM')`` is ``self.perturbed(δM)`` with its base side moved by the
        rigid motion ``base = (R, t)`` (points ``p → R p + t``, directions turned by ``R``) and its platform
        joints by ``platform``: a truth moved into an outside instrument's gauge (spec §7, §15)."""
        ...

    def coordinates(self, R: np.ndarray, t: np.ndarray, *, lengthening: np.ndarray | None = None) -> np.ndarray:
        """Inverse kinematics: ``(..., n)`` the ``e`` closing each leg, longer by ``lengthening``, at
        ``(R, t)``, NaN where a leg cannot reach it (rotary: spec §15's branch rule)."""
        ...

    def forward_kinematics(
        self,
        e: np.ndarray,
        guess=None,
        tol_mm: float | None = FK_TOLERANCE_MM,
        strict: bool = True,
        along: bool = False,
        *,
        lengthening: np.ndarray | None = None,
    ) -> FKSolution:
        """Poses closing every leg, longer by ``lengthening``, at coordinates ``e (..., n)``."""
        ...

    def solve_fk(
        self, e: np.ndarray, guess, what: str, *, lengthening: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """One pose from ``guess``, then cold; ``SampleRejected`` when neither converges."""
        ...

    def joint_lengths(self, e: np.ndarray) -> np.ndarray:
        """``(..., n)`` each leg's length from joint to joint at coordinates ``e`` [mm]: what its
        temperature scales (spec §17)."""
        ...

    def unit_vectors(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """``(..., n, 3)`` in {J}: the direction each leg's force acts along (prismatic: the leg;
        rotary: the rod, a two-force member)."""
        ...

    def prior_sigmas(self, noise) -> np.ndarray:
        """``(n_params,)`` prior σ of δM in code units from a :class:`~stewart_calib.config.NoiseConfig`."""
        ...

    def walk_sigmas(self, noise) -> np.ndarray:
        """``(n_params,)`` random walk of δM [code units /√s]."""
        ...

    def coordinate_sigma(self, noise) -> float:
        """σ of one logged leg coordinate in code units (prismatic: the stroke's [mm]; rotary: one
        commanded servo angle's [rad]): it enters the EKF's measurement covariance through ``J_e``."""
        ...


#: ``[drive] kind`` → its leg model: the one registry of leg kinds (one line per kind)
LEG_KINDS: dict[str, type] = {"prismatic": LegGeometry, "rotary": RotaryLegs}
