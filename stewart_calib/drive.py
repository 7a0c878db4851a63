"""The drive as one model: its legs, its unknown blocks, its per-sample inputs, its residual.

Every estimator, factor and analysis talks to the drive only through a :class:`DriveModel`, as
it talks to the instrument only through an :class:`~stewart_calib.instruments.InstrumentModel`:
none of them names a block of the drive. Drive leg i (paper eq. 1, spec §7)::

    r_i = ‖t + R d_i − j_i‖ − (l_i + e_i),     e_i = Σ_b (o_b + v_{b,i}) g_b u_{b,i}

``(j_i, d_i, l_i)`` are the leg's seven parameters ``M + δM`` (paper order); the extension
``e_i`` is a sum of per-leg *terms* (:class:`LegTerm`): term b has an offset ``o_b``, six values
``v_b`` (its nominal from the platform file, plus an error where it is an unknown block) and a
gain ``g_b`` on six columns ``u_b`` of the sample's drive inputs ``u``. The one term today is the
stroke: ``o = 1``, ``v = k`` (the stroke scale), ``g u = q`` (the logged strokes), so
``e_i = (1 + k_i) q_i``. Since every term is linear in its values, ``∂r_i/∂v_{b,i} = −g_b u_{b,i}``.

The unknown vector of a drive is ``x_drive = [δM (42) | the errors of its unknown terms, six
each, in term order]`` (:attr:`DriveModel.size` entries): the first entries of every estimator's
unknown vector (:mod:`stewart_calib.unknowns`), so the drive's Jacobians are its first columns.

Compiled code sees a drive as :meth:`DriveModel.kernel_terms`: ``(starts, gains, offsets, values,
columns)`` of its terms, evaluated by :func:`stewart_calib._kernels.leg_extensions` (the EKF's
fast path, :mod:`stewart_calib.estimators.kalman`) and by the drive-leg factor's kernel
(:mod:`stewart_calib.factors._kernels`). To add a drive error source see docs/architecture.md.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from . import kinematics as kin
from .config import NoiseConfig
from .platform import N_LEGS, N_PARAMS, PARAMETER_NAMES, LegGeometry, Platform
from .unknowns import UnknownBlock

#: the stroke term's key: the result's ``"stroke_scale"`` block (spec §7)
STROKE_SCALE = "stroke_scale"

#: prior σ a drive's blocks declare where the method itself takes no prior (the batch fit, the
#: identifiability and accuracy analyses): only the result's block carries it (10 %)
BLOCK_PRIOR_SIGMA = 0.1

#: prior σ of the stroke scale with an instrument outside the robot when ``noise.stroke_scale_sigma``
#: is 0: such logs come from encoders whose mm per count is the builders' nominal, a few per cent
#: off per leg (issue 13: one leg 6 %), and the frame-and-target fit identifies k alongside
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
    """

    key: str
    names: tuple[str, ...]
    offset: float
    nominal: np.ndarray
    input_start: int
    gain: float = 1.0
    prior_sigma: float | None = None

    def block(self) -> UnknownBlock:
        """The unknown block of its errors (about :attr:`nominal`, σ :attr:`prior_sigma`)."""
        return UnknownBlock(self.key, self.names, self.nominal, np.full(N_LEGS, self.prior_sigma))


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
        legs: the nominal geometry ``M``.
        terms: the extension's terms; those with a ``prior_sigma`` are unknown blocks.
    """

    legs: LegGeometry
    terms: tuple[LegTerm, ...]
    # derived once (a filter asks for them at every sample): see __post_init__
    _unknown: tuple[tuple[int, slice], ...] = field(init=False, repr=False, compare=False)
    _nominal: np.ndarray = field(init=False, repr=False, compare=False)
    _factors: np.ndarray = field(init=False, repr=False, compare=False)
    _stroke: int = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        unknown, start = [], N_PARAMS
        for row, term in enumerate(self.terms):
            if term.prior_sigma is not None:
                unknown.append((row, slice(start, start + N_LEGS)))
                start += N_LEGS
        nominal = np.array([term.nominal for term in self.terms], dtype=float)
        factors = np.array([term.offset + term.nominal for term in self.terms], dtype=float)
        for array in (nominal, factors):
            array.setflags(write=False)
        stroke = next(row for row, term in enumerate(self.terms) if term.input_start == 0)
        for name, value in (("_unknown", tuple(unknown)), ("_nominal", nominal), ("_factors", factors)):
            object.__setattr__(self, name, value)
        object.__setattr__(self, "_stroke", stroke)

    # ------------------------------------------------------------------ layout

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """The 42 names of δM (paper order)."""
        return PARAMETER_NAMES

    @property
    def unknown_terms(self) -> tuple[LegTerm, ...]:
        return tuple(self.terms[row] for row, _ in self._unknown)

    @property
    def blocks(self) -> tuple[UnknownBlock, ...]:
        """The unknown blocks after δM, in the order of ``x_drive``."""
        return tuple(term.block() for term in self.unknown_terms)

    @property
    def size(self) -> int:
        """Entries of ``x_drive``: 42 + six per unknown term."""
        return N_PARAMS + N_LEGS * len(self._unknown)

    @property
    def input_width(self) -> int:
        """Columns of a sample's drive inputs ``u``."""
        return max(term.input_start + N_LEGS for term in self.terms)

    def inputs(self, strokes: np.ndarray) -> np.ndarray:
        """The drive inputs ``u`` of samples with logged ``strokes`` ``(..., 6)`` [mm]."""
        return np.asarray(strokes, dtype=float)

    # ------------------------------------------------------------------ values

    def parameter_error(self, x_drive: np.ndarray) -> np.ndarray:
        """δM: the leg parameters' part of ``x_drive`` (or of an unknown vector that starts with it)."""
        return np.asarray(x_drive)[:N_PARAMS]

    def geometry(self, x_drive: np.ndarray | None = None) -> LegGeometry:
        """``M + δM`` (the nominal legs for None)."""
        return self.legs if x_drive is None else self.legs.perturbed(self.parameter_error(x_drive))

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
        """``e = Σ_b (o_b + v_b) g_b u_b``, ``(..., 6)`` [mm], at ``x_drive`` (None: nominal values)."""
        inputs = np.asarray(inputs, dtype=float)
        parts = []
        for term, factor in zip(self.terms, self._term_factors(x_drive), strict=True):
            u = inputs[..., term.input_start : term.input_start + N_LEGS]
            parts.append(factor * (u if term.gain == 1.0 else term.gain * u))
        out = parts[0]
        for part in parts[1:]:  # in term order, as the compiled leg_extensions sums them
            out = out + part
        return out

    def extension_per_stroke(self, x_drive: np.ndarray | None = None) -> np.ndarray:
        """``(6,)`` ``∂e_i/∂q_i`` (the stroke noise's gain into the leg): ``1 + k_i``."""
        return self._term_factors(x_drive)[self._stroke]

    def identifying(self, prior_sigma: float = BLOCK_PRIOR_SIGMA) -> DriveModel:
        """The same drive with every term an unknown block of prior σ ``prior_sigma``."""
        return replace(self, terms=tuple(replace(term, prior_sigma=prior_sigma) for term in self.terms))

    def onto(self, platform: Platform) -> Platform:
        """``platform`` with this drive's legs and its terms' values (a term's key names the
        platform's field of its nominal values, as the platform file's ``[drive]`` table does)."""
        values: dict[str, Any] = {term.key: term.nominal.copy() for term in self.terms}
        return replace(platform, drive=self.legs, **values)

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
        return DriveModel(self.legs.perturbed(np.asarray(error, dtype=float)), terms)

    # ------------------------------------------------------------------ residual and Jacobians

    def residual(self, x_drive: np.ndarray | None, R: np.ndarray, t: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """``r`` of the six legs at poses ``(R, t)``, ``(..., 6)`` [mm]."""
        return kin.leg_residuals(self.geometry(x_drive), R, t, self.extensions(inputs, x_drive))

    def jacobians(
        self, x_drive: np.ndarray | None, R: np.ndarray, t: np.ndarray, inputs: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(∂r/∂ξ (..., 6, 6), ∂r/∂x_drive (..., 6, size))``, body tangent ``ξ = [ω, v]``."""
        J_pose, J_M = kin.leg_residual_jacobians(self.geometry(x_drive), R, t)
        return J_pose, self.with_terms(J_M, inputs)

    def with_terms(self, J_M: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """``∂r/∂M (..., 6, 42)`` completed with ``∂r_i/∂v_{b,i} = −g_b u_{b,i}`` of the unknown
        terms: ``∂r/∂x_drive (..., 6, size)`` (``J_M`` itself where there are none)."""
        rows = self._unknown
        if not rows:
            return J_M
        inputs = np.asarray(inputs, dtype=float)
        J = np.zeros((*J_M.shape[:-1], self.size))
        J[..., :N_PARAMS] = J_M
        legs = np.arange(N_LEGS)
        for row, columns in rows:
            term = self.terms[row]
            u = inputs[..., term.input_start : term.input_start + N_LEGS]
            J[..., legs, columns.start + legs] = -(u if term.gain == 1.0 else term.gain * u)
        return J

    def pose_jacobian(self, x_drive: np.ndarray | None, R: np.ndarray, t: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """``∂ξ/∂x_drive (..., 6, size)`` of forward-kinematics poses ``(R, t)``: by the implicit
        function theorem on ``r(ξ; x) = 0``, ``−(∂r/∂ξ)⁻¹ ∂r/∂x``.

        Raises:
            numpy.linalg.LinAlgError: a pose at a singularity of the drive (``∂r/∂ξ`` singular).
        """
        J_pose, J_x = self.jacobians(x_drive, R, t, inputs)
        return -np.linalg.solve(J_pose, J_x)

    def observation(
        self,
        x_drive: np.ndarray,
        R: np.ndarray,
        t: np.ndarray,
        inputs: np.ndarray,
        pose_covariance: np.ndarray,
        stroke_sigma_mm: float,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The EKF's observation at a pose ``(R, t)`` measured with covariance ``Σ_x``, one compiled
        call (:func:`~stewart_calib.kinematics.leg_ekf_observation`): ``(r (6,), ∂r/∂x_drive (6,
        size), J_x Σ_x J_xᵀ + σ_q² I, J_x = ∂r/∂ξ)``."""
        r, H_M, R_meas, J_x = kin.leg_ekf_observation(
            self.legs,
            self.parameter_error(x_drive),
            R,
            t,
            self.extensions(inputs, x_drive),
            pose_covariance,
            stroke_sigma_mm,
        )
        return r, self.with_terms(H_M, inputs), R_meas, J_x

    # ------------------------------------------------------------------ kinematics

    def forward_kinematics(
        self,
        inputs: np.ndarray,
        x_drive: np.ndarray | None = None,
        guess=None,
        strict: bool = True,
        tol_mm: float = kin.FK_TOLERANCE_MM,
    ) -> kin.FKSolution:
        """Poses of samples ``inputs (..., width)`` (:func:`~stewart_calib.kinematics.forward_kinematics`)."""
        return kin.forward_kinematics(
            self.geometry(x_drive), self.extensions(inputs, x_drive), guess=guess, tol_mm=tol_mm, strict=strict
        )

    def solve_fk(
        self, inputs: np.ndarray, x_drive: np.ndarray | None, guess, what: str = "drive model"
    ) -> tuple[np.ndarray, np.ndarray]:
        """One sample's pose from ``guess``, then cold (:func:`~stewart_calib.kinematics.solve_fk`);
        ``SampleRejected`` when neither converges."""
        return kin.solve_fk(self.geometry(x_drive), self.extensions(inputs, x_drive), guess, what)

    def inverse_kinematics(
        self, R: np.ndarray, t: np.ndarray, x_drive: np.ndarray | None = None, inputs: np.ndarray | None = None
    ) -> np.ndarray:
        """The strokes ``q (..., 6)`` [mm] that put the platform at ``(R, t)``: the legs' length
        change less the other terms' part, over the stroke term's ``1 + k_i``.

        Args:
            inputs: ``(..., width)`` the samples' other drive inputs (their stroke columns are
                ignored); needed only where the drive has terms besides the stroke.
        """
        lengths = kin.inverse_kinematics(self.geometry(x_drive), R, t)
        factors = self._term_factors(x_drive)
        for row, (term, factor) in enumerate(zip(self.terms, factors, strict=True)):
            if row == self._stroke:
                continue
            if inputs is None:
                raise ValueError(f"inverse kinematics of this drive needs the inputs of its term '{term.key}'")
            u = np.asarray(inputs, dtype=float)[..., term.input_start : term.input_start + N_LEGS]
            lengths = lengths - factor * term.gain * u
        return lengths / factors[self._stroke]

    # ------------------------------------------------------------------ compiled code

    def kernel_terms(self, x_drive: np.ndarray | None = None) -> tuple:
        """The terms as compiled code takes them: ``(starts (b,) int64, gains (b,), offsets (b,),
        values (b, 6) at x_drive, columns (b, 6) int64 of their errors in x_drive, −1 where known)``."""
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


def plain_drive(legs: LegGeometry) -> DriveModel:
    """``legs`` whose strokes are their length changes (stroke scale 0, no other term)."""
    return DriveModel(legs, (stroke_term(np.zeros(N_LEGS)),))


def drive_model(platform: Platform, noise: NoiseConfig | None = None, outside_instrument: bool = False) -> DriveModel:
    """The drive of ``platform``: its legs, the stroke term about ``[drive] stroke_scale``, unknown
    when ``noise.stroke_scale_sigma`` > 0 or, with an instrument outside the robot, always
    (:data:`STROKE_SCALE_SIGMA_OUTSIDE` by default); all terms known without ``noise``."""
    sigma = 0.0 if noise is None else noise.stroke_scale_sigma
    if sigma <= 0.0 and outside_instrument:
        sigma = STROKE_SCALE_SIGMA_OUTSIDE
    return DriveModel(platform.drive, (stroke_term(platform.stroke_scale, sigma if sigma > 0.0 else None),))
