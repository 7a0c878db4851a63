"""Nominal geometry of a 6-6 Stewart platform and its in-situ tracker; the 42-vector layout.

Fixed geometry lives here and nowhere else; per-sample data (strokes, readings, poses)
is passed to the pure functions of :mod:`stewart_calib.kinematics`.

The 42 kinematic parameters follow the paper's order (δM, eq. 9)::

    [j1x j1y j1z d1x d1y d1z l1  j2x ... l2  ...  j6x j6y j6z d6x d6y d6z l6]

and are held as a ``(6, 7)`` array ``[j_i (3) | d_i (3) | l_i]`` per leg; :func:`params_to_vector`
and :func:`vector_to_params` convert between the two, and nothing else reorders them.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from . import resources
from .errors import CalibError, did_you_mean
from .inputs import implausible_sigma_mm
from .rotations import pose_to_rt, transform_points

if TYPE_CHECKING:
    from .model.rotary import RotaryLegs

N_LEGS = 6
N_PARAMS_PER_LEG = 7
N_PARAMS = N_LEGS * N_PARAMS_PER_LEG
#: the seven parameters of one leg, in the paper's order (rerun entity paths use them as is).
PARAMETER_FIELDS: tuple[str, ...] = ("j_x", "j_y", "j_z", "d_x", "d_y", "d_z", "l")
#: the 42 parameter names ``j1x j1y j1z d1x d1y d1z l1 … l6`` (spec §4–§5 columns and keys).
PARAMETER_NAMES: tuple[str, ...] = tuple(
    f"{field[0]}{leg}{field[2:]}" for leg in range(1, N_LEGS + 1) for field in PARAMETER_FIELDS
)


@dataclass(frozen=True)
class LegGeometry:
    """Six legs between base and platform: ``length_i = ‖t + R p_i − b_i‖``.

    For the drive this is (j_i, d_i, l_i) of paper eq. 1; for the tracker (z_i, h_i, l_si)
    of Table 2. ``length_i = initial_lengths[i] + stroke_i``.

    Attributes:
        base_joints: ``(6, 3)`` joint centres in the base frame {J} [mm].
        platform_joints: ``(6, 3)`` joint centres in the platform frame {D} [mm].
        initial_lengths: ``(6,)`` leg lengths at zero stroke / zero reading [mm].
    """

    base_joints: np.ndarray
    platform_joints: np.ndarray
    initial_lengths: np.ndarray

    def __post_init__(self) -> None:
        for name, shape in (("base_joints", (6, 3)), ("platform_joints", (6, 3)), ("initial_lengths", (6,))):
            value = np.array(getattr(self, name), dtype=float)
            if value.shape != shape:
                raise ValueError(f"{name} must have shape {shape}, got {value.shape}")
            value.setflags(write=False)
            object.__setattr__(self, name, value)

    #: the leg model's kind (:class:`~stewart_calib.model.legs.LegModel`): the platform file's ``[drive] kind``
    kind = "prismatic"
    #: the unit of a leg's coordinate ``e_i`` (its extension) in files: the log's ``q{i}_mm``
    coordinate_unit = "mm"
    #: the leg model's compiled kernels (:mod:`stewart_calib._kernels`) apply to it
    compiled = True

    @property
    def n_legs(self) -> int:
        """Legs of the set (six for a 6-6 Gough platform and for the Table 2 tracker)."""
        return len(self.initial_lengths)

    @property
    def parameter_degrees(self) -> np.ndarray:
        """``(n_params,)`` bool: which entries files give in degrees (none: all mm)."""
        return np.zeros(self.n_params, dtype=bool)

    @property
    def gauge_columns(self) -> tuple[np.ndarray, np.ndarray]:
        """``((n, 3), (n, 3))`` int: the entries of M holding the base joints ``j_i`` and the platform
        joints ``d_i``, leg by leg, x y z (spec §7's gauge of an outside instrument)."""
        base = N_PARAMS_PER_LEG * np.arange(self.n_legs)[:, None] + np.arange(3)
        return base, base + 3

    def prior_sigmas(self, noise) -> np.ndarray:
        """``(n_params,)`` prior σ of δM [mm]: ``noise.prior_sigma_mm`` on every entry."""
        return np.full(self.n_params, noise.prior_sigma_mm)

    def walk_sigmas(self, noise) -> np.ndarray:
        """``(n_params,)`` random walk of δM [mm/√s]: ``noise.random_walk_mm_per_sqrt_s`` on every entry."""
        return np.full(self.n_params, noise.random_walk_mm_per_sqrt_s)

    def coordinate_sigma(self, noise) -> float:
        """σ of one leg's logged coordinate [mm]: ``noise.stroke_sigma_mm`` (the encoder)."""
        return float(noise.stroke_sigma_mm)

    def kernel_geometry(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(base joints (n, 3), platform joints (n, 3), initial lengths (n,))`` [mm], read-only C
        arrays: the leg set as the compiled kernels (:mod:`stewart_calib._kernels`) take it."""
        return self.base_joints, self.platform_joints, self.initial_lengths

    # The leg model's arithmetic is the compiled kinematics' (imported here, not with the module: a
    # platform file is read by commands that never compute, see :meth:`perturbed`).

    def residuals(self, R: np.ndarray, t: np.ndarray, e: np.ndarray) -> np.ndarray:
        """``r_i = ‖t + R d_i − j_i‖ − (l_i + e_i)``, ``(..., n)`` [mm] (paper eq. 1)."""
        from . import kinematics

        return kinematics.leg_residuals(self, R, t, e)

    def residual_jacobians(
        self, R: np.ndarray, t: np.ndarray, e: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(∂r/∂ξ (..., n, 6), ∂r/∂M (..., n, n_params), ∂r_i/∂e_i (..., n) = −1)`` of :meth:`residuals`."""
        from . import kinematics

        J_pose, J_M = kinematics.leg_residual_jacobians(self, R, t)
        return J_pose, J_M, np.full(J_M.shape[:-1], -1.0)

    def moved(self, delta: np.ndarray, base: tuple, platform: tuple) -> np.ndarray:
        """``δM'`` of ``self.perturbed(δM)`` with its base joints moved by the rigid motion ``base = (R, t)``
        (``j → R j + t``) and its platform joints by ``platform`` (``d → R d + t``); lengths kept."""
        moved = self.as_vector() + np.asarray(delta, dtype=float)
        for columns, (R, t) in zip(self.gauge_columns, (base, platform), strict=True):
            moved[columns] = moved[columns] @ np.asarray(R).T + t
        return moved - self.as_vector()

    def coordinates(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """The extensions ``(..., n)`` [mm] that close each leg at ``(R, t)`` (inverse kinematics)."""
        from . import kinematics

        return kinematics.inverse_kinematics(self, R, t)

    def forward_kinematics(
        self, e: np.ndarray, guess=None, tol_mm: float | None = None, strict: bool = True, along: bool = False
    ):
        """:func:`~stewart_calib.kinematics.forward_kinematics` of extensions ``e (..., n)`` [mm]
        (``tol_mm`` None: :data:`~stewart_calib.kinematics.FK_TOLERANCE_MM`)."""
        from . import kinematics

        tol = kinematics.FK_TOLERANCE_MM if tol_mm is None else tol_mm
        return kinematics.forward_kinematics(self, e, guess=guess, tol_mm=tol, strict=strict, along=along)

    def solve_fk(self, e: np.ndarray, guess, what: str) -> tuple[np.ndarray, np.ndarray]:
        """One pose of extensions ``e (n,)`` from ``guess``, then cold (:func:`~stewart_calib.kinematics.solve_fk`)."""
        from . import kinematics

        return kinematics.solve_fk(self, e, guess, what)

    def unit_vectors(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """``(..., n, 3)`` unit leg vectors in {J}: the direction each leg's force acts along."""
        from . import kinematics

        return kinematics.leg_unit_vectors(self, R, t)

    @property
    def n_params(self) -> int:
        """Entries of the set's parameter vector: seven a leg (42 for six legs)."""
        return self.n_legs * N_PARAMS_PER_LEG

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """The names of the parameter vector's entries, paper order (``j1x … l6``)."""
        return PARAMETER_NAMES

    @property
    def params(self) -> np.ndarray:
        """``(6, 7)`` array ``[j_i | d_i | l_i]`` per leg [mm]."""
        return np.hstack([self.base_joints, self.platform_joints, self.initial_lengths[:, None]])

    @classmethod
    def from_params(cls, params: np.ndarray) -> LegGeometry:
        """Build from a ``(6, 7)`` array or a 42-vector in the paper's order [mm]."""
        p = np.asarray(params, dtype=float).reshape(N_LEGS, N_PARAMS_PER_LEG)
        return cls(p[:, 0:3], p[:, 3:6], p[:, 6])

    def as_vector(self) -> np.ndarray:
        """The 42-vector M in the paper's order [mm]."""
        return params_to_vector(self.params)

    def perturbed(self, delta: np.ndarray) -> LegGeometry:
        """Geometry ``M + δM`` for a 42-vector (or ``(6, 7)``) error δM [mm].

        Called once per sample by the EKFs: the sums (one compiled call) are new C-contiguous float
        arrays of the right shapes by construction, so they skip ``__post_init__``'s
        copies and checks (more than half its cost; same values bit for bit). The kernels are imported
        here, not with the module: a platform file is read by commands that never compute
        (``import``'s check of the instrument kind), and numba alone is ~130 MB of RSS.
        """
        from . import _kernels

        d = np.ascontiguousarray(delta, dtype=float).reshape(N_PARAMS)
        return LegGeometry._trusted(
            *_kernels.perturbed_legs(self.base_joints, self.platform_joints, self.initial_lengths, d)
        )

    @classmethod
    def _trusted(cls, base_joints: np.ndarray, platform_joints: np.ndarray, initial_lengths: np.ndarray) -> LegGeometry:
        """Build from fresh, C-contiguous float arrays of the right shapes, without validation."""
        legs = object.__new__(cls)
        for name, value in (
            ("base_joints", base_joints),
            ("platform_joints", platform_joints),
            ("initial_lengths", initial_lengths),
        ):
            value.setflags(write=False)
            object.__setattr__(legs, name, value)
        return legs


def params_to_vector(params: np.ndarray) -> np.ndarray:
    """``(..., 6, 7)`` per-leg parameters → ``(..., 42)`` paper-order vector."""
    p = np.asarray(params, dtype=float)
    return p.reshape(*p.shape[:-2], N_PARAMS)


def vector_to_params(vector: np.ndarray) -> np.ndarray:
    """``(..., 42)`` paper-order vector → ``(..., 6, 7)`` per-leg parameters."""
    v = np.asarray(vector, dtype=float)
    return v.reshape(*v.shape[:-1], N_LEGS, N_PARAMS_PER_LEG)


@dataclass(frozen=True)
class Workspace:
    """Reachable box about home (paper §4.1: ±200 mm, ±20°).

    Attributes:
        home: ``(6,)`` home pose ``[x, y, z [mm], roll, pitch, yaw [rad]]``.
        translation_limit: ± per axis about home [mm].
        rotation_limit: ± per axis about home [rad].
    """

    home: np.ndarray
    translation_limit: float = 200.0
    rotation_limit: float = math.radians(20.0)


@dataclass(frozen=True)
class InstrumentSection:
    """What one kind of instrument reads of the platform file (spec §7): the file's reader and
    writer learn a kind here alone; its model is :data:`stewart_calib.instruments.registry.MODELS`'
    entry of the same name.

    Attributes:
        keys: the keys of ``[instrument]`` it reads besides ``kind``, in the order they are
            written; a kind with none is the default, written as no ``[instrument]`` table.
        required: those of ``keys`` without a default.
        reads_tracker: whether it reads the ``[tracker]`` table (its legs are the instrument).
        log_columns: ``K → names``: the log's columns of one reading with ``K`` targets, in the
            order of the measurement (spec §3, §7); read by the log reader, the model and the imports.
    """

    keys: tuple[str, ...]
    log_columns: Callable[[int], tuple[str, ...]]
    required: tuple[str, ...] = ()
    reads_tracker: bool = False


def _point_columns(n_targets: int) -> tuple[str, ...]:
    """``p1x_mm p1y_mm p1z_mm … pKx_mm pKy_mm pKz_mm``: the targets' measured positions."""
    return tuple(f"p{k}{axis}_mm" for k in range(1, n_targets + 1) for axis in "xyz")


#: ``[instrument] kind`` → what it reads of the file; the first is the default (no ``[instrument]``).
INSTRUMENT_SECTIONS = {
    "tracker": InstrumentSection((), lambda _: tuple(f"s{i}_mm" for i in range(1, N_LEGS + 1)), reads_tracker=True),
    "pose": InstrumentSection(
        ("frame", "target", "position_sigma_mm", "orientation_sigma_deg"),
        lambda _: ("mx_mm", "my_mm", "mz_mm", "mroll_deg", "mpitch_deg", "myaw_deg"),
    ),
    "points": InstrumentSection(
        ("frame", "targets_mm", "position_sigma_mm", "visibility_cone_deg", "target_axes"),
        _point_columns,
        required=("targets_mm",),
    ),
}
INSTRUMENT_KINDS = tuple(INSTRUMENT_SECTIONS)

#: ``[instrument]`` defaults (spec §7): σ of one measured coordinate [mm] and of one measured
#: angle [deg], the spec's example values (a good motion-capture system or laser tracker).
DEFAULT_POSITION_SIGMA_MM = 0.1
DEFAULT_ORIENTATION_SIGMA_DEG = 0.02


@dataclass(frozen=True, eq=False)
class Instrument:
    """What measured the logs (spec §7): the in-situ tracker, a 6-DOF pose, or 3-D targets.

    Attributes:
        kind: ``"tracker"``, ``"pose"`` or ``"points"``.
        frame: ``(6,)`` nominal pose of the instrument frame {I} in {J} ``[mm, rad]`` (pose6).
        target: ``(6,)`` nominal pose of the measured body {T} in {D} ``[mm, rad]`` (pose only).
        targets: ``(K, 3)`` nominal target positions in {D} [mm] (points only), else ``(0, 3)``.
        position_sigma_mm: σ of one measured coordinate [mm].
        orientation_sigma_rad: σ of one measured angle [rad] (pose only).
        visibility_cone_deg: points only: half-angle [deg] about each target's axis within which
            the instrument at the nominal frame's origin sees it (an SMR's acceptance angle), or
            None (always seen). Used by ``plan`` and ``identifiability --poses``.
        target_axes: ``(K, 3)`` each target's axis in {D} (points; default {D}'s z), unnormalised.
    """

    kind: str = INSTRUMENT_KINDS[0]
    frame: np.ndarray = field(default_factory=lambda: np.zeros(6))
    target: np.ndarray = field(default_factory=lambda: np.zeros(6))
    targets: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    position_sigma_mm: float = DEFAULT_POSITION_SIGMA_MM
    orientation_sigma_rad: float = math.radians(DEFAULT_ORIENTATION_SIGMA_DEG)
    visibility_cone_deg: float | None = None
    target_axes: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def n_targets(self) -> int:
        return len(self.targets)


#: standard gravity [m/s² = N/kg] (spec §10)
G_N_PER_KG = 9.80665

#: the default prior σ of the compliance is the one at which the platform's own weight, shared by six
#: legs, would shorten a leg by this much [mm]: no hexapod that positions to a millimetre gives
#: more, and it spans the industrial machine's µm/kN and the hobby build's hundreds of mm/kN alike.
DEFAULT_WEIGHT_DEFLECTION_MM = 2.0


def default_compliance_sigma(platform_mass_kg: float) -> float:
    """The default prior σ of c_i [mm/kN] (:data:`DEFAULT_WEIGHT_DEFLECTION_MM`): 2 mm over a
    sixth of the platform's weight [kN]."""
    return DEFAULT_WEIGHT_DEFLECTION_MM / (platform_mass_kg * G_N_PER_KG / N_LEGS / 1000.0)


#: the lightest moving platform accepted [kg]: a plate that carries six joints weighs more than a
#: gram; below it the weight's leg forces (µN) give no leg anything to measure, and the default
#: compliance σ (2 mm over a sixth of that weight) runs to astronomic values
MIN_PLATFORM_MASS_KG = 1e-3


def give_reference_mm(drive: LegGeometry | RotaryLegs, stroke_range: tuple[float, float] | None) -> tuple[float, str]:
    """``(length [mm], what it is)`` no leg can give under a load: the stroke range (a leg that gave
    more would leave its drive no stroke to hold any pose), or without one the shortest leg's length
    at zero stroke (a leg cannot shorten by more than its length); for another leg kind (a rotary
    drive, spec §15, which takes no ``[elastic]``) its shortest rod."""
    if stroke_range is not None:
        return float(stroke_range[1] - stroke_range[0]), "the stroke range"
    if not isinstance(drive, LegGeometry):
        return float(np.min(drive.rod_lengths)), "the shortest rod's length"
    return float(np.min(drive.initial_lengths)), "the shortest leg's length"


def least_give_mm_per_kg(compliance_mm_per_kN: float) -> float:
    """The least shortening [mm] of the most loaded leg per kg on the platform at compliance
    ``c`` [mm/kN]: six legs hold the weight ``m g`` along z, so one of them carries at least a sixth
    of it axially, whatever the pose (``Σ f_i n_i,z = m g`` with ``n_i,z ≤ 1``)."""
    return abs(compliance_mm_per_kN) * G_N_PER_KG / N_LEGS / 1000.0


def payload_limit_kg(elastic: Elastic, reference_mm: float) -> float:
    """The largest payload [kg] a platform declaring ``elastic`` can carry: beyond it the legs, at
    their nominal compliance plus one prior σ, would give more than ``reference_mm``
    (:func:`give_reference_mm`) under the weight of platform and payload; inf for legs declared rigid."""
    per_kg = least_give_mm_per_kg(
        float(np.max(np.abs(elastic.compliance_mm_per_kN))) + elastic.compliance_sigma_mm_per_kN
    )
    return math.inf if per_kg == 0.0 else max(reference_mm / per_kg - elastic.platform_mass_kg, 0.0)


def payload_limit(platform: Platform) -> float:
    """The largest payload [kg] ``platform`` can carry (:func:`payload_limit_kg`); inf without ``[elastic]``."""
    if platform.elastic is None or not isinstance(platform.drive, LegGeometry):  # [elastic]: prismatic legs only
        return math.inf
    return payload_limit_kg(platform.elastic, give_reference_mm(platform.drive, platform.stroke_range)[0])


def payload_refusal(platform: Platform, load_kg: float) -> str | None:
    """What a log's ``load_kg`` beyond the payload ``platform`` can carry (:func:`payload_limit_kg`)
    should have been, for a refusal naming its row and column; None when it is within (or the
    platform has no ``[elastic]``). A value a thousand times a payload it could carry looks like grams."""
    elastic = platform.elastic
    if elastic is None or not isinstance(platform.drive, LegGeometry):  # [elastic]: prismatic legs only
        return None
    reference_mm, what = give_reference_mm(platform.drive, platform.stroke_range)
    limit = payload_limit(platform)
    if load_kg <= limit:
        return None
    grams = f"; it looks like grams ({load_kg / 1000.0:.6g} kg)" if load_kg / 1000.0 <= limit else ""
    return (
        f"a payload the platform can carry, at most {limit:.4g} kg: under {load_kg:.6g} kg its legs (compliance "
        f"{float(np.max(np.abs(elastic.compliance_mm_per_kN))):.4g} + prior σ {elastic.compliance_sigma_mm_per_kN:.4g} "
        f"mm/kN, [elastic]) would give more than {reference_mm:.4g} mm of {what}{grams}"
    )


#: a centre of mass farther than this many platform radii (the largest ``‖d_i‖``) from {D}'s origin
#: is refused: a value typed in the wrong unit, not a payload the legs could hold.
COM_RADII_LIMIT = 10.0


def centre_too_far(drive: LegGeometry, centre_mm: np.ndarray) -> str | None:
    """What a centre of mass in {D} [mm] farther than :data:`COM_RADII_LIMIT` platform radii of ``drive``
    (the largest ``‖d_i‖``) should have been, for a refusal naming its key; None when it is within."""
    radius = float(np.max(np.linalg.norm(drive.platform_joints, axis=-1)))
    distance = float(np.linalg.norm(centre_mm))
    if distance <= COM_RADII_LIMIT * radius:
        return None
    return (
        f"[x, y, z] in mm within {COM_RADII_LIMIT:g} platform radii ({COM_RADII_LIMIT * radius:.6g} mm) of "
        f"{{D}}'s origin, got one {distance:.6g} mm away (a length in the wrong unit?)"
    )


@dataclass(frozen=True, eq=False)
class Elastic:
    """The robot under its own weight and a payload (spec §10, ``[elastic]``).

    Attributes:
        platform_mass_kg: the moving platform and all that is fixed to it [kg], > 0.
        platform_com_mm: ``(3,)`` its centre of mass in {D} [mm].
        payload_com_mm: ``(3,)`` the payload's centre of mass in {D} [mm].
        compliance_mm_per_kN: ``(6,)`` nominal axial compliance c_i of each drive leg [mm/kN = µm/N]:
            ``l_i + (1 + k_i) q_i − c_i f_i / 1000 = ‖t + R d_i − j_i‖``, f_i [N] compression > 0.
        compliance_sigma_mm_per_kN: prior σ of c_i about the nominal; 0: held at nominal (default:
            :func:`default_compliance_sigma` of the platform's mass).
        true_compliance_mm_per_kN: ``(6,)`` the truth a simulated platform carries for reports and
            checks (``simulate``), never read by an estimator; None on a real robot.
        payload_sigma_kg: > 0: ``ekf`` and ``isam2`` estimate the payload that the log does not
            announce, a mass [kg] at ``payload_com_mm`` on top of each sample's ``load_kg`` (0 where the
            log has none), with this prior σ, and take a step of it where the samples after a candidate
            step (this σ added at one sample) confirm it (:mod:`stewart_calib.estimators.ekf`; ``isam2``'s
            front end decides, :mod:`stewart_calib.estimators.isam2`); 0 (default): the payload is the log's
            ``load_kg``.
    """

    platform_mass_kg: float
    platform_com_mm: np.ndarray
    payload_com_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    compliance_mm_per_kN: np.ndarray = field(default_factory=lambda: np.zeros(N_LEGS))
    compliance_sigma_mm_per_kN: float = None  # type: ignore[assignment]  # None: the default, set in __post_init__
    true_compliance_mm_per_kN: np.ndarray | None = None
    payload_sigma_kg: float = 0.0

    def __post_init__(self) -> None:
        if self.compliance_sigma_mm_per_kN is None:
            object.__setattr__(self, "compliance_sigma_mm_per_kN", default_compliance_sigma(self.platform_mass_kg))


@dataclass(frozen=True)
class Platform:
    """A platform file: nominal drive geometry, tracker geometry, instrument, ranges, workspace.

    Attributes:
        name: free-text identifier.
        drive: nominal drive legs — what the controller believes: prismatic (j_i, d_i, l_i, spec §2) or
            rotary (spec §15, :class:`~stewart_calib.model.rotary.RotaryLegs`).
        tracker: tracker legs (z_i, h_i, l_si) (paper Table 2), or None when the platform
            file has no ``[tracker]`` (allowed when another instrument measured the logs).
        stroke_range: ``(min, max)`` drive stroke q_i [mm], or None (always for a rotary drive, whose
            commanded angles' range is its legs' ``angle_range``).
        reading_range: ``(min, max)`` grating reading s_i [mm], or None.
        workspace: reachable box, or None.
        description: free text.
        instrument: what measured the logs (spec §7); the tracker by default.
        stroke_scale: ``(6,)`` nominal stroke scale k_i (dimensionless): a drive leg is
            ``l_i + (1 + k_i) q_i`` long (spec §7; ``[drive] stroke_scale``, default 0).
        tracker_geometry_sigma_mm: prior σ of the tracker's own 42 values [mm] (``[tracker]
            geometry_sigma_mm``); 0: known exactly.
        elastic: masses and leg compliances (spec §10, ``[elastic]``), or None: a rigid robot.
    """

    name: str
    drive: LegGeometry | RotaryLegs
    tracker: LegGeometry | None
    stroke_range: tuple[float, float] | None = None
    reading_range: tuple[float, float] | None = None
    workspace: Workspace | None = None
    description: str = ""
    source: str = field(default="<memory>", compare=False)
    instrument: Instrument = field(default_factory=Instrument, compare=False)
    stroke_scale: np.ndarray = field(default_factory=lambda: np.zeros(N_LEGS), compare=False)
    tracker_geometry_sigma_mm: float = 0.0
    elastic: Elastic | None = field(default=None, compare=False)

    @property
    def coordinate_range(self) -> tuple[float, float] | None:
        """``(min, max)`` of the log's drive coordinates in code units, or None: the stroke range [mm],
        or a rotary drive's commanded angles' ``angle_range`` [rad] (spec §15)."""
        return self.stroke_range if isinstance(self.drive, LegGeometry) else self.drive.angle_range

    def required_tracker(self, what: str) -> LegGeometry:
        """:attr:`tracker` for ``what``, which needs the in-situ tracker's legs.

        Raises:
            CalibError: the platform file has no ``[tracker]``.
        """
        if self.tracker is None:
            raise CalibError(
                f"{self.source}: key 'tracker': expected a [tracker] table; {what} needs the tracker's legs"
            )
        return self.tracker

    def required_workspace(self, what: str) -> Workspace:
        """:attr:`workspace` for ``what``, which draws or places poses in it.

        Raises:
            CalibError: the platform file has no ``[workspace]``.
        """
        if self.workspace is None:
            raise CalibError(f"{self.source}: key 'workspace': expected a [workspace] table; {what} places poses in it")
        return self.workspace


#: the keys a platform file may hold, per table ("" = top level). A misspelt optional key
#: would otherwise be ignored without a word (a stroke range silently not enforced).
#: ``[instrument]``'s keys depend on its kind; :func:`parse_instrument` checks them.
PLATFORM_KEYS: dict[str, set[str]] = {
    "": {"name", "description", "drive", "tracker", "workspace", "instrument", "elastic"},
    "tracker": {"base_joints_mm", "platform_joints_mm", "initial_lengths_mm", "reading_range_mm", "geometry_sigma_mm"},
    "workspace": {"home", "translation_limit_mm", "rotation_limit_deg"},
    "elastic": {
        "platform_mass_kg",
        "platform_com_mm",
        "payload_com_mm",
        "compliance_mm_per_kN",
        "compliance_sigma_mm_per_kN",
        "true_compliance_mm_per_kN",
        "payload_sigma_kg",
    },
}

#: the keys of ``[drive]`` per ``kind`` (spec §2, §15); a ``[drive]`` without ``kind`` is the first.
DRIVE_KEYS: dict[str, frozenset[str]] = {
    "prismatic": frozenset(
        {"kind", "base_joints_mm", "platform_joints_mm", "initial_lengths_mm", "stroke_range_mm", "stroke_scale"}
    ),
    "rotary": frozenset(
        {
            "kind",
            "crank_centres_mm",
            "crank_axes",
            "crank_zero_directions",
            "horn_lengths_mm",
            "rod_lengths_mm",
            "platform_joints_mm",
            "angle_offsets_deg",
            "angle_range_deg",
            "stroke_scale",
        }
    ),
}
DRIVE_KINDS = tuple(DRIVE_KEYS)

#: a crank's zero direction farther than this from orthogonal to its axis is refused [deg] (spec §15)
ZERO_DIRECTION_TOLERANCE_DEG = 1.0

#: a leg set whose every coordinate and length is below this [mm] was written in metres: no
#: hexapod a tracker of grating rulers measures is under a centimetre.
METRES_SUSPECT_MM = 10.0

#: joints whose second principal extent is below this fraction of the first lie on one line
#: (or one point): the platform can then turn about that line with no leg changing length.
COLLINEAR_RATIO = 1e-3


def _refuse(source: str, key: str, expected: str) -> CalibError:
    return CalibError(f"{source}: key '{key}': expected {expected}")


def drive_kind(doc: dict, source: str) -> str:
    """``[drive] kind`` of a platform document (spec §15): ``"prismatic"`` where absent.

    Raises:
        CalibError: a kind that is not one of :data:`DRIVE_KINDS`, naming ``source`` and the key.
    """
    table = doc.get("drive")
    kind = table.get("kind", DRIVE_KINDS[0]) if isinstance(table, dict) else DRIVE_KINDS[0]
    if kind not in DRIVE_KINDS:
        raise _refuse(source, "drive.kind", f"one of {', '.join(map(repr, DRIVE_KINDS))}, got {kind!r}")
    return kind


def _check_keys(doc: dict, source: str) -> None:
    """Refuse a key :data:`PLATFORM_KEYS` (``[drive]``: :data:`DRIVE_KEYS` of its kind) does not know,
    suggesting the nearest known one — of another drive kind too, saying which kind uses it."""
    kind = drive_kind(doc, source)
    for table, known in {**PLATFORM_KEYS, "drive": DRIVE_KEYS[kind]}.items():
        values = doc if not table else doc.get(table)
        if not isinstance(values, dict):
            continue
        for key in values:
            if key not in known:
                # a key with a newline or other control character would break the one-line message
                shown = key if key.isprintable() else key.encode("unicode_escape").decode("ascii")
                full = f"{table}.{shown}" if table else shown
                hint = did_you_mean(key, known)
                if table == "drive":
                    hint = _drive_key_hint(key, kind) or hint
                raise CalibError(f"{source}: unknown key '{full}'{hint}; expected one of {', '.join(sorted(known))}")


def _drive_key_hint(key: str, kind: str) -> str:
    """Where ``key``, or the ``[drive]`` key nearest it, belongs to another drive kind than ``kind``:
    a hint naming that kind (and the key meant); else ``""``."""
    other = next((name for name, keys in DRIVE_KEYS.items() if key in keys), None)
    if other is not None:
        return f' (a key of [drive] kind = "{other}", spec §15; this [drive] is kind = "{kind}")'
    nearest = did_you_mean(key, set().union(*DRIVE_KEYS.values()))
    if not nearest or nearest == did_you_mean(key, DRIVE_KEYS[kind]):
        return ""
    other = next(name for name, keys in DRIVE_KEYS.items() if nearest == did_you_mean(key, keys))
    return f'{nearest[:-1]} it is a key of [drive] kind = "{other}" (spec §15); this [drive] is kind = "{kind}")'


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _numbers_only(value) -> bool:
    """True when ``value`` is a number or nested lists of numbers (never text such as ``"1048.5"``)."""
    if isinstance(value, list):
        return all(_numbers_only(v) for v in value)
    return _is_number(value)


def _array(table: dict, key: str, shape: tuple[int, ...], source: str, prefix: str) -> np.ndarray:
    full = f"{prefix}.{key}"
    if key not in table:
        raise _refuse(source, full, f"{_shape_words(shape)} (missing)")
    if not _numbers_only(table[key]):  # numpy would read the text "1048.5" as a number
        raise _refuse(source, full, f"{_shape_words(shape)} of numbers (not quoted text)")
    try:
        value = np.array(table[key], dtype=float)
    except (TypeError, ValueError, OverflowError):  # OverflowError: an integer beyond float range
        raise _refuse(source, full, f"{_shape_words(shape)} of numbers") from None
    if value.shape != shape:
        raise _refuse(source, full, f"{_shape_words(shape)}, got shape {value.shape}")
    if not np.all(np.isfinite(value)):
        raise _refuse(source, full, f"{_shape_words(shape)} of finite numbers")
    return value


def _shape_words(shape: tuple[int, ...]) -> str:
    if shape == (6, 3):
        return "6 rows of [x, y, z] in mm"
    if len(shape) == 1:
        return f"a list of {shape[0]} numbers"
    return f"an array of shape {shape}"


def _range(table: dict, key: str, source: str, prefix: str) -> tuple[float, float] | None:
    if key not in table:
        return None
    lo, hi = _array(table, key, (2,), source, prefix)
    if not lo < hi:
        raise _refuse(source, f"{prefix}.{key}", f"[min, max] with min < max, got [{lo}, {hi}]")
    return float(lo), float(hi)


def _legs(doc: dict, section: str, source: str) -> tuple[LegGeometry, dict]:
    table = doc.get(section)
    if not isinstance(table, dict):
        raise _refuse(source, section, f"a [{section}] table")
    legs = LegGeometry(
        _array(table, "base_joints_mm", (6, 3), source, section),
        _array(table, "platform_joints_mm", (6, 3), source, section),
        _array(table, "initial_lengths_mm", (6,), source, section),
    )
    if np.any(legs.initial_lengths <= 0):
        raise _refuse(source, f"{section}.initial_lengths_mm", "6 positive lengths in mm")
    largest = max(np.abs(legs.base_joints).max(), np.abs(legs.platform_joints).max(), legs.initial_lengths.max())
    if largest < METRES_SUSPECT_MM:
        raise CalibError(
            f"{source}: [{section}]: the geometry looks like metres (largest coordinate or length {largest:.4g}); "
            "expected millimetres (spec §2)"
        )
    for key, joints in (("base_joints_mm", legs.base_joints), ("platform_joints_mm", legs.platform_joints)):
        _check_spread(joints, source, f"{section}.{key}")
    return legs, table


def _rotary(doc: dict, source: str) -> tuple[RotaryLegs, dict]:
    """The ``[drive]`` table of ``kind = "rotary"`` (spec §15) as :class:`~stewart_calib.model.rotary.RotaryLegs`
    [mm, rad]: axes normalised, zero directions made orthogonal to their axes and normalised."""
    from .model.rotary import RotaryLegs, orthonormal_zero_directions  # the leg models import this module

    table = doc.get("drive")
    if not isinstance(table, dict):
        raise _refuse(source, "drive", "a [drive] table")
    centres = _array(table, "crank_centres_mm", (N_LEGS, 3), source, "drive")
    given = {key: _array(table, key, (N_LEGS, 3), source, "drive") for key in ("crank_axes", "crank_zero_directions")}
    for key, rows in given.items():
        bad = np.flatnonzero(~(np.linalg.norm(rows, axis=1) > 0.0))
        if bad.size:
            raise _refuse(source, f"drive.{key}[{int(bad[0]) + 1}]", "a direction [x, y, z] of nonzero length")
    axes, zeros, off_deg = orthonormal_zero_directions(given["crank_axes"], given["crank_zero_directions"])
    bad = np.flatnonzero(~(off_deg <= ZERO_DIRECTION_TOLERANCE_DEG))  # NaN: along the axis
    if bad.size:
        i = int(bad[0])
        raise _refuse(
            source,
            f"drive.crank_zero_directions[{i + 1}]",
            f"a direction within {ZERO_DIRECTION_TOLERANCE_DEG:g}° of orthogonal to its axis (crank_axes row "
            f"{i + 1}), got one {90.0 if np.isnan(off_deg[i]) else off_deg[i]:.4g}° from orthogonal",
        )
    lengths = {}
    for key in ("horn_lengths_mm", "rod_lengths_mm"):
        lengths[key] = _array(table, key, (N_LEGS,), source, "drive")
        if np.any(lengths[key] <= 0):
            raise _refuse(source, f"drive.{key}", "6 positive lengths in mm")
    joints = _array(table, "platform_joints_mm", (N_LEGS, 3), source, "drive")
    offsets_deg = (
        _array(table, "angle_offsets_deg", (N_LEGS,), source, "drive")
        if "angle_offsets_deg" in table
        else np.zeros(N_LEGS)
    )
    if np.any(np.abs(offsets_deg) > 180.0):
        raise _refuse(source, "drive.angle_offsets_deg", f"6 zero trims within ±180 deg, got {offsets_deg.tolist()}")
    if "angle_range_deg" not in table:
        raise _refuse(
            source,
            "drive.angle_range_deg",
            '[min, max] in degrees: the commanded angles the servos accept (missing; required with kind = "rotary")',
        )
    low, high = _range(table, "angle_range_deg", source, "drive")  # type: ignore[misc]  # present: not None
    if high - low > 360.0:
        raise _refuse(source, "drive.angle_range_deg", f"[min, max] at most 360 deg apart, got [{low}, {high}]")
    largest = max(np.abs(centres).max(), np.abs(joints).max(), *(values.max() for values in lengths.values()))
    if largest < METRES_SUSPECT_MM:
        raise CalibError(
            f"{source}: [drive]: the geometry looks like metres (largest coordinate or length {largest:.4g}); "
            "expected millimetres (spec §15)"
        )
    for key, points in (("crank_centres_mm", centres), ("platform_joints_mm", joints)):
        _check_spread(points, source, f"drive.{key}")
    legs = RotaryLegs(
        crank_centres=centres,
        crank_axes=axes,
        zero_directions=zeros,
        horn_lengths=lengths["horn_lengths_mm"],
        rod_lengths=lengths["rod_lengths_mm"],
        platform_joints=joints,
        angle_offsets=np.radians(offsets_deg),
        angle_range=(math.radians(low), math.radians(high)),
    )
    return legs, table


def _check_spread(joints: np.ndarray, source: str, key: str) -> None:
    """Refuse six joints that coincide or lie on one line: a rotation about that line (or any,
    about a point) changes no leg length, so no pose could be solved or calibrated."""
    centred = joints - joints.mean(axis=0)
    extents = np.linalg.svd(centred, compute_uv=False)
    if extents[0] <= 1e-9 * max(1.0, float(np.abs(joints).max())):
        raise _refuse(source, key, f"6 joints spread in a plane; joints 1–6 all coincide at {joints[0].tolist()}")
    if extents[1] < COLLINEAR_RATIO * extents[0]:
        raise _refuse(source, key, "6 joints spread in a plane; joints 1–6 lie on one line")


def parse_platform(doc: dict, source: str = "<memory>") -> Platform:
    """Validate a parsed platform TOML document (spec §2) and build a :class:`Platform`.

    Raises:
        CalibError: naming ``source``, the key and what was expected.
    """
    _check_keys(doc, source)
    name = doc.get("name")
    if not isinstance(name, str) or not name.strip():
        raise _refuse(source, "name", "a non-empty string")
    description = doc.get("description", "")
    if not isinstance(description, str):
        raise _refuse(source, "description", "a string")
    rotary = drive_kind(doc, source) == "rotary"
    drive, drive_table = _rotary(doc, source) if rotary else _legs(doc, "drive", source)
    if rotary and "elastic" in doc:
        raise _refuse(
            source,
            "elastic",
            'no [elastic] table with [drive] kind = "rotary" (a servo\'s torsional give is not modelled)',
        )
    instrument = _instrument(doc, source)
    tracker, reading_range, geometry_sigma = None, None, 0.0
    if INSTRUMENT_SECTIONS[instrument.kind].reads_tracker or "tracker" in doc:
        tracker, tracker_table = _legs(doc, "tracker", source)
        reading_range = _range(tracker_table, "reading_range_mm", source, "tracker")
        geometry_sigma = _non_negative(tracker_table, "geometry_sigma_mm", 0.0, source, "tracker")
    stroke_range = None if rotary else _range(drive_table, "stroke_range_mm", source, "drive")
    stroke_scale = (
        _array(drive_table, "stroke_scale", (N_LEGS,), source, "drive")
        if "stroke_scale" in drive_table
        else np.zeros(N_LEGS)
    )
    if np.any(np.abs(stroke_scale) > 0.5):
        raise _refuse(
            source,
            "drive.stroke_scale",
            f"6 scale errors k_i within ±0.5 (a leg moves (1 + k_i) mm per logged mm), got {stroke_scale.tolist()}",
        )

    workspace = None
    if "workspace" in doc:
        ws = doc["workspace"]
        if not isinstance(ws, dict):
            raise _refuse(source, "workspace", "a [workspace] table")
        home = _array(ws, "home", (6,), source, "workspace")
        limits = {}
        for key, default in (("translation_limit_mm", 200.0), ("rotation_limit_deg", 20.0)):
            value = ws.get(key, default)
            finite = (
                isinstance(value, (int, float)) and not isinstance(value, bool) and abs(value) <= sys.float_info.max
            )
            if not finite or math.isnan(value) or value < 0:
                raise _refuse(source, f"workspace.{key}", "a finite non-negative number")
            limits[key] = float(value)
        workspace = Workspace(
            home=np.concatenate([home[:3], np.radians(home[3:])]),
            translation_limit=limits["translation_limit_mm"],
            rotation_limit=math.radians(limits["rotation_limit_deg"]),
        )

    elastic = (
        _elastic(doc, drive, source, give_reference_mm(drive, stroke_range)) if isinstance(drive, LegGeometry) else None
    )
    platform = Platform(
        name,
        drive,
        tracker,
        stroke_range,
        reading_range,
        workspace,
        description,
        source,
        instrument,
        stroke_scale,
        geometry_sigma,
        elastic,
    )
    if workspace is not None:
        _check_home_reachable(platform, workspace, source)
    return platform


def _number(table: dict, key: str, default: float, source: str, prefix: str) -> float:
    value = table.get(key, default)
    finite = isinstance(value, (int, float)) and not isinstance(value, bool) and abs(value) <= sys.float_info.max
    if not finite or math.isnan(value):
        raise _refuse(source, f"{prefix}.{key}", "a finite number")
    return float(value)


def _non_negative(table: dict, key: str, default: float, source: str, prefix: str) -> float:
    value = _number(table, key, default, source, prefix)
    if value < 0:
        raise _refuse(source, f"{prefix}.{key}", f"a σ ≥ 0 (0: known exactly), got {value!r}")
    return value


def _positive(table: dict, key: str, default: float, source: str, prefix: str) -> float:
    value = _number(table, key, default, source, prefix)
    if not value > 0:
        raise _refuse(source, f"{prefix}.{key}", f"a positive σ, got {value!r}")
    implausible = implausible_sigma_mm(value) if key.endswith("_mm") else None
    if implausible:
        raise _refuse(source, f"{prefix}.{key}", implausible)
    if key.endswith("_deg") and not 1e-9 <= value <= 180.0:
        raise _refuse(source, f"{prefix}.{key}", f"a σ within [1e-9, 180] deg, got {value!r}")
    return value


def _elastic(doc: dict, drive: LegGeometry, source: str, reference: tuple[float, str]) -> Elastic | None:
    """The optional ``[elastic]`` table (spec §10); None without it. ``reference``: what no leg can
    give (:func:`give_reference_mm`), which bounds the compliances, their σ and the payload's σ."""
    if "elastic" not in doc:
        return None
    table = doc["elastic"]
    if not isinstance(table, dict):
        raise _refuse(source, "elastic", "an [elastic] table")
    if "platform_mass_kg" not in table:
        raise _refuse(source, "elastic.platform_mass_kg", "the platform's mass in kg (missing)")
    mass = _number(table, "platform_mass_kg", 0.0, source, "elastic")
    if not mass >= MIN_PLATFORM_MASS_KG:
        raise _refuse(
            source,
            "elastic.platform_mass_kg",
            f"a mass in kg of at least {MIN_PLATFORM_MASS_KG:g} (a gram), got {mass!r}",
        )
    centres = {}
    for key in ("platform_com_mm", "payload_com_mm"):
        centre = (
            _array(table, key, (3,), source, "elastic") if key in table or key == "platform_com_mm" else np.zeros(3)
        )
        too_far = centre_too_far(drive, centre)
        if too_far:
            raise _refuse(source, f"elastic.{key}", too_far)
        centres[key] = centre
    compliance = (
        _array(table, "compliance_mm_per_kN", (N_LEGS,), source, "elastic")
        if "compliance_mm_per_kN" in table
        else np.zeros(N_LEGS)
    )
    truth = (
        _array(table, "true_compliance_mm_per_kN", (N_LEGS,), source, "elastic")
        if "true_compliance_mm_per_kN" in table
        else None
    )
    sigma = _non_negative(table, "compliance_sigma_mm_per_kN", default_compliance_sigma(mass), source, "elastic")
    reference_mm, what = reference
    weight_n = mass * G_N_PER_KG / N_LEGS
    at_most = reference_mm / (least_give_mm_per_kg(1.0) * mass)  # [mm/kN]: a leg gives its reference length
    for key, values in (("compliance_mm_per_kN", compliance), ("compliance_sigma_mm_per_kN", np.array([sigma]))):
        largest = float(np.max(np.abs(values)))
        if not largest <= at_most:
            raise _refuse(
                source,
                f"elastic.{key}",
                f"legs that can hold the platform: {largest:.4g} mm/kN gives a leg at least "
                f"{least_give_mm_per_kg(largest) * mass:.4g} mm under a sixth of the platform's weight "
                f"({weight_n:.4g} N), beyond {reference_mm:.4g} mm of {what} (expected at most {at_most:.4g} mm/kN)",
            )
    elastic = Elastic(
        mass,
        centres["platform_com_mm"],
        centres["payload_com_mm"],
        compliance,
        sigma,
        truth,
        _non_negative(table, "payload_sigma_kg", 0.0, source, "elastic"),
    )
    limit = payload_limit_kg(elastic, reference_mm)
    if not elastic.payload_sigma_kg <= limit:
        raise _refuse(
            source,
            "elastic.payload_sigma_kg",
            f"a payload σ the platform could carry: at most {limit:.4g} kg, beyond which its legs (compliance "
            f"{float(np.max(np.abs(compliance))):.4g} + σ {sigma:.4g} mm/kN) would give more than "
            f"{reference_mm:.4g} mm of {what}; got {elastic.payload_sigma_kg!r}",
        )
    return elastic


def _pose6(table: dict, key: str, source: str) -> np.ndarray:
    """A ``[x, y, z mm, roll, pitch, yaw deg]`` key (default all zero) as pose6 ``[mm, rad]``."""
    if key not in table:
        return np.zeros(6)
    value = _array(table, key, (6,), source, "instrument")
    return np.concatenate([value[:3], np.radians(value[3:])])


def _instrument(doc: dict, source: str) -> Instrument:
    """The optional ``[instrument]`` table (spec §7); without it, the tracker."""
    if "instrument" not in doc:
        return Instrument()
    return parse_instrument(doc["instrument"], source)


def parse_instrument(table, source: str) -> Instrument:
    """Validate an ``[instrument]`` table (spec §7).

    Raises:
        CalibError: an unknown kind, a key the kind does not use, a wrong shape or a σ ≤ 0,
            naming ``source`` and the key.
    """
    if not isinstance(table, dict):
        raise _refuse(source, "instrument", "an [instrument] table")
    kind = table.get("kind", INSTRUMENT_KINDS[0])
    if kind not in INSTRUMENT_KINDS:
        raise _refuse(source, "instrument.kind", f"one of {', '.join(map(repr, INSTRUMENT_KINDS))}, got {kind!r}")
    section = INSTRUMENT_SECTIONS[kind]
    unused = sorted(set(table) - {"kind", *section.keys})
    if unused:
        known = {key for other in INSTRUMENT_SECTIONS.values() for key in other.keys}
        why = (
            f"a key that kind = {kind!r} uses"
            if unused[0] in known
            else f"a known key (spec §7){did_you_mean(unused[0], section.keys)}"
        )
        raise _refuse(source, f"instrument.{unused[0]}", why)
    # a key the kind does not read was refused above: every other key takes its default when absent
    targets = np.zeros((0, 3))
    if "targets_mm" in section.required and "targets_mm" not in table:
        raise _refuse(source, "instrument.targets_mm", "1..K rows of [x, y, z] in mm (missing)")
    if "targets_mm" in table:
        try:
            targets = np.array(table["targets_mm"], dtype=float)
        except (TypeError, ValueError, OverflowError):
            targets = np.zeros((0,))
        if targets.ndim != 2 or targets.shape[1:] != (3,) or len(targets) == 0 or not np.all(np.isfinite(targets)):
            raise _refuse(source, "instrument.targets_mm", "1..K rows of [x, y, z] in mm (finite numbers)")
    cone, axes = _visibility(table, len(targets), source)
    return Instrument(
        kind=kind,
        frame=_pose6(table, "frame", source),
        target=_pose6(table, "target", source),
        targets=targets,
        position_sigma_mm=_positive(table, "position_sigma_mm", DEFAULT_POSITION_SIGMA_MM, source, "instrument"),
        orientation_sigma_rad=math.radians(
            _positive(table, "orientation_sigma_deg", DEFAULT_ORIENTATION_SIGMA_DEG, source, "instrument")
        ),
        visibility_cone_deg=cone,
        target_axes=axes,
    )


def _visibility(table: dict, n_targets: int, source: str) -> tuple[float | None, np.ndarray]:
    """``[instrument] visibility_cone_deg`` (in (0, 180]) and ``target_axes`` (K nonzero rows,
    default {D}'s z for every target; only with the cone)."""
    axes = np.tile([0.0, 0.0, 1.0], (n_targets, 1))
    if "visibility_cone_deg" not in table:
        if "target_axes" in table:
            raise _refuse(source, "instrument.target_axes", "visibility_cone_deg beside it (the axes are of the cone)")
        return None, axes
    cone = _number(table, "visibility_cone_deg", 0.0, source, "instrument")
    if not 0.0 < cone <= 180.0:
        raise _refuse(source, "instrument.visibility_cone_deg", f"a half-angle in (0, 180] degrees, got {cone!r}")
    if "target_axes" in table:
        axes = _array(table, "target_axes", (n_targets, 3), source, "instrument")
        if np.any(np.linalg.norm(axes, axis=1) == 0.0):
            raise _refuse(source, "instrument.target_axes", f"{n_targets} nonzero [x, y, z] directions in {{D}}")
    return float(cone), axes


def _check_home_reachable(platform: Platform, workspace: Workspace, source: str) -> None:
    R, t = pose_to_rt(workspace.home)
    drive = platform.drive
    if not isinstance(drive, LegGeometry):  # a rotary drive (spec §15)
        angles = drive.coordinates(R, t)
        bad = np.flatnonzero(~np.isfinite(angles))
        if bad.size:
            low, high = np.degrees(drive.angle_range)
            raise _refuse(
                source,
                "workspace.home",
                f"a home pose every crank reaches with a commanded angle within [{low:g}, {high:g}] deg "
                f"(drive.angle_range_deg); leg {int(bad[0]) + 1} cannot",
            )
    for legs, bounds, what in (
        (drive if isinstance(drive, LegGeometry) else None, platform.stroke_range, "drive strokes"),
        (platform.tracker, platform.reading_range, "tracker readings"),
    ):
        if bounds is None or legs is None:
            continue
        strokes = np.linalg.norm(transform_points(R, t, legs.platform_joints) - legs.base_joints, axis=-1)
        strokes -= legs.initial_lengths
        bad = np.flatnonzero((strokes < bounds[0]) | (strokes > bounds[1]))
        if bad.size:
            i = int(bad[0])
            raise _refuse(
                source,
                "workspace.home",
                f"a home pose whose {what} lie within [{bounds[0]}, {bounds[1]}] mm; "
                f"leg {i + 1} needs {strokes[i]:.3f} mm",
            )


def load_platform(path: str | Path) -> Platform:
    """Read and validate a platform TOML file (spec §2), given by path or by the name of a shipped
    platform (``"nim-stewart"``, spec §8).

    Raises:
        CalibError: one line naming the file, the key and what was expected.
    """
    path, doc = resources.read_toml(path, "platforms", "platform file")
    return parse_platform(doc, str(path))


def _toml_rows(rows: np.ndarray) -> str:
    return "[\n" + "".join(f"    [{', '.join(repr(float(v)) for v in row)}],\n" for row in rows) + "]"


def _toml_list(values) -> str:
    return "[" + ", ".join(repr(float(v)) for v in values) + "]"


def platform_to_toml(platform: Platform) -> str:
    """Serialise to the spec §2 TOML (a rotary drive's ``[drive]``: spec §15);
    ``parse_platform(tomllib.loads(...))`` round-trips exactly (a rotary drive's directions and
    angles to the last bit or two: they are normalised and converted again on reading)."""
    lines = [f"name = {_toml_str(platform.name)}"]
    if platform.description:
        lines.append(f"description = {_toml_str(platform.description)}")
    drive, prismatic = platform.drive, None
    if isinstance(drive, LegGeometry):
        prismatic = drive
    else:  # a rotary drive (spec §15)
        lines += _rotary_toml(drive)
        if np.any(platform.stroke_scale != 0):
            lines.append(f"stroke_scale = {_toml_list(platform.stroke_scale)}")
    for section, legs, key, bounds in (
        ("drive", prismatic, "stroke_range_mm", platform.stroke_range),
        ("tracker", platform.tracker, "reading_range_mm", platform.reading_range),
    ):
        if legs is None:
            continue
        lines += [
            "",
            f"[{section}]",
            f"base_joints_mm = {_toml_rows(legs.base_joints)}",
            f"platform_joints_mm = {_toml_rows(legs.platform_joints)}",
            f"initial_lengths_mm = {_toml_list(legs.initial_lengths)}",
        ]
        if bounds is not None:
            lines.append(f"{key} = {_toml_list(bounds)}")
        if section == "drive" and np.any(platform.stroke_scale != 0):
            lines.append(f"stroke_scale = {_toml_list(platform.stroke_scale)}")
        if section == "tracker" and platform.tracker_geometry_sigma_mm > 0:
            lines.append(f"geometry_sigma_mm = {platform.tracker_geometry_sigma_mm!r}")
    lines += _instrument_toml(platform.instrument)
    lines += _elastic_toml(platform.elastic)
    if platform.workspace is not None:
        ws = platform.workspace
        home = np.concatenate([ws.home[:3], np.degrees(ws.home[3:])])
        lines += [
            "",
            "[workspace]",
            f"home = {_toml_list(home)}",
            f"translation_limit_mm = {float(ws.translation_limit)!r}",
            f"rotation_limit_deg = {math.degrees(ws.rotation_limit)!r}",
        ]
    return "\n".join(lines) + "\n"


def _rotary_toml(legs: RotaryLegs) -> list[str]:
    """The ``[drive]`` lines of a rotary drive (spec §15): its axes and zero directions as they are
    (turned, in a calibrated platform), the zero trims in degrees."""
    return [
        "",
        "[drive]",
        'kind = "rotary"',
        f"crank_centres_mm = {_toml_rows(legs.crank_centres)}",
        f"crank_axes = {_toml_rows(legs.crank_axes)}",
        f"crank_zero_directions = {_toml_rows(legs.zero_directions)}",
        f"horn_lengths_mm = {_toml_list(legs.horn_lengths)}",
        f"rod_lengths_mm = {_toml_list(legs.rod_lengths)}",
        f"platform_joints_mm = {_toml_rows(legs.platform_joints)}",
        f"angle_offsets_deg = {_toml_list(np.degrees(legs.angle_offsets))}",
        f"angle_range_deg = {_toml_list(np.degrees(legs.angle_range))}",
    ]


def _pose6_toml(pose6: np.ndarray) -> str:
    return _toml_list(np.concatenate([pose6[:3], np.degrees(pose6[3:])]))


#: ``[instrument]`` key → its value in TOML, or None where it is left out (the cone's keys without a cone).
_INSTRUMENT_TOML = {
    "frame": lambda instrument: _pose6_toml(instrument.frame),
    "target": lambda instrument: _pose6_toml(instrument.target),
    "targets_mm": lambda instrument: _toml_rows(instrument.targets),
    "position_sigma_mm": lambda instrument: repr(float(instrument.position_sigma_mm)),
    "orientation_sigma_deg": lambda instrument: repr(math.degrees(instrument.orientation_sigma_rad)),
    "visibility_cone_deg": lambda instrument: (
        None if instrument.visibility_cone_deg is None else repr(float(instrument.visibility_cone_deg))
    ),
    "target_axes": lambda instrument: (
        None if instrument.visibility_cone_deg is None else _toml_rows(instrument.target_axes)
    ),
}


def _instrument_toml(instrument: Instrument) -> list[str]:
    """The ``[instrument]`` lines: the keys its kind reads (none for the default, the tracker)."""
    keys = INSTRUMENT_SECTIONS[instrument.kind].keys
    if not keys:
        return []
    values = {key: _INSTRUMENT_TOML[key](instrument) for key in keys}
    lines = ["", "[instrument]", f"kind = {_toml_str(instrument.kind)}"]
    return lines + [f"{key} = {value}" for key, value in values.items() if value is not None]


def _elastic_toml(elastic: Elastic | None) -> list[str]:
    """The ``[elastic]`` lines (none for a rigid robot)."""
    if elastic is None:
        return []
    lines = [
        "",
        "[elastic]",
        f"platform_mass_kg = {float(elastic.platform_mass_kg)!r}",
        f"platform_com_mm = {_toml_list(elastic.platform_com_mm)}",
        f"payload_com_mm = {_toml_list(elastic.payload_com_mm)}",
        f"compliance_mm_per_kN = {_toml_list(elastic.compliance_mm_per_kN)}",
        f"compliance_sigma_mm_per_kN = {float(elastic.compliance_sigma_mm_per_kN)!r}",
    ]
    if elastic.true_compliance_mm_per_kN is not None:
        lines.append(f"true_compliance_mm_per_kN = {_toml_list(elastic.true_compliance_mm_per_kN)}")
    if elastic.payload_sigma_kg > 0.0:
        lines.append(f"payload_sigma_kg = {float(elastic.payload_sigma_kg)!r}")
    return lines


def _toml_str(text: str) -> str:
    """``text`` as a TOML basic string that reads back as ``text`` whatever it holds: a backslash,
    a quote and every control character (which TOML forbids raw in a string) escaped."""
    escaped = "".join(
        "\\\\" if ch == "\\" else '\\"' if ch == '"' else f"\\u{ord(ch):04x}" if ch < " " or ch == "\x7f" else ch
        for ch in text
    )
    return f'"{escaped}"'
