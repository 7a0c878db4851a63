"""The drive as one model: its legs, its unknown blocks, its per-sample inputs, its residual.

Every estimator, factor and analysis talks to the drive only through a :class:`DriveModel`, as
it talks to the instrument only through an :class:`~stewart_calib.instruments.InstrumentModel`:
none of them names a block of the drive. Drive leg i (paper eq. 1, spec §7)::

    r_i = r_i(pose; M + δM, e_i),     e_i = Σ_b (o_b + v_{b,i}) g_b u_{b,i}

with ``r_i`` the leg model's closure residual (:class:`~stewart_calib.model.legs.LegModel`: a
prismatic leg's ``‖t + R d_i − j_i‖ − (l_i + e_i)``, paper eq. 1; a rotary leg's rod closure,
spec §15) and ``M`` its parameters; the extension
``e_i`` is a sum of per-leg *terms* (:class:`LegTerm`): term b has an offset ``o_b``, six values
``v_b`` (its nominal from the platform file, plus an error where it is an unknown block) and a
gain ``g_b`` on six columns ``u_b`` of the sample's drive inputs ``u``. Every drive has the stroke
term: ``o = 1``, ``v = k`` (the stroke scale), ``g u = q`` (the logged strokes), so a rigid drive's
``e_i = (1 + k_i) q_i``; an elastic drive adds the compliance term on the leg forces (spec §10), a
drive with ``[thermal]`` the expansion term on each leg's temperature (spec §17).

A term whose source *lengthens* the leg (:attr:`TermSource.lengthens`: the expansion, which scales
the leg's length from joint to joint) belongs to ``e_i`` only where the leg's coordinate is that
length (``legs.coordinate_is_length``: prismatic, ``(l_i + e_i)`` grows). Elsewhere (a rotary leg,
whose ``e_i`` is an angle and whose rod grows, spec §17) such terms sum to the leg model's
*lengthening* ``Δℓ_i = Σ (o_b + v_{b,i}) g_b u_{b,i}`` [mm] (:meth:`DriveModel.lengthening`), which
every kinematic method of the leg model takes beside ``e``, with ``∂r_i/∂Δℓ_i = −1``.

A term's inputs come from its *source* (:data:`TERM_SOURCES`): the logged strokes, or a function of
the sample's named input channels (:data:`~stewart_calib.samples.LOAD_KG`,
:data:`~stewart_calib.samples.TEMPERATURE_C`, :data:`~stewart_calib.samples.GRAVITY`:
``Sample.inputs``, ``Log.inputs``) and, for the leg forces, of the pose. Estimators hand a
sample's channels to :meth:`DriveModel.inputs` as they come and never read one by name, so a new
input is one source here and one line where the log's columns are parsed (docs/architecture.md).
Since every term is linear in its values, ``∂r_i/∂v_{b,i} = J_e,i g_b u_{b,i}`` with the leg
model's ``J_e,i = ∂r_i/∂e_i`` (prismatic: −1), and ``−g_b u_{b,i}`` for a term of the lengthening.
A rotary drive's stroke input is the commanded angle [rad], so ``k`` is its angle scale.

The unknown vector of a drive is ``x_drive = [δM (n_params) | the errors of its unknown terms, six
each, in term order]`` (:attr:`DriveModel.size` entries): the first entries of every estimator's
unknown vector (:mod:`stewart_calib.model.unknowns`), so the drive's Jacobians are its first columns.

Compiled code (prismatic legs only: ``legs.compiled``; elsewhere numpy of the same formulas) sees
a drive as :meth:`DriveModel.kernel_terms`: ``(starts, gains, offsets, values,
columns)`` of its terms, evaluated by :func:`stewart_calib.model._kernels.leg_extensions` (the EKF's
fast path, :mod:`stewart_calib.estimators.kalman`) and by the drive-leg factor's kernel
(:mod:`stewart_calib.factors._kernels`). To add a drive error source see docs/architecture.md.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..config import NoiseConfig
from ..errors import CalibError
from ..samples import CHANNEL_SHAPES, GRAVITY, LOAD_KG, TEMPERATURE_C, Inputs
from . import kinematics as kin
from .legs import LegModel
from .platform import DOWN, G_N_PER_KG, N_LEGS, Elastic, LegGeometry, Platform, Thermal
from .statics import gravity_leg_forces, masses_and_centres, moment_radius
from .unknowns import UnknownBlock

#: the stroke term's key: the result's ``"stroke_scale"`` block (spec §7)
STROKE_SCALE = "stroke_scale"

#: prior σ a drive's blocks declare where the method itself takes no prior (the batch fit, the
#: identifiability and accuracy analyses): only the result's block carries it (10 %)
BLOCK_PRIOR_SIGMA = 0.1

#: prior σ of the stroke scale with an instrument outside the robot when ``noise.stroke_scale_sigma``
#: is 0: such logs come from encoders whose mm per count is the builders' nominal, a few per cent
#: off per leg (up to ~6 %), and the frame-and-target fit identifies k alongside
STROKE_SCALE_SIGMA_OUTSIDE = 0.05


@dataclass(frozen=True)
class LegTerm:
    """One term ``(o + v_i) g u_i`` of every drive leg's extension (see the module docstring).

    Attributes:
        key: the result's key of the term's values (``"stroke_scale"``).
        names: six names of its values, as the result lists them (``k1…k6``).
        offset: ``o``.
        nominal: ``(6,)`` nominal values ``v`` (the platform file's).
        input_start: the first of its six columns in the sample's drive inputs ``u``.
        gain: ``g`` (code units of the extension per unit of input).
        prior_sigma: prior σ of its errors where they are unknowns, None where the term is known.
        source: the key in :data:`TERM_SOURCES` of what its six inputs are.
    """

    key: str
    names: tuple[str, ...]
    offset: float
    nominal: np.ndarray
    input_start: int
    gain: float = 1.0
    prior_sigma: float | None = None
    source: str = "strokes"

    def block(self) -> UnknownBlock:
        """The unknown block of its errors (about :attr:`nominal`, σ :attr:`prior_sigma`)."""
        return UnknownBlock(self.key, self.names, self.nominal, np.full(N_LEGS, self.prior_sigma))


#: at most this many forward-kinematics passes before the last one in :meth:`DriveModel.settled_kinematics`
SETTLING_PASSES = 30
#: the settling stops once no leg's extension moved more than this between passes [mm]
SETTLED_MM = 1e-7

#: the compliance term's key: the result's ``"compliance"`` block (spec §10)
COMPLIANCE = "compliance"

#: what a pose-dependent term takes for a channel a sample lacks (:meth:`DriveModel.packed_pose_channels`),
#: where the drive's own tables do not say (:meth:`DriveModel.channel_default`: gravity along
#: ``[elastic] gravity``)
CHANNEL_DEFAULTS = {LOAD_KG: 0.0}

#: the thermal expansion term's key: the result's ``"thermal"`` block (spec §17)
THERMAL = "thermal"

#: the units a report gives a term's values (and σ) in, by the term's key
TERM_UNITS = {STROKE_SCALE: "-", COMPLIANCE: "mm/kN", THERMAL: "ppm/K"}


def compliance_term(elastic: Elastic) -> LegTerm:
    """``−c_i f_i / 1000``: the leg forces ``f`` [N] (inputs 6…11, compression > 0) with each leg's
    compliance ``c`` [mm/kN] about ``[elastic] compliance_mm_per_kN``, an unknown block where its σ
    is positive (spec §10)."""
    sigma = float(elastic.compliance_sigma_mm_per_kN)
    return LegTerm(
        COMPLIANCE,
        tuple(f"c{i}" for i in range(1, N_LEGS + 1)),
        0.0,
        np.array(elastic.compliance_mm_per_kN, dtype=float),
        N_LEGS,
        -1e-3,
        sigma if sigma > 0.0 else None,
        "leg_forces",
    )


def thermal_term(thermal: Thermal, input_start: int) -> LegTerm:
    """``α_i (T_i − T_ref) · 1e-6 · L_i``: each leg's growth [mm] with its temperature (spec §17; a
    term that lengthens the leg, :attr:`TermSource.lengthens`: a rotary leg's rod ``L_i = r_i`` grows), the
    expansion ``α`` [ppm/K] about ``[thermal] expansion_ppm_per_K``, an unknown block where its σ is
    positive. The input ``(T_i − T_ref) · 1e-6 · L_i`` takes ``L_i`` the nominal leg's length from
    joint to joint at its nominal extension (:func:`_thermal_inputs`), so the term is linear in ``α``
    like every other: ``(l_i + e_i)(1 + α_i ΔT_i · 1e-6) = l_i + e_i + α_i ΔT_i · 1e-6 (l_i + e_i)``, off
    by ``α ΔT`` times what the calibration corrects in ``l_i + e_i`` — 20 ppm/K · 15 K · 2 mm = 0.6 µm."""
    sigma = float(thermal.expansion_sigma_ppm_per_K)
    return LegTerm(
        THERMAL,
        tuple(f"alpha{i}" for i in range(1, N_LEGS + 1)),
        0.0,
        np.array(thermal.expansion_ppm_per_K, dtype=float),
        input_start,
        1.0,
        sigma if sigma > 0.0 else None,
        "thermal",
    )


#: the unannounced payload's key: the result's ``"payload"`` block (``[elastic] payload_sigma_kg``)
PAYLOAD = "payload"


def payload_block(elastic: Elastic | None) -> UnknownBlock | None:
    """The payload mass [kg] the log does not announce, about 0 with ``[elastic] payload_sigma_kg``
    (None: the payload is the log's ``load_kg``): an online method's own unknown, which steps."""
    if elastic is None or not elastic.payload_sigma_kg > 0.0:
        return None
    return UnknownBlock(PAYLOAD, ("payload_kg",), np.zeros(1), np.array([elastic.payload_sigma_kg]))


def stroke_term(nominal_scale: np.ndarray, prior_sigma: float | None = None) -> LegTerm:
    """``(1 + k_i) q_i``: the logged strokes ``q`` (inputs 0…5) with the encoders' scale ``k``."""
    return LegTerm(
        STROKE_SCALE,
        tuple(f"k{i}" for i in range(1, N_LEGS + 1)),
        1.0,
        np.array(np.broadcast_to(np.asarray(nominal_scale, dtype=float), (N_LEGS,))),
        0,
        1.0,
        prior_sigma,
    )


@dataclass(frozen=True)
class DriveModel:
    """The drive legs ``M`` and the terms of their extensions (see the module docstring).

    Attributes:
        legs: the nominal leg model ``M`` (:class:`~stewart_calib.model.legs.LegModel`).
        terms: the extension's terms; those with a ``prior_sigma`` are unknown blocks.
        elastic: the masses whose weight the legs carry where a term takes the leg forces as inputs
            (the compliance, spec §10), else None.
        thermal: the reference temperature of the legs' geometry where a term takes their
            temperatures (the expansion, spec §17), else None.
    """

    legs: LegModel
    terms: tuple[LegTerm, ...]
    elastic: Elastic | None = None
    thermal: Thermal | None = None
    # derived once (a filter asks for them at every sample): see __post_init__
    _unknown: tuple[tuple[int, slice], ...] = field(init=False, repr=False, compare=False)
    _nominal: np.ndarray = field(init=False, repr=False, compare=False)
    _factors: np.ndarray = field(init=False, repr=False, compare=False)
    _stroke: int = field(init=False, repr=False, compare=False)
    _lengthening: tuple[int, ...] = field(init=False, repr=False, compare=False)
    _last_geometry: tuple = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.elastic is not None and self.legs.kind != "prismatic":
            raise ValueError(f"an elastic drive needs prismatic legs, not {self.legs.kind}")
        unknown, start = [], self.legs.n_params
        for row, term in enumerate(self.terms):
            if term.prior_sigma is not None:
                unknown.append((row, slice(start, start + self.legs.n_legs)))
                start += self.legs.n_legs
        nominal = np.array([term.nominal for term in self.terms], dtype=float)
        factors = np.array([term.offset + term.nominal for term in self.terms], dtype=float)
        for array in (nominal, factors):
            array.setflags(write=False)
        stroke = next(row for row, term in enumerate(self.terms) if term.input_start == 0)
        for name, value in (("_unknown", tuple(unknown)), ("_nominal", nominal), ("_factors", factors)):
            object.__setattr__(self, name, value)
        object.__setattr__(self, "_stroke", stroke)
        # a lengthening term is the leg's coordinate itself where that is a length: only the
        # other legs' models take it apart from e (see the module docstring)
        lengthening = () if self.legs.coordinate_is_length else self._lengthening_rows()
        object.__setattr__(self, "_lengthening", lengthening)
        object.__setattr__(self, "_last_geometry", (None, self.legs))

    def _lengthening_rows(self) -> tuple[int, ...]:
        """The rows of the terms whose source lengthens the leg (:attr:`TermSource.lengthens`)."""
        return tuple(row for row, term in enumerate(self.terms) if TERM_SOURCES[term.source].lengthens)

    # ------------------------------------------------------------------ layout

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """The names of δM (paper order)."""
        return self.legs.parameter_names

    @property
    def n_params(self) -> int:
        """Entries of δM, the legs' geometry: the first entries of ``x_drive`` (42 prismatic, 66 rotary)."""
        return self.legs.n_params

    @property
    def unknown_terms(self) -> tuple[LegTerm, ...]:
        return tuple(self.terms[row] for row, _ in self._unknown)

    @property
    def blocks(self) -> tuple[UnknownBlock, ...]:
        """The unknown blocks after δM, in the order of ``x_drive``."""
        return tuple(term.block() for term in self.unknown_terms)

    @property
    def rows(self) -> int:
        """Rows of its residual per sample: one per leg."""
        return self.legs.n_legs

    @property
    def size(self) -> int:
        """Entries of ``x_drive``: δM's + one per leg per unknown term."""
        return self.legs.n_params + self.legs.n_legs * len(self._unknown)

    @property
    def input_width(self) -> int:
        """Columns of a sample's drive inputs ``u``."""
        return max(term.input_start + N_LEGS for term in self.terms)

    @property
    def channels(self) -> tuple[str, ...]:
        """The input channels its terms read (:data:`TERM_SOURCES`), those a log must carry first."""
        names: list[str] = []
        for term in self.terms:
            for name in TERM_SOURCES[term.source].channels:
                if name not in names:
                    names.append(name)
        return tuple(names)

    @property
    def required_channels(self) -> tuple[str, ...]:
        """The channels without which its inputs cannot be formed (a leg's temperature under ``[thermal]``)."""
        return tuple(name for term in self.terms for name in TERM_SOURCES[term.source].required)

    @property
    def needs_pose(self) -> bool:
        """Whether a term's inputs depend on the pose (the leg forces): forward kinematics then settles."""
        return any(TERM_SOURCES[term.source].needs_pose for term in self.terms)

    def inputs(
        self, strokes: np.ndarray, channels: Inputs | None = None, R: np.ndarray | None = None, t=None, x_drive=None
    ) -> np.ndarray:
        """The drive inputs ``u (..., input_width)`` of samples with logged ``strokes`` ``(..., 6)`` and
        input ``channels`` (a sample's or a log's ``inputs``; None: none), each term's six columns in
        term order from its source (:data:`TERM_SOURCES`): the strokes; an elastic drive's leg forces
        [N] at poses ``(R, t)`` (:meth:`leg_forces`); a drive with ``[thermal]`` each leg's
        ``(T_i − T_ref) · 1e-6 · L_i`` [mm per ppm/K].

        The forces are taken at the pose given — the measured one where the instrument fixes a pose,
        else the drive's own forward kinematics (:meth:`settled_kinematics`) — on the nominal legs:
        both are off the truth by what the calibration corrects, some 1e-3 of the arms, so the
        forces by ~1e-3 relative, ~0.1 µm of ``c·f`` at 1 mm/kN and 100 N (tests/test_elastic.py).

        Raises:
            ValueError: a term needs the pose and none is given, or a channel the samples lack.
        """
        strokes = np.asarray(strokes, dtype=float)
        if len(self.terms) == 1:
            return strokes
        if self.needs_pose and (R is None or t is None):
            raise ValueError("an elastic drive's inputs need the poses its leg forces are taken at")
        return self._inputs(strokes, channels or {}, R, t, x_drive)

    def _inputs(self, strokes: np.ndarray, channels: Inputs, R, t, x_drive) -> np.ndarray:
        """:meth:`inputs`, the pose-dependent columns 0 where ``R`` is None."""
        parts = []
        for term in self.terms:
            source = TERM_SOURCES[term.source]
            if source.needs_pose and R is None:
                parts.append(np.zeros_like(strokes))
            else:
                part = source.inputs(self, strokes, channels, R, t, x_drive)
                parts.append(np.broadcast_to(part, np.broadcast_shapes(np.shape(part), strokes.shape)))
        shape = np.broadcast_shapes(*(np.shape(part) for part in parts))
        return np.concatenate([np.broadcast_to(part, shape) for part in parts], axis=-1)

    def inputs_near(self, strokes: np.ndarray, channels: Inputs | None = None, pose=None, x_drive=None) -> np.ndarray:
        """:meth:`inputs` at ``pose = (R, t)`` where one is known near the samples' (a warm start),
        else with no force: a first guess for forward kinematics, whose pose then gives the inputs."""
        strokes = np.asarray(strokes, dtype=float)
        if pose is not None or not self.needs_pose:
            R, t = (None, None) if pose is None else pose
            return self.inputs(strokes, channels, R, t, x_drive)
        return self._inputs(strokes, channels or {}, None, None, x_drive)

    def channel_default(self, name: str) -> np.ndarray:
        """What its terms take for channel ``name`` where a sample lacks it: gravity along ``[elastic]
        gravity`` (−z without it), the others :data:`CHANNEL_DEFAULTS` (no payload: 0 kg)."""
        if name == GRAVITY:
            return np.array(DOWN if self.elastic is None else self.elastic.gravity, dtype=float)
        return np.full(CHANNEL_SHAPES[name], CHANNEL_DEFAULTS[name])

    def gravity(self, channels: Inputs | None = None) -> np.ndarray:
        """``(..., 3)`` the unit vector in {J} gravity acts along for samples of ``channels``: their
        ``gravity`` channel (a tilting mount, spec §17), a sample without one (NaN in a buffer of
        samples, :func:`~stewart_calib.samples.packed_inputs`) and samples without the channel at
        :meth:`channel_default`. Taken as given: a log's rows and ``[elastic] gravity`` are normalised
        where they are read (:mod:`stewart_calib.io`), and a longer vector here is a heavier platform."""
        default = self.channel_default(GRAVITY)
        given = (channels or {}).get(GRAVITY)
        if given is None:
            return default
        given = np.asarray(given, dtype=float)
        missing = np.isnan(given)
        return np.where(missing, default, given) if missing.any() else given

    def leg_forces(self, R: np.ndarray, t: np.ndarray, channels: Inputs | None = None, x_drive=None) -> np.ndarray:
        """``(..., 6)`` axial forces [N] of the nominal legs holding the platform and the payload of the
        samples' ``load_kg`` channel (scalar or ``(...)``; absent: 0) at poses ``(R, t)`` (spec §10), under
        gravity along their ``gravity`` channel (:meth:`gravity`; spec §17)."""
        e = self.elastic
        if e is None:
            raise ValueError("a rigid drive carries no leg forces")
        batch = np.shape(t)[:-1]
        payload = (channels or {}).get(LOAD_KG)
        masses, coms = masses_and_centres(
            e.platform_mass_kg, e.platform_com_mm, 0.0 if payload is None else payload, e.payload_com_mm, batch
        )
        return gravity_leg_forces(self.prismatic(x_drive), R, t, masses, coms, self.gravity(channels))

    def payload_leg_forces(
        self, R: np.ndarray, t: np.ndarray, x_drive=None, channels: Inputs | None = None
    ) -> np.ndarray:
        """``(..., 6)`` leg forces [N] per kg of payload at ``[elastic] payload_com_mm`` under the gravity
        of ``channels`` (:meth:`gravity`): the forces are linear in the masses, so a payload ``m`` adds
        ``m`` times these to :meth:`leg_forces`."""
        e = self.elastic
        if e is None:
            raise ValueError("a rigid drive carries no leg forces")
        batch = np.shape(t)[:-1]
        down = self.gravity(channels)
        return gravity_leg_forces(self.prismatic(x_drive), R, t, np.ones(batch + (1,)), e.payload_com_mm[None], down)

    @property
    def pose_channels(self) -> tuple[str, ...]:
        """The channels that the pose-dependent terms read (:meth:`reposed` takes them again)."""
        return tuple(
            dict.fromkeys(
                name
                for term in self.terms
                if TERM_SOURCES[term.source].needs_pose
                for name in TERM_SOURCES[term.source].channels
            )
        )

    def packed_pose_channels(self, channels: Inputs | None) -> np.ndarray:
        """A sample's :attr:`pose_channels` as one flat float vector, a channel it lacks at what the
        terms take for it (:meth:`channel_default`: no payload, 0 kg; gravity along ``[elastic] gravity``):
        how a filter keeps them beside its prepared inputs (:meth:`unpacked_pose_channels` reads it back)."""
        channels = channels or {}
        parts = [
            self.channel_default(name) if channels.get(name) is None else channels[name] for name in self.pose_channels
        ]
        return np.concatenate([np.ravel(np.asarray(part, dtype=float)) for part in parts]) if parts else np.zeros(0)

    @property
    def packed_width(self) -> int:
        """Entries of :meth:`packed_pose_channels`."""
        return sum(int(np.prod(CHANNEL_SHAPES[name], dtype=int)) for name in self.pose_channels)

    def unpacked_pose_channels(self, packed: np.ndarray) -> dict[str, np.ndarray]:
        """:meth:`packed_pose_channels` back."""
        channels, start = {}, 0
        for name in self.pose_channels:
            shape = CHANNEL_SHAPES[name]
            width = int(np.prod(shape, dtype=int))
            channels[name] = np.asarray(packed[start : start + width], dtype=float).reshape(shape)
            start += width
        return channels

    def reposed(
        self, inputs: np.ndarray, channels: Inputs | None, R: np.ndarray, t: np.ndarray, x_drive=None
    ) -> np.ndarray:
        """``inputs`` with the pose-dependent terms' columns (the leg forces) taken again at ``(R, t)``."""
        out = np.array(inputs, dtype=float)
        for term in self.terms:
            source = TERM_SOURCES[term.source]
            if source.needs_pose:
                columns = slice(term.input_start, term.input_start + N_LEGS)
                out[..., columns] = source.inputs(self, out[..., :N_LEGS], channels or {}, R, t, x_drive)
        return out

    def force_columns(self) -> slice:
        """The six columns of ``u`` that hold the leg forces (the compliance term's)."""
        start = next(term.input_start for term in self.terms if term.source == "leg_forces")
        return slice(start, start + N_LEGS)

    def loaded_inputs(self, inputs: np.ndarray, per_kg: np.ndarray, payload_kg: float) -> np.ndarray:
        """``inputs`` with ``payload_kg`` more payload: its leg forces (:meth:`payload_leg_forces`,
        ``per_kg``) added to the force columns."""
        loaded = np.array(inputs, dtype=float)
        loaded[..., self.force_columns()] += payload_kg * np.asarray(per_kg)
        return loaded

    def force_gains(self, x_drive: np.ndarray | None = None) -> np.ndarray:
        """``(6,)`` ``∂e_i/∂f_i`` [mm/N] of the leg forces at ``x_drive``: ``−c_i / 1000``."""
        gains = np.zeros(N_LEGS)
        for term, factor in zip(self.terms, self._term_factors(x_drive), strict=True):
            if term.source == "leg_forces":
                gains = gains + factor * term.gain
        return gains

    def settled_kinematics(
        self,
        strokes: np.ndarray,
        channels: Inputs | None = None,
        x_drive: np.ndarray | None = None,
        guess=None,
        strict: bool = True,
    ) -> tuple[kin.FKSolution, np.ndarray]:
        """``(forward kinematics, the inputs at its poses)`` of logged ``strokes (N, 6)``: for an
        elastic drive the fixed point of forces ↔ pose, as the loaded robot settles, passes until no
        extension moves by :data:`SETTLED_MM`. An industrial robot's forces change with the pose by
        ~1e-3 of themselves per mm, so each pass gains three orders (2–3 passes); a hobby robot's
        legs of 150 mm/kN under a payload of twice the platform's weight gain one order a pass (two
        passes leave 0.13 mm there, benchmarks/hobby.py's soft legs with 5 kg)."""
        strokes = np.asarray(strokes, dtype=float)
        if not self.needs_pose:
            inputs = self.inputs(strokes, channels)
            return self.forward_kinematics(inputs, x_drive, guess=guess, strict=strict), inputs
        inputs = self.inputs_near(strokes, channels, guess, x_drive)
        extension = self.extensions(inputs, x_drive)
        for _ in range(SETTLING_PASSES):
            sol = self.forward_kinematics(inputs, x_drive, guess=guess, strict=strict)
            guess = (sol.R, sol.t)
            inputs = self.inputs(strokes, channels, sol.R, sol.t, x_drive)
            previous, extension = extension, self.extensions(inputs, x_drive)
            moved = np.abs(extension - previous)
            if not np.any(moved > SETTLED_MM):  # NaN (a pose FK did not reach, strict=False): nothing to settle
                break
        return self.forward_kinematics(inputs, x_drive, guess=guess, strict=strict), inputs

    # ------------------------------------------------------------------ values

    def parameter_error(self, x_drive: np.ndarray) -> np.ndarray:
        """δM: the leg parameters' part of ``x_drive`` (or of an unknown vector that starts with it)."""
        return np.asarray(x_drive)[: self.legs.n_params]

    def prior_sigmas(self, noise: NoiseConfig) -> np.ndarray:
        """``(n_params,)`` prior σ of δM, entry by entry, as the leg model gives it (code units)."""
        return self.legs.prior_sigmas(noise)

    def walk_sigmas(self, noise: NoiseConfig) -> np.ndarray:
        """``(n_params,)`` random walk of δM [code units/√s], entry by entry, as the leg model gives it."""
        return self.legs.walk_sigmas(noise)

    def coordinate_sigma(self, noise: NoiseConfig) -> float:
        """σ of one logged drive coordinate (code units): the stroke's [mm], a servo angle's [rad]."""
        return self.legs.coordinate_sigma(noise)

    def prismatic(self, x_drive: np.ndarray | None = None) -> LegGeometry:
        """:meth:`geometry` where the legs are prismatic (:class:`~stewart_calib.model.platform.LegGeometry`):
        what the compiled kernels and the statics of an elastic drive take.

        Raises:
            ValueError: legs of another kind.
        """
        legs = self.geometry(x_drive)
        if not isinstance(legs, LegGeometry):
            raise ValueError(f"the compiled kernels and the statics model prismatic legs, not {legs.kind}")
        return legs

    def geometry(self, x_drive: np.ndarray | None = None) -> LegModel:
        """``M + δM`` (the nominal legs for None). Legs without compiled kernels keep the last one: a
        graph's factors are linearised at one ``x_drive`` each (a rotary set's ``perturbed`` turns 12 axes
        and zero directions, a third of a factor's cost)."""
        if x_drive is None:
            return self.legs
        delta = self.parameter_error(x_drive)
        if self.legs.compiled:
            return self.legs.perturbed(delta)
        key = np.asarray(delta, dtype=float).tobytes()
        last_key, legs = self._last_geometry
        if key != last_key:
            legs = self.legs.perturbed(delta)
            object.__setattr__(self, "_last_geometry", (key, legs))
        return legs

    def term_values(self, x_drive: np.ndarray | None = None) -> np.ndarray:
        """``(terms, 6)`` absolute values ``v`` of every term: nominal, plus the error in ``x_drive``."""
        if x_drive is None or not self._unknown:
            return self._nominal
        values = self._nominal.copy()
        for row, columns in self._unknown:
            values[row] = self._nominal[row] + np.asarray(x_drive)[columns]
        return values

    def _term_factors(self, x_drive: np.ndarray | None) -> np.ndarray:
        """``(terms, 6)`` ``o_b + v_b`` at ``x_drive``."""
        if x_drive is None or not self._unknown:
            return self._factors
        return np.array([term.offset for term in self.terms])[:, None] + self.term_values(x_drive)

    def extensions(self, inputs: np.ndarray, x_drive: np.ndarray | None = None) -> np.ndarray:
        """``e = Σ_b (o_b + v_b) g_b u_b``, ``(..., 6)`` (the legs' coordinates: [mm] prismatic, [rad]
        rotary), at ``x_drive`` (None: nominal values), over the terms but those of the
        :meth:`lengthening`."""
        return self._sum(inputs, x_drive, lengthening=False)

    def lengthening(self, inputs: np.ndarray, x_drive: np.ndarray | None = None) -> np.ndarray | None:
        """``Δℓ = Σ_b (o_b + v_b) g_b u_b`` ``(..., 6)`` [mm] over the terms that lengthen legs whose
        coordinate is no length (a rotary leg's rod grown with its temperature), at ``x_drive``; None
        where there are none (prismatic legs: :meth:`extensions` holds them)."""
        return self._sum(inputs, x_drive, lengthening=True) if self._lengthening else None

    def _sum(self, inputs: np.ndarray, x_drive: np.ndarray | None, lengthening: bool) -> np.ndarray:
        """:meth:`extensions` (``lengthening`` False) or :meth:`lengthening`'s sum."""
        inputs = np.asarray(inputs, dtype=float)
        parts = []
        for row, (term, factor) in enumerate(zip(self.terms, self._term_factors(x_drive), strict=True)):
            if (row in self._lengthening) != lengthening:
                continue
            u = inputs[..., term.input_start : term.input_start + N_LEGS]
            parts.append(factor * (u if term.gain == 1.0 else term.gain * u))
        out = parts[0]
        for part in parts[1:]:  # in term order, as the compiled leg_extensions sums them
            out = out + part
        return out

    def extension_per_stroke(self, x_drive: np.ndarray | None = None) -> np.ndarray:
        """``(6,)`` ``∂e_i/∂q_i`` (the stroke noise's gain into the leg): ``1 + k_i``."""
        return self._term_factors(x_drive)[self._stroke]

    def stroke_gains(self, x_drive: np.ndarray | None, R: np.ndarray, t: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """``(..., n)`` ``∂r_i/∂q_i = J_e,i (1 + k_i)`` at poses ``(R, t)``: a logged coordinate's gain into
        its leg's residual (prismatic legs: ``−(1 + k_i)``, whatever the pose)."""
        per_stroke = self.extension_per_stroke(x_drive)
        if self.legs.compiled:
            return -per_stroke
        extensions, lengthening = self.extensions(inputs, x_drive), self.lengthening(inputs, x_drive)
        _, _, J_e = self.geometry(x_drive).residual_jacobians(R, t, extensions, lengthening=lengthening)
        return J_e * per_stroke

    def identifying(self, prior_sigma: float = BLOCK_PRIOR_SIGMA) -> DriveModel:
        """The same drive with every term an unknown block of prior σ ``prior_sigma`` — the compliance
        and the expansion with their tables' own σ (mm/kN and ppm/K, not a fraction; held where 0)."""
        terms = tuple(
            compliance_term(self.elastic)
            if term.key == COMPLIANCE and self.elastic is not None
            else thermal_term(self.thermal, term.input_start)
            if term.key == THERMAL and self.thermal is not None
            else replace(term, prior_sigma=prior_sigma)
            for term in self.terms
        )
        return replace(self, terms=terms)

    def onto(self, platform: Platform) -> Platform:
        """``platform`` with this drive's legs and its terms' values (a term's key names the
        platform's field of its nominal values, as the platform file's ``[drive]`` table does; the
        compliance goes to ``[elastic] compliance_mm_per_kN``, the expansion to ``[thermal]
        expansion_ppm_per_K``)."""
        tables = (COMPLIANCE, THERMAL)
        fields: dict[str, Any] = {term.key: term.nominal.copy() for term in self.terms if term.key not in tables}
        platform = replace(platform, drive=self.legs, **fields)  # type: ignore[arg-type]  # any leg kind
        for term in self.terms:
            if term.key == COMPLIANCE and platform.elastic is not None:
                elastic = replace(platform.elastic, compliance_mm_per_kN=term.nominal.copy())
                platform = replace(platform, elastic=elastic)
            if term.key == THERMAL and platform.thermal is not None:
                platform = replace(platform, thermal=replace(platform.thermal, expansion_ppm_per_K=term.nominal.copy()))
        return platform

    def calibrated_by(self, estimate) -> DriveModel:
        """:meth:`calibrated` with an :class:`~stewart_calib.estimate.Estimate`'s δM and the values of
        the blocks it identified."""
        return self.calibrated(estimate.error, {term.key: estimate.block_values(term.key) for term in self.terms})

    def calibrated(self, error: np.ndarray, values: Mapping[str, np.ndarray | None]) -> DriveModel:
        """The drive ``M + error`` with the terms' nominal values replaced by ``values[key]``
        (absolute; a key absent or None keeps the nominal), all known: what a calibration identified."""
        terms = tuple(
            replace(term, nominal=np.asarray(values[term.key], dtype=float), prior_sigma=None)
            if values.get(term.key) is not None
            else replace(term, prior_sigma=None)
            for term in self.terms
        )
        return DriveModel(self.legs.perturbed(np.asarray(error, dtype=float)), terms, self.elastic, self.thermal)

    def true_drive(self, error: np.ndarray, values: Mapping[str, np.ndarray]) -> DriveModel:
        """:meth:`calibrated` to a simulator's truth (spec §4, §7: its terms' ``values`` by block
        key): a term the truth does not give is 0 there (a robot of exact scale)."""
        return self.calibrated(error, {term.key: values.get(term.key, np.zeros(N_LEGS)) for term in self.terms})

    # ------------------------------------------------------------------ residual and Jacobians

    def residual(self, x_drive: np.ndarray | None, R: np.ndarray, t: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """``r`` of the legs at poses ``(R, t)``, ``(..., n_legs)`` [mm] (the leg model's residuals)."""
        extensions, lengthening = self.extensions(inputs, x_drive), self.lengthening(inputs, x_drive)
        return self.geometry(x_drive).residuals(R, t, extensions, lengthening=lengthening)

    def jacobians(
        self, x_drive: np.ndarray | None, R: np.ndarray, t: np.ndarray, inputs: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(∂r/∂ξ (..., n, 6), ∂r/∂x_drive (..., n, size))``, body tangent ``ξ = [ω, v]``."""
        if self.legs.compiled:  # J_e = −1 and no extension needed: the compiled kinematics' Jacobians alone
            J_pose, J_M = kin.leg_residual_jacobians(self.prismatic(x_drive), R, t)
            return J_pose, self.with_terms(J_M, inputs)
        extensions, lengthening = self.extensions(inputs, x_drive), self.lengthening(inputs, x_drive)
        _, J_pose, J_M, J_e = self.leg_rows(x_drive, R, t, extensions, lengthening)
        return J_pose, self.with_terms(J_M, inputs, J_e)

    def leg_rows(
        self,
        x_drive: np.ndarray | None,
        R: np.ndarray,
        t: np.ndarray,
        extensions: np.ndarray,
        lengthening: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(r, J_pose, J_M, J_e)``: the leg model's residuals and Jacobians of :meth:`geometry` at
        ``x_drive`` for the legs' ``extensions`` and :meth:`lengthening`, one perturbed set for both."""
        legs = self.geometry(x_drive)
        return (
            legs.residuals(R, t, extensions, lengthening=lengthening),
            *legs.residual_jacobians(R, t, extensions, lengthening=lengthening),
        )

    def with_terms(self, J_M: np.ndarray, inputs: np.ndarray, J_e: np.ndarray | None = None) -> np.ndarray:
        """``∂r/∂M (..., n, n_params)`` completed with ``∂r_i/∂v_{b,i} = J_e,i g_b u_{b,i}`` of the
        unknown terms (``−g_b u_{b,i}`` of a term of the :meth:`lengthening`, which enters a leg as its
        fixed length does): ``∂r/∂x_drive (..., n, size)`` (``J_M`` itself where there are none).

        Args:
            J_e: ``(..., n)`` the leg model's ``∂r_i/∂e_i``; None: −1, a prismatic leg's.
        """
        rows = self._unknown
        if not rows:
            return J_M
        inputs = np.asarray(inputs, dtype=float)
        n_legs, n_params = self.legs.n_legs, self.legs.n_params
        J = np.zeros((*J_M.shape[:-1], self.size))
        J[..., :n_params] = J_M
        legs = np.arange(n_legs)
        for row, columns in rows:
            term = self.terms[row]
            u = inputs[..., term.input_start : term.input_start + n_legs]
            gained = u if term.gain == 1.0 else term.gain * u
            if J_e is None or row in self._lengthening:  # ∂r_i/∂e_i of a prismatic leg, or ∂r_i/∂Δℓ_i: −1
                J[..., legs, columns.start + legs] = -gained
            else:
                J[..., legs, columns.start + legs] = J_e * gained
        return J

    def extension_jacobian(self, inputs: np.ndarray) -> np.ndarray:
        """``∂e/∂(the unknown terms' errors)`` ``(..., 6, size − 42)``: ``g_b u_{b,i}`` on leg i's own
        value of each unknown term (the extension enters a leg as its initial length does)."""
        inputs = np.asarray(inputs, dtype=float)
        n_params = self.legs.n_params
        return -self.with_terms(np.zeros((*inputs.shape[:-1], self.legs.n_legs, n_params)), inputs)[..., n_params:]

    def pose_jacobian(self, x_drive: np.ndarray | None, R: np.ndarray, t: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """``∂ξ/∂x_drive (..., 6, size)`` of forward-kinematics poses ``(R, t)``: by the implicit
        function theorem on ``r(ξ; x) = 0``, ``−(∂r/∂ξ)⁻¹ ∂r/∂x``.

        Raises:
            numpy.linalg.LinAlgError: a pose at a singularity of the drive (``∂r/∂ξ`` singular).
        """
        J_pose, J_x = self.jacobians(x_drive, R, t, inputs)
        return -np.linalg.solve(J_pose, J_x)

    def settled_pose_jacobian(
        self,
        x_drive: np.ndarray | None,
        R: np.ndarray,
        t: np.ndarray,
        inputs: np.ndarray,
        channels: Inputs | None = None,
    ) -> np.ndarray:
        """:meth:`pose_jacobian` of :meth:`settled_kinematics`' poses, whose leg forces move with the
        pose and the joints: ``r(ξ; x, f(ξ, M)) = 0``, so ``∂r/∂ξ`` and ``∂r/∂M`` gain
        ``(∂r/∂f) ∂f/∂ξ`` and ``(∂r/∂f) ∂f/∂M`` (:func:`~stewart_calib.model.statics.leg_force_jacobians`).
        They are ~1e-3 of the rows they join, but a batch fit's weakest directions (compliance against
        the leg offsets, condition ~1e6) are where that shows: without them ``ls`` creeps along that
        valley and stops at its 200 evaluations on a simulated hobby hexapod (benchmarks/hobby.py,
        soft-legs seed 0). A rigid drive: :meth:`pose_jacobian`."""
        if self.elastic is None:
            return self.pose_jacobian(x_drive, R, t, inputs)
        from .statics import leg_force_jacobians

        payload_kg = (channels or {}).get(LOAD_KG)
        down = self.gravity(channels)

        J_pose, J_x = self.jacobians(x_drive, R, t, inputs)
        row = next(row for row, term in enumerate(self.terms) if term.key == COMPLIANCE)
        term = self.terms[row]
        forces = np.asarray(inputs, dtype=float)[..., term.input_start : term.input_start + N_LEGS]
        e = self.elastic
        masses, coms = masses_and_centres(
            e.platform_mass_kg,
            e.platform_com_mm,
            0.0 if payload_kg is None else payload_kg,
            e.payload_com_mm,
            np.shape(t)[:-1],
        )
        df_dxi, df_dM = leg_force_jacobians(self.prismatic(x_drive), R, t, forces, masses, coms, down)
        dr_df = (-term.gain * self._term_factors(x_drive)[row])[:, None]  # r = ‖…‖ − (l + e): ∂r_i/∂f_i = −(o + c_i) g
        J_pose = J_pose + dr_df * df_dxi
        J_x = J_x.copy()
        J_x[..., : self.legs.n_params] += dr_df * df_dM
        return -np.linalg.solve(J_pose, J_x)

    def observation(
        self,
        x_drive: np.ndarray,
        R: np.ndarray,
        t: np.ndarray,
        inputs: np.ndarray,
        pose_covariance: np.ndarray,
        coordinate_sigma: float,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The EKF's observation at a pose ``(R, t)`` measured with covariance ``Σ_x``: ``(r (n,),
        ∂r/∂x_drive (n, size), J_x Σ_x J_xᵀ + diag(J_e² σ_e²), J_x = ∂r/∂ξ)`` with ``σ_e``
        (``coordinate_sigma``, :meth:`coordinate_sigma`) the σ of one logged coordinate; one compiled
        call for compiled legs (:func:`~stewart_calib.model.kinematics.leg_ekf_observation`, ``J_e = −1``)."""
        extensions = self.extensions(inputs, x_drive)
        if self.legs.compiled:
            r, H_M, R_meas, J_x = kin.leg_ekf_observation(
                self.prismatic(), self.parameter_error(x_drive), R, t, extensions, pose_covariance, coordinate_sigma
            )
            return r, self.with_terms(H_M, inputs), R_meas, J_x
        r, J_x, H_M, J_e = self.leg_rows(x_drive, R, t, extensions, self.lengthening(inputs, x_drive))
        R_meas = J_x @ pose_covariance @ J_x.T + np.diag((J_e * coordinate_sigma) ** 2)
        return r, self.with_terms(H_M, inputs, J_e), R_meas, J_x

    # ------------------------------------------------------------------ kinematics

    def forward_kinematics(
        self,
        inputs: np.ndarray,
        x_drive: np.ndarray | None = None,
        guess=None,
        strict: bool = True,
        tol_mm: float = kin.FK_TOLERANCE_MM,
    ) -> kin.FKSolution:
        """Poses of samples ``inputs (..., width)`` (the leg model's forward kinematics)."""
        return self.geometry(x_drive).forward_kinematics(
            self.extensions(inputs, x_drive),
            guess=guess,
            tol_mm=tol_mm,
            strict=strict,
            lengthening=self.lengthening(inputs, x_drive),
        )

    def solve_fk(
        self, inputs: np.ndarray, x_drive: np.ndarray | None, guess, what: str = "drive model"
    ) -> tuple[np.ndarray, np.ndarray]:
        """One sample's pose from ``guess``, then cold (the leg model's ``solve_fk``);
        ``SampleRejected`` when neither converges."""
        extensions, lengthening = self.extensions(inputs, x_drive), self.lengthening(inputs, x_drive)
        return self.geometry(x_drive).solve_fk(extensions, guess, what, lengthening=lengthening)

    def inverse_kinematics(
        self,
        R: np.ndarray,
        t: np.ndarray,
        x_drive: np.ndarray | None = None,
        inputs: np.ndarray | None = None,
        channels: Inputs | None = None,
    ) -> np.ndarray:
        """The strokes ``q (..., n)`` (the log's drive coordinates) that put the platform at ``(R, t)``:
        the legs' coordinates (the leg model's inverse kinematics, NaN where a leg cannot reach) less
        the other terms' part, over the stroke term's ``1 + k_i``.

        Args:
            inputs: ``(..., width)`` the samples' other drive inputs (their stroke columns are
                ignored); needed only where the drive has terms besides the stroke. Default: the
                inputs of the samples' ``channels`` at ``(R, t)`` (the leg forces there) and at the
                strokes of the stroke term alone (a leg's length for its growth with temperature,
                which the strokes then change by its growth times α ΔT, 1e-9 of it). Legs that take
                a :meth:`lengthening` are solved again with it.
        """
        legs = self.geometry(x_drive)
        coordinates = legs.coordinates(R, t)
        if inputs is None and len(self.terms) > 1:
            first = coordinates / self._term_factors(x_drive)[self._stroke]
            inputs = self.inputs(first, channels, R, t, x_drive)
        if self._lengthening:
            if inputs is None:
                raise ValueError("inverse kinematics of this drive needs the inputs of its lengthening")
            coordinates = legs.coordinates(R, t, lengthening=self.lengthening(inputs, x_drive))
        return self.strokes_for(coordinates, x_drive, inputs)

    def strokes_for(
        self, extensions: np.ndarray, x_drive: np.ndarray | None = None, inputs: np.ndarray | None = None
    ) -> np.ndarray:
        """The strokes ``q (..., 6)`` that put the legs at the coordinates ``extensions`` ``e (..., 6)``
        ([mm] prismatic, [rad] rotary): ``e`` less the other terms' part (those of :meth:`extensions`:
        a :meth:`lengthening` is no part of ``e``), over the stroke term's ``1 + k_i`` (``inputs`` as
        :meth:`inverse_kinematics` takes them)."""
        factors = self._term_factors(x_drive)
        for row, (term, factor) in enumerate(zip(self.terms, factors, strict=True)):
            if row == self._stroke or row in self._lengthening:
                continue
            if inputs is None:
                raise ValueError(f"inverse kinematics of this drive needs the inputs of its term '{term.key}'")
            u = np.asarray(inputs, dtype=float)[..., term.input_start : term.input_start + N_LEGS]
            extensions = extensions - factor * term.gain * u
        return extensions / factors[self._stroke]

    # ------------------------------------------------------------------ compiled code

    def kernel_terms(self, x_drive: np.ndarray | None = None) -> tuple:
        """The terms as compiled code takes them: ``(starts (b,) int64, gains (b,), offsets (b,),
        values (b, 6) at x_drive, columns (b, 6) int64 of their errors in x_drive, −1 where known)``.

        Raises:
            ValueError: legs the compiled kernels do not model (``legs.compiled`` False).
        """
        if not self.legs.compiled:
            raise ValueError(f"the compiled drive kernels model prismatic legs, not {self.legs.kind}")
        columns = np.full((len(self.terms), N_LEGS), -1, dtype=np.int64)
        for row, span in self._unknown:
            columns[row] = np.arange(span.start, span.stop)
        return (
            np.array([term.input_start for term in self.terms], dtype=np.int64),
            np.array([term.gain for term in self.terms], dtype=float),
            np.array([term.offset for term in self.terms], dtype=float),
            np.array(self.term_values(x_drive)),  # writable: one compiled signature
            columns,
        )


def tracker_reading_residuals(
    drives: list[DriveModel],
    tracker: LegGeometry,
    strokes: np.ndarray,
    readings: np.ndarray,
    channels: Inputs | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The tracker's ``readings (N, 6)`` minus what it reads where each of ``drives`` (the same terms,
    e.g. the nominal and a calibrated one) puts the platform for the logged ``strokes (N, 6)``, in one
    compiled pass (:func:`~stewart_calib.model.kinematics.tracker_reading_residuals`): elastic drives
    settled under the platform and the payload of the log's ``channels`` (``load_kg`` ``(N,)`` [kg]; absent: 0),
    gravity along their ``gravity`` (``(N, 3)``; absent: ``[elastic] gravity``, :meth:`DriveModel.gravity`), as
    :meth:`DriveModel.settled_kinematics` settles them — the same fixed point, stopped by the same
    :data:`SETTLED_MM`, per sample — by the simulator's compiled settling
    (:func:`~stewart_calib.model._kernels.settle_pose`) with the joints rigid and the compliance the term
    on the forces. ``(residuals (m, N, 6) [mm], converged (m, N))``."""
    kernel_terms = [drive.kernel_terms() for drive in drives]
    starts, gains = kernel_terms[0][:2]
    terms = (starts, gains, np.array([offsets[:, None] + values for _, _, offsets, values, _ in kernel_terms]))
    legs, elastic = [drive.prismatic() for drive in drives], drives[0].elastic
    inputs = [drive.inputs_near(strokes, channels) for drive in drives]  # an elastic drive's forces 0 until settled
    if elastic is None or not any(np.any(drive.force_gains()) for drive in drives):
        # rigid, or no leg gives under its force (the nominal compliance 0, before a calibration): the
        # first FK is where each settles, and the forces need not be solved for
        return kin.tracker_reading_residuals(tracker, readings, legs, inputs, terms)
    payload_kg = (channels or {}).get(LOAD_KG)
    masses, centres = masses_and_centres(
        elastic.platform_mass_kg,
        elastic.platform_com_mm,
        0.0 if payload_kg is None else payload_kg,
        elastic.payload_com_mm,
        (len(readings),),
    )
    force_start = drives[0].force_columns().start
    radii = np.array([moment_radius(drive.prismatic()) for drive in drives])
    downs = np.broadcast_to(drives[0].gravity(channels), (len(readings), 3))
    load = (force_start, masses * G_N_PER_KG, downs, centres, radii, SETTLING_PASSES + 1, SETTLED_MM)
    return kin.tracker_reading_residuals(tracker, readings, legs, inputs, terms, load)


def plain_drive(legs: LegModel) -> DriveModel:
    """``legs`` whose strokes are their length changes (stroke scale 0, no other term)."""
    return DriveModel(legs, (stroke_term(np.zeros(N_LEGS)),))


def drive_model(platform: Platform, noise: NoiseConfig | None = None, outside_instrument: bool = False) -> DriveModel:
    """The drive of ``platform``: its legs, the stroke term about ``[drive] stroke_scale``, unknown
    when ``noise.stroke_scale_sigma`` > 0 or, with an instrument outside the robot, always
    (:data:`STROKE_SCALE_SIGMA_OUTSIDE` by default), and with ``[elastic]`` the legs' compliance
    (:func:`compliance_term`, its σ from ``[elastic]``), with ``[thermal]`` the legs' expansion
    (:func:`thermal_term`, its σ from ``[thermal]``); all terms known without ``noise``."""
    if platform.elastic is not None and platform.drive.kind != "prismatic":
        raise CalibError(
            f"{platform.source}: [elastic] models prismatic legs' compliance; "
            f"a {platform.drive.kind} drive takes no [elastic] table (yet)"
        )
    sigma = 0.0 if noise is None else noise.stroke_scale_sigma
    if sigma <= 0.0 and outside_instrument:
        sigma = STROKE_SCALE_SIGMA_OUTSIDE
    terms: tuple[LegTerm, ...] = (stroke_term(platform.stroke_scale, sigma if sigma > 0.0 else None),)
    if platform.elastic is not None:
        compliance = compliance_term(platform.elastic)
        terms += (compliance if noise is not None else replace(compliance, prior_sigma=None),)
    if platform.thermal is not None:
        thermal = thermal_term(platform.thermal, N_LEGS * len(terms))
        terms += (thermal if noise is not None else replace(thermal, prior_sigma=None),)
    return DriveModel(platform.drive, terms, platform.elastic, platform.thermal)


@dataclass(frozen=True)
class TermSource:
    """What a term's six inputs are: a function of the samples' strokes, input channels, poses and the
    drive, and what it reads.

    Attributes:
        inputs: ``(drive, strokes (..., 6), channels, R, t, x_drive) → (..., 6)``.
        channels: the input channels it reads (:class:`~stewart_calib.samples.Log` ``inputs``).
        required: those of them it cannot do without.
        needs_pose: whether it reads the pose (then forward kinematics settles, :meth:`DriveModel.settled_kinematics`).
        lengthens: whether its term adds to each leg's length from joint to joint (the expansion):
            part of the leg's coordinate where that is a length, else the leg model's lengthening
            (:meth:`DriveModel.lengthening`).
    """

    inputs: Any
    channels: tuple[str, ...] = ()
    required: tuple[str, ...] = ()
    needs_pose: bool = False
    lengthens: bool = False


def _thermal_inputs(drive: DriveModel, strokes: np.ndarray, channels: Inputs, R, t, x_drive) -> np.ndarray:
    """``(T_i − T_ref) · 1e-6 · L_i`` [mm per ppm/K] with ``L_i`` the nominal leg's length from joint
    to joint at the strokes' nominal extension (:func:`thermal_term`); 0 without temperatures (the
    legs at the reference: a log's rows are refused before, :attr:`DriveModel.required_channels`)."""
    if drive.thermal is None:
        raise ValueError("a drive without [thermal] takes no temperatures")
    temperature = channels.get(TEMPERATURE_C)
    if temperature is None:  # a pose list, a command without a temperature: the reference (spec §17)
        return np.zeros_like(strokes)
    extension = strokes * drive.extension_per_stroke()
    lengths = drive.legs.joint_lengths(extension)
    return (np.asarray(temperature, dtype=float) - drive.thermal.reference_temperature_C) * 1e-6 * lengths


#: every term's source by its key (:attr:`LegTerm.source`): adding a drive input is one entry here
#: and one line where the log's columns are parsed (:mod:`stewart_calib.io.logs`)
TERM_SOURCES: dict[str, TermSource] = {
    "strokes": TermSource(lambda drive, strokes, channels, R, t, x_drive: strokes),
    "leg_forces": TermSource(
        lambda drive, strokes, channels, R, t, x_drive: drive.leg_forces(R, t, channels, x_drive),
        channels=(LOAD_KG, GRAVITY),
        needs_pose=True,
    ),
    "thermal": TermSource(_thermal_inputs, channels=(TEMPERATURE_C,), required=(TEMPERATURE_C,), lengthens=True),
}
