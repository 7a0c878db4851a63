"""One task of a sweep: simulate one cell's data for one seed, run every method on it, score them.

Pure of Dask: :func:`run_task` takes plain objects and returns rows (dicts), so a worker
anywhere computes the same rows from the same (cell, seed) — every draw comes from
``np.random.default_rng([seed, *cell id words])``, nothing from the worker or the order.

**The data** (:func:`simulate`): the controlled laboratory of the benchmarks — a true δM drawn
i.i.d. N(0, error_sigma²), random workspace poses (one sample each at ``rate_hz``), strokes from
IK of the true drive, tracker readings from IK of the known tracker geometry, white noise of
exactly the estimators' model. With ``drift_mm_per_sqrt_s`` > 0 the true δM walks (the
estimators' process model, matched). A glitch adds ±``glitch_size_mm`` to one reading (leg drawn
at random) in a ``glitch_rate`` fraction of the samples — what a dirty grating or a lost count does.

**The scores** (:func:`score`), each of the final estimate against the true δM in force at the
last sample:

* ``rms_mm``: RMS of the 42 errors.
* ``rms_over_crb``: RMS of the errors in units of the bound (:func:`bound_stddev_mm`) over the
  identified parameters — 1 for an efficient estimator.
* ``nees``: ``eᵀ Σ⁻¹ e`` with the estimate's own covariance (χ²(42) when consistent).
* ``z2``: mean of ``(e_p / σ_p)²`` over the 42 parameters with the estimate's own σ_p — 1 when
  the reported standard deviations are right, whatever their correlations.
* ``closed_loop_mm`` / ``closed_loop_deg``: mean pose error when the controller commands IK with
  the estimated drive to ``validation_poses`` fresh poses and the true robot goes to FK of those
  strokes; ``closed_loop_nominal_mm`` is the same with the nominal drive (uncalibrated).
* ``seconds`` / ``cpu_seconds``: wall and CPU time of the method on the log (CPU time does not
  grow when other work shares the machine: what a study's projection to a cluster uses);
  ``samples_rejected``: samples it refused.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .. import kinematics as kin
from ..config import NoiseConfig
from ..errors import CalibError, SampleRejected
from ..estimators import BatchEstimator, make_estimator
from ..estimators.base import fit_all
from ..identifiability import identifiability_report, whitened_leg_jacobian
from ..platform import N_PARAMS, Platform, vector_to_params
from ..samples import Log
from ..simulation.trajectories import random_static_poses
from .spec import Cell, Family

#: Range margin of the random poses [mm]: the true robot stands up to a few mm from where the
#: nominal model puts it, and glitch-free readings must stay inside the reading range.
POSE_MARGIN_MM = 10.0

METRICS = (
    "rms_mm",
    "rms_over_crb",
    "nees",
    "z2",
    "closed_loop_mm",
    "closed_loop_deg",
    "closed_loop_nominal_mm",
    "seconds",
    "cpu_seconds",
)


@dataclass(frozen=True)
class SweepData:
    """One task's simulated data.

    Attributes:
        platform: the nominal platform (a family's draw, or the cell's platform).
        log: what the estimators see (N samples).
        true_params: ``(N, 42)`` true drive parameters in force at each sample [mm].
        glitched: ``(N,)`` True where one reading carries a glitch.
        validation_poses: ``(V, 6)`` fresh poses of the closed-loop check [mm, rad].
    """

    platform: Platform
    log: Log
    true_params: np.ndarray
    glitched: np.ndarray
    validation_poses: np.ndarray

    @property
    def true_error(self) -> np.ndarray:
        """δM in force at the last sample [mm]."""
        return self.true_params[-1] - self.platform.drive.as_vector()


def task_rng(cell_id: str, seed: int) -> np.random.Generator:
    """The task's generator: the seed and the cell id's 48 bits as three 16-bit words."""
    return np.random.default_rng([seed, *(int(cell_id[k : k + 4], 16) for k in range(0, len(cell_id), 4))])


def simulate(settings: dict, platform: Platform | Family, rng: np.random.Generator) -> SweepData:
    """The data of one task (see the module docstring); draws in a fixed order from ``rng``."""
    nominal = platform.draw(rng) if isinstance(platform, Family) else platform
    n = settings["samples"]
    dt_s = 1.0 / settings["rate_hz"]
    error0 = rng.normal(0.0, settings["error_sigma_mm"], N_PARAMS)
    poses = random_static_poses(nominal, n, rng, settings["workspace_fraction"], POSE_MARGIN_MM)
    steps = rng.normal(0.0, settings["drift_mm_per_sqrt_s"] * np.sqrt(dt_s), (n, N_PARAMS))
    steps[0] = 0.0
    true_params = nominal.drive.as_vector() + error0 + np.cumsum(steps, axis=0)
    R, t = kin.pose_to_rt(poses)
    strokes = _leg_lengths(true_params, R, t) - vector_to_params(true_params)[..., 6]
    strokes += rng.normal(0.0, settings["stroke_sigma_mm"], strokes.shape)
    readings = kin.inverse_kinematics(nominal.required_tracker("the sweep"), R, t) + rng.normal(
        0.0, settings["reading_sigma_mm"], (n, 6)
    )
    glitched = rng.random(n) < settings["glitch_rate"]
    legs = rng.integers(0, 6, n)
    signs = rng.choice([-1.0, 1.0], n)
    readings[glitched, legs[glitched]] += signs[glitched] * settings["glitch_size_mm"]
    validation = random_static_poses(
        nominal, settings["validation_poses"], rng, settings["workspace_fraction"], POSE_MARGIN_MM
    )
    log = Log(t_s=np.arange(n) * dt_s, strokes=strokes, readings=readings, desired_poses=poses)
    return SweepData(nominal, log, true_params, glitched, validation)


def _leg_lengths(params: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``‖t + R d_i − j_i‖`` with a drive of its own per pose, ``(N, 6)`` [mm]."""
    p = vector_to_params(params)
    base, plat = p[..., 0:3], p[..., 3:6]
    return np.linalg.norm(t[:, None, :] + np.einsum("nij,nkj->nki", R, plat) - base, axis=-1)


