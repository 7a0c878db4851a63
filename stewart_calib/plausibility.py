"""Is an estimate credible for the platform it was made for? Refuse a log of another platform.

Two symptoms, each far outside what a log of the right platform can produce:

* **Parameters far beyond the prior.** The prior says each δM component is N(0, σ_p²)
  (``noise.prior_sigma_mm``, the manufacturing tolerance). A component beyond
  :data:`PRIOR_SIGMAS` σ_p has prior probability below 1e-20: the platform file does not
  describe the robot. This catches the methods that fit any 6-6 drive exactly (``isam2``,
  ``ls``: 42 parameters are the whole drive geometry), whose residuals stay small.
* **Residuals orders of magnitude above the noise.** The RMS drive-leg residual
  ``‖t + R d_i − j_i‖ − (l_i + q_i)`` at the estimate, with the tracker's pose from FK of the
  readings, against the configured measurement σ (``noise.reading_sigma_mm`` and
  ``stroke_sigma_mm``, the larger): beyond :data:`RESIDUAL_SIGMAS` × σ no noise model explains
  it (a filter that diverged on foreign data).

A third symptom, when the estimator measures the noise (``ekf``, ``isam2``): a scatter two
orders of magnitude beyond the configured σ (:data:`NOISE_SCALE_LIMIT`), what a stream in
which every sample is a glitch looks like.

The thresholds are in units of the user's own σ, so they follow the configuration, and both
sit orders of magnitude past the largest values measured on logs of the right platform whose
noise is mismatched 5× (tests/test_plausibility.py).
"""

from __future__ import annotations

import numpy as np

from . import kinematics as kin
from .config import NoiseConfig
from .errors import CalibError
from .platform import Platform

#: a parameter error beyond this many prior σ is refused (two-sided tail probability < 1e-20).
PRIOR_SIGMAS = 10.0
#: an RMS leg residual beyond this many measurement σ is refused (three orders of magnitude).
RESIDUAL_SIGMAS = 1000.0
#: a measurement noise the estimator finds beyond this multiple of the configured σ is refused
#: (two orders of magnitude: σ wrong by 2–5× or a sagging platform's ~10× pass).
NOISE_SCALE_LIMIT = 100.0


def rms_leg_residual_mm(platform: Platform, error: np.ndarray, strokes: np.ndarray, readings: np.ndarray) -> float:
    """RMS of the drive-leg residuals [mm] of the samples (strokes ``(N, legs)``, tracker readings
    ``(N, rulers)``) at the model ``M + error``.

    Samples whose tracker FK does not converge are left out (nan when none converges).
    """
    strokes = np.asarray(strokes, dtype=float).reshape(-1, platform.drive.n_legs)
    if not len(strokes):
        return float("nan")
    tracker = platform.required_tracker("the plausibility check")
    readings = np.asarray(readings, dtype=float).reshape(-1, tracker.n_legs)
    # The drive's residual at the tracker's FK pose is the tracker-reading residual with the two
    # leg sets' roles swapped (q − (‖t + R d_i − j_i‖ − l_i), the negated leg residual): one
    # compiled pass whose FK starts from the sample before (track checks every --every rows,
    # ~3.5x the cold batch FK measured).
    residuals, converged = kin.tracker_reading_residuals(
        platform.drive.perturbed(error), strokes, [tracker], [readings]
    )
    if not converged.any():
        return float("nan")
    return float(np.sqrt(np.mean(np.square(residuals[converged]))))


def check_plausible(
    platform: Platform,
    error: np.ndarray,
    noise: NoiseConfig,
    strokes: np.ndarray,
    readings: np.ndarray,
    method: str,
    noise_scale: float | None = None,
) -> None:
    """Refuse an estimate that the log cannot have come from ``platform`` with (see the module).

    Args:
        error: δM [mm] of the estimate. strokes, readings: ``(N, legs)``, ``(N, rulers)`` samples it was fitted to
            (all of them, or the most recent ones for an online run) [mm]; with none, only
            the parameters are checked.
        noise_scale: the measurement noise the estimator found in the data, as a multiple of
            the configured σ (``ekf``, ``isam2``; None: not checked). Beyond
            :data:`NOISE_SCALE_LIMIT` no sample agrees with the others — a stream of glitches.
    Raises:
        CalibError: one line with the RMS residual, the largest parameter error and both limits.
    """
    error = np.asarray(error, dtype=float)
    sigma_mm = max(noise.reading_sigma_mm, noise.stroke_sigma_mm)
    rms_mm = rms_leg_residual_mm(platform, error, strokes, readings)
    worst = int(np.argmax(np.abs(error)))
    beyond_prior = abs(error[worst]) > PRIOR_SIGMAS * noise.prior_sigma_mm
    # nan (no pose could be solved) counts as beyond the noise
    beyond_noise = np.size(strokes) > 0 and not rms_mm <= RESIDUAL_SIGMAS * sigma_mm
    scattered = noise_scale is not None and noise_scale > NOISE_SCALE_LIMIT
    if beyond_prior or beyond_noise or scattered:
        scatter = (
            f"; the samples scatter {noise_scale:.3g} × the configured noise σ (limit {NOISE_SCALE_LIMIT:g} ×)"
            if noise_scale is not None
            else ""
        )
        # an outside instrument's samples are not checked here (no tracker legs): no residual to name
        residual = (
            f"RMS leg residual {rms_mm:.3g} mm at the estimate ({rms_mm / sigma_mm:.3g} × the noise σ {sigma_mm:g} mm; "
            f"limit {RESIDUAL_SIGMAS:g} ×), "
            if np.size(strokes)
            else ""
        )
        raise CalibError(
            f"{method}: the log does not fit platform '{platform.name}': {residual}largest "
            f"parameter error {platform.drive.parameter_names[worst]} = {error[worst]:.4g} mm "
            f"({abs(error[worst]) / noise.prior_sigma_mm:.3g} × the prior σ {noise.prior_sigma_mm:g} mm; limit "
            f"{PRIOR_SIGMAS:g} ×){scatter} — a log of another platform, glitches in every sample, or a platform file "
            "that does not describe this robot?"
        )
