"""Small, exact test data straight from the kinematics (no load model, no tracker bias).

The simulator (``stewart_calib.simulation``) is the honest laboratory; this is the
controlled one: a true drive ``nominal + δM``, random workspace poses, strokes from IK of
the true drive, tracker readings from IK of the known tracker geometry plus white noise.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stewart_calib.io.platform_file import load_platform
from stewart_calib.model import kinematics as kin
from stewart_calib.model.platform import LegGeometry, Platform
from stewart_calib.samples import Log

ROOT = Path(__file__).resolve().parents[1]
NIM_STEWART = ROOT / "configs" / "platforms" / "nim-stewart.toml"


def nim_stewart() -> Platform:
    return load_platform(NIM_STEWART)


class NumpyLegs(LegGeometry):
    """The paper's legs as a leg model the compiled kernels do not take (only the exact
    :class:`LegGeometry` is theirs): the yardstick of the paths a rotary drive takes."""

    kind = "prismatic"
    parameter_degrees = np.zeros(42, dtype=bool)

    def residual_jacobians(self, R, t, e, *, lengthening=None):
        J_pose, J_M = kin.leg_residual_jacobians(self, R, t)
        return J_pose, J_M, -np.ones(np.shape(e))

    def perturbed(self, delta):
        return numpy_legs(LegGeometry.perturbed(self, delta))

    def coordinate_sigma(self, noise):
        return noise.stroke_sigma_mm

    def prior_sigmas(self, noise):
        return np.full(self.n_params, noise.prior_sigma_mm)


def numpy_legs(legs: LegGeometry) -> NumpyLegs:
    return NumpyLegs(legs.base_joints, legs.platform_joints, legs.initial_lengths)


def random_poses(platform: Platform, n: int, rng: np.random.Generator, fraction: float = 1.0) -> np.ndarray:
    """``(n, 6)`` pose6 uniform in ``fraction`` of the workspace box, tracker readings in range."""
    ws = platform.workspace
    half = fraction * np.r_[[ws.translation_limit] * 3, [ws.rotation_limit] * 3]
    poses = np.empty((0, 6))
    while len(poses) < n:
        cand = ws.home + rng.uniform(-1.0, 1.0, (2 * n, 6)) * half
        s = kin.inverse_kinematics(platform.tracker, *kin.pose_to_rt(cand))
        lo, hi = platform.reading_range or (-np.inf, np.inf)
        poses = np.vstack([poses, cand[np.all((s >= lo) & (s <= hi), axis=1)]])
    return poses[:n]


def random_error(rng: np.random.Generator, sigma_mm: float = 1.0) -> np.ndarray:
    """A 42-vector δM [mm] drawn i.i.d. normal."""
    return rng.normal(0.0, sigma_mm, 42)


def make_log(
    platform: Platform,
    true_error: np.ndarray,
    poses: np.ndarray,
    rng: np.random.Generator,
    reading_sigma_mm: float = 0.0,
    stroke_sigma_mm: float = 0.0,
    dt_s: float = 0.1,
) -> tuple[Log, np.ndarray]:
    """A log of the true robot at ``poses``; returns ``(log, true_params (N, 42))``.

    ``true_error`` is a 42-vector (constant) or ``(N, 42)`` (time-varying, for drift tests).
    The platform actually sits at ``poses`` (strokes are what put it there on the true robot).
    """
    n = len(poses)
    errors = np.broadcast_to(np.asarray(true_error, dtype=float), (n, 42))
    R, t = kin.pose_to_rt(poses)
    if np.ndim(true_error) == 1:  # one true geometry: one vectorised IK (10⁶ samples in seconds)
        strokes = kin.inverse_kinematics(platform.drive.perturbed(errors[0]), R, t)
    else:
        strokes = np.empty((n, 6))
        for k in range(n):  # true geometry differs per sample
            strokes[k] = kin.inverse_kinematics(platform.drive.perturbed(errors[k]), R[k], t[k])
    readings = kin.inverse_kinematics(platform.tracker, R, t)
    strokes = strokes + rng.normal(0.0, stroke_sigma_mm, strokes.shape) if stroke_sigma_mm else strokes
    readings = readings + rng.normal(0.0, reading_sigma_mm, readings.shape) if reading_sigma_mm else readings
    log = Log(t_s=np.arange(n) * dt_s, strokes=strokes, readings=readings, desired_poses=poses.copy())
    return log, platform.drive.as_vector() + errors


def tracked_log(seed: int, n: int) -> Log:
    """``n`` samples of nim-stewart at random poses with δM of σ 1 mm, reading and stroke noise of
    2 and 1 µm: the small log the command-line tests feed."""
    platform = nim_stewart()
    rng = np.random.default_rng(seed)
    log, _ = make_log(
        platform,
        random_error(rng, 1.0),
        random_poses(platform, n, rng),
        rng,
        reading_sigma_mm=0.002,
        stroke_sigma_mm=0.001,
    )
    return log


def static_logs(platform: Platform, n_poses: int, seed: int) -> tuple[np.ndarray, Log, Log]:
    """``(δM, noise-free log, noisy log)`` at the same ``n_poses`` rich poses, constant δM (σ 1 mm).

    The noisy log has σ_s = 2 µm and σ_q = 1 µm: the defaults of ``configs/estimators/default.toml``,
    so estimators whose noise model matches the data can be checked for consistency.
    """
    rng = np.random.default_rng(seed)
    poses = random_poses(platform, n_poses, rng)
    delta = random_error(rng)
    clean, _ = make_log(platform, delta, poses, rng)
    noisy, _ = make_log(platform, delta, poses, rng, reading_sigma_mm=0.002, stroke_sigma_mm=0.001)
    return delta, clean, noisy
