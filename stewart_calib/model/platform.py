"""Nominal geometry of a 6-6 Stewart platform and its in-situ tracker; the 42-vector layout.

Fixed geometry lives here and nowhere else; per-sample data (strokes, readings, poses)
is passed to the pure functions of :mod:`stewart_calib.model.kinematics`.

The 42 kinematic parameters follow the paper's order (δM, eq. 9)::

    [j1x j1y j1z d1x d1y d1z l1  j2x ... l2  ...  j6x j6y j6z d6x d6y d6z l6]

and are held as a ``(6, 7)`` array ``[j_i (3) | d_i (3) | l_i]`` per leg; :func:`params_to_vector`
and :func:`vector_to_params` convert between the two, and nothing else reorders them.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..errors import CalibError

if TYPE_CHECKING:
    from .rotary import RotaryLegs

N_LEGS = 6
N_PARAMS_PER_LEG = 7
N_PARAMS = N_LEGS * N_PARAMS_PER_LEG
#: the seven parameters of one leg, in the paper's order (rerun entity paths use them as is).
PARAMETER_FIELDS: tuple[str, ...] = ("j_x", "j_y", "j_z", "d_x", "d_y", "d_z", "l")
#: the 42 parameter names ``j1x j1y j1z d1x d1y d1z l1 … l6`` (spec §4–§5 columns and keys).
PARAMETER_NAMES: tuple[str, ...] = tuple(
    f"{field[0]}{leg}{field[2:]}" for leg in range(1, N_LEGS + 1) for field in PARAMETER_FIELDS
)


def _lengthened(e: np.ndarray, lengthening: np.ndarray | None) -> np.ndarray:
    """A prismatic leg's extension ``e + Δℓ`` [mm]: its coordinate is a length (``e`` itself for None)."""
    return e if lengthening is None else np.asarray(e, dtype=float) + lengthening


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
    #: the leg model's compiled kernels (:mod:`stewart_calib.model._kernels`) apply to it
    compiled = True
    #: ``e_i`` is the leg's length change, so a lengthening ``Δℓ`` is the extension ``e + Δℓ``
    coordinate_is_length = True

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
        arrays: the leg set as the compiled kernels (:mod:`stewart_calib.model._kernels`) take it."""
        return self.base_joints, self.platform_joints, self.initial_lengths

    # The leg model's arithmetic is the compiled kinematics' (imported here, not with the module: a
    # platform file is read by commands that never compute, see :meth:`perturbed`).

    def residuals(
        self, R: np.ndarray, t: np.ndarray, e: np.ndarray, *, lengthening: np.ndarray | None = None
    ) -> np.ndarray:
        """``r_i = ‖t + R d_i − j_i‖ − (l_i + e_i + Δℓ_i)``, ``(..., n)`` [mm] (paper eq. 1), ``Δℓ`` the
        ``lengthening`` (None: 0)."""
        from . import kinematics

        return kinematics.leg_residuals(self, R, t, _lengthened(e, lengthening))

    def residual_jacobians(
        self, R: np.ndarray, t: np.ndarray, e: np.ndarray, *, lengthening: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(∂r/∂ξ (..., n, 6), ∂r/∂M (..., n, n_params), ∂r_i/∂e_i (..., n) = −1)`` of :meth:`residuals`
        (none depends on ``e`` or the ``lengthening``)."""
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

    def joint_lengths(self, e: np.ndarray) -> np.ndarray:
        """``(..., n)`` each leg's length from joint to joint at extensions ``e`` [mm]: ``l_i + e_i``, what
        its temperature scales (spec §17)."""
        return self.initial_lengths + np.asarray(e, dtype=float)

    def coordinates(self, R: np.ndarray, t: np.ndarray, *, lengthening: np.ndarray | None = None) -> np.ndarray:
        """The extensions ``(..., n)`` [mm] that close each leg at ``(R, t)`` (inverse kinematics), less
        the ``lengthening`` ``Δℓ (..., n)`` [mm] the legs have besides (None: 0)."""
        from . import kinematics

        extensions = kinematics.inverse_kinematics(self, R, t)
        return extensions if lengthening is None else extensions - lengthening

    def forward_kinematics(
        self,
        e: np.ndarray,
        guess=None,
        tol_mm: float | None = None,
        strict: bool = True,
        along: bool = False,
        *,
        lengthening: np.ndarray | None = None,
    ):
        """:func:`~stewart_calib.model.kinematics.forward_kinematics` of extensions ``e + Δℓ (..., n)`` [mm]
        (``tol_mm`` None: :data:`~stewart_calib.model.kinematics.FK_TOLERANCE_MM`; ``lengthening`` Δℓ None: 0)."""
        from . import kinematics

        tol = kinematics.FK_TOLERANCE_MM if tol_mm is None else tol_mm
        extensions = _lengthened(e, lengthening)
        return kinematics.forward_kinematics(self, extensions, guess=guess, tol_mm=tol, strict=strict, along=along)

    def solve_fk(
        self, e: np.ndarray, guess, what: str, *, lengthening: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """One pose of extensions ``e + Δℓ (n,)`` from ``guess``, then cold
        (:func:`~stewart_calib.model.kinematics.solve_fk`)."""
        from . import kinematics

        return kinematics.solve_fk(self, _lengthened(e, lengthening), guess, what)

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


def payload_expected(platform: Platform | None, load_kg: float) -> str | None:
    """What a payload ``load_kg`` [kg] (a log's ``load_kg``, an option's) should have been, for a
    refusal naming where it came from: a finite payload ≥ 0 kg and, with ``platform``, one it can
    carry (:func:`payload_refusal`); None when it is both."""
    if not (math.isfinite(load_kg) and load_kg >= 0.0):
        return f"a finite payload ≥ 0 kg (an input where the platform has [elastic], spec §10), got {load_kg!r}"
    return None if platform is None else payload_refusal(platform, load_kg)


def check_payload_option(option: str, load_kg: float, platform: Platform | None = None) -> None:
    """Refuse a payload given on the command line (``--load-kg``, ``--payload-kg``) that
    :func:`payload_expected` refuses, in one line naming ``option``.

    Raises:
        CalibError: ``load_kg`` is not finite, below 0, or (with ``platform``) beyond its payload limit.
    """
    not_a_payload = payload_expected(platform, load_kg)
    if not_a_payload:
        raise CalibError(f"{option}: expected {not_a_payload}")


def payloads_refused(platform: Platform | None, load_kg: np.ndarray) -> np.ndarray:
    """Which of the payloads ``load_kg`` [kg] :func:`payload_expected` refuses (not finite, below 0 or,
    with ``platform``, beyond its :func:`payload_limit`), at once."""
    limit = math.inf if platform is None else payload_limit(platform)
    return ~(np.isfinite(load_kg) & (load_kg >= 0.0) & (load_kg <= limit))


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


#: the direction gravity acts along in {J} where nothing else is declared: −z (spec §10)
DOWN = np.array([0.0, 0.0, -1.0])

#: the most a leg's thermal expansion coefficient may be [ppm/K] (spec §17): steel's is 11.5, aluminium's 23
EXPANSION_LIMIT_PPM_PER_K = 100.0
#: the temperatures a log or a command may give [°C] (spec §17)
TEMPERATURE_RANGE_C = (-50.0, 150.0)


@dataclass(frozen=True, eq=False)
class Thermal:
    """Each drive leg's thermal expansion (spec §17, ``[thermal]``): leg i at temperature ``T_i`` has
    its joint-to-joint length scaled by ``1 + α_i (T_i − T_ref) · 1e-6`` (a prismatic leg's
    ``l_i + (1 + k_i) q_i − c_i f_i / 1000``, a rotary leg's rod).

    Attributes:
        reference_temperature_C: ``T_ref`` [°C], where the geometry of ``[drive]`` holds.
        expansion_ppm_per_K: ``(6,)`` nominal ``α_i`` [ppm/K = µm/(m·K)].
        expansion_sigma_ppm_per_K: prior σ of ``α_i`` about the nominal [ppm/K]; 0: held at nominal.
        true_expansion_ppm_per_K: ``(6,)`` the truth a simulated platform carries for reports and
            checks (``simulate``), never read by an estimator; None on a real robot.
    """

    reference_temperature_C: float = 20.0
    expansion_ppm_per_K: np.ndarray = field(default_factory=lambda: np.zeros(N_LEGS))
    expansion_sigma_ppm_per_K: float = 20.0
    true_expansion_ppm_per_K: np.ndarray | None = None


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
        gravity: ``(3,)`` the unit vector in {J} gravity acts along (spec §17 ``[elastic] gravity``, default
            −z); a log's ``gravity_x/y/z`` columns give it per row instead (a tilting mount).
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
    gravity: np.ndarray = field(default_factory=lambda: DOWN.copy())

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
        thermal: each leg's thermal expansion (spec §17, ``[thermal]``), or None: temperature ignored.
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
    thermal: Thermal | None = field(default=None, compare=False)

    @property
    def coordinate_range(self) -> tuple[float, float] | None:
        """``(min, max)`` of the log's drive coordinates in code units, or None: the stroke range [mm],
        or a rotary drive's commanded angles' ``angle_range`` [rad] (spec §15)."""
        return self.stroke_range if isinstance(self.drive, LegGeometry) else self.drive.angle_range

    def prismatic_drive(self, what: str) -> LegGeometry:
        """:attr:`drive` for ``what``, which takes prismatic legs (the paper's error Jacobian, the
        statics, the LinuxCNC kinematics, the paper's experiments).

        Raises:
            CalibError: the drive is of another kind (a rotary drive, spec §15).
        """
        if not isinstance(self.drive, LegGeometry):
            raise CalibError(
                f"{self.source}: key 'drive.kind': {what} takes prismatic legs; this drive is {self.drive.kind}"
            )
        return self.drive

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
