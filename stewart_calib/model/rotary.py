"""Rotary (servo-horn, 6-RSS) legs of spec §15: pure, vectorised numpy, mm and rad.

A crank (horn) of length ``h_i`` turns about the axis ``n_i`` through its centre ``a_i`` (in {J});
at the angle ``φ_i = e_i + o_i`` (``e_i`` the leg's coordinate, the commanded angle scaled by the
drive, ``o_i`` the zero trim) its ball joint is at::

    b_i = a_i + h_i (cos φ_i u_i + sin φ_i w_i),   w_i = n_i × u_i

with ``u_i`` the horn's direction at angle 0, and a rod of length ``r_i`` joins it to the platform
joint ``d_i`` (in {D}). The closure residual of leg i at the pose ``(R, t)`` of {D} in {J} is::

    r_i = ‖t + R d_i − b_i‖ − r_i      [mm]

The parameter vector M holds 11 entries a leg, leg by leg (spec §15):
``a_x a_y a_z d_x d_y d_z h r o tu tw`` — ``o``, ``tu``, ``tw`` in rad in code (degrees in files).
``tu``, ``tw`` tilt the crank's axis: :meth:`RotaryLegs.perturbed` turns the axis and the zero
direction by ``Rot(u_i, tu) Rot(w_i, tw)`` about the set's own ``u_i``, ``w_i`` (the right-hand
rotation first), so a set reports ``tu = tw = 0`` for itself and is the reference of its own tilts.

Pose perturbations are in the body tangent ``ξ = [ω, v]`` (rotation first), ``R ← R Exp(ω)``,
``t ← t + R v``, the tangent of ``gtsam.Pose3.retract`` (:mod:`stewart_calib.rotations`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..platform import N_LEGS
from ..rotations import so3_exp

#: the 11 entries of one leg's parameters, spec §15 order: ``(prefix, suffix)`` of the name ``{prefix}{leg}{suffix}``
PARAMETER_FIELDS: tuple[tuple[str, str], ...] = (
    ("a", "x"),
    ("a", "y"),
    ("a", "z"),
    ("d", "x"),
    ("d", "y"),
    ("d", "z"),
    ("h", ""),
    ("r", ""),
    ("o", ""),
    ("tu", ""),
    ("tw", ""),
)
_PER_LEG = len(PARAMETER_FIELDS)
#: columns of one leg's block of M: crank centre, platform joint, horn, rod, zero offset, tilts
_A, _D, _H, _ROD, _O, _TU, _TW = slice(0, 3), slice(3, 6), 6, 7, 8, 9, 10
#: a zero direction whose part orthogonal to its axis is below this fraction of its length has no direction
_DEGENERATE = 1e-12


def orthonormal_zero_directions(
    axes: np.ndarray, zero_directions: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Crank axes normalised and zero directions made orthogonal to their axis and normalised (spec §15).

    Args:
        axes: ``(..., 3)`` crank axes ``n_i`` (any length).
        zero_directions: ``(..., 3)`` horn directions at angle 0 ``u_i`` (any length).
    Returns:
        ``(n (..., 3), u (..., 3), off_deg (...))``: the unit axes, the unit zero directions with
        their part along the axis removed (Gram–Schmidt), and how far each given zero direction
        is from orthogonal to its axis, ``asin(|n̂·û|)`` [deg]. Rows where the axis or the zero
        direction is of zero length (or the zero direction lies along the axis) are NaN in all three.
    """
    axes = np.asarray(axes, dtype=float)
    zero = np.asarray(zero_directions, dtype=float)
    axis_norm = np.linalg.norm(axes, axis=-1, keepdims=True)
    zero_norm = np.linalg.norm(zero, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = np.where(axis_norm > 0.0, axes / axis_norm, np.nan)
        along = np.sum(zero * n, axis=-1, keepdims=True)
        rest = zero - along * n
        rest_norm = np.linalg.norm(rest, axis=-1, keepdims=True)
        ok = (zero_norm > 0.0) & (rest_norm > _DEGENERATE * zero_norm)
        u = np.where(ok, rest / rest_norm, np.nan)
        sine = np.clip(np.abs(along[..., 0]) / zero_norm[..., 0], 0.0, 1.0)
        off_deg = np.where(ok[..., 0], np.degrees(np.arcsin(sine)), np.nan)
    n = np.where(ok, n, np.nan)
    return n, u, off_deg


def _turned(vectors: np.ndarray, turns: np.ndarray) -> np.ndarray:
    """``(..., 3)`` vectors turned by the ``(..., 3, 3)`` rotations ``turns``."""
    return np.einsum("...ij,...j->...i", turns, vectors)


@dataclass(frozen=True)
class RotaryLegs:
    """Six servo-horn legs between base {J} and platform {D} (spec §15); implements the leg-model protocol.

    Attributes:
        crank_centres: ``(6, 3)`` ``a_i``, each crank's centre on its axis, in {J} [mm].
        crank_axes: ``(6, 3)`` ``n_i``, unit (normalised on construction).
        zero_directions: ``(6, 3)`` ``u_i``, the horn's direction at angle 0, unit and ⟂ ``n_i``
            (made so on construction, :func:`orthonormal_zero_directions`).
        horn_lengths: ``(6,)`` ``h_i``, axis → the horn's ball joint [mm], > 0.
        rod_lengths: ``(6,)`` ``r_i``, horn's ball joint → platform ball joint [mm], > 0.
        platform_joints: ``(6, 3)`` ``d_i`` in {D} [mm].
        angle_offsets: ``(6,)`` ``o_i``, the servos' zero trim [rad].
        angle_range: ``(min, max)`` commanded angles the servos accept [rad], at most a turn wide:
            it chooses between the two horn solutions of the inverse kinematics (:meth:`coordinates`).
    """

    crank_centres: np.ndarray
    crank_axes: np.ndarray
    zero_directions: np.ndarray
    horn_lengths: np.ndarray
    rod_lengths: np.ndarray
    platform_joints: np.ndarray
    angle_offsets: np.ndarray
    angle_range: tuple[float, float]

    kind: ClassVar[str] = "rotary"
    coordinate_unit: ClassVar[str] = "deg"
    compiled: ClassVar[bool] = False

    def __post_init__(self) -> None:
        arrays = {}
        for name, shape in (
            ("crank_centres", (N_LEGS, 3)),
            ("crank_axes", (N_LEGS, 3)),
            ("zero_directions", (N_LEGS, 3)),
            ("horn_lengths", (N_LEGS,)),
            ("rod_lengths", (N_LEGS,)),
            ("platform_joints", (N_LEGS, 3)),
            ("angle_offsets", (N_LEGS,)),
        ):
            value = np.array(getattr(self, name), dtype=float)
            if value.shape != shape:
                raise ValueError(f"{name} must have shape {shape}, got {value.shape}")
            if not np.all(np.isfinite(value)):
                raise ValueError(f"{name} must be finite")
            arrays[name] = value
        for name in ("horn_lengths", "rod_lengths"):
            if not np.all(arrays[name] > 0.0):
                raise ValueError(f"{name} must be positive, got {arrays[name]}")
        n, u, _ = orthonormal_zero_directions(arrays["crank_axes"], arrays["zero_directions"])
        bad = np.flatnonzero(np.isnan(u[:, 0]))
        if len(bad):
            raise ValueError(f"crank axis and zero direction of leg {bad[0] + 1} span no plane")
        arrays["crank_axes"], arrays["zero_directions"] = n, u
        for name, value in arrays.items():
            value.setflags(write=False)
            object.__setattr__(self, name, value)
        low, high = (float(x) for x in self.angle_range)
        if not (np.isfinite(low) and np.isfinite(high) and low < high <= low + 2.0 * np.pi):
            raise ValueError(f"angle_range must be finite, min < max, at most 2π wide, got {self.angle_range}")
        object.__setattr__(self, "angle_range", (low, high))

    # ------------------------------------------------------------------ the parameter vector

    @property
    def n_legs(self) -> int:
        """Legs of the set (six)."""
        return len(self.horn_lengths)

    @property
    def n_params(self) -> int:
        """Entries of M: 11 a leg (66)."""
        return self.n_legs * _PER_LEG

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """``a1x a1y a1z d1x d1y d1z h1 r1 o1 tu1 tw1 … tw6`` (spec §15)."""
        legs = range(1, self.n_legs + 1)
        return tuple(f"{prefix}{leg}{suffix}" for leg in legs for prefix, suffix in PARAMETER_FIELDS)

    @property
    def parameter_degrees(self) -> np.ndarray:
        """``(66,)`` True where files give the entry in degrees (``o``, ``tu``, ``tw``; code keeps rad)."""
        per_leg = np.zeros(_PER_LEG, dtype=bool)
        per_leg[[_O, _TU, _TW]] = True
        return np.tile(per_leg, self.n_legs)

    @property
    def gauge_columns(self) -> tuple[np.ndarray, np.ndarray]:
        """``((6, 3), (6, 3))`` columns in M of the crank centres ``a_i`` and of the platform joints
        ``d_i``: an outside instrument's gauge holds their mean rigid motion at nominal (spec §15)."""
        first = _PER_LEG * np.arange(self.n_legs)[:, None]
        return first + np.arange(_A.start, _A.stop), first + np.arange(_D.start, _D.stop)

    @property
    def w_directions(self) -> np.ndarray:
        """``(6, 3)`` ``w_i = n_i × u_i``: the horn's direction at angle +90°."""
        return np.cross(self.crank_axes, self.zero_directions)

    def as_vector(self) -> np.ndarray:
        """``(66,)`` M leg by leg ``[a_i | d_i | h_i r_i o_i | tu_i tw_i]`` [mm, rad]; the tilts are 0:
        a set is the reference of its own tilts."""
        blocks = np.zeros((self.n_legs, _PER_LEG))
        blocks[:, _A] = self.crank_centres
        blocks[:, _D] = self.platform_joints
        blocks[:, _H] = self.horn_lengths
        blocks[:, _ROD] = self.rod_lengths
        blocks[:, _O] = self.angle_offsets
        return blocks.reshape(-1)

    def perturbed(self, delta: np.ndarray) -> RotaryLegs:
        """The set ``M + δM`` for a ``(66,)`` (or ``(6, 11)``) δM [mm, rad].

        Positions, lengths and offsets add. Each crank's axis and zero direction are turned by
        ``Rot(u_i, δtu_i) Rot(w_i, δtw_i)`` (``Rot(w_i, δtw_i)`` applied first) about this set's own
        ``u_i`` and ``w_i = n_i × u_i``: a ``δtu`` tilts the axis towards ``−w_i`` and keeps ``u_i``,
        a ``δtw`` turns ``u_i`` towards ``−n_i`` and keeps ``w_i``.
        """
        d = np.asarray(delta, dtype=float).reshape(self.n_legs, _PER_LEG)
        u, w = self.zero_directions, self.w_directions
        turn = so3_exp(u * d[:, _TU, None]) @ so3_exp(w * d[:, _TW, None])
        return RotaryLegs(
            self.crank_centres + d[:, _A],
            _turned(self.crank_axes, turn),
            _turned(u, turn),
            self.horn_lengths + d[:, _H],
            self.rod_lengths + d[:, _ROD],
            self.platform_joints + d[:, _D],
            self.angle_offsets + d[:, _O],
            self.angle_range,
        )