def bound_stddev_mm(data: SweepData, settings: dict, prior_sigma_mm: float) -> np.ndarray:
    """Lower bound on the standard deviation of each parameter of the final δM, ``(42,)`` [mm].

    Constant parameters: the Cramér–Rao bound ``(AᵀA)⁻¹`` of the information matrix of these
    poses under the simulated noise (:func:`~stewart_calib.identifiability.identifiability_report`;
    inf for a parameter the poses do not identify). Drifting parameters: the posterior
    (Bayesian) bound of the final value — the information recursion ``J_k = (J_{k−1}⁻¹ + q²Δt I)⁻¹
    + A_kᵀA_k`` over the same whitened rows ``A_k``, from the estimators' prior
    ``J_0 = I / prior_sigma²`` (Tichavský et al. 1998): with a random walk no estimator can
    beat the optimal filter of the linearised model.
    """
    noise, poses = _true_noise(settings), data.log.desired_poses
    if poses is None:
        raise ValueError("a sweep's simulated log holds its poses")
    if settings["drift_mm_per_sqrt_s"] == 0:
        return identifiability_report(data.platform, poses, noise, paper_form=False).predicted_stddev_mm
    rows = whitened_leg_jacobian(data.platform, poses, noise)
    walk = settings["drift_mm_per_sqrt_s"] ** 2 / settings["rate_hz"] * np.eye(N_PARAMS)
    covariance = prior_sigma_mm**2 * np.eye(N_PARAMS)
    for k, A in enumerate(rows):
        predicted = covariance + walk if k else covariance
        covariance = np.linalg.inv(np.linalg.inv(predicted) + A.T @ A)
    return np.sqrt(np.diag(covariance))


def _true_noise(settings: dict) -> NoiseConfig:
    """The simulated noise (what the bound is for, whatever the estimators are told)."""
    return NoiseConfig(settings["reading_sigma_mm"], settings["stroke_sigma_mm"], settings["drift_mm_per_sqrt_s"])


def closed_loop_errors(data: SweepData, error: np.ndarray) -> tuple[float, float]:
    """Mean position [mm] and orientation [deg] error at the validation poses when IK uses
    ``nominal + error`` and the true robot (parameters of the last sample) executes the strokes."""
    R_d, t_d = kin.pose_to_rt(data.validation_poses)
    strokes = kin.inverse_kinematics(data.platform.drive.perturbed(error), R_d, t_d)
    true_drive = data.platform.drive.perturbed(data.true_error)
    actual = kin.forward_kinematics(true_drive, strokes, (R_d, t_d))
    position_mm, orientation_deg = kin.pose_error(R_d, t_d, actual.R, actual.t)
    return float(position_mm.mean()), float(orientation_deg.mean())


