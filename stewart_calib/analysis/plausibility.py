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

Before any of these, :func:`check_readings_follow` asks the question every command asks of a log
(``calibrate``, ``validate`` and ``import`` through :func:`~stewart_calib.workflows.diagnosis.diagnose_log`,
``track`` on its last samples): do the instrument's readings move where the logged strokes move
the platform? Readings that stand still while the strokes move it by many times the instrument's
noise (a column left at 0, a tracking system that lost the body and repeats a value) fit no
geometry; an estimator fed them finds a nonsense stroke scale or fails far from the cause.
"""

from __future__ import annotations

import math

import numpy as np

from ..chi_square import chdtri
from ..config import NoiseConfig
from ..errors import CalibError
from ..instruments import instrument_kind
from ..io.results import parameter_file_scale
from ..model import kinematics as kin
from ..model.drive import drive_model, plain_drive
from ..model.platform import Elastic, LegGeometry, Platform, give_reference_mm, least_give_mm_per_kg

#: a parameter error beyond this many prior σ is refused (two-sided tail probability < 1e-20).
PRIOR_SIGMAS = 10.0
#: the largest parameter error of a robot built to the prior stays within the bound of this probability
#: (family-wise over the parameters: :func:`prior_reach_warning`)
PRIOR_REACH_PROBABILITY = 0.99
#: an RMS leg residual beyond this many measurement σ is refused (three orders of magnitude).
RESIDUAL_SIGMAS = 1000.0
#: a measurement noise the estimator finds beyond this multiple of the configured σ is refused
#: (two orders of magnitude: σ wrong by 2–5× or a sagging platform's ~10× pass).
NOISE_SCALE_LIMIT = 100.0
#: a log whose strokes and readings (lengths) all spread less than this fraction of the stroke range
#: (without one: of the shortest leg) does not move: a hundredth, five times the sliver that strokes in
#: metres fill (diagnosis: 1e-3 × its unit tolerance 2), and far below any calibration's poses
REST_FRACTION = 0.01
#: readings spreading less than this fraction of the spread the strokes give the platform do not
#: follow it (diagnosis.SPREAD_LIMIT's factor: the spreads of the same motions agree within the drive's errors) …
STILL_FRACTION = 0.2
#: … once the strokes move the platform by more than this many times what the instrument's noise
#: alone spreads (a robot dwelling at one pose moves by its encoders' noise: nothing to compare)
MOVED_NOISE = 10.0


def check_readings_follow(
    platform: Platform, R: np.ndarray, t: np.ndarray, readings: np.ndarray, where: str, columns
) -> None:
    """Refuse readings of an instrument outside the robot that stand still while the strokes move
    the platform (see the module): each group of channels (positions, orientations, a target's
    positions) against the spread of the nominal instrument's readings at the strokes' nominal
    poses ``(R, t)`` (:meth:`~.instruments.base.InstrumentModel.spreads`).

    Args:
        R, t: ``(N, 3, 3)``, ``(N, 3)`` the nominal drive's forward kinematics of the logged strokes.
        readings: ``(N, m)`` the instrument's readings in code units (mm, rad; NaN: not seen).
        where: names the log (its path, or the command) in the message; columns: the readings' names.
    Raises:
        CalibError: one line naming the columns, both spreads and the noise's.
    """
    kind = instrument_kind(platform)
    if not kind.outside or len(R) < 2:
        return
    instrument = platform.instrument
    columns = list(columns)
    for spread in kind.spreads(platform, R, t, readings):
        # the RMS distance from their centroid that white noise alone gives three coordinates or angles
        sigma = np.degrees(instrument.orientation_sigma_rad) if spread.angle else instrument.position_sigma_mm
        noise = float(np.sqrt(3.0) * sigma)
        unit = "°" if spread.angle else " mm"
        moved = spread.expected > MOVED_NOISE * noise
        if moved and not spread.measured >= STILL_FRACTION * spread.expected:  # NaN: nothing seen moves
            names = columns[spread.channels]
            named = names[0] if len(names) == 1 else f"{names[0]}…{names[-1]}"
            raise CalibError(
                f"{where}: the {spread.what} {named} do not follow the platform: they spread "
                f"{spread.measured:.3g}{unit} where the logged strokes move it {spread.expected:.4g}{unit} "
                f"(the instrument's noise alone: {noise:.3g}{unit}); expected readings that move with the "
                "robot (a column left at 0 or repeating one value, a body the instrument lost?)"
            )


def strokes_poses(platform: Platform, strokes: np.ndarray):
    """The nominal drive's forward kinematics of ``strokes (N, legs)``, as the settled robot would
    stand (non-converged rows marked, not raised)."""
    return drive_model(platform).settled_kinematics(np.asarray(strokes, dtype=float), strict=False)[0]


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
    legs = platform.drive.perturbed(error)
    if type(legs) is LegGeometry:  # the leg set the compiled kernels take
        residuals, converged = kin.tracker_reading_residuals(legs, strokes, [tracker], [readings])
    else:
        fk = kin.forward_kinematics(tracker, readings, strict=False)
        converged = fk.converged[None]
        residuals = plain_drive(legs).residual(None, fk.R, fk.t, strokes)[None]
    if not converged.any():
        return float("nan")
    return float(np.sqrt(np.mean(np.square(residuals[converged]))))


def prior_reach_warning(platform: Platform, error: np.ndarray, noise: NoiseConfig, method: str) -> str | None:
    """A warning where ``method``'s estimate ``error`` (δM, code units) reaches farther beyond the prior than
    the largest of its errors does on a robot built to it (:data:`PRIOR_REACH_PROBABILITY`, Šidák over the
    parameters: 3.7 prior σ for 42), naming the parameter and the prior σ to give; None otherwise, and for
    ``ls``, which the prior does not draw.

    The prior draws the directions the data barely see toward nominal: a laser tracker's three reflectors
    on a hand-built hobby hexapod whose encoder zeros are 15 mm off (prior σ 5 mm) left ekf at 1.63 and lm at
    1.52 × the Cramér–Rao bound where ls is at 1.24 (with a 20 mm prior: 1.39 and 1.25); their largest
    errors reached 1.4–6.2 prior σ (5 of 8 robots beyond the bound), a machined robot's (zeros 3 mm off)
    at most 1.6."""
    if method == "ls":
        return None
    legs = platform.drive
    sigma = np.asarray(legs.prior_sigmas(noise), dtype=float)
    reach = np.abs(np.asarray(error, dtype=float)) / sigma
    worst = int(np.argmax(reach))
    tail = 1.0 - PRIOR_REACH_PROBABILITY ** (1.0 / len(reach))  # two-sided, per parameter
    bound = math.sqrt(chdtri(1, tail))
    if not reach[worst] > bound:
        return None
    scale = parameter_file_scale(legs)[worst]
    unit, key = ("°", "noise.angle_prior_sigma_deg") if scale != 1.0 else ("mm", "noise.prior_sigma_mm")
    value, prior = error[worst] * scale, sigma[worst] * scale
    return (
        f"warning: {method}'s estimate reaches {reach[worst]:.3g} × the prior σ ({legs.parameter_names[worst]} = "
        f"{value:.4g} {unit} against {key} {prior:.3g} {unit}; on a robot built to the prior the largest of its "
        f"{len(reach)} errors stays within {bound:.2g} × in {PRIOR_REACH_PROBABILITY:.0%} of robots): the robot is "
        "built looser than the prior says, which draws the directions the data barely see toward nominal (ls is not "
        f"drawn); run again with --set {key}={abs(value) / 2.0:.2g} or more"
    )


def payload_walk_warning(elastic: Elastic | None, estimate) -> str | None:
    """A warning where the δM random walk could carry an unannounced payload put on gradually (the platform's
    ``[elastic]`` table ``elastic``); None otherwise.

    An unannounced payload (``[elastic] payload_sigma_kg``) is found from the leg change it makes,
    ``c_i f_i / 1000`` (spec §10). Put on at once, that change is a step the filter tests; put on gradually,
    it is a slow leg change that δM's random walk explains as well, where the walk can reach that far. Over
    the run's ``T`` s the walk in use (``ρ`` [mm/√s], ``estimate.details["payload_walk"]``) moves each
    parameter ``ρ √T``; where that is more than the least give of the most loaded leg under a payload of
    ``payload_sigma_kg`` (:func:`~stewart_calib.model.platform.least_give_mm_per_kg` at the largest
    compliance, the estimate's where it identified one), a payload of the size the platform declares can pass
    for drift. On the paper's experiment, 40 kg over a 20 s ramp: ``--config paper`` walks 1.46 mm over the
    212 s against a 0.26 mm give (payload found 21–25 kg, 2.8–4.9 σ low), the default and ``paper-elastic``
    0.015 mm (38.7–40.6 kg). The test is one-sided: below it a walk can still take part of a ramp (``--config
    paper`` with a walk of 0.005 mm/√s, 0.07 mm over the run: isam2 31.5 kg)."""
    walk = (estimate.details or {}).get("payload_walk")
    if not walk or elastic is None or not elastic.payload_sigma_kg > 0.0:
        return None
    compliance = estimate.block_values("compliance")
    if compliance is None:
        compliance = elastic.compliance_mm_per_kN
    give_mm = least_give_mm_per_kg(float(np.max(np.abs(compliance)))) * elastic.payload_sigma_kg
    rate, run_s = float(walk["mm_per_sqrt_s"]), float(walk["over_s"])
    walked_mm = rate * math.sqrt(run_s)
    if not (give_mm > 0.0 and walked_mm > give_mm):
        return None
    column = estimate.layout.slice("payload").start
    sigma = math.sqrt(estimate.full_covariance[column, column]) if estimate.full_covariance is not None else math.nan
    return (
        f"warning: a payload put on gradually passes for drift here, and the payload found "
        f"({estimate.unannounced_payload_kg():.3g} ± {sigma:.2g} kg) is then too low: over the run's {run_s:.4g} s "
        f"the δM random walk in use ({rate:.3g} mm/√s) moves each parameter {walked_mm:.3g} mm, more than the "
        f"{give_mm:.3g} mm a payload of {elastic.payload_sigma_kg:g} kg (elastic.payload_sigma_kg) gives the most "
        "loaded leg; give the log a load_kg column, or a walk far slower than "
        f"{give_mm / math.sqrt(run_s):.2g} mm/√s (the default's 0.001, or --config paper-elastic on the paper's "
        "tracker)"
    )


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
        error: δM [mm] of the estimate. strokes, readings: ``(N, legs)``, ``(N, m)`` samples it was fitted to
            (all of them, or the most recent ones for an online run) [mm, rad]; with none, only
            the parameters are checked. An outside instrument's readings are checked to follow the
            strokes (:func:`check_readings_follow`); the tracker's, for their leg residual.
        noise_scale: the measurement noise the estimator found in the data, as a multiple of
            the configured σ (``ekf``, ``isam2``; None: not checked). Beyond
            :data:`NOISE_SCALE_LIMIT` no sample agrees with the others — a stream of glitches.
    Raises:
        CalibError: one line with the RMS residual, the largest parameter error and both limits.
    """
    error = np.asarray(error, dtype=float)
    if instrument_kind(platform).outside:
        if np.size(strokes):
            fk = strokes_poses(platform, strokes)
            ok = fk.converged
            columns = instrument_kind(platform).columns_of(platform.instrument)
            check_readings_follow(platform, fk.R[ok], fk.t[ok], np.asarray(readings, dtype=float)[ok], method, columns)
        strokes = readings = np.zeros((0, platform.drive.n_legs))  # no leg set of known geometry to take residuals on
    sigma_mm = max(noise.reading_sigma_mm, noise.stroke_sigma_mm)
    rms_mm = rms_leg_residual_mm(platform, error, strokes, readings)
    worst = int(np.argmax(np.abs(error)))
    beyond_prior = abs(error[worst]) > PRIOR_SIGMAS * noise.prior_sigma_mm
    # nan (no pose could be solved) counts as beyond the noise
    beyond_noise = np.size(strokes) > 0 and not rms_mm <= RESIDUAL_SIGMAS * sigma_mm
    scattered = noise_scale is not None and noise_scale > NOISE_SCALE_LIMIT
    if beyond_prior or beyond_noise or scattered:
        # the samples checked at rest (track's last ones): that, not the fit, is what to name first
        span = float(np.max(np.ptp(strokes, axis=0))) if np.size(strokes) else None
        reference, what = give_reference_mm(platform.drive, platform.stroke_range)
        still = (
            f"the last {len(strokes)} samples it used do not move (their strokes span {span:.3g} mm, within "
            f"{REST_FRACTION:g} of {what}, {reference:.4g} mm): a robot at rest fixes no parameter; "
            if span is not None and span < REST_FRACTION * reference
            else ""
        )
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
            f"{method}: {still}the log does not fit platform '{platform.name}': {residual}largest "
            f"parameter error {platform.drive.parameter_names[worst]} = {error[worst]:.4g} mm "
            f"({abs(error[worst]) / noise.prior_sigma_mm:.3g} × the prior σ {noise.prior_sigma_mm:g} mm; limit "
            f"{PRIOR_SIGMAS:g} ×){scatter} — a log of another platform, glitches in every sample, or a platform file "
            "that does not describe this robot?"
        )
