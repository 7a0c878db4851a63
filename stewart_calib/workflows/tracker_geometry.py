"""The in-situ tracker's own geometry error, measured on the calibration log.

A real tracker's 42 values (its base and platform joints, its rulers' lengths) are never exactly its
nominal ones. Taken as exact, their error has two parts: what the drive's parameters take up (the
calibrated drive then follows the tracker's wrong poses: an error of the result that no sample
shows) and the rest, a reading error that stays while the platform holds a pose. The estimators
count every reading as independent, so both parts are missing from the reported covariance, and
the gate meets readings further off than their σ. Identified with the drive under the prior
``N(nominal, σ_g²)`` (``noise.tracker_geometry_sigma_mm``) they are in the model: the covariance
holds what the log cannot tell apart and the readings are white again. The σ_g to give is what this
module measures.

**The model.** At the drive's least-squares fit ``x̂`` (``ls``), the readings' residuals ``r``
(``N × rulers``, every sample's readings minus what the tracker reads where the drive puts the
platform) are, to first order,

    r = H δx + G δθ + w,    δθ ~ N(0, σ_g² I),    w ~ N(0, σ_w² I),

with ``H = ∂r/∂x`` the drive's unknowns (δM and its unknown terms: compliance, expansion),
``G = ∂r/∂θ`` the tracker's 42 values (central differences of the compiled residual pass of
:func:`~stewart_calib.model.drive.tracker_reading_residuals`) and ``w`` the readings' and strokes'
white noise. Projected off ``H`` (what the drive takes up, and the tracker's rigid motions, which
are the drive's gauge), ``P r`` has the covariance ``σ_w² I + σ_g² (P G)(P G)ᵀ``: along the left
singular vectors of ``P G`` (singular values ``s_k``) its components have variance
``σ_w² + σ_g² s_k²``, elsewhere ``σ_w²``. ``σ_w`` and ``σ_g`` are their maximum-likelihood values
(the ratio ``ρ = σ_g²/σ_w²`` by a search on the profile likelihood, ``σ_w²`` in closed form given
``ρ``). A geometry error is taken as there where the likelihood ratio against ``σ_g = 0`` passes
the test at :data:`FALSE_ALARM` (the ratio is ½χ²₀ + ½χ²₁ under ``σ_g = 0``, a variance at the
boundary of its range); else the tracker is as its nominal geometry says, to what the log can
show, and nothing changes. No repeated poses are needed: white noise spreads over every direction
of the residual, a geometry error only over the few that ``P G`` spans.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import cast

import numpy as np

from .. import estimators
from ..chi_square import chdtri
from ..config import EstimatorConfig
from ..errors import CalibError
from ..estimators.base import BatchEstimator
from ..estimators.measurement import estimator_drive
from ..instruments import instrument_kind
from ..model.drive import tracker_reading_residuals
from ..model.platform import Platform
from ..samples import HeldPoseSamples, Log

#: the probability that a tracker of exactly its nominal geometry is taken as off (the test's size)
FALSE_ALARM = 1e-3
#: the log's first this many samples are what the estimate reads (a streamed log is not read twice)
ESTIMATE_SAMPLES = 2000
#: a streamed log's head holds at most this many times :data:`ESTIMATE_SAMPLES` samples while it looks for
#: them (a log that holds one pose for longer gets no estimate, and says so)
HEAD_LIMIT = 20
#: central-difference step of the drive's parameters and the tracker's values [mm]; a term's values
#: (compliance [mm/kN], expansion, stroke scale) step by 10⁻³ of their prior σ
STEP_MM = 1e-2
#: a sample whose residual RMS is beyond this many times the median sample's is a gross error, left out: a
#: geometry error's share of a sample's residual changes with the pose by a few times, not by ten
GROSS_RATIO = 10.0
#: singular values below this fraction of the largest are directions the data do not see (central differences
#: of residuals solved to 1e-7 mm leave the tracker's rigid motions, which the drive takes up, at ~1e-7)
RANK_TOLERANCE = 1e-6


@dataclass(frozen=True)
class TrackerGeometryEstimate:
    """What the log says of the tracker's own geometry.

    Attributes:
        sigma_mm: σ_g, the maximum-likelihood σ of each of its 42 values' error [mm] (0 where the
            likelihood is highest there).
        white_sigma_mm: σ_w, the readings' white noise beside it [mm].
        likelihood_ratio: ``2 (ln L(σ̂_g) − ln L(0))``.
        threshold: the ratio a geometry error needs to pass (``FALSE_ALARM``).
        directions: the directions of the residual a geometry error moves (the rank of ``P G``).
        samples: the samples it read.
    """

    sigma_mm: float
    white_sigma_mm: float
    likelihood_ratio: float
    threshold: float
    directions: int
    samples: int

    @property
    def detected(self) -> bool:
        """Whether the log shows a geometry error (the likelihood ratio past its threshold)."""
        return self.sigma_mm > 0.0 and self.likelihood_ratio > self.threshold


def applies(platform: Platform, config: EstimatorConfig) -> bool:
    """Whether the estimate is asked for: an in-situ tracker whose geometry is taken as exact (no
    ``[tracker] geometry_sigma_mm``, ``noise.tracker_geometry_sigma_mm = 0``) with
    ``noise.estimate_tracker_geometry`` on, on prismatic drive legs (the compiled residual pass)."""
    return (
        config.noise.estimate_tracker_geometry
        and not instrument_kind(platform).outside
        and platform.tracker is not None
        and platform.tracker_geometry_sigma_mm <= 0.0
        and config.noise.tracker_geometry_sigma_mm <= 0.0
        and platform.drive.compiled
    )


def estimate_samples() -> HeldPoseSamples:
    """An empty pick of the samples the estimate reads: the log's first :data:`ESTIMATE_SAMPLES`, at most
    :data:`~stewart_calib.samples.HELD_SAMPLES` of one held pose, among its first :data:`HEAD_LIMIT` ×
    :data:`ESTIMATE_SAMPLES` (a streamed log's head is held until it is complete)."""
    return HeldPoseSamples(ESTIMATE_SAMPLES, HEAD_LIMIT * ESTIMATE_SAMPLES)


def estimate_tracker_geometry(platform: Platform, log: Log, config: EstimatorConfig) -> TrackerGeometryEstimate | None:
    """σ_g and σ_w of the module's model, measured on ``log``'s :func:`estimate_samples`; None where the
    drive's fit fails or leaves fewer residuals than unknowns: the log is then the method's to judge (its
    plausibility check names a log of another robot), and the geometry stays as given."""
    picked = estimate_samples()
    picked.add(log.strokes)
    log = log.select(np.array(picked.indices, dtype=int))
    noise = dataclasses.replace(config.noise, tracker_geometry_sigma_mm=0.0, pose_misfit_sigma_mm=0.0)
    fit_config = dataclasses.replace(config, noise=noise)
    try:
        fitted = cast(BatchEstimator, estimators.make_estimator("ls", platform, fit_config)).fit(iter(log))
    except CalibError:
        return None
    drive = estimator_drive(platform, noise)
    tracker = platform.required_tracker("the tracker's geometry estimate")
    values = {term.key: fitted.block_values(term.key) for term in drive.terms}
    # the drive's unknowns the fit identified, flat: δM, then each unknown term's values
    unknown = [(term, value) for term in drive.unknown_terms if (value := values[term.key]) is not None]
    fitted_x = np.concatenate([fitted.error, *(value for _, value in unknown)])
    sizes = np.cumsum([len(fitted.error), *(len(value) for _, value in unknown)])[:-1]

    def drive_at(x: np.ndarray):
        error, *terms = np.split(x, sizes)
        return drive.calibrated(error, {**values, **{term.key: v for (term, _), v in zip(unknown, terms, strict=True)}})

    def drives_at(steps: list[tuple[int, float]]) -> list:
        """The fitted drive with its unknown ``steps`` ``(column, step)`` applied one at a time."""
        moved = []
        for column, step in steps:
            x = fitted_x.copy()
            x[column] += step
            moved.append(drive_at(x))
        return moved

    def residuals(drives, legs):
        r, converged = tracker_reading_residuals(drives, legs, log.strokes, log.readings, log.inputs)
        return r, converged.all(axis=0)

    at_fit = [drive_at(fitted_x)]
    (r0,), ok = residuals(at_fit, tracker)
    # a term's values (compliance [mm/kN], expansion, stroke scale) step by 10⁻³ of their prior σ
    steps = [STEP_MM] * len(fitted.error)
    for term, value in unknown:
        steps += [cast(float, term.prior_sigma) * 1e-3] * len(value)  # an unknown term has its σ
    plus = drives_at(list(enumerate(steps)))
    minus = drives_at([(k, -h) for k, h in enumerate(steps)])
    r_plus, ok_plus = residuals(plus, tracker)
    r_minus, ok_minus = residuals(minus, tracker)
    H = ((r_plus - r_minus) / (2.0 * np.asarray(steps))[:, None, None]).reshape(len(steps), -1).T
    G_columns, ok_g = [], ok & ok_plus & ok_minus
    base = tracker.as_vector()
    for k in range(len(base)):
        delta = np.zeros_like(base)
        delta[k] = STEP_MM
        (above,), ok_above = residuals(at_fit, tracker.perturbed(delta))
        (below,), ok_below = residuals(at_fit, tracker.perturbed(-delta))
        ok_g &= ok_above & ok_below
        G_columns.append(((above - below) / (2.0 * STEP_MM)).ravel())
    G = np.array(G_columns).T
    rulers = log.readings.shape[1]
    kept = ok_g.copy()  # a sample whose FK fails in any model is left out, and a gross error
    kept[ok_g] = ~_gross(r0[ok_g].ravel(), H[np.repeat(ok_g, rulers)], rulers)
    rows = np.repeat(kept, rulers)
    if rows.sum() <= H.shape[1] + G.shape[1]:
        return None
    return _variance_components(r0.ravel()[rows], H[rows], G[rows], int(kept.sum()))


def _gross(r: np.ndarray, H: np.ndarray, rulers: int) -> np.ndarray:
    """The samples whose residual off ``H`` is beyond :data:`GROSS_RATIO` × the median sample's RMS: a
    glitch of a reading, which would otherwise be taken for white noise of every reading (one 1 mm
    glitch among quick's 120 samples raised σ_w from 0.5 to 38 µm)."""
    U = _range_basis(H)
    rms = np.sqrt(np.mean((r - U @ (U.T @ r)).reshape(-1, rulers) ** 2, axis=1))
    return rms > GROSS_RATIO * np.median(rms)


def _range_basis(H: np.ndarray) -> np.ndarray:
    """An orthonormal basis of what ``H``'s columns span (what the drive's unknowns take up)."""
    U, s, _ = np.linalg.svd(H, full_matrices=False)
    return U[:, s > RANK_TOLERANCE * s[0]]


def _variance_components(r: np.ndarray, H: np.ndarray, G: np.ndarray, samples: int) -> TrackerGeometryEstimate:
    """σ_g, σ_w of ``r = H δx + G δθ + w`` (the module's model) by maximum likelihood."""
    U = _range_basis(H)
    projected_r = r - U @ (U.T @ r)
    projected_G = G - U @ (U.T @ G)
    V, s_g, _ = np.linalg.svd(projected_G, full_matrices=False)
    seen = s_g > RANK_TOLERANCE * max(s_g[0], 1e-300)
    V, s2 = V[:, seen], s_g[seen] ** 2
    along = (V.T @ projected_r) ** 2
    rest = max(float(projected_r @ projected_r - along.sum()), 0.0)
    n = len(r) - U.shape[1]  # the residual's dimensions off H: len(s2) along P G, the rest white alone

    def white_variance(ratio: float) -> float:
        return (float(np.sum(along / (1.0 + ratio * s2))) + rest) / n

    def log_likelihood(ratio: float) -> float:
        return -0.5 * (float(np.sum(np.log1p(ratio * s2))) + n * np.log(white_variance(ratio)))

    # ρ s² from 10⁻⁴ to 10⁸ of the mean direction's: a log-spaced search, then a golden-section refinement
    ratios = np.concatenate([[0.0], np.logspace(-4.0, 8.0, 241) / np.mean(s2)])
    values = np.array([log_likelihood(ratio) for ratio in ratios])
    best = int(np.argmax(values))
    if best > 0:
        low, high = ratios[best - 1], ratios[min(best + 1, len(ratios) - 1)]
        golden = (np.sqrt(5.0) - 1.0) / 2.0
        for _ in range(60):
            a, b = high - golden * (high - low), low + golden * (high - low)
            low, high = (low, b) if log_likelihood(a) > log_likelihood(b) else (a, high)
        ratio = 0.5 * (low + high)
    else:
        ratio = 0.0
    white = white_variance(ratio)
    return TrackerGeometryEstimate(
        sigma_mm=float(np.sqrt(ratio * white)),
        white_sigma_mm=float(np.sqrt(white)),
        likelihood_ratio=float(2.0 * (log_likelihood(ratio) - log_likelihood(0.0))),
        threshold=chdtri(1.0, 2.0 * FALSE_ALARM),
        directions=len(s2),
        samples=samples,
    )


def with_estimated_geometry(
    platform: Platform, method: str, config: EstimatorConfig, log: Log
) -> tuple[EstimatorConfig, TrackerGeometryEstimate | None]:
    """``config`` with ``noise.tracker_geometry_sigma_mm`` the σ_g and ``noise.reading_sigma_mm`` the σ_w
    that ``log`` shows where it :func:`applies`, the log shows a geometry error and ``method`` identifies
    the tracker's geometry (:attr:`~stewart_calib.estimators.registry.MethodSpec.tracker_geometry`), else
    ``config``; and the estimate (None where it does not apply or cannot be made).

    The reading σ is the white noise measured beside the geometry error because a reading σ that also
    holds that error (``configs/estimators/in-situ-tracker.toml``'s 0.02 mm) counts it twice once the
    geometry is identified, and ``isam2``'s noise scale, measured from the data, would then sit far from 1:
    its graph keeps the prior at the configured scale, and the directions the prior holds (the
    geometry's that the log does not see) come out over-confident by that scale (the paper experiment,
    σ_s 2 µm against 0.5 µm measured: isam2's z² 11.9, 2.4 at the measured σ)."""
    if not applies(platform, config):
        return config, None
    estimate = estimate_tracker_geometry(platform, log, config)
    if estimate is None or not (estimate.detected and estimators.method_spec(method).tracker_geometry):
        return config, estimate
    # with the geometry in the model, what the readings have beside it is the white σ_w measured with it
    noise = dataclasses.replace(
        config.noise, tracker_geometry_sigma_mm=estimate.sigma_mm, reading_sigma_mm=estimate.white_sigma_mm
    )
    return dataclasses.replace(config, noise=noise), estimate