def score(data: SweepData, error: np.ndarray, covariance: np.ndarray | None, crb_mm: np.ndarray) -> dict:
    """Scores of one estimate (see the module docstring), ``seconds`` left to the caller."""
    e = error - data.true_error
    identified = np.isfinite(crb_mm)
    nees = z2 = float("nan")
    if covariance is not None:
        try:
            nees = float(e @ np.linalg.solve(covariance, e))
        except np.linalg.LinAlgError:
            pass
        variance = np.diag(covariance)
        if np.all(variance > 0):
            z2 = float(np.mean(e**2 / variance))
    position_mm, orientation_deg = closed_loop_errors(data, error)
    return {
        "rms_mm": float(np.sqrt(np.mean(e**2))),
        "rms_over_crb": float(np.sqrt(np.mean((e[identified] / crb_mm[identified]) ** 2)))
        if identified.any()
        else float("nan"),
        "nees": nees,
        "z2": z2,
        "closed_loop_mm": position_mm,
        "closed_loop_deg": orientation_deg,
    }


def run_method(
    method: str, data: SweepData, cell: Cell, checkpoints: tuple[int, ...], refit: bool, crb_mm: np.ndarray
) -> dict:
    """Run one method on the task's log; its scores, rejections and checkpoint ratios."""
    samples = list(data.log)
    nominal = data.platform.drive.as_vector()
    estimator = make_estimator(method, data.platform, cell.estimator_config)
    at_checkpoint = {}
    start, cpu_start = time.perf_counter(), time.process_time()
    if isinstance(estimator, BatchEstimator):  # the methods that are not online
        estimate = estimator.fit(samples)
        rejected = len(estimator.rejected)
        for n in checkpoints if refit else ():
            try:
                at_checkpoint[n] = fit_all(
                    make_estimator(method, data.platform, cell.estimator_config), samples[:n]
                ).error
            except CalibError:  # e.g. ls not converging on a short prefix: that checkpoint is NaN
                at_checkpoint[n] = np.full(N_PARAMS, np.nan)
    else:
        rejected = 0
        for k, sample in enumerate(samples, start=1):
            try:
                estimator.update(sample)
            except SampleRejected:
                rejected += 1
            if k in checkpoints:
                at_checkpoint[k] = estimator.current_error()
        estimate = estimator.estimate()
    seconds, cpu_seconds = time.perf_counter() - start, time.process_time() - cpu_start
    row = score(data, estimate.error, estimate.covariance, crb_mm)
    row["seconds"], row["cpu_seconds"] = seconds, cpu_seconds
    row["samples_rejected"] = rejected
    for n in checkpoints:  # against the bound of the whole log (the benchmarks' convergence measure)
        error = at_checkpoint.get(n)
        z = (error - (data.true_params[n - 1] - nominal)) / crb_mm if error is not None else np.full(N_PARAMS, np.nan)
        row[f"rms_over_crb_at_{n}"] = float(np.sqrt(np.mean(z[np.isfinite(crb_mm)] ** 2)))
    return row


def run_task(
    cell: Cell,
    seed: int,
    methods: tuple[str, ...],
    checkpoints: tuple[int, ...] = (),
    refit_at_checkpoints: tuple[str, ...] = (),
) -> list[dict]:
    """Every method on one (cell, seed): one row per method (settings, scores, ``failure``).

    A method that refuses the data (a :class:`CalibError`, e.g. least squares not converging,
    or a singular solve) gives a row of NaN scores with ``failure`` saying why; anything else
    propagates (a bug, reported by the runner with the task named).
    """
    rng = task_rng(cell.id, seed)
    data = simulate(cell.settings, cell.platform, rng)
    crb_mm = bound_stddev_mm(data, cell.settings, cell.estimator_config.noise.prior_sigma_mm)
    nominal_mm, _ = closed_loop_errors(data, np.zeros(N_PARAMS))
    rows = []
    for method in methods:
        try:
            scores = run_method(method, data, cell, checkpoints, method in refit_at_checkpoints, crb_mm)
            failure = ""
        except (CalibError, np.linalg.LinAlgError) as err:
            scores = {name: float("nan") for name in METRICS} | {"samples_rejected": None}
            scores |= {f"rms_over_crb_at_{n}": float("nan") for n in checkpoints}
            failure = str(err).splitlines()[0] if str(err) else err.__class__.__name__
        scores["closed_loop_nominal_mm"] = nominal_mm
        rows.append(
            {
                "cell": cell.id,
                "seed": seed,
                "method": method,
                **cell.settings,
                **scores,
                "glitches": int(data.glitched.sum()),
                "failure": failure,
            }
        )
    return rows
