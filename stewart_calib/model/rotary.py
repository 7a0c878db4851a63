"""Rotary (servo-horn, 6-RSS) legs of spec §15: pure, vectorised numpy, mm and rad.

A crank (horn) of length ``h_i`` turns about the axis ``n_i`` through its centre ``a_i`` (in {J});
at the angle ``φ_i = e_i + o_i`` (``e_i`` the leg's coordinate, the commanded angle scaled by the
drive, ``o_i`` the zero trim) its ball joint is at::

    b_i = a_i + h_i (cos φ_i u_i + sin φ_i w_i),   w_i = n_i × u_i

with ``u_i`` the horn's direction at angle 0, and a rod of length ``r_i`` joins it to the platform
joint ``d_i`` (in {D}). The closure residual of leg i at the pose ``(R, t)`` of {D} in {J} is::

    r_i = ‖t + R d_i − b_i‖ − (r_i + Δℓ_i)      [mm]

with ``Δℓ_i`` the leg's lengthening besides its geometry (its growth with temperature, spec §17: the
rod is what grows; 0 unless given), an input of every kinematic method like ``e``.

The parameter vector M holds 11 entries a leg, leg by leg (spec §15):
``a_x a_y a_z d_x d_y d_z h r o tu tw`` — ``o``, ``tu``, ``tw`` in rad in code (degrees in files).
``tu``, ``tw`` tilt the crank's axis: :meth:`RotaryLegs.perturbed` turns the axis and the zero
direction by ``Rot(u_i, tu) Rot(w_i, tw)`` about the set's own ``u_i``, ``w_i`` (the right-hand
rotation first), so a set reports ``tu = tw = 0`` for itself and is the reference of its own tilts.

Pose perturbations are in the body tangent ``ξ = [ω, v]`` (rotation first), ``R ← R Exp(ω)``,
``t ← t + R v``, the tangent of ``gtsam.Pose3.retract`` (:mod:`stewart_calib.model.rotations`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from functools import cached_property
from typing import cast

import numpy as np

from .kinematics import FK_MAX_ITERATIONS, FK_TOLERANCE_MM, FKSolution, fk_failed, fk_solution
from .platform import N_LEGS
from .rotations import retract, rotation_angle

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
#: FK's Newton step is capped at this rotation [rad], and at this fraction of the mean rod length in
#: translation (one rod's swing by the same angle), so that a poor start stays in Newton's basin
MAX_STEP_RAD = 0.2
#: FK's damping ``μ = FK_DAMPING · tr(JᵀJ) / 6`` of the normal equations ``(JᵀJ + μ I) ξ = −Jᵀ r``: a
#: singular Jacobian still gives a bounded step, and near a solution the step is Newton's to a factor
#: ``1 − μ/σ_min²`` (≈ 1 − 1e-8 for a servo build: quadratic convergence is kept to far below FK's tolerance)
FK_DAMPING = 1e-12
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


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a × b`` over the last axis (``np.cross`` costs several times more on small arrays)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _rotated(x: np.ndarray, k: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rodrigues: ``(..., 3)`` vectors ``x`` turned by ``angle (...)`` [rad] about the unit ``k (..., 3)``;
    ``x`` itself where the angle is 0."""
    c, s = np.cos(angle)[..., None], np.sin(angle)[..., None]
    return c * x + s * _cross(k, x) + (1.0 - c) * np.sum(k * x, axis=-1, keepdims=True) * k


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
        tilt_reference: ``(6, 3)`` the zero directions ``u⁰_i`` the tilts ``tu`` are taken about: the
            set's own ``u_i`` (default), or, for a set :meth:`perturbed` from another, that set's. The
            drive perturbs its nominal legs by the whole δM, so ``∂/∂tu`` at a tilted set turns about
            ``u⁰_i``, not about its own (tilted) ``u_i``; ``∂/∂tw`` turns about ``Rot(u⁰, tu) w⁰ = w_i``.
        reach_margin: the crank angle [rad] a pose must keep from where a leg's two horn solutions
            meet (rod in line with the horn, fully stretched or folded) for :meth:`coordinates` to
            count it reachable: 0 (default) for the exact inverse kinematics; a plan's margin, so that
            a calibrated model, whose rods and horns differ from the nominal, still reaches its poses.
    """

    crank_centres: np.ndarray
    crank_axes: np.ndarray
    zero_directions: np.ndarray
    horn_lengths: np.ndarray
    rod_lengths: np.ndarray
    platform_joints: np.ndarray
    angle_offsets: np.ndarray
    angle_range: tuple[float, float]
    tilt_reference: np.ndarray | None = field(default=None, compare=False, repr=False)
    reach_margin: float = 0.0

    #: the leg model's kind (:class:`~stewart_calib.model.legs.LegModel`): the platform file's ``[drive] kind``
    kind = "rotary"
    #: the unit of the log's drive columns ``q{i}_deg`` (spec §15: commanded angles)
    coordinate_unit = "deg"
    #: no compiled kernels: the numpy paths of the drive and the estimators apply
    compiled = False
    #: ``e_i`` is an angle: a leg's lengthening goes to its rod (spec §17), not to ``e``
    coordinate_is_length = False

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
        if self.tilt_reference is not None:
            reference = np.array(self.tilt_reference, dtype=float)
            if reference.shape != (N_LEGS, 3):
                raise ValueError(f"tilt_reference must have shape {(N_LEGS, 3)}, got {reference.shape}")
            arrays["tilt_reference"] = reference
        else:
            arrays["tilt_reference"] = u.copy()
        for name, value in arrays.items():
            value.setflags(write=False)
            object.__setattr__(self, name, value)
        low, high = (float(x) for x in self.angle_range)
        if not (np.isfinite(low) and np.isfinite(high) and low < high <= low + 2.0 * np.pi):
            raise ValueError(f"angle_range must be finite, min < max, at most 2π wide, got {self.angle_range}")
        object.__setattr__(self, "angle_range", (low, high))
        if not 0.0 <= float(self.reach_margin) < 0.5 * np.pi:
            raise ValueError(f"reach_margin must be in [0, π/2) rad, got {self.reach_margin}")
        object.__setattr__(self, "reach_margin", float(self.reach_margin))

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

    def prior_sigmas(self, noise) -> np.ndarray:
        """``(66,)`` prior σ of δM in code units from a :class:`~stewart_calib.config.NoiseConfig`:
        ``noise.prior_sigma_mm`` on the lengths and positions, ``noise.angle_prior_sigma_deg`` (in rad)
        on the zero offsets and axis tilts."""
        return self._per_entry(noise.prior_sigma_mm, np.radians(noise.angle_prior_sigma_deg))

    def walk_sigmas(self, noise) -> np.ndarray:
        """``(66,)`` random walk of δM [mm/√s, rad/√s]: ``noise.random_walk_mm_per_sqrt_s`` on the lengths
        and positions, ``noise.angle_random_walk_deg_per_sqrt_s`` (in rad) on the angles."""
        return self._per_entry(noise.random_walk_mm_per_sqrt_s, np.radians(noise.angle_random_walk_deg_per_sqrt_s))

    def coordinate_sigma(self, noise) -> float:
        """σ of one logged coordinate, a commanded servo angle [rad]: ``noise.angle_sigma_deg``."""
        return float(np.radians(noise.angle_sigma_deg))

    def _per_entry(self, length: float, angle: float) -> np.ndarray:
        """``(66,)`` ``angle`` where M holds an angle (:attr:`parameter_degrees`), ``length`` elsewhere."""
        return np.where(self.parameter_degrees, float(angle), float(length))

    @cached_property
    def w_directions(self) -> np.ndarray:
        """``(6, 3)`` ``w_i = n_i × u_i``: the horn's direction at angle +90° (read-only; every residual needs it)."""
        w = _cross(self.crank_axes, self.zero_directions)
        w.setflags(write=False)
        return w

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

        def turned(x: np.ndarray) -> np.ndarray:  # Rot(u, tu) Rot(w, tw) x
            return _rotated(_rotated(x, w, d[:, _TW]), u, d[:, _TU])

        return RotaryLegs._trusted(
            self.crank_centres + d[:, _A],
            turned(self.crank_axes),
            turned(u),
            self.horn_lengths + d[:, _H],
            self.rod_lengths + d[:, _ROD],
            self.platform_joints + d[:, _D],
            self.angle_offsets + d[:, _O],
            self.angle_range,
            np.array(u),
            self.reach_margin,
        )

    def moved(self, delta: np.ndarray, base: tuple, platform: tuple) -> np.ndarray:
        """``δM'`` such that ``self.perturbed(δM')`` is ``self.perturbed(δM)`` with its base side moved by the
        rigid motion ``base = (R, t)`` (crank centres ``a → R a + t``, axes and zero directions turned by ``R``)
        and its platform joints by ``platform = (R, t)`` (``d → R d + t``): spec §15's rigid move of the base.

        The turned axis ``n'`` gives the tilts about this set's ``u⁰``, ``w⁰`` (``Rot(u⁰, tu) Rot(w⁰, tw) n⁰ =
        sin tw u⁰ + cos tw (cos tu n⁰ − sin tu w⁰)``), and the turned zero direction's angle from where those
        tilts put ``u⁰``, about ``n'``, adds to the zero offset.
        """
        legs = self.perturbed(delta)
        (R_J, t_J), (R_D, t_D) = base, platform
        n, u = legs.crank_axes @ np.asarray(R_J).T, legs.zero_directions @ np.asarray(R_J).T
        u0, w0, n0 = self.zero_directions, self.w_directions, self.crank_axes
        tw = np.arcsin(np.clip(np.sum(n * u0, axis=-1), -1.0, 1.0))
        tu = np.arctan2(-np.sum(n * w0, axis=-1), np.sum(n * n0, axis=-1))

        def turned(x: np.ndarray) -> np.ndarray:  # Rot(u⁰, tu) Rot(w⁰, tw) x, as perturbed turns it
            return _rotated(_rotated(x, w0, tw), u0, tu)

        turn = np.arctan2(np.sum(u * turned(w0), axis=-1), np.sum(u * turned(u0), axis=-1))
        out = np.zeros((self.n_legs, _PER_LEG))
        out[:, _A] = legs.crank_centres @ np.asarray(R_J).T + t_J - self.crank_centres
        out[:, _D] = legs.platform_joints @ np.asarray(R_D).T + t_D - self.platform_joints
        out[:, _H] = legs.horn_lengths - self.horn_lengths
        out[:, _ROD] = legs.rod_lengths - self.rod_lengths
        out[:, _O] = legs.angle_offsets + turn - self.angle_offsets
        out[:, _TU], out[:, _TW] = tu, tw
        return out.reshape(-1)

    @classmethod
    def _trusted(cls, *values) -> RotaryLegs:
        """A set of fresh float arrays of the right shapes, without ``__post_init__``'s copies and checks:
        :meth:`perturbed`'s sums, and its axes and zero directions turned by one rotation (orthonormal
        to rounding), so a zero δM gives the same set bit for bit."""
        legs = object.__new__(cls)
        for member, value in zip(fields(cls), values, strict=True):
            if isinstance(value, np.ndarray):
                value.setflags(write=False)
            object.__setattr__(legs, member.name, value)
        return legs

    def on_rings(
        self,
        base_radius_mm: float,
        platform_radius_mm: float,
        base_half_angle_deg: float,
        platform_half_angle_deg: float,
        home: tuple[np.ndarray, np.ndarray],
    ) -> RotaryLegs:
        """This servo build with its shafts and platform joints moved onto two rings, laid out as
        ``configs/platforms/servo-hexapod.toml`` is: leg ``2k + m`` (k = 0, 1, 2; m = 0, 1) has its crank
        centre at angle ``120k ∓ a`` on a circle of ``base_radius_mm`` and its platform joint at ``120k ∓ b``
        on ``platform_radius_mm`` (``a``, ``b``: the half angles [deg]), at this set's heights.

        Each shaft lies along its ring's radius, pointing in for m = 0 and out for m = 1, so ``w = n × u`` is
        +z in every leg (a positive angle lifts each horn); at angle 0 the horn is level along the tangent,
        away from its pair's partner. Horns, angle range and zero trim 0 as this set has them; each rod
        spans the horn's tip at angle 0 to its platform joint at the pose ``home = (R, t)``, so every angle
        is 0 there.
        """
        side = np.tile([-1.0, 1.0], 3)  # m = 0: shaft in, horn clockwise; m = 1: shaft out, horn counter-clockwise

        def ring(radius_mm: float, half_angle_deg: float, heights_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            angles = np.radians(np.repeat([0.0, 120.0, 240.0], 2) + side * half_angle_deg)
            return np.column_stack([radius_mm * np.cos(angles), radius_mm * np.sin(angles), heights_mm]), angles

        centres, angles = ring(base_radius_mm, base_half_angle_deg, self.crank_centres[:, 2])
        joints, _ = ring(platform_radius_mm, platform_half_angle_deg, self.platform_joints[:, 2])
        radial = np.column_stack([np.cos(angles), np.sin(angles), np.zeros(self.n_legs)])
        tangent = np.column_stack([-np.sin(angles), np.cos(angles), np.zeros(self.n_legs)])
        axes, zero = side[:, None] * radial, side[:, None] * tangent
        R, t = home
        tips = centres + self.horn_lengths[:, None] * zero
        rods = np.linalg.norm(np.asarray(t) + joints @ np.asarray(R).T - tips, axis=1)
        return RotaryLegs(centres, axes, zero, self.horn_lengths, rods, joints, np.zeros(self.n_legs), self.angle_range)

    # ------------------------------------------------------------------ kinematics

    def horn_joints(self, e: np.ndarray) -> np.ndarray:
        """``(..., 6, 3)`` the horns' ball joints ``b_i = a_i + h_i (cos φ_i u_i + sin φ_i w_i)``, ``φ_i = e_i + o_i``,
        in {J} [mm], for coordinates ``e`` ``(..., 6)`` [rad]."""
        phi = np.asarray(e, dtype=float) + self.angle_offsets
        horn = np.cos(phi)[..., None] * self.zero_directions + np.sin(phi)[..., None] * self.w_directions
        return self.crank_centres + self.horn_lengths[:, None] * horn

    def _platform_points(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """``(..., 6, 3)`` the platform joints in {J}, ``t + R d_i`` [mm] (one batched matrix product)."""
        return self.platform_joints @ np.swapaxes(R, -1, -2) + np.asarray(t, dtype=float)[..., None, :]

    def _rods(self, R: np.ndarray, t: np.ndarray, e: np.ndarray) -> np.ndarray:
        """``(..., 6, 3)`` the rods ``t + R d_i − b_i`` (horn joint → platform joint) in {J} [mm]."""
        return self._platform_points(R, t) - self.horn_joints(e)

    def rods_lengthened(self, lengthening: np.ndarray | None) -> np.ndarray:
        """``(..., 6)`` the rods' lengths ``r_i + Δℓ_i`` [mm] with the ``lengthening`` ``Δℓ (..., 6)``
        (None: the rods ``r_i``)."""
        return self.rod_lengths if lengthening is None else self.rod_lengths + np.asarray(lengthening, dtype=float)

    def residuals(
        self, R: np.ndarray, t: np.ndarray, e: np.ndarray, *, lengthening: np.ndarray | None = None
    ) -> np.ndarray:
        """``(..., 6)`` closure residuals ``‖t + R d_i − b_i(e_i)‖ − (r_i + Δℓ_i)`` [mm] at poses ``(R (..., 3, 3),
        t (..., 3) [mm])``, coordinates ``e (..., 6)`` [rad] and the rods' ``lengthening`` Δℓ ``(..., 6)`` [mm]
        (None: 0)."""
        return np.linalg.norm(self._rods(R, t, e), axis=-1) - self.rods_lengthened(lengthening)

    def joint_lengths(self, e: np.ndarray) -> np.ndarray:
        """``(..., 6)`` each leg's length from joint to joint whatever its angle ``e`` [rad]: the rod ``r_i``
        [mm], what its temperature scales (spec §17)."""
        return np.broadcast_to(self.rod_lengths, np.shape(e)).copy()

    def unit_vectors(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """``(..., 6, 3)`` unit rods (horn joint → platform joint) in {J} at the pose ``(R, t)`` with each
        leg's coordinate from :meth:`coordinates`: the line a rod's force acts along (a two-force
        member). NaN where a leg cannot reach the pose."""
        rods = self._rods(R, t, self.coordinates(R, t))
        return rods / np.linalg.norm(rods, axis=-1, keepdims=True)

    def residual_jacobians(
        self, R: np.ndarray, t: np.ndarray, e: np.ndarray, *, lengthening: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Jacobians of :meth:`residuals`: ``(J_pose (..., 6, 6), J_M (..., 6, 66), J_e (..., 6))``, none of
        which depends on the rods' ``lengthening`` (``∂r_i/∂Δℓ_i = −1``, as ``∂r_i/∂r_i``).

        With ``m_i`` the unit rod, ``c, s = cos φ_i, sin φ_i``:

        * ``J_pose`` on the body tangent ``ξ = [ω, v]``: row i ``[(d_i × Rᵀm_i)ᵀ, (Rᵀm_i)ᵀ]``;
        * ``J_M`` block-diagonal, leg i's row in its own 11 columns: ``∂/∂a = −m``, ``∂/∂d = Rᵀm``,
          ``∂/∂h = −m·(c u + s w)``, ``∂/∂r = −1``, ``∂/∂o = J_e``, and the tilts, which turn the
          horn ``c u + s w`` about ``u⁰`` (:attr:`tilt_reference`) and about ``w``:
          ``∂/∂tu = −h m·(u⁰ × (c u + s w))`` (``−h s (m·n)`` at tilt 0, where ``u⁰ = u``),
          ``∂/∂tw = −h m·(w × (c u + s w)) = h c (m·n)``;
        * ``J_e = ∂r_i/∂e_i = −h (m·(−s u + c w))``.
        """
        phi = np.asarray(e, dtype=float) + self.angle_offsets
        c, s = np.cos(phi), np.sin(phi)
        u, w, n = self.zero_directions, self.w_directions, self.crank_axes
        rods = self._rods(R, t, e)
        m = rods / np.linalg.norm(rods, axis=-1, keepdims=True)
        batch = m.shape[:-2]
        J_pose = self._pose_rows(np.broadcast_to(R, batch + (3, 3)), m)
        m_body = J_pose[..., 3:]
        mu, mw, mn = np.sum(m * u, axis=-1), np.sum(m * w, axis=-1), np.sum(m * n, axis=-1)
        h = self.horn_lengths
        J_e = -h * (c * mw - s * mu)
        rows = np.empty(batch + (self.n_legs, _PER_LEG))
        rows[..., _A] = -m
        rows[..., _D] = m_body
        rows[..., _H] = -(c * mu + s * mw)
        rows[..., _ROD] = -1.0
        rows[..., _O] = J_e
        horn = c[..., None] * u + s[..., None] * w
        rows[..., _TU] = -h * np.sum(m * _cross(cast(np.ndarray, self.tilt_reference), horn), axis=-1)
        rows[..., _TW] = h * c * mn
        J_M = (rows[..., :, None, :] * np.eye(self.n_legs)[:, :, None]).reshape(batch + (self.n_legs, self.n_params))
        return J_pose, J_M, J_e

    def _pose_rows(self, R: np.ndarray, m: np.ndarray) -> np.ndarray:
        """``(..., 6, 6)`` ``∂r_i/∂ξ`` rows ``[(d_i × Rᵀm_i)ᵀ, (Rᵀm_i)ᵀ]`` for unit rods ``m (..., 6, 3)``."""
        m_body = m @ R  # Rᵀ m_i per leg
        return np.concatenate([_cross(self.platform_joints, m_body), m_body], axis=-1)

    def _window_centre(self) -> float:
        """The centre of the 360° window a horn solution is taken in (spec §15): 0, i.e. (−π, π], or
        the range's own middle where the range crosses ±π."""
        low, high = self.angle_range
        return 0.5 * (low + high) if low < -np.pi or high > np.pi else 0.0

    def coordinates(self, R: np.ndarray, t: np.ndarray, *, lengthening: np.ndarray | None = None) -> np.ndarray:
        """Inverse kinematics: ``(..., 6)`` coordinates ``e_i`` [rad] closing each leg at ``(R, t)``, its rod
        ``r_i`` longer by the ``lengthening`` Δℓ ``(..., 6)`` [mm] (None: 0).

        With ``v = t + R d_i − a_i``, ``A = v·u_i``, ``B = v·w_i``, ``C = (|v|² + h_i² − r_i²) / (2 h_i)``,
        closure is ``A cos φ + B sin φ = C``: ``φ = atan2(B, A) ± acos(C / √(A² + B²))``, and
        ``e = φ − o_i``. Each of the two is taken in (−π, π] (or in the range's own 360° window where
        the range crosses ±π); the one inside ``angle_range`` is returned, the one nearer the range's
        middle where both are (spec §15's branch rule, applied to ``e``, which differs from the
        commanded angle by the drive's angle scale only). NaN where the rod cannot reach the horn's
        circle (``|C| > √(A² + B²)``), comes within :attr:`reach_margin` of it (``acos`` within the
        margin of 0 or π), or neither solution is inside the range.
        """
        v = self._platform_points(R, t) - self.crank_centres
        A = np.sum(v * self.zero_directions, axis=-1)
        B = np.sum(v * self.w_directions, axis=-1)
        h, r = self.horn_lengths, self.rods_lengthened(lengthening)
        C = (np.sum(v * v, axis=-1) + h * h - r * r) / (2.0 * h)
        with np.errstate(invalid="ignore", divide="ignore"):
            opening = np.arccos(C / np.hypot(A, B))  # NaN where |C| > √(A² + B²): unreachable
        if self.reach_margin > 0.0:
            opening = np.where((opening >= self.reach_margin) & (opening <= np.pi - self.reach_margin), opening, np.nan)
        centre, (low, high) = self._window_centre(), self.angle_range
        middle = 0.5 * (low + high)
        best = np.full(opening.shape, np.nan)
        distance = np.full(opening.shape, np.inf)
        for sign in (1.0, -1.0):
            e = np.arctan2(B, A) + sign * opening - self.angle_offsets
            e = centre + np.pi - np.mod(centre + np.pi - e, 2.0 * np.pi)  # in (centre − π, centre + π]
            nearer = (e >= low) & (e <= high) & (np.abs(e - middle) < distance)
            best = np.where(nearer, e, best)
            distance = np.where(nearer, np.abs(e - middle), distance)
        return best

    # ------------------------------------------------------------------ forward kinematics

    @property
    def max_step_mm(self) -> float:
        """FK's cap on a Newton step's translation [mm]: :data:`MAX_STEP_RAD` of the mean rod."""
        return MAX_STEP_RAD * float(np.mean(self.rod_lengths))

    def default_guess(self, e: np.ndarray, lengthening: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """A level pose for coordinates ``e (..., 6)``: {D}'s joints centred over the horn joints
        ``b_i(e)`` and raised so that the mean rod length (with its ``lengthening``) is matched (the
        rods' horizontal spans from that centring)."""
        b = self.horn_joints(e)
        xy = np.mean(b[..., :2] - self.platform_joints[:, :2], axis=-2)
        span = b[..., :2] - (xy[..., None, :] + self.platform_joints[:, :2])
        rise = np.sqrt(np.maximum(self.rods_lengthened(lengthening) ** 2 - np.sum(span**2, axis=-1), 1.0))
        t = np.concatenate([xy, np.mean(rise + b[..., 2] - self.platform_joints[:, 2], axis=-1)[..., None]], axis=-1)
        return np.broadcast_to(np.eye(3), t.shape[:-1] + (3, 3)).copy(), t

    def _newton(
        self, e: np.ndarray, rod_mm: np.ndarray, R: np.ndarray, t: np.ndarray, tol_mm: float, max_iterations: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Damped, capped Newton in the body tangent for flat ``e (N, 6)`` and rod lengths ``rod_mm (N, 6)``
        [mm] from ``(R (N, 3, 3), t (N, 3))``.

        Each sample iterates until its own max |residual| is at most ``tol_mm`` (a NaN residual stops
        too) or ``max_iterations`` steps; only the unfinished ones are computed each step. Returns
        ``(R, t, iterations (N,), residual_mm (N,))``; non-finite ``e``: start kept, 0 steps, ``inf``.
        """
        R, t = R.copy(), t.copy()
        iterations = np.zeros(len(e), dtype=np.int64)
        residual = np.full(len(e), np.inf)
        active = np.flatnonzero(np.all(np.isfinite(e), axis=-1))
        horns = self.horn_joints(e)
        cap_mm = self.max_step_mm
        for step in range(max_iterations + 1):
            R_a = R[active]
            rods = self._platform_points(R_a, t[active]) - horns[active]
            length = np.linalg.norm(rods, axis=-1)
            r = length - rod_mm[active]
            worst = np.max(np.abs(r), axis=-1)
            residual[active] = worst
            iterations[active] = step
            going = (worst > tol_mm) & (step < max_iterations)
            active, r = active[going], r[going]
            if not len(active):
                break
            J = self._pose_rows(R_a[going], rods[going] / length[going][..., None])
            Jt = np.swapaxes(J, -1, -2)
            JtJ = Jt @ J
            JtJ += (FK_DAMPING / 6.0) * np.trace(JtJ, axis1=-2, axis2=-1)[:, None, None] * np.eye(6)
            xi = -np.linalg.solve(JtJ, Jt @ r[..., None])[..., 0]
            norm_w, norm_v = np.linalg.norm(xi[:, :3], axis=-1), np.linalg.norm(xi[:, 3:], axis=-1)
            with np.errstate(divide="ignore"):
                scale = np.minimum(1.0, np.minimum(MAX_STEP_RAD / norm_w, cap_mm / norm_v))
            R[active], t[active] = retract(R[active], t[active], scale[:, None] * xi)
        return R, t, iterations, residual

    def _within_a_step(self, R_a, t_a, R_b, t_b) -> np.ndarray:
        """Whether poses are less than one uncapped Newton step apart (:data:`MAX_STEP_RAD`, :attr:`max_step_mm`)."""
        turn = rotation_angle(np.swapaxes(R_a, -1, -2) @ R_b)
        return (np.linalg.norm(t_b - t_a, axis=-1) <= self.max_step_mm) & (turn <= MAX_STEP_RAD)

    def forward_kinematics(
        self,
        e: np.ndarray,
        guess: tuple[np.ndarray, np.ndarray] | None = None,
        tol_mm: float | None = FK_TOLERANCE_MM,
        strict: bool = True,
        along: bool = False,
        max_iterations: int = FK_MAX_ITERATIONS,
        *,
        lengthening: np.ndarray | None = None,
    ) -> FKSolution:
        """The pose closing every rod for coordinates ``e (..., 6)`` [rad], by damped, capped Newton.

        Solves ``‖t + R d_i − b_i(e_i)‖ = r_i + Δℓ_i`` (``lengthening`` Δℓ ``(..., 6)`` [mm], None: 0)
        in the body tangent ``ξ = [ω, v]`` with ``J_pose`` of :meth:`residual_jacobians`, all samples at
        once, each until its own max |residual| ≤ ``tol_mm``.
        A step is capped at :data:`MAX_STEP_RAD` and :attr:`max_step_mm`; the normal equations are
        damped by :data:`FK_DAMPING` (a singular pose gets a bounded step).

        Args:
            guess: starting ``(R, t)`` broadcastable to the batch; default :meth:`default_guess`.
            tol_mm: None: :data:`~stewart_calib.model.kinematics.FK_TOLERANCE_MM`.
            strict: raise :class:`~stewart_calib.model.kinematics.FKError` if any sample fails; otherwise
                report it in ``converged``.
            along: ``e (N, 6)`` are a log's samples in order and each follows the one before: where
                sample k − 1 converged and sample k's solution from its start is not within one
                uncapped step of it (not converged, or another assembly of the legs), sample k is
                solved again from sample k − 1's solution and takes that one if it converges within a
                step of it. A sample so changed makes its successor a candidate in turn; each round
                is one batch solve of the candidates.
        Raises:
            FKError: ``strict`` and a sample's rods unreachable or no convergence within the cap.
        """
        tol_mm = FK_TOLERANCE_MM if tol_mm is None else float(tol_mm)
        e = np.asarray(e, dtype=float)
        batch = e.shape[:-1]
        flat = e.reshape(-1, self.n_legs)
        rods = np.broadcast_to(self.rods_lengthened(lengthening), e.shape).reshape(-1, self.n_legs)
        R0, t0 = np.empty(batch + (3, 3)), np.empty(batch + (3,))
        R0[...], t0[...] = self.default_guess(e, lengthening) if guess is None else guess
        R, t, iterations, residual = self._newton(
            flat, rods, R0.reshape(-1, 3, 3), t0.reshape(-1, 3), tol_mm, max_iterations
        )
        if along:
            candidates = np.arange(1, len(flat))
            while len(candidates):
                before = candidates - 1
                keep = residual[before] <= tol_mm
                keep[keep] = ~(
                    (residual[candidates[keep]] <= tol_mm)
                    & self._within_a_step(R[before[keep]], t[before[keep]], R[candidates[keep]], t[candidates[keep]])
                )
                candidates, before = candidates[keep], before[keep]
                R_k, t_k, it_k, res_k = self._newton(
                    flat[candidates], rods[candidates], R[before], t[before], tol_mm, max_iterations
                )
                taken = (res_k <= tol_mm) & self._within_a_step(R[before], t[before], R_k, t_k)
                changed = candidates[taken]
                R[changed], t[changed], residual[changed] = R_k[taken], t_k[taken], res_k[taken]
                iterations[changed] += it_k[taken]
                candidates = changed[changed + 1 < len(flat)] + 1
        return fk_solution(
            R,
            t,
            iterations,
            residual,
            residual <= tol_mm,
            flat,
            batch,
            strict,
            "rotary forward kinematics",
            "angles",
            "crank angles",
        )

    def solve_fk(
        self,
        e: np.ndarray,
        guess: tuple[np.ndarray, np.ndarray] | None,
        what: str,
        tol_mm: float = FK_TOLERANCE_MM,
        *,
        lengthening: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """One sample's FK for ``e (6,)`` [rad] and the rods' ``lengthening`` ``(6,)`` [mm] (None: 0) from
        ``guess`` (the previous pose), then from :meth:`default_guess`: a jump between samples can leave the
        old pose outside Newton's basin.

        Raises:
            SampleRejected: neither start converges; ``what`` names the leg set.
        """
        if guess is not None:
            warm = self.forward_kinematics(e, guess, tol_mm, strict=False, lengthening=lengthening)
            if warm.converged:
                return warm.R, warm.t
        cold = self.forward_kinematics(e, None, tol_mm, strict=False, lengthening=lengthening)
        if cold.converged:
            return cold.R, cold.t
        raise fk_failed(what, float(cold.residual_mm))
