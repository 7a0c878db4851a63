"""The paper's baseline: batch least squares on ``P_v − P_m = J_p δM`` (eq. 9–11), iterated.

For every sample the tracker gives the measured pose ``P_v`` (FK of the readings); the
model ``M + δM`` gives ``P_m`` (FK of the executed strokes). Stacking ``J_p`` over the
samples and solving for the step is one Gauss–Newton iteration; it is repeated at the
updated model until the step is below ``ls.tolerance_mm``.

A sample's six pose rows are neither independent nor of one variance (``P_v`` is the FK of six
tracker readings, ``P_m`` of six noisy strokes): their noise is ``Σ_k = σ_z² G_v G_vᵀ + σ_q² G_m G_mᵀ``
(``G`` the pose's sensitivity to the six readings at ``P_v`` and to the six strokes at ``P_m``, the
``l_i`` columns of ``J_p``; :class:`PoseNoise`). ``ls.weighting`` says how the rows are weighed
(:func:`pose_weights`): ``noise`` (the default) whitens each sample's rows by ``Σ_k`` — generalised
least squares, the maximum-likelihood fit of the readings and strokes to first order, whose
covariance is the leg-length form's Cramér–Rao bound that ``identifiability`` and ``plan`` state;
``paper`` is the paper's own weighting, the rotation rows [rad] scaled by ``ls.rotation_weight_mm`` so
the stacked residual is in mm throughout, which on planned (A-optimal) poses leaves 1.3–1.4× the bound's
error. Either way the covariance is the sandwich of the weighted fit,
``s² (AᵀA)⁻¹ (Σ_k A_kᵀ S_k A_k) (AᵀA)⁻¹`` with ``A`` the weighted stacked Jacobian and ``S_k = W_k Σ_k W_kᵀ``
the weighted pose noise of sample k (the identity where ``W_k`` whitens, and the sandwich
``(AᵀA)⁻¹``). ``s²`` is the data's own noise scale on the told σ's:
``‖b − A δ‖² / (Σ_k tr S_k − tr((AᵀA)⁻¹ Σ_k A_kᵀ S_k A_k))``, the residual over its expectation at
``s = 1``. With the paper's weighting ``σ̂² (AᵀA)⁻¹``, which takes the rows as independent of one
variance, is 1.1–1.4× too confident with the paper's tracker. The covariance is None when the system
is rank deficient (too few or too poor poses); ``singular_values`` says which.

The paper's LS takes every sample in, gross errors too (a glitched reading off by millimetres moves
the whole fit), where ``ekf``, ``isam2`` and ``lm`` gate them. It stays the paper's baseline, and says
so: after the fit each sample's six drive-leg residuals are tested against the noise model
(:func:`gross_outliers`), and the samples no noise explains are named in the result (``"outliers"``),
which ``calibrate`` prints as a warning.

With an instrument outside the robot (spec §7 ``pose``, ``points``) the same class runs the
batch maximum-likelihood fit of :mod:`.batch` instead: drive, stroke scale and the instrument's
frame and target(s) together, the 12 gauge directions fixed and stated in the result.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np
from threadpoolctl import threadpool_limits

from ..chi_square import chdtri
from ..config import EstimatorConfig, LSConfig, NoiseConfig
from ..errors import CalibError, SampleRejected
from ..estimate import Estimate
from ..instruments import OutsideModel, instrument_kind, outside_model
from ..model import kinematics as kin
from ..model.drive import DriveModel, drive_model
from ..model.platform import LegGeometry, Platform
from ..model.unknowns import UnknownLayout
from ..samples import Sample, input_rows, packed_inputs, unpacked_inputs
from .base import BufferedFit
from .measurement import WarmPose, check_sample, drive_only_model, measured_pose, pose_difference

#: singular values below this fraction of the largest count as zero (rank deficiency).
RANK_TOLERANCE = 1e-10
#: samples :func:`gross_outliers` names in its warning, worst first
NAMED_OUTLIERS = 5
#: samples whose stacked Jacobian is formed at a time: each chunk's rows are folded into the
#: triangular factor of the whole system (a QR update), so memory stays that of one chunk
#: (~8 MB) however long the log, where the stacked ``6N × 42`` Jacobian and its SVD took
#: ~15 GB at 10⁶ samples; a QR of the rows keeps the SVD's accuracy (the normal equations
#: would square the condition number that the rank test reads). The factorisations are small
#: and run on one BLAS thread: on a busy machine OpenBLAS's waiting threads made one 100×
#: slower, and the result does not depend on the thread count.
CHUNK_SAMPLES = 4096


@dataclass(frozen=True)
class PoseNoise:
    """The noise of ``P_v − P_m`` that :func:`gauss_newton`'s covariance carries (and, with
    ``ls.weighting = "noise"``, its weighting).

    Attributes:
        tracker: the tracker's legs, whose readings' FK is ``P_v``.
        reading_sigma_mm: σ_z of a tracker reading [mm].
        stroke_sigma_mm: σ_q of an executed stroke [mm].
    """

    tracker: LegGeometry
    reading_sigma_mm: float
    stroke_sigma_mm: float


@dataclass(frozen=True)
class LSSolution:
    """Result of :func:`gauss_newton`.

    Attributes:
        error: ``(size,)`` the drive's unknowns ``[δM [mm] | its unknown terms]`` (δM alone,
            ``n_params``, without a drive model).
        covariance: ``(size, size)``, the sandwich of the weighted fit (module docstring), or None
            when rank deficient.
        singular_values: ``(min(6N, size),)`` of the weighted stacked ``J_p`` at the solution,
            descending (the paper's weighting: [mm / mm]; the noise's: [1 / mm]); their ratio is the
            conditioning of the identification.
        iterations: Gauss–Newton iterations taken.
        residual_rms: RMS of the weighted stacked residual at the solution (the paper's weighting:
            [mm]; the noise's: in σ, near 1 where the noise is as told).
    """

    error: np.ndarray
    covariance: np.ndarray | None
    singular_values: np.ndarray
    iterations: int
    residual_rms: float


def gauss_newton(
    nominal: LegGeometry,
    strokes: np.ndarray,
    R_v: np.ndarray,
    t_v: np.ndarray,
    config: LSConfig,
    noise: PoseNoise,
    drive: DriveModel | None = None,
    channels: Mapping[str, np.ndarray] | None = None,
) -> LSSolution:
    """Iterated least squares ``min Σ_k ‖W_k (P_v,k − P_m,k(x))‖²`` (paper eq. 9–11; ``W_k``:
    :func:`pose_weights`).

    Args:
        nominal: nominal drive legs M (prismatic: the paper's error Jacobian ``J_p``).
        strokes: ``(N, n_legs)`` executed strokes [mm] (with ``drive``: as logged).
        R_v, t_v: ``(N, 3, 3)``, ``(N, 3)`` measured poses P_v.
        config: tolerance, iteration cap, weighting (and the paper's rotation weight).
        noise: the readings' and strokes' noise, which the covariance (and the noise's weighting)
            carries through both FKs.
        drive: the drive model whose extensions the strokes go through, its unknown terms fitted
            with δM (an extension enters ``P_m`` as the leg's initial length does, so their columns
            are ``J_p``'s ``l_i`` columns times ``∂e_i/∂v``); an elastic drive's leg forces are taken
            at ``P_v`` under the samples' input ``channels`` (each ``(N, ...)``, ``Log.inputs``) with the
            geometry of each iteration. None: the
            strokes are the legs' length changes and the unknowns δM alone.
    Raises:
        CalibError: the model's FK fails (the iteration diverged) or no convergence.
    """
    n_params = nominal.n_params
    size = n_params if drive is None else drive.size
    n = len(strokes)
    error = np.zeros(size)
    R_m, t_m = np.array(R_v, dtype=float), np.array(t_v, dtype=float)  # P_v: the best warm start for the FK
    with threadpool_limits(limits=1):
        for iteration in range(1, config.max_iterations + 1):
            legs = nominal.perturbed(error[:n_params])
            factor = np.zeros((0, size + 1))  # the triangular factor of [A | b] over the chunks so far
            for chunk in range(0, n, CHUNK_SAMPLES):
                rows = slice(chunk, min(n, chunk + CHUNK_SAMPLES))
                lengths, inputs = strokes[rows], None
                if drive is not None:  # an elastic drive's forces at P_v
                    inputs = _drive_inputs(drive, strokes, channels, R_v, t_v, error, rows)
                    lengths = drive.extensions(inputs, error)
                sol = legs.forward_kinematics(lengths, guess=(R_m[rows], t_m[rows]), strict=False)
                if not np.all(sol.converged):
                    raise CalibError(f"ls: model forward kinematics failed at iteration {iteration}; the fit diverged")
                R_m[rows], t_m[rows] = sol.R, sol.t
                J_p = _pose_jacobian(legs, sol.R, sol.t, drive, inputs, size)
                W_k = _weighted_noise(config, noise, legs, R_v[rows], t_v[rows], J_p, carriers=False)[0]
                b = (W_k @ pose_difference(R_v[rows], t_v[rows], sol.R, sol.t)[..., None]).reshape(-1)
                A = (W_k @ J_p).reshape(-1, size)
                factor = np.asarray(np.linalg.qr(np.vstack([factor, np.column_stack([A, b])]), mode="r"))
            # [A | b] = Q [[R, c], [0, ρ]]: A's singular values and right vectors are R's, and
            # ‖b − A δ‖² = ρ² + ‖c − R δ‖²
            R, c = factor[:size, :size], factor[:size, size]
            rho2 = float(factor[size, size]) ** 2 if len(factor) > size else 0.0
            U, s, Vt = np.linalg.svd(R, full_matrices=False)
            keep = s > RANK_TOLERANCE * s[0]
            step = Vt[keep].T @ ((U[:, keep].T @ c) / s[keep])
            linearised, error = error, error + step
            if np.max(np.abs(step)) < config.tolerance_mm:
                break
        else:
            raise CalibError(f"ls: Gauss–Newton did not converge in {config.max_iterations} iterations")
        full_rank = bool(np.all(keep)) and 6 * n > size
        if full_rank:
            # at the last iteration's linearisation, as (AᵀA)⁻¹: once, not at every iteration
            meat, noise_trace = _pose_noise_meat(
                legs, strokes, R_v, t_v, R_m, t_m, config, noise, drive, channels, linearised
            )
    residual2 = rho2 + float(np.sum((c - R @ step) ** 2))
    covariance = None
    if full_rank:
        bread = (Vt.T / s**2) @ Vt  # (AᵀA)⁻¹
        sandwich = bread @ meat @ bread
        expected_residual2 = noise_trace - float(np.sum(bread * meat))  # E‖b − Aδ‖² at s = 1
        covariance = residual2 / expected_residual2 * sandwich
    return LSSolution(error, covariance, s, iteration, float(np.sqrt(residual2 / (6 * n))))


def pose_weights(config: LSConfig, readings: np.ndarray, strokes: np.ndarray) -> np.ndarray:
    """``(N, 6, 6)`` the weights ``W_k`` of each sample's pose rows ``P_v − P_m``.

    ``readings``, ``strokes``: ``(N, 6, n_legs)`` the pose's sensitivities to the readings and to the
    strokes, each times its σ [mm], so that the pose noise is ``Σ_k = G_v G_vᵀ + G_m G_mᵀ``.
    ``ls.weighting = "noise"``: ``W_k = L_k⁻¹`` with ``Σ_k = L_k L_kᵀ`` (each sample's rows whitened);
    ``"paper"``: the paper's ``diag(1, 1, 1, w, w, w)``, ``w = ls.rotation_weight_mm``.
    """
    if config.weighting == "paper":
        weight = np.r_[np.ones(3), np.full(3, config.rotation_weight_mm)]
        return np.broadcast_to(np.diag(weight), (len(readings), 6, 6))
    pose_noise = readings @ np.swapaxes(readings, -1, -2) + strokes @ np.swapaxes(strokes, -1, -2)
    return np.linalg.inv(np.linalg.cholesky(pose_noise))


def _weighted_noise(
    config: LSConfig,
    noise: PoseNoise,
    legs: LegGeometry,
    R_v: np.ndarray,
    t_v: np.ndarray,
    J_p: np.ndarray,
    carriers: bool = True,
) -> tuple[np.ndarray, ...]:
    """``(W_k, W_k G_v, W_k G_m)`` of samples at the measured poses ``(R_v, t_v)`` whose model poses
    have the Jacobian ``J_p`` (of ``legs``): :func:`pose_weights` and the weighted pose's sensitivities
    to the readings and the strokes, each times its σ [mm]; ``(W_k,)`` alone without ``carriers`` (a
    Gauss–Newton iteration needs only the weights, and the paper's are the noise's of no sample). A
    leg's length change moves a pose as its initial length l_i does; the strokes' through the drive's
    extensions is taken at its unit gain (stroke scales are 1 to ~1e-3)."""
    if config.weighting == "paper" and not carriers:
        return (pose_weights(config, J_p, J_p),)
    per_leg = legs.n_params // legs.n_legs  # a leg's parameters, its initial length the last
    readings_k = noise.reading_sigma_mm * _length_columns(noise.tracker, R_v, t_v)
    strokes_k = noise.stroke_sigma_mm * J_p[..., per_leg - 1 : legs.n_params : per_leg]
    W_k = pose_weights(config, readings_k, strokes_k)
    return (W_k, W_k @ readings_k, W_k @ strokes_k) if carriers else (W_k,)


def _drive_inputs(
    drive: DriveModel,
    strokes: np.ndarray,
    channels: Mapping[str, np.ndarray] | None,
    R_v: np.ndarray,
    t_v: np.ndarray,
    error: np.ndarray,
    rows: slice,
) -> np.ndarray:
    """The drive's inputs of the samples ``rows`` (an elastic drive's forces at ``P_v``)."""
    return drive.inputs(strokes[rows], input_rows(channels or {}, rows), R_v[rows], t_v[rows], error)


def _pose_jacobian(
    legs: LegGeometry, R: np.ndarray, t: np.ndarray, drive: DriveModel | None, inputs: np.ndarray | None, size: int
) -> np.ndarray:
    """``(N, 6, size)``: ``J_p`` at the poses ``(R, t)`` the model ``legs`` reach, with the drive's unknown
    terms' columns (``J_p``'s ``l_i`` columns times ``∂e_i/∂v``)."""
    J_p = kin.error_jacobian(legs, R, t)
    if drive is not None and inputs is not None and size > legs.n_params:
        per_leg = legs.n_params // legs.n_legs
        J_p = np.concatenate([J_p, J_p[..., per_leg - 1 :: per_leg] @ drive.extension_jacobian(inputs)], -1)
    return J_p


def _pose_noise_meat(
    legs: LegGeometry,
    strokes: np.ndarray,
    R_v: np.ndarray,
    t_v: np.ndarray,
    R_m: np.ndarray,
    t_m: np.ndarray,
    config: LSConfig,
    noise: PoseNoise,
    drive: DriveModel | None,
    channels: Mapping[str, np.ndarray] | None,
    error: np.ndarray,
) -> tuple[np.ndarray, float]:
    """``(Σ_k A_kᵀ S_k A_k, Σ_k tr S_k [mm²])`` of the sandwich covariance (module docstring), ``S_k`` the
    weighted pose noise of sample ``k``, ``A_k`` its weighted ``J_p`` at the model poses ``(R_m, t_m)`` that
    ``legs`` (of the unknowns ``error``) reach, chunk by chunk as :func:`gauss_newton` forms them."""
    n = len(strokes)
    size = legs.n_params if drive is None else drive.size
    meat, noise_trace = np.zeros((size, size)), 0.0
    for chunk in range(0, n, CHUNK_SAMPLES):
        rows = slice(chunk, min(n, chunk + CHUNK_SAMPLES))
        inputs = None if drive is None else _drive_inputs(drive, strokes, channels, R_v, t_v, error, rows)
        J_p = _pose_jacobian(legs, R_m[rows], t_m[rows], drive, inputs, size)
        W_k, *carriers = _weighted_noise(config, noise, legs, R_v[rows], t_v[rows], J_p)
        A_k = W_k @ J_p
        for G in carriers:
            carried = (np.swapaxes(G, -1, -2) @ A_k).reshape(-1, size)
            meat += carried.T @ carried
            noise_trace += float(np.sum(G**2))
    return meat, noise_trace


def _length_columns(legs: LegGeometry, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(..., 6, n_legs)``: ``∂P/∂length_i`` in ``pose_difference``'s coordinates at the poses
    ``legs`` reach, the ``l_i`` columns of their error Jacobian ``J_p``."""
    per_leg = legs.n_params // legs.n_legs
    return kin.error_jacobian(legs, R, t)[..., per_leg - 1 :: per_leg]


class Rows:
    """Rows of one width appended one at a time, held in one array that doubles when full: a
    list of per-sample arrays costs several times their values in object headers (~0.6 kB a
    sample for ls's four, against 0.15 kB of values)."""

    def __init__(self) -> None:
        self._data: np.ndarray | None = None
        self._count = 0

    def append(self, row) -> None:
        """Append ``row`` (a number or an array: its values in order)."""
        row = np.ravel(row)
        if self._data is None:
            self._data = np.empty((256, row.size))
        elif self._count == len(self._data):
            self._data = np.concatenate([self._data, np.empty_like(self._data)])
        self._data[self._count] = row
        self._count += 1

    def __len__(self) -> int:
        return self._count

    def values(self) -> np.ndarray:
        """``(rows, width)``: the rows appended, in order (a view)."""
        assert self._data is not None, "no rows yet"
        return self._data[: self._count]


def gross_outliers(
    platform: Platform,
    noise: NoiseConfig,
    gate_probability: float,
    error: np.ndarray,
    residuals: np.ndarray,
    R_v: np.ndarray,
    t_v: np.ndarray,
    t_s: np.ndarray,
) -> dict | None:
    """The samples whose post-fit residuals no noise explains, or None when chance explains them all.

    Each sample's six drive-leg residuals ``r`` [mm] at the fitted model and its measured pose have
    the covariance ``C = σ_q² I + σ_s² (J_d J_s⁻¹)(J_d J_s⁻¹)ᵀ`` (the stroke noise, and the tracker
    readings' noise carried through the tracker's FK onto the drive legs; ``J`` the leg–pose
    Jacobians of drive and tracker), so ``χ² = rᵀ C⁻¹ r`` is χ²(6) for a good sample. A sample is a
    gross outlier when its χ² is beyond the gate's χ²(6) quantile times the scale the bulk fits at
    (the median χ² over χ²(6)'s median, at least 1): a noise σ configured too small scales every
    sample alike and names none. Chance puts ``N (1 − p)`` samples beyond the gate; the outliers are
    reported when more are, by three Poisson σ and one.

    Returns:
        ``{"count", "samples", "gate_chi2", "bulk_scale", "t_s", "chi2", "noise_multiple"}`` of the outliers
        (the :data:`NAMED_OUTLIERS` worst named by time, with their χ² and their RMS residual over the
        noise's), JSON-ready; None when the gate is off.
    """
    if not 0.0 < gate_probability < 1.0 or len(residuals) == 0:
        return None
    tracker = platform.required_tracker("the ls outlier test")
    legs = platform.prismatic_drive("the ls outlier test").perturbed(error[: platform.drive.n_params])
    carried = kin.leg_pose_jacobian(legs, R_v, t_v) @ np.linalg.inv(kin.leg_pose_jacobian(tracker, R_v, t_v))
    covariance = noise.stroke_sigma_mm**2 * np.eye(legs.n_legs) + noise.reading_sigma_mm**2 * (
        carried @ np.swapaxes(carried, -1, -2)
    )
    chi2 = np.einsum("ki,ki->k", residuals, np.linalg.solve(covariance, residuals[..., None])[..., 0])
    dof = legs.n_legs
    gate = chdtri(dof, 1.0 - gate_probability)
    scale = max(float(np.median(chi2)) / chdtri(dof, 0.5), 1.0)
    beyond = np.flatnonzero(chi2 > gate * scale)
    chance = len(chi2) * (1.0 - gate_probability)
    if len(beyond) <= chance + 3.0 * np.sqrt(chance) + 1.0:
        return None
    worst = beyond[np.argsort(chi2[beyond])[::-1][:NAMED_OUTLIERS]]
    multiple = np.sqrt(chi2[worst] / dof)  # RMS whitened residual: the residual in units of its σ
    return {
        "count": len(beyond),
        "samples": len(chi2),
        "gate_chi2": float(gate),
        "bulk_scale": scale,
        "t_s": [float(v) for v in t_s[worst]],
        "chi2": [float(v) for v in chi2[worst]],
        "noise_multiple": [float(v) for v in multiple],
    }


def outlier_warning(outliers: dict) -> str:
    """The one-line warning of :func:`gross_outliers`' result."""
    times = ", ".join(f"{t:.6g}" for t in outliers["t_s"])
    low, high = min(outliers["noise_multiple"]), max(outliers["noise_multiple"])
    bulk = outliers["bulk_scale"]
    return (
        f"warning: ls took in {outliers['count']} of {outliers['samples']} samples that no noise explains: their "
        f"post-fit leg residuals are up to {high:.3g}× their σ (χ² up to {max(outliers['chi2']):.4g} against the "
        f"gate's {outliers['gate_chi2']:.3g}{f' × {bulk:.3g}, the scale the others fit at' if bulk > 1 else ''}; "
        f"the worst at t_s = {times} s, {low:.3g}–{high:.3g}× σ) — gross errors that move the whole fit; ekf, "
        "isam2 and lm gate them"
    )


class LeastSquares(BufferedFit):
    """Batch LS: ``update`` buffers measured poses, ``estimate`` fits all of them.

    Attributes:
        singular_values: of the weighted stacked ``J_p`` at the last fit (None before).
        rejected: ``(index in the fitted samples, SampleRejected)`` of samples :meth:`fit` skipped.
    """

    name = "ls"

    def __init__(self, platform: Platform, config: EstimatorConfig):
        self.platform = platform
        self.config = config.ls
        # the outlier test's noise model and gate: those ekf gates the same samples with
        self._noise, self._gate_probability = config.noise, config.ekf.gate_probability
        self.drive = drive_model(platform)
        self._external = outside_model(platform) if instrument_kind(platform).outside else None
        if self._external is None:
            if platform.drive.kind != "prismatic":  # eq. 8–11: the error Jacobian of prismatic legs
                raise CalibError(
                    f"{platform.source}: ls with the in-situ tracker fits the paper's prismatic legs, not a "
                    f"{platform.drive.kind} drive; use ekf, isam2 or lm"
                )
            self.model = drive_only_model(self.name, platform, config, drive_blocks=True)
            self._pose = WarmPose(self.model)
            fitted = drive_model(platform, config.noise)
            # the paper's LS on δM alone where the drive has no unknown term and no leg forces
            self._fitted = fitted if fitted.blocks or fitted.elastic is not None else None
        self._strokes, self._channels = Rows(), Rows()
        self._R_v = Rows()  # R_v, or with an outside instrument the readings
        self._t_v = Rows()  # t_v, or with an outside instrument the sample times
        self._t_s = float("nan")
        self._times: list[float] = []  # the tracker's samples' t_s, which name the outliers
        self.singular_values: np.ndarray | None = None
        self.rejected: list[tuple[int, SampleRejected]] = []

    def update(self, sample: Sample) -> None:
        """Buffer one sample's strokes and measured pose ``P_v`` (paper Fig. 3 step 1), or with an
        outside instrument its strokes and readings."""
        if self._external is not None:
            strokes, readings = check_sample(self.platform, self._external, sample)
            self._strokes.append(strokes)
            self._channels.append(packed_inputs(sample.inputs))
            self._R_v.append(readings)
            self._t_v.append(sample.t_s)
            self._t_s = sample.t_s
            return
        strokes, z = check_sample(self.platform, self.model, sample)
        if self._fitted is None:
            strokes = self.drive.extensions(self.drive.inputs(strokes, sample.inputs))  # the drive's nominal terms
        R_v, t_v = measured_pose(self._pose, z, sample.t_s)
        self._strokes.append(strokes)
        self._channels.append(packed_inputs(sample.inputs))
        self._R_v.append(R_v)
        self._t_v.append(t_v)
        self._times.append(sample.t_s)
        self._t_s = sample.t_s

    def estimate(self) -> Estimate:
        """Fit every buffered sample; zeros and no covariance before the first sample."""
        if not len(self._strokes):
            return Estimate(np.zeros(self.drive.n_params), None, self.name)
        if self._external is not None:
            return self._estimate_external(self._external)
        strokes, R_v = self._strokes.values(), self._R_v.values().reshape(-1, 3, 3)
        t_v, channels = self._t_v.values(), unpacked_inputs(self._channels.values())
        solution = gauss_newton(
            self.platform.prismatic_drive("ls with the in-situ tracker"),
            strokes,
            R_v,
            t_v,
            self.config,
            PoseNoise(
                self.platform.required_tracker("ls with the in-situ tracker"),
                self._noise.reading_sigma_mm,
                self._noise.stroke_sigma_mm,
            ),
            self._fitted,
            channels,
        )
        self.singular_values = solution.singular_values
        if self._fitted is None or not self._fitted.blocks:
            estimate = Estimate(solution.error, solution.covariance, self.name, len(self._strokes), self._t_s)
        else:
            layout = UnknownLayout(self._fitted.blocks, n_params=self._fitted.n_params)
            estimate = Estimate.of_state(
                solution.error, solution.covariance, layout, self.name, len(self._strokes), self._t_s
            )
        extensions = strokes  # the legs' length changes: δM's fit, or the fitted drive's terms at its solution
        if self._fitted is not None:
            inputs = self._fitted.inputs(strokes, channels, R_v, t_v, solution.error)
            extensions = self._fitted.extensions(inputs, solution.error)
        legs = self.platform.drive.perturbed(solution.error[: self.platform.drive.n_params])
        residuals = legs.coordinates(R_v, t_v) - extensions
        outliers = gross_outliers(
            self.platform,
            self._noise,
            self._gate_probability,
            solution.error,
            residuals,
            R_v,
            t_v,
            np.array(self._times),
        )
        return estimate if outliers is None else replace(estimate, details={"outliers": outliers})

    def _estimate_external(self, model: OutsideModel) -> Estimate:
        from ..instruments.gauge import GAUGE_STATEMENT
        from .batch import BatchProblem, fit

        channels = unpacked_inputs(self._channels.values())
        problem = BatchProblem(
            drive=self.drive.identifying(),
            inputs=self.drive.inputs_near(self._strokes.values(), channels),
            channels=channels,
            measured=self._R_v.values(),
            model=model,
            t_s=self._t_v.values()[:, 0],
        )
        sol = fit(
            problem,
            self.config.robust_k,
            self.config.estimate_noise,
            self.config.drive_blocks,
            self.config.tolerance_mm,
        )
        self.rejected.extend(sol.rejected)
        self.singular_values = sol.singular_values
        return external_estimate(self.name, problem.drive, model, sol, int(sol.used.sum()), self._t_s, GAUGE_STATEMENT)


def external_estimate(method: str, drive, model, sol, samples_used: int, t_s: float, gauge: str) -> Estimate:
    """An :class:`Estimate` over ``[x_drive | instrument]`` (spec §7 blocks) from a
    :class:`~.batch.BatchSolution` of ``drive``; the instrument's tangent covariance carried into its θ."""
    from ..model.unknowns import UnknownLayout

    layout = UnknownLayout((*drive.blocks, model.unknowns), n_params=drive.n_params)
    x = np.concatenate([sol.x_drive, model.theta(sol.unknowns) - model.unknowns.nominal])
    P = None
    if sol.covariance is not None:
        lift = np.eye(layout.size)
        lift[drive.size :, drive.size :] = model.theta_jacobian(sol.unknowns)
        P = lift @ sol.covariance @ lift.T
    details = {
        "gauge": gauge,
        **{f"{block.key}_identified": sol.drive_blocks_fitted[block.key] for block in drive.blocks},
        "noise_estimated": sol.noise_sigmas,
        "residual_rms": sol.residual_rms,
        "readings_downweighted": sol.downweighted,
        "readings_rejected_as_gross_errors": sol.rejected_as_gross,
    }
    return replace(Estimate.of_state(x, P, layout, method, samples_used, t_s), details=details)
