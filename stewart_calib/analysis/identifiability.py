"""Is a pose set good enough to identify the 42 drive parameters? (the conditioning a result reports)

Two stacked identification Jacobians over the N poses:

* **Leg-length form** (what ``ekf``, ``isam2`` and ``lm`` estimate with): per pose the six rows
  ``∂r_i/∂M`` of ``r_i = ‖t + R d_i − j_i‖ − (l_i + q_i)``, whitened by the residual's noise
  ``C = J_x Σ_x J_xᵀ + σ_q² I``, where ``Σ_x`` is the tracker FK pose covariance from the
  reading noise σ_s and ``J_x = ∂r/∂ξ``. ``A = [C_k^{-1/2} ∂r/∂M]`` has units 1/mm; ``AᵀA`` is
  the Fisher information, and ``(AᵀA)⁻¹`` the Cramér–Rao bound of any unbiased estimate.
  All 42 parameters are in mm, so no column scaling is needed and the singular values and
  condition number are unit-consistent.
* **The paper's J_p form** (eq. 8–11, what ``ls`` and ``paper-ekf`` fit): ``δE = J_p δM`` per
  pose, unweighted as in the paper, with the three rotation rows (rad) multiplied by a length
  (:func:`rotation_row_scale_mm`, the platform joints' mean radius: a rotation δθ moves a
  platform joint by about that radius × δθ) so that they weigh like the position rows (mm).

The observability indices of Borm & Menq (1991) are of the whitened leg-length form, so
``1/σ_i`` is the standard deviation [mm] of the estimate along the i-th singular direction.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TypeGuard

import numpy as np

from ..config import NoiseConfig
from ..errors import CalibError
from ..instruments.gauge import joint_columns
from ..model import _kernels
from ..model import kinematics as kin
from ..model.drive import TERM_UNITS, DriveModel, drive_model
from ..model.platform import PARAMETER_NAMES, LegGeometry, Platform
from ..samples import Inputs, broadcast_inputs, input_rows

#: A singular value below this fraction of the largest counts as zero. Round-off in the
#: whitened Jacobian sits near 1e-13 relative; a direction 1e-8 times weaker than the best
#: would need 1e8 times the measurement noise's information to be seen at all.
RANK_RTOL = 1e-8

#: Above this condition number (leg-length form) the verdict is "poorly conditioned". Rich
#: random pose sets on nim-stewart give about 400 at 20 poses and 250 at 200 poses (the best
#: achievable spread of the 42 directions); above 1e3 the weakest direction is at least 3× less
#: well determined than that, a sign that the poses do not move some joint along its leg.
CONDITION_POOR = 1e3
#: significant digits the verdict reads a condition number to (:func:`poorly_conditioned`). The
#: kernels' ahead-of-time and JIT forms round the whitened rows differently in the last bit (5.5e-16
#: relative on the same poses: condition numbers that differ in the 16th digit), so a
#: number within 1e-13 of the threshold would be "poorly conditioned" on one and not on the other;
#: nine digits are far above that rounding and far below any change of the poses.
CONDITION_DIGITS = 9


def poorly_conditioned(condition_number: float) -> bool:
    """The one decision of every conditioning verdict and warning (the leg-length form's, an outside
    instrument's equilibrated number): beyond :data:`CONDITION_POOR`, read to :data:`CONDITION_DIGITS`."""
    return float(f"{condition_number:.{CONDITION_DIGITS}g}") > CONDITION_POOR


#: A named direction lists the components with at least this magnitude (unit vector).
COMPONENT_MIN = 0.1

#: The refusal of a log where no sample's readings give a pose.
NO_POSE = "tracker readings: forward kinematics converged for no sample; no pose to assess"

#: How many of the weakest (non-null) directions a report spells out.
N_WEAKEST = 3

VERDICTS = ("identifiable", "poorly conditioned", "rank-deficient")


def residual_covariance(platform: Platform, R: np.ndarray, t: np.ndarray, noise: NoiseConfig) -> np.ndarray:
    """Noise of the drive's leg residuals at each pose, ``J_x Σ_x J_xᵀ + σ_q² diag(J_e²)``, ``(N, legs, legs)`` [mm²]
    (``J_e = ∂r_i/∂e_i`` of the drive coordinate: −1 for a prismatic leg; σ_q the leg model's
    ``coordinate_sigma``, ``noise.stroke_sigma_mm`` for prismatic legs).

    The pose enters through tracker FK, so the reading noise σ_s reaches every leg residual
    through the pose: leaving ``J_x Σ_x J_xᵀ`` out makes the weights wrong by orders of
    magnitude (docs/measured-facts.md: an EKF with ``σ² I`` alone diverged).
    """
    return _leg_rows(platform, R, t, noise)[1]


def _leg_rows(platform: Platform, R: np.ndarray, t: np.ndarray, noise: NoiseConfig) -> tuple[np.ndarray, np.ndarray]:
    """``(∂r/∂M (N, legs, n_params), C (N, legs, legs))`` of the nominal drive at poses ``(R, t)``, its
    inputs those its inverse kinematics gives there (a rotary leg's Jacobians depend on its angle)."""
    drive = drive_model(platform)
    inputs = drive.inputs(drive.inverse_kinematics(R, t), None, R, t)
    J_x, J_M = drive.jacobians(None, R, t, inputs)
    sigma_x = kin.pose_covariance_from_legs(
        platform.required_tracker("the leg covariance"), R, t, noise.reading_sigma_mm
    )
    if _compiled(drive.legs):  # r = ‖t + R d − j‖ − (l + e): ∂r/∂e = −1
        noise_q = noise.stroke_sigma_mm**2 * np.eye(J_x.shape[-2])
    else:  # one logged coordinate's σ (a commanded servo angle's [rad]) through ∂r_i/∂e_i
        J_e = drive.legs.residual_jacobians(R, t, drive.extensions(inputs))[2]
        sigma_e = drive.legs.coordinate_sigma(noise)
        noise_q = sigma_e**2 * J_e[..., :, None] ** 2 * np.eye(J_x.shape[-2])
    return J_M, J_x @ sigma_x @ np.swapaxes(J_x, -1, -2) + noise_q


def _degrees(legs) -> np.ndarray:
    """``(n_params,)`` True where the leg model's parameter vector holds an angle (prismatic legs: none)."""
    return np.zeros(legs.n_params, dtype=bool) if _compiled(legs) else np.asarray(legs.parameter_degrees, dtype=bool)


def _compiled(legs) -> TypeGuard[LegGeometry]:
    """Whether ``legs`` are the leg set the prismatic compiled kernels take."""
    return type(legs) is LegGeometry


def whitened_leg_jacobian(platform: Platform, poses: np.ndarray, noise: NoiseConfig) -> np.ndarray:
    """Per-pose whitened rows ``C^{-1/2} ∂r/∂M`` of the leg-length form, ``(N, legs, n_params)``
    [1/mm] (``(N, 6, 42)`` for the paper's drive).

    ``C = L Lᵀ`` (:func:`residual_covariance`) by Cholesky and ``C^{-1/2} = L⁻¹``: for the prismatic
    legs one compiled loop over the poses (:func:`stewart_calib.model._kernels.whitened_leg_rows`: numpy's
    batched 6 × 6 Cholesky and solve cost over an order of magnitude more a pose), numpy's for any
    other leg model (:func:`_whitened_rows`).

    Args:
        poses: ``(N, 6)`` pose6 ``[mm, rad]``.
    Raises:
        CalibError: both noise sigmas zero (no noise model, no weights), or a pose where the
            residual covariance is singular (the tracker cannot measure that pose).
    """
    if noise.reading_sigma_mm <= 0 and noise.stroke_sigma_mm <= 0:
        raise CalibError("noise: reading_sigma_mm and stroke_sigma_mm are both 0: expected a positive noise level")
    poses = np.asarray(poses, dtype=float)
    R, t = kin.pose_to_rt(poses.reshape(-1, 6))
    drive, tracker = platform.drive, platform.required_tracker("the whitened leg Jacobian")
    if _compiled(drive):
        rows = np.empty((len(R), drive.n_legs, drive.n_params))
        _kernels.whitened_leg_rows(
            drive.base_joints,
            drive.platform_joints,
            drive.initial_lengths,
            tracker.base_joints,
            tracker.platform_joints,
            np.ascontiguousarray(R),
            np.ascontiguousarray(t),
            float(noise.reading_sigma_mm) ** 2,
            float(noise.stroke_sigma_mm) ** 2,
            rows,
        )
    else:
        rows = _whitened_rows(platform, R, t, noise)
    singular = ~np.isfinite(rows).all(axis=(1, 2))
    if singular.any():
        k = int(np.argmax(singular))
        raise CalibError(
            f"pose {k + 1} {np.round(poses.reshape(-1, 6)[k], 6).tolist()}: the leg residual covariance is singular "
            "there (the tracker's Jacobian loses rank); expected a pose the tracker can measure"
        )
    return rows.reshape(poses.shape[:-1] + rows.shape[1:])


def _whitened_rows(platform: Platform, R: np.ndarray, t: np.ndarray, noise: NoiseConfig) -> np.ndarray:
    """``L⁻¹ ∂r/∂M`` ``(N, legs, n_params)`` with ``C = L Lᵀ`` (:func:`_leg_rows`) of any leg model; NaN
    rows at a pose whose ``C`` is not positive definite (as the compiled kernel gives them)."""
    J_M, C = _leg_rows(platform, R, t, noise)
    rows = np.full(J_M.shape, np.nan)
    positive = np.all(np.isfinite(C), axis=(1, 2)) & np.all(np.linalg.eigvalsh(np.nan_to_num(C)) > 0.0, axis=1)
    rows[positive] = np.linalg.solve(np.linalg.cholesky(C[positive]), J_M[positive])
    return rows


def platform_joints_mm(platform: Platform) -> np.ndarray:
    """``(legs, 3)`` the drive's nominal platform joints ``d_i`` in {D} [mm]."""
    legs = platform.drive
    return legs.as_vector()[joint_columns(legs)[1]].reshape(legs.n_legs, 3)


def rotation_row_scale_mm(platform: Platform) -> float:
    """Length [mm] the paper-form rotation rows are multiplied by: mean radius of the ``d_i``."""
    return float(np.mean(np.linalg.norm(platform_joints_mm(platform)[:, :2], axis=1)))


def paper_jacobian(platform: Platform, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The paper's error Jacobian ``J_p`` (eq. 8–11) of the nominal drive at poses ``(R, t)``,
    ``(N, 6, n_params)``: ``δE = [δh [mm], δθ (roll, pitch, yaw) [rad]] = J_p δM`` of the pose
    reached with fixed drive coordinates. The prismatic legs' closed form
    (:func:`~stewart_calib.model.kinematics.error_jacobian`), else the drive's forward-kinematics Jacobian
    ``∂ξ/∂M`` (body tangent ``[ω, v]``) turned into it: ``δh = R v``, ``δθ = E⁻¹ R ω`` with ``E`` the
    roll-pitch-yaw rates' angular velocity in {J} (``R = Rz(yaw) Ry(pitch) Rx(roll)``)."""
    if _compiled(platform.drive):
        return kin.error_jacobian(platform.drive, R, t)
    drive = drive_model(platform)
    inputs = drive.inputs(drive.inverse_kinematics(R, t), None, R, t)
    J_xi = drive.pose_jacobian(None, R, t, inputs)[..., : drive.n_params]
    _, pitch, yaw = np.moveaxis(kin.rotation_to_rpy(R), -1, 0)
    zero, one = np.zeros_like(yaw), np.ones_like(yaw)
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    E = np.stack(  # columns: Rz Ry e_x, Rz e_y, e_z
        [
            np.stack([cy * cp, -sy, zero], axis=-1),
            np.stack([sy * cp, cy, zero], axis=-1),
            np.stack([-sp, zero, one], axis=-1),
        ],
        axis=-2,
    )
    position = R @ J_xi[..., 3:, :]
    rotation = np.linalg.solve(E, R @ J_xi[..., :3, :])
    return np.concatenate([position, rotation], axis=-2)


def scaled_paper_jacobian(platform: Platform, poses: np.ndarray) -> np.ndarray:
    """The paper's ``J_p`` (:func:`paper_jacobian`) per pose, rotation rows × :func:`rotation_row_scale_mm`,
    ``(N, 6, n_params)``."""
    R, t = kin.pose_to_rt(np.asarray(poses, dtype=float))
    J_p = paper_jacobian(platform, R, t)
    J_p[..., 3:, :] *= rotation_row_scale_mm(platform)
    return J_p


def observability_indices(singular_values: np.ndarray, n_rows: int) -> dict[str, float]:
    """Borm & Menq O1…O5 of a Jacobian with ``n_rows`` rows and these (descending) singular values.

    O1 = (σ1⋯σn)^(1/n)/√m, O2 = σmin/σmax, O3 = σmin, O4 = σmin²/σmax, O5 = 1/Σ(1/σi);
    all but O1 are 0 when σmin is 0 (O1 then is 0 too: the product vanishes).
    """
    s = np.asarray(singular_values, dtype=float)
    s_min, s_max = float(s[-1]), float(s[0])
    o1 = float(np.exp(np.mean(np.log(s)))) / np.sqrt(n_rows) if s_min > 0 else 0.0
    return {
        "O1": o1,
        "O2": s_min / s_max,
        "O3": s_min,
        "O4": s_min**2 / s_max,
        "O5": 1.0 / float(np.sum(1.0 / s)) if s_min > 0 else 0.0,
    }


def name_direction(
    vector: np.ndarray, min_component: float = COMPONENT_MIN, names: tuple[str, ...] | list[str] = PARAMETER_NAMES
) -> str:
    """``"0.62·j3z − 0.68·l3"``: the components with ``|coef| ≥ min_component``, largest first
    (``names``: the components' names, the 42 drive parameters by default)."""
    # Rounded magnitudes, then parameter order: equal-looking terms print in a fixed order.
    order = np.lexsort((np.arange(len(vector)), -np.round(np.abs(vector), 2)))
    terms = [(float(vector[k]), names[k]) for k in order if abs(vector[k]) >= min_component]
    parts: list[str] = []
    for coef, name in terms:
        term = f"{abs(coef):.2f}·{name}"
        parts.append(("− " if coef < 0 else "+ ") + term if parts else ("−" if coef < 0 else "") + term)
    return " ".join(parts)


def _sign_fixed(vectors: np.ndarray) -> np.ndarray:
    """Columns with their largest-magnitude component positive (an SVD's sign is arbitrary)."""
    big = np.argmax(np.abs(vectors), axis=0)
    return vectors * np.sign(vectors[big, np.arange(vectors.shape[1])])


def _pivot_columns(A: np.ndarray, k: int) -> np.ndarray:
    """The ``k`` columns QR with column pivoting picks first (Businger–Golub, as LAPACK's ``geqp3``): at each
    step the column of the largest norm left, the first of equal ones, then projected out of the rest.
    Written out for a matrix of a few rows, so that ``calibrate`` does not import ``scipy.linalg`` (~0.2 s)."""
    residual = np.array(A, dtype=float)
    chosen: list[int] = []
    for _ in range(k):
        norms = np.einsum("ij,ij->j", residual, residual)
        norms[chosen] = -1.0
        column = int(np.argmax(norms))
        chosen.append(column)
        q = residual[:, column] / np.sqrt(norms[column])
        residual -= np.outer(q, q @ residual)
    return np.array(chosen)


def readable_basis(basis: np.ndarray) -> np.ndarray:
    """Re-express an orthonormal basis ``(n, k)`` of a subspace with few parameters per vector.

    An SVD returns an arbitrary rotation of the null space; reduced row-echelon form over
    the k most independent parameters (QR with column pivoting) gives vectors that each
    carry one pivot parameter, e.g. ``0.71·j1x + 0.71·d1x`` per leg and axis. Unit columns.
    """
    k = basis.shape[1]
    if k == 0:
        return basis
    pivots = np.sort(_pivot_columns(basis.T, k))  # parameter order, so leg 1's vectors come first
    echelon = np.linalg.solve(basis.T[:, pivots], basis.T).T
    return _sign_fixed(echelon / np.linalg.norm(echelon, axis=0))


@dataclass(frozen=True)
class IdentifiabilityReport:
    """How well N poses identify the drive parameters δM (and its blocks), under a noise model.

    Attributes:
        n_poses: number of poses N.
        noise: the noise model the weights and predictions use.
        singular_values: ``(n,)`` of the whitened leg-length Jacobian, descending [1/mm].
        rank: number of singular values above ``RANK_RTOL`` × the largest.
        condition_number: σmax/σmin of the leg-length form (inf when rank-deficient).
        paper_singular_values: ``(n_params,)`` of the stacked ``J_p`` with scaled rotation rows (NaN: left out).
        paper_condition_number: σmax/σmin of that form.
        rotation_row_scale_mm: the length the ``J_p`` rotation rows were multiplied by [mm].
        predicted_stddev_mm: ``(n_params,)`` Cramér–Rao standard deviation per parameter [mm]; inf for
            a parameter that moves along the null space (not identifiable from these poses).
        observability: Borm & Menq O1…O5 of the leg-length form.
        weakest: up to :data:`N_WEAKEST` ``(singular value, unit n-vector)``, weakest first,
            among the identified directions.
        null_space: ``(n, n − rank)`` unit basis of the unidentified directions.
        verdict: one of :data:`VERDICTS`.
        parameters_per_leg: entries of δM a leg (the text report's rows: 7 for the paper's drive).
        parameter_degrees: ``(n_params,)`` True where δM holds an angle (a servo's zero offset and axis
            tilts, spec §15): in rad here and in the JSON, which then lists this mask; in degrees in the
            text report.
        names: the unknowns' names: δM's (``n_params``, 42 for the paper's drive), then the drive's
            unknown blocks where the report covers them (:class:`InformationAccumulator`'s
            ``drive``); the singular values, the weakest directions and the null space are then
            over all ``n`` of them, each block's column in
            :attr:`block_scale` units (the RMS leg-length change [mm] a unit of it makes), and
            :attr:`block_stddev` holds their Cramér–Rao σ in their own units.
        block_stddev: ``{key: (names, σ)}`` of the drive's unknown blocks (mm/kN, dimensionless k).
        block_scale: ``(n − n_params,)`` [mm per unit] the blocks' columns were scaled by.
    """

    n_poses: int
    noise: NoiseConfig
    singular_values: np.ndarray
    rank: int
    condition_number: float
    paper_singular_values: np.ndarray
    paper_condition_number: float
    rotation_row_scale_mm: float
    predicted_stddev_mm: np.ndarray
    observability: dict[str, float]
    null_space: np.ndarray
    names: tuple[str, ...]
    parameters_per_leg: int
    parameter_degrees: np.ndarray
    weakest: list[tuple[float, np.ndarray]] = field(default_factory=list)
    verdict: str = "identifiable"
    block_stddev: dict[str, tuple[tuple[str, ...], np.ndarray]] = field(default_factory=dict)
    block_scale: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def null_space_dimension(self) -> int:
        return self.null_space.shape[1]

    @property
    def size(self) -> int:
        """Unknowns the report covers: δM's, and the drive's unknown blocks."""
        return len(self.names)

    def weakest_names(self) -> list[str]:
        return [name_direction(v, names=self.names) for _, v in self.weakest]

    def null_space_names(self) -> list[str]:
        return [name_direction(v, names=self.names) for v in self.null_space.T]

    def to_dict(self) -> dict:
        """JSON-ready: lists of floats, ``null`` for infinities."""

        def num(x: float) -> float | None:
            return float(x) if np.isfinite(x) else None

        return {
            "format": "stewart-calib/identifiability@1",
            "n_poses": self.n_poses,
            "noise": {"reading_sigma_mm": self.noise.reading_sigma_mm, "stroke_sigma_mm": self.noise.stroke_sigma_mm},
            "parameter_names": list(self.names[: len(self.predicted_stddev_mm)]),
            "leg_length_form": {
                "singular_values": [float(s) for s in self.singular_values],
                "condition_number": num(self.condition_number),
                "rank": self.rank,
                "rank_rtol": RANK_RTOL,
                "observability": self.observability,
            },
            "paper_form": {
                "singular_values": [float(s) for s in self.paper_singular_values],
                "condition_number": num(self.paper_condition_number),
                "rotation_row_scale_mm": self.rotation_row_scale_mm,
            },
            "predicted_stddev_mm": [num(s) for s in self.predicted_stddev_mm],
            **({"parameter_degrees": self.parameter_degrees.tolist()} if self.parameter_degrees.any() else {}),
            "weakest_directions": [
                {
                    "singular_value": float(s),
                    "stddev_mm": 1.0 / float(s),
                    "vector": [float(x) for x in v],
                    "named": name_direction(v, names=self.names),
                }
                for s, v in self.weakest
            ],
            "null_space": {
                "dimension": self.null_space_dimension,
                "basis": [[float(x) for x in v] for v in self.null_space.T],
                "named": self.null_space_names(),
            },
            "verdict": self.verdict,
            "thresholds": {"condition_poor": CONDITION_POOR, "rank_rtol": RANK_RTOL},
            **self._blocks_dict(num),
        }

    def _blocks_dict(self, num) -> dict:
        """With the drive's unknown blocks: ``"unknown_names"`` (the order of every vector above) and
        ``"blocks"`` ``{key: {"names", "predicted_stddev", "column_scale_mm"}}``."""
        if not self.block_stddev:
            return {}
        blocks, start = {}, 0
        for key, (names, stddev) in self.block_stddev.items():
            blocks[key] = {
                "names": list(names),
                "predicted_stddev": [num(v) for v in stddev],
                "column_scale_mm": [float(v) for v in self.block_scale[start : start + len(names)]],
            }
            start += len(names)
        return {"unknown_names": list(self.names), "blocks": blocks}

    def format_text(self) -> str:
        """The terminal report."""
        s = self.singular_values
        covered = "".join(f" and {names[0]}…{names[-1]}" for names, _ in self.block_stddev.values())
        n_params = len(self.predicted_stddev_mm)
        lines = [
            f"Identifiability of the {n_params} drive parameters{covered} from {self.n_poses} poses "
            f"(σ_s = {self.noise.reading_sigma_mm:g} mm, σ_q = {self.noise.stroke_sigma_mm:g} mm)",
            f"verdict: {self.verdict}  (rank {self.rank}/{self.size}; condition number "
            f"{self.condition_number:.4g}; poorly conditioned above {CONDITION_POOR:g}, "
            f"rank counts σ > {RANK_RTOL:g}·σmax)",
            "",
            "leg-length form (rows ∂r_i/∂M whitened by J_x Σ_x J_xᵀ + σ_q² I) [1/mm]:",
            f"  σmax {s[0]:.4g}  σmin {s[-1]:.4g}  condition number {self.condition_number:.4g}",
            "  singular values: " + " ".join(f"{v:.3g}" for v in s),
            "  observability (Borm & Menq, of this whitened form): "
            + "  ".join(f"{k} {v:.4g}" for k, v in self.observability.items()),
            f"paper J_p form (eq. 8–11, rotation rows × {self.rotation_row_scale_mm:.1f} mm, unweighted):",
            f"  σmax {self.paper_singular_values[0]:.4g}  σmin {self.paper_singular_values[-1]:.4g}  "
            f"condition number {self.paper_condition_number:.4g}",
            "",
            "weakest directions (σ, predicted std dev along it):",
        ]
        if self.block_stddev:
            lines.insert(4, "  (the blocks' columns in mm: the RMS leg-length change a unit of each makes)")
        lines += [
            f"  {sv:.4g} /mm  ({1.0 / sv:.3g} mm)  {name_direction(v, names=self.names)}" for sv, v in self.weakest
        ]
        if self.null_space_dimension:
            lines += ["", f"null space: dimension {self.null_space_dimension} (not identified by these poses):"]
            lines += [f"  {name}" for name in self.null_space_names()]
        degrees = self.parameter_degrees
        units = "mm, angles in deg" if degrees.any() else "mm"
        lines += ["", f"predicted standard deviation per parameter (Cramér–Rao) [{units}]:"]
        sd = np.where(degrees, np.degrees(self.predicted_stddev_mm), self.predicted_stddev_mm)
        per_leg = self.parameters_per_leg
        for start in range(0, len(sd), per_leg):
            cols = range(start, start + per_leg)
            lines.append("  " + "  ".join(f"{self.names[k]:>4} {_fmt_sd(sd[k])}" for k in cols))
        for key, (names, stddev) in self.block_stddev.items():
            unit = f" [{TERM_UNITS[key]}]" if key in TERM_UNITS else ""
            lines.append(
                f"  {key}{unit}: " + "  ".join(f"{n} {_fmt_sd(v)}" for n, v in zip(names, stddev, strict=True))
            )
        return "\n".join(lines)


def _fmt_sd(value: float) -> str:
    return f"{value:9.3g}" if np.isfinite(value) else "   not id"


#: Poses whose whitened rows are stacked under the running factor at a time: the only buffer
#: that grows with a block, never with N. The stack, (6 · 256 + 42) × 42 floats (0.5 MB: the paper's drive), stays
#: in a core's L2 cache (1 MB here) through the QR's 42 Householder passes: 2048 poses (4 MB)
#: measured ~1.4× slower per pose, the flops being the same.
BLOCK_POSES = 256


def _stacked_factor(factor: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Upper-triangular ``R'`` with ``R'ᵀR' = RᵀR + rowsᵀrows``: QR of ``[R; rows]``, ``(≤ n, n)``.

    Householder QR is an orthogonal transform, so ``R'`` has exactly the singular values and
    right singular vectors of every row stacked so far (to round-off): the information
    ``AᵀA = RᵀR`` is kept as its square root, which resolves singular values down to ~1e-16
    of the largest — forming ``AᵀA`` itself would square the condition number and lose all
    below ~1e-8 (√eps), exactly where :data:`RANK_RTOL` decides the rank. LAPACK's ``geqrf``
    on a column-major stack, through numpy's own LAPACK (``np.linalg.qr`` copies to that layout
    and is 4× slower; scipy's ``dgeqrf``, the same routine and the same ``R`` bit for bit, costs
    ``calibrate`` the ~0.2 s of importing ``scipy.linalg``).
    """
    from numpy.linalg import lapack_lite

    n = factor.shape[1]
    rows = rows.reshape(-1, n)
    m = len(factor) + len(rows)
    stack = np.empty((n, m))  # C order of the transpose: the (m, n) stack in LAPACK's column-major order
    stack[:, : len(factor)], stack[:, len(factor) :] = factor.T, rows.T
    tau, size = np.empty(min(m, n)), np.empty(1)
    lapack_lite.dgeqrf(m, n, stack, m, tau, size, -1, 0)  # the workspace's optimal size
    done = lapack_lite.dgeqrf(m, n, stack, m, tau, np.empty(max(int(size[0]), 1)), max(int(size[0]), 1), 0)
    if done["info"] != 0:
        raise ValueError(f"LAPACK dgeqrf: argument {-done['info']} is invalid")
    return np.triu(stack.T[: min(m, n)])


class InformationAccumulator:
    """The n × n information of a pose stream (n = 42: the paper's δM), accumulated block by block
    (O(N) time, O(1) memory).

    For the leg-length form ``AᵀA = Σ_k A_kᵀ A_k`` with ``A_k`` the whitened rows of pose k
    (:func:`whitened_leg_jacobian`), and likewise for the paper's ``J_p`` form; each kept as
    its square-root factor (:func:`_stacked_factor`). :meth:`report` decomposes only these
    n × n factors, never an N-sized matrix, and gives what an SVD of the stacked rows gives.

    Args:
        platform: nominal geometry (Jacobians at the nominal drive).
        noise: reading and stroke sigmas (the whitening).
        paper_form: also the paper's form; False leaves it out (the report's paper fields NaN), for
            callers that read the leg form only (``calibrate``'s conditioning: its compile, ~2 s on a
            first run, and its time a pose).
        drive: the drive model the estimators identify (:func:`~stewart_calib.model.drive.drive_model`
            with the config's noise): where it has unknown blocks (the compliance c1…c6 with
            ``[elastic]``, the stroke scale where configured) the leg-length form covers them too,
            ``∂r_i/∂v_{b,i} = −g_b u_{b,i}`` whitened as the rows (then :meth:`add` needs the
            samples' strokes and, for an elastic drive, payloads). None: δM alone.
    Raises:
        CalibError: both noise sigmas zero (no noise model, no weights).
    """

    def __init__(
        self, platform: Platform, noise: NoiseConfig, paper_form: bool = True, drive: DriveModel | None = None
    ):
        if noise.reading_sigma_mm <= 0 and noise.stroke_sigma_mm <= 0:
            raise CalibError("noise: reading_sigma_mm and stroke_sigma_mm are both 0: expected a positive noise level")
        self.platform = platform
        self.noise = noise
        self.n_poses = 0
        self.n_params = n_params = platform.drive.n_params
        self.drive = drive if drive is not None and drive.size > n_params else None
        size = n_params if self.drive is None else self.drive.size
        self._leg_factor = np.zeros((0, size))
        self._paper_factor = np.zeros((0, n_params)) if paper_form else None
        self._block_squares = np.zeros(size - n_params)  # Σ over rows of each block column², unwhitened
        self._block_rows = 0

    def add(self, poses: np.ndarray, strokes: np.ndarray | None = None, channels: Inputs | None = None) -> None:
        """Add the information of ``(n, 6)`` pose6 ``[mm, rad]``, :data:`BLOCK_POSES` at a time; with
        the drive's blocks, their ``(n, legs)`` logged strokes [mm] (None: the drive's inverse
        kinematics) and input channels (``Log.inputs``, each ``(n, ...)`` or one value for all; None:
        none, 0 kg at the reference temperature)."""
        poses = np.asarray(poses, dtype=float).reshape(-1, 6)
        rows_of = broadcast_inputs(channels, len(poses))
        if self.drive is not None and strokes is None:
            strokes = self.drive.inverse_kinematics(*kin.pose_to_rt(poses), channels=rows_of)
        for start in range(0, len(poses), BLOCK_POSES):
            block = poses[start : start + BLOCK_POSES]
            rows = whitened_leg_jacobian(self.platform, block, self.noise)
            if self.drive is not None and strokes is not None:
                span = slice(start, start + len(block))
                rows = np.concatenate(
                    [rows, self._block_columns(block, strokes[span], input_rows(rows_of, span))], axis=-1
                )
            self._leg_factor = _stacked_factor(self._leg_factor, rows)
            if self._paper_factor is not None:
                self._paper_factor = _stacked_factor(self._paper_factor, scaled_paper_jacobian(self.platform, block))
            self.n_poses += len(block)

    def _block_columns(self, poses: np.ndarray, strokes: np.ndarray, channels: Inputs) -> np.ndarray:
        """``C^{-1/2} ∂r/∂v`` of the drive's unknown blocks at the poses, ``(n, legs, size − n_params)``
        [1/unit]: the same whitening ``C = L Lᵀ`` (:func:`residual_covariance`) as δM's rows'."""
        drive = self.drive
        assert drive is not None
        R, t = kin.pose_to_rt(poses)
        inputs = drive.inputs(strokes, channels, R, t)
        columns = drive.with_terms(np.zeros((len(R), drive.rows, drive.n_params)), inputs)[..., drive.n_params :]
        self._block_squares += np.sum(columns**2, axis=(0, 1))
        self._block_rows += len(R)
        L = np.linalg.cholesky(residual_covariance(self.platform, R, t, self.noise))
        return np.linalg.solve(L, columns)

    @property
    def names(self) -> tuple[str, ...]:
        """The unknowns' names: δM's, then the drive's blocks'."""
        blocks = () if self.drive is None else self.drive.blocks
        return self.platform.drive.parameter_names + tuple(name for block in blocks for name in block.names)

    def _column_scale(self) -> np.ndarray:
        """``(size,)`` 1 on δM; on a block's column the RMS leg-length change [mm] a unit of it makes
        (over the poses, on its own leg): the SVD is of the unknowns ``v · scale``, each then in mm
        (their columns over the scale)."""
        rms = np.sqrt(self._block_squares / max(self._block_rows, 1))
        return np.concatenate([np.ones(self.n_params), np.where(rms > 0.0, rms, 1.0)])

    def covariance(self, blocks: bool = False) -> np.ndarray | None:
        """Cramér–Rao covariance ``(AᵀA)⁻¹`` of δM ``(n_params, n_params)`` [mm²] of the leg-length form (the
        drive's blocks, where covered, marginalised; ``blocks``: over δM and the blocks, ``(size, size)`` in
        code units), from its square-root factor (``R⁻¹R⁻ᵀ``); None when the poses leave it rank-deficient."""
        size = self._leg_factor.shape[1]
        if len(self._leg_factor) < size:
            return None
        s = np.linalg.svd(self._leg_factor / self._column_scale(), compute_uv=False)
        if s[-1] <= RANK_RTOL * s[0]:
            return None
        inverse = np.linalg.solve(self._leg_factor, np.eye(size))
        covariance = inverse @ inverse.T
        return covariance if blocks else covariance[: self.n_params, : self.n_params]

    def report(self) -> IdentifiabilityReport:
        """Singular values, Cramér–Rao bound, weakest directions and verdict of the poses added.

        Raises:
            CalibError: no pose added.
        """
        if self.n_poses == 0:
            raise CalibError("poses: expected at least one pose, got none")
        # Full SVD of the (≤ n) × n factor: with fewer than 7 poses it has fewer rows than
        # columns and the null space is in the trailing rows of Vᵀ, which a reduced SVD omits.
        size, scale = self._leg_factor.shape[1], self._column_scale()
        _, s_all, Vt = np.linalg.svd(self._leg_factor / scale, full_matrices=True)
        s = np.zeros(size)
        s[: len(s_all)] = s_all
        rank = int(np.sum(s > RANK_RTOL * s[0]))
        s[rank:] = 0.0  # round-off, not information
        V_range, null = Vt[:rank].T, Vt[rank:].T

        stddev = _bounded_stddev(s, rank, Vt) / scale
        block_stddev, start = {}, self.n_params
        for block in () if self.drive is None else self.drive.blocks:
            block_stddev[block.key] = (block.names, stddev[start : start + block.size] * block.file_scale)
            start += block.size

        s_paper = np.full(self.n_params, np.nan)
        if self._paper_factor is not None:
            s_paper[:] = 0.0
            s_paper_all = np.linalg.svd(self._paper_factor, compute_uv=False)
            s_paper[: len(s_paper_all)] = s_paper_all
            s_paper[s_paper <= RANK_RTOL * s_paper[0]] = 0.0

        condition = s[0] / s[-1] if rank == size else np.inf
        if rank < size:
            verdict = "rank-deficient"
        elif poorly_conditioned(condition):
            verdict = "poorly conditioned"
        else:
            verdict = "identifiable"
        weak_idx = range(rank - 1, max(rank - 1 - N_WEAKEST, -1), -1)
        weak_vectors = _sign_fixed(V_range[:, list(weak_idx)]) if rank else np.zeros((size, 0))
        return IdentifiabilityReport(
            n_poses=self.n_poses,
            noise=self.noise,
            singular_values=s,
            rank=rank,
            condition_number=float(condition),
            paper_singular_values=s_paper,
            paper_condition_number=float(s_paper[0] / s_paper[-1]) if not s_paper[-1] <= 0 else float("inf"),
            rotation_row_scale_mm=rotation_row_scale_mm(self.platform),
            predicted_stddev_mm=stddev[: self.n_params],
            observability=observability_indices(s, self.platform.drive.n_legs * self.n_poses),
            weakest=[(float(s[k]), weak_vectors[:, j]) for j, k in enumerate(weak_idx)],
            null_space=readable_basis(null),
            verdict=verdict,
            names=self.names,
            parameters_per_leg=self.n_params // self.platform.drive.n_legs,
            parameter_degrees=_degrees(self.platform.drive),
            block_stddev=block_stddev,
            block_scale=scale[self.n_params :],
        )


def _bounded_stddev(s: np.ndarray, rank: int, Vt: np.ndarray) -> np.ndarray:
    """Cramér–Rao σ per column from the SVD ``(s, Vᵀ)`` of a whitened factor: ``Σ = (AᵀA)⁻¹`` on the
    identified subspace; a column with a component along the null space is not identified at
    all (inf: its variance is unbounded)."""
    variance = np.sum((Vt[:rank].T / s[:rank]) ** 2, axis=1)
    touches_null = np.linalg.norm(Vt[rank:].T, axis=1) > 1e-6
    return np.where(touches_null, np.inf, np.sqrt(variance))


def stddev_from_factor(factor: np.ndarray) -> np.ndarray:
    """Cramér–Rao σ of each of the ``n`` columns of a whitened factor ``A`` ``(rows, n)``, with the
    rank rule of :class:`InformationAccumulator` (inf where the rows do not identify a column)."""
    _, s_all, Vt = np.linalg.svd(factor, full_matrices=True)
    s = np.zeros(factor.shape[1])
    s[: len(s_all)] = s_all
    return _bounded_stddev(s, int(np.sum(s > RANK_RTOL * s[0])), Vt)


def identifiability_report(
    platform: Platform,
    poses: np.ndarray,
    noise: NoiseConfig,
    paper_form: bool = True,
    drive: DriveModel | None = None,
    strokes: np.ndarray | None = None,
    channels: Inputs | None = None,
) -> IdentifiabilityReport:
    """Singular values, Cramér–Rao bound, weakest directions and verdict for a pose set.

    Args:
        platform: nominal geometry (Jacobians are evaluated at the nominal drive).
        poses: ``(N, 6)`` pose6 ``[mm, rad]``.
        noise: reading and stroke sigmas.
        paper_form: also the paper's ``J_p`` form (:class:`InformationAccumulator`).
        drive, strokes, channels: the drive's unknown blocks too (:class:`InformationAccumulator`).
    Raises:
        CalibError: no poses, or no noise.
    """
    poses = np.atleast_2d(np.asarray(poses, dtype=float))
    if poses.shape[0] == 0 or poses.shape[1] != 6:
        raise CalibError(f"poses: expected an (N, 6) array with N ≥ 1, got shape {poses.shape}")
    information = InformationAccumulator(platform, noise, paper_form, drive)
    information.add(poses, strokes, channels)
    return information.report()


def tracker_poses(platform: Platform, log) -> np.ndarray:
    """Tracker FK poses of a log's readings, ``(n, 6)`` [mm, rad]; samples whose FK fails are left out."""
    return tracker_samples(platform, log)[0]


def tracker_samples(platform: Platform, log) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """``(poses (n, 6) [mm, rad], strokes (n, legs), input channels)`` of a log's samples whose
    tracker FK converges (the others left out)."""
    # The desired pose is within a few mm of the real one: a good Newton start when present.
    guess = None if log.desired_poses is None else kin.pose_to_rt(log.desired_poses)
    fk = kin.forward_kinematics(platform.required_tracker("tracker poses"), log.readings, guess, strict=False)
    channels = input_rows(log.inputs, fk.converged)
    return fk.pose6[fk.converged], np.asarray(log.strokes, dtype=float)[fk.converged], channels


def measured_samples(platform: Platform, log) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """:func:`tracker_samples`, refusing a log where none converges.

    Raises:
        CalibError: no sample's readings give a pose.
    """
    samples = tracker_samples(platform, log)
    if not len(samples[0]):
        raise CalibError(NO_POSE)
    return samples


def instrument_conditioning(report: dict) -> dict:
    """The "conditioning" section of an outside instrument's calibration result (JSON-ready): the
    keys of :func:`conditioning_summary` from :func:`~stewart_calib.estimators.batch.identifiability`'s
    report, whose verdict and weakest directions are of its Jacobian with unit columns, and both
    condition numbers (``"condition_number"`` in mm, rad and k as for ``identifiability --log``)."""
    keys = (
        "unknowns",
        "rank",
        "condition_number",
        "condition_number_equilibrated",
        "null_space_dimension",
        "weakest_directions",
        "null_space",
        "verdict",
    )
    return {key: report[key] for key in keys}


def conditioning_summary(report: IdentifiabilityReport) -> dict:
    """The small "conditioning" section of a calibration result (JSON-ready)."""
    return {
        "rank": report.rank,
        "condition_number": float(report.condition_number) if np.isfinite(report.condition_number) else None,
        "null_space_dimension": report.null_space_dimension,
        "weakest_directions": report.weakest_names(),
        "null_space": report.null_space_names(),
        "verdict": report.verdict,
    }


def warning_line(report: IdentifiabilityReport) -> str | None:
    """One line naming the unidentified or weakest directions, or None when identifiable."""
    if report.verdict == "rank-deficient":
        names = report.null_space_names()
        shown = "; ".join(names[:3]) + (f"; … ({len(names) - 3} more)" if len(names) > 3 else "")
        return (
            f"warning: the poses do not identify all {report.size} parameters (rank {report.rank}, "
            f"{report.null_space_dimension} unidentified directions: {shown})"
        )
    if report.verdict == "poorly conditioned":
        sv = report.weakest[0][0]
        return (
            f"warning: poorly conditioned (condition number {report.condition_number:.3g} > "
            f"{CONDITION_POOR:g}); weakest direction {report.weakest_names()[0]} (σ {1.0 / sv:.3g} mm)"
        )
    return None
