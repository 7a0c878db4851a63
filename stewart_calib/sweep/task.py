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
A rotary drive (``drive = "rotary"``, spec §15) is a servo build measured from outside, its truth a
servo build's errors (:func:`simulate_rotary`).

**The scores** (:func:`score`), each of the final estimate against the true δM in force at the
last sample:

* ``rms_mm``: RMS of the errors of δM (the 42 of a 6-6 drive; a rotary drive's lengths and positions),
  ``rms_deg`` a rotary drive's angles' (zero offsets, axis tilts) [deg] (None, a null, on a prismatic drive).
* ``rms_over_crb``: RMS of the errors in units of the bound (:func:`bound_stddev_mm`) over the
  identified parameters — 1 for an efficient estimator.
* ``nees``: ``eᵀ Σ⁻¹ e`` with the estimate's own covariance (χ²(42) when consistent).
* ``z2``: mean of ``(e_p / σ_p)²`` over the scored parameters with the estimate's own σ_p — 1 when
  the reported standard deviations are right, whatever their correlations.
* ``closed_loop_mm`` / ``closed_loop_deg``: mean pose error when the controller commands IK with
  the estimated drive to ``validation_poses`` fresh poses and the true robot goes to FK of those
  strokes; ``closed_loop_nominal_mm`` is the same with the nominal drive (uncalibrated).
  ``closed_loop_motion_mm`` / ``_deg``: the same for the motion from home (spec §15), what an outside
  instrument sees and scores a rotary drive.
* ``seconds`` / ``cpu_seconds``: wall and CPU time of the method on the log (CPU time does not
  grow when other work shares the machine: what a study's projection to a cluster uses);
  ``samples_rejected``: samples it refused in the end (as ``calibrate``'s ``samples_rejected``: those a
  robust start-up batch left out in, those a lock-out recovery or a payload step took back in out).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import numpy as np
from threadpoolctl import threadpool_limits

from ..analysis.identifiability import (
    identifiability_report,
    residual_covariance,
    stddev_from_factor,
    whitened_leg_jacobian,
)
from ..errors import CalibError, SampleRejected
from ..estimate import Estimate
from ..estimators import BatchEstimator, make_estimator
from ..estimators.base import accounted_estimate, fit_all, readmitted_count, take_late_rejections
from ..estimators.batch import BatchProblem, cramer_rao
from ..instruments import MODELS, gauge, instrument_kind, registered
from ..model import kinematics as kin
from ..model.drive import COMPLIANCE, DriveModel, drive_model, plain_drive
from ..model.platform import Elastic, Instrument, LegGeometry, Platform
from ..model.rotations import motion_error
from ..samples import LOAD_KG, Log
from ..simulation.experiment import RotaryRobotConfig
from ..simulation.instrument import InstrumentTruth, SimulatedInstrument, truth_in_gauge
from ..simulation.robot import rotary_errors
from ..simulation.trajectories import random_static_poses
from .spec import Cell, Family, simulated_noise

#: Range margin of the random poses [mm]: the true robot stands up to a few mm from where the
#: nominal model puts it, and glitch-free readings must stay inside the reading range.
POSE_MARGIN_MM = 10.0

METRICS = (
    "rms_mm",
    "rms_deg",
    "rms_over_crb",
    "nees",
    "z2",
    "closed_loop_mm",
    "closed_loop_deg",
    "closed_loop_nominal_mm",
    "closed_loop_nominal_deg",
    "closed_loop_motion_mm",
    "closed_loop_motion_deg",
    "closed_loop_nominal_motion_mm",
    "closed_loop_nominal_motion_deg",
    "seconds",
    "cpu_seconds",
)


@dataclass(frozen=True)
class SweepData:
    """One task's simulated data.

    Attributes:
        platform: the nominal platform (a family's draw, or the cell's platform) with the
            cell's nominal instrument.
        log: what the estimators see (N samples).
        true_params: ``(N, 42)`` true drive parameters in force at each sample [mm].
        glitched: ``(N,)`` True where one reading carries a glitch.
        validation_poses: ``(V, 6)`` fresh poses of the closed-loop check [mm, rad].
        true_terms: the true values ``(6,)`` of the drive's terms by block key
            (:class:`~stewart_calib.model.drive.LegTerm`): the stroke scales k_i (logged strokes are
            ``q / (1 + k)``) and, on an elastic robot, its legs' compliance [mm/kN].
        true_instrument: the true outside instrument (None for the tracker).
        true_elastic: the robot's masses and, as ``true_compliance_mm_per_kN``, its legs' true
            compliance (None: a rigid robot).
        payload_kg: ``(N,)`` the true payload of every sample [kg] (None: a rigid robot).
        scored: the drive's blocks scored after δM (:func:`scored_blocks`).
    """

    platform: Platform
    log: Log
    true_params: np.ndarray
    glitched: np.ndarray
    validation_poses: np.ndarray
    true_terms: dict[str, np.ndarray]
    true_instrument: SimulatedInstrument | None = None
    true_elastic: Elastic | None = None
    payload_kg: np.ndarray | None = None
    scored: tuple[str, ...] = ()

    @property
    def true_error(self) -> np.ndarray:
        """δM in force at the last sample [mm]."""
        return self.true_params[-1] - self.platform.drive.as_vector()

    @property
    def true_drive(self) -> DriveModel:
        """The robot's drive at the last sample, all known: δM, its terms' true values and, on an
        elastic robot, the masses its legs carry."""
        robot = drive_model(replace(self.platform, elastic=self.true_elastic))
        return robot.true_drive(self.true_error, self.true_terms)

    @property
    def true_inputs(self) -> dict[str, np.ndarray]:
        """The true payload of every sample as the log's channel would give it (none: a rigid robot)."""
        return {} if self.payload_kg is None else {LOAD_KG: self.payload_kg}

    @property
    def final_payload_kg(self) -> float:
        """The payload at the last sample [kg] (0 on a rigid robot): the closed loop's."""
        return 0.0 if self.payload_kg is None else float(self.payload_kg[-1])


def task_rng(cell_id: str, seed: int) -> np.random.Generator:
    """The task's generator: the seed and the cell id's 48 bits as three 16-bit words."""
    return np.random.default_rng([seed, *(int(cell_id[k : k + 4], 16) for k in range(0, len(cell_id), 4))])


def simulate(settings: dict, platform: Platform | Family, rng: np.random.Generator) -> SweepData:
    """The data of one task (see the module docstring); draws in a fixed order from ``rng``.

    The tracker's draws come first, in a fixed order of their own, so a tracker cell's data do
    not depend on the settings of the other instruments; the stroke scale and an outside
    instrument draw after them. A rotary drive's data are :func:`simulate_rotary`'s.
    """
    if settings["drive"] == "rotary":
        return simulate_rotary(settings, platform, rng)
    nominal = with_instrument(platform.draw(rng) if isinstance(platform, Family) else platform, settings)
    n = settings["samples"]
    dt_s = 1.0 / settings["rate_hz"]
    drive = nominal.drive
    reading_legs = instrument_kind(nominal).reading_legs(nominal)
    # an outside instrument draws the leg readings' noise and glitched legs all the same, to keep the order
    read_legs = drive if reading_legs is None else reading_legs
    error0 = rng.normal(0.0, settings["error_sigma_mm"], drive.n_params)
    poses = random_static_poses(nominal, n, rng, settings["workspace_fraction"], POSE_MARGIN_MM)
    steps = rng.normal(0.0, settings["drift_mm_per_sqrt_s"] * np.sqrt(dt_s), (n, drive.n_params))
    steps[0] = 0.0
    true_params = drive.as_vector() + error0 + np.cumsum(steps, axis=0)
    R, t = kin.pose_to_rt(poses)
    stroke_noise = rng.normal(0.0, settings["stroke_sigma_mm"], (n, drive.n_legs))
    reading_noise = rng.normal(0.0, settings["reading_sigma_mm"] * settings["noise_scale"], (n, read_legs.n_legs))
    glitched = rng.random(n) < settings["glitch_rate"]
    legs = rng.integers(0, read_legs.n_legs, n)
    signs = rng.choice([-1.0, 1.0], n)
    validation = random_static_poses(
        nominal, settings["validation_poses"], rng, settings["workspace_fraction"], POSE_MARGIN_MM
    )
    # the rigid drive's terms (the stroke scale), each drawn with its simulated spread (its prior σ there)
    rigid = drive_model(replace(nominal, elastic=None), simulated_noise(settings))
    true_terms = {term.key: rng.normal(0.0, term.prior_sigma or 0.0, rigid.rows) for term in rigid.terms}
    true_rigid = rigid.true_drive(np.zeros(rigid.n_params), true_terms)
    strokes = true_rigid.strokes_for(_extensions(drive, true_params, R, t))
    per_stroke = true_rigid.extension_per_stroke()
    strokes += stroke_noise
    instrument = None
    if reading_legs is not None:
        readings = kin.inverse_kinematics(reading_legs, R, t) + reading_noise
        readings[glitched, legs[glitched]] += signs[glitched] * settings["glitch_size_mm"]
    else:
        instrument = SimulatedInstrument.build(true_noise(nominal, settings), _instrument_truth(settings, rng), rng)
        readings = instrument.read(R, t, instrument.draw(n, rng))
        # a glitch moves one measured position coordinate (pose: x, y or z; points: one of the
        # first target's), as a reflection or a swapped marker does
        readings[glitched, legs[glitched] % 3] += signs[glitched] * settings["glitch_size_mm"]
    true_elastic = payload = None
    announced: dict[str, np.ndarray] = {}
    if settings["platform_mass_kg"] > 0:  # the legs give under the weight: longer strokes reach the same pose
        spread = rng.normal(0.0, settings["compliance_spread"], drive.n_legs)
        true_elastic = replace(
            elastic_table(settings), true_compliance_mm_per_kN=settings["compliance_mm_per_kN"] * (1.0 + spread)
        )
        payload = payload_schedule(settings)
        loaded = replace(true_rigid, legs=LegGeometry.from_params(true_params[0]), elastic=true_elastic)
        forces = loaded.leg_forces(R, t, {LOAD_KG: payload})
        strokes += true_elastic.true_compliance_mm_per_kN * forces / 1000.0 / per_stroke
        true_terms[COMPLIANCE] = np.asarray(true_elastic.true_compliance_mm_per_kN)
        announced = {LOAD_KG: payload} if settings["payload_known"] else {}
        if settings["elastic_model"]:
            nominal = replace(nominal, elastic=elastic_table(settings))
    log = Log(t_s=np.arange(n) * dt_s, strokes=strokes, readings=readings, desired_poses=poses, inputs=announced)
    return SweepData(
        nominal,
        log,
        true_params,
        glitched,
        validation,
        true_terms,
        instrument,
        true_elastic,
        payload,
        scored_blocks(nominal, settings),
    )


def simulate_rotary(settings: dict, platform: Platform | Family, rng: np.random.Generator) -> SweepData:
    """The data of one task of a servo-horn (6-RSS) drive, spec §15; draws in a fixed order from ``rng``.

    The true legs carry a servo build's errors (:func:`rotary_robot`, drawn by
    :func:`~stewart_calib.simulation.robot.rotary_errors`): zero offsets uniform in ±
    ``angle_offset_limit_deg``, horns, rods, crank centres and platform joints (``error_sigma_mm`` a
    coordinate) and the shafts' tilts normal. The logged angles close the true legs at random workspace
    poses over the true angle scales ``1 + k_i`` (``stroke_scale_error``), plus each servo's white
    error of σ ``angle_sigma_deg``; the outside instrument reads the true poses, a glitch moving one
    measured position coordinate as it does on the prismatic drive.

    Raises:
        CalibError: the true servos cannot reach a pose the nominal ones reach (a horn past the angle
            range or a rod beyond its horn's circle: errors out of proportion to the build).
    """
    nominal = with_instrument(platform.draw(rng) if isinstance(platform, Family) else platform, settings)
    n = settings["samples"]
    legs = nominal.drive
    error = rotary_errors(rotary_robot(settings), legs, rng)
    poses = random_static_poses(nominal, n, rng, settings["workspace_fraction"], POSE_MARGIN_MM)
    R, t = kin.pose_to_rt(poses)
    angle_noise = rng.normal(0.0, math.radians(settings["angle_sigma_deg"]), (n, legs.n_legs))
    glitched = rng.random(n) < settings["glitch_rate"]
    coordinates = rng.integers(0, 3, n)
    signs = rng.choice([-1.0, 1.0], n)
    validation = random_static_poses(
        nominal, settings["validation_poses"], rng, settings["workspace_fraction"], POSE_MARGIN_MM
    )
    rigid = drive_model(nominal, simulated_noise(settings))
    true_terms = {term.key: rng.normal(0.0, term.prior_sigma or 0.0, rigid.rows) for term in rigid.terms}
    strokes = rigid.true_drive(error, true_terms).inverse_kinematics(R, t)
    if not np.all(np.isfinite(strokes)):
        raise CalibError(
            f"the true servos of {nominal.name} cannot reach {int(np.sum(~np.isfinite(strokes).all(axis=1)))} of "
            "the random poses: lower the rotary errors or workspace_fraction"
        )
    strokes += angle_noise
    instrument = SimulatedInstrument.build(true_noise(nominal, settings), _instrument_truth(settings, rng), rng)
    readings = instrument.read(R, t, instrument.draw(n, rng))
    readings[glitched, coordinates[glitched]] += signs[glitched] * settings["glitch_size_mm"]
    log = Log(t_s=np.arange(n) / settings["rate_hz"], strokes=strokes, readings=readings, desired_poses=poses)
    true_params = np.tile(legs.as_vector() + error, (n, 1))
    return SweepData(
        nominal, log, true_params, glitched, validation, true_terms, instrument, scored=scored_blocks(nominal, settings)
    )


def rotary_robot(settings: dict) -> RotaryRobotConfig:
    """The true servo build's error spreads of a rotary cell (the experiments' ``[robot]`` table, spec §15)."""
    return RotaryRobotConfig(
        angle_offset_limit_deg=settings["angle_offset_limit_deg"],
        horn_spread_mm=settings["horn_spread_mm"],
        rod_spread_mm=settings["rod_spread_mm"],
        joint_spread_mm=settings["error_sigma_mm"],
        axis_tilt_spread_deg=settings["axis_tilt_spread_deg"],
        angle_scale_spread=settings["stroke_scale_error"],
        angle_noise_deg=settings["angle_sigma_deg"],
    )


def elastic_table(settings: dict) -> Elastic:
    """The ``[elastic]`` table of the cell's robot as a user writes it (spec §10): its platform
    mass, both centres of mass at {D}'s origin, the nominal compliance 0 and the default prior σ."""
    return Elastic(settings["platform_mass_kg"], np.zeros(3), np.zeros(3))


def payload_schedule(settings: dict) -> np.ndarray:
    """``(N,)`` the payload of every sample [kg] (spec ``payload_schedule``)."""
    n, heaviest = settings["samples"], settings["payload_kg"]
    k = np.arange(n)
    steps = {"constant": np.ones(n), "step": (k >= n // 2).astype(float), "stages": np.floor(3 * k / n) / 2}
    return heaviest * steps[settings["payload_schedule"]]


def simulated_drive(platform: Platform, settings: dict, elastic: bool = True) -> DriveModel:
    """``platform``'s drive with the unknown blocks of the cell's simulation: the terms whose true
    values spread (:func:`~stewart_calib.sweep.spec.simulated_noise`), the encoders' scale with an
    instrument outside the robot as the estimators have it, and with ``elastic`` the compliance of an
    elastic robot (:func:`elastic_table`)."""
    table = elastic_table(settings) if elastic and settings["platform_mass_kg"] > 0 else None
    outside = MODELS[settings["instrument"]].outside
    return drive_model(replace(platform, elastic=table), simulated_noise(settings), outside_instrument=outside)


def scored_blocks(platform: Platform, settings: dict) -> tuple[str, ...]:
    """The drive's blocks scored after δM: :func:`simulated_drive`'s, the compliance where the
    estimators model the robot's elasticity."""
    return tuple(block.key for block in simulated_drive(platform, settings, settings["elastic_model"]).blocks)


def with_instrument(platform: Platform, settings: dict) -> Platform:
    """``platform`` measured by the cell's instrument: the tracker as the platform file has it,
    or a nominal outside instrument of the cell's σ — its frame at {J}'s origin, a pose target at
    {D}'s origin, point targets halfway out towards platform joints 1, 3, 5 and 25 mm above."""
    instrument = MODELS[settings["instrument"]].placed_on(
        platform, settings["instrument_sigma_mm"], math.radians(settings["instrument_sigma_deg"]), settings["targets"]
    )
    return replace(platform, instrument=instrument)


def true_noise(platform: Platform, settings: dict) -> Instrument:
    """The platform's outside instrument with the simulated σ (``noise_scale`` × what it says)."""
    scale = settings["noise_scale"]
    instrument = platform.instrument
    return replace(
        instrument,
        position_sigma_mm=scale * instrument.position_sigma_mm,
        orientation_sigma_rad=scale * instrument.orientation_sigma_rad,
    )


def _instrument_truth(settings: dict, rng: np.random.Generator) -> InstrumentTruth:
    """The true frame ``frame_offset_mm`` and ``frame_offset_deg`` from nominal, in directions
    drawn per task; targets as nominal (the estimators identify them all the same)."""
    directions = rng.normal(size=(2, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    offset = np.r_[settings["frame_offset_mm"] * directions[0], settings["frame_offset_deg"] * directions[1]]
    return InstrumentTruth(offset, np.zeros(6), dropout_probability=settings["dropout_rate"])


def _extensions(nominal, params: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(N, legs)`` the coordinates that close the legs at poses ``(R, t)`` of a drive of its own per
    pose, absolute parameters ``params (N, n_params)`` of the leg model ``nominal``: one compiled pass
    for the prismatic legs, else each distinct drive's inverse kinematics."""
    if type(nominal) is LegGeometry:
        return kin.leg_residuals_per_sample(params, R, t, np.zeros((len(params), nominal.n_legs)))
    distinct, which = np.unique(params, axis=0, return_inverse=True)
    extensions = np.empty((len(params), nominal.n_legs))
    for k, row in enumerate(distinct):
        at = which.ravel() == k
        legs = nominal.perturbed(row - nominal.as_vector())
        extensions[at] = plain_drive(legs).inverse_kinematics(R[at], t[at])
    return extensions


def bound_stddev_mm(data: SweepData, settings: dict, prior_sigma_mm: float) -> np.ndarray:
    """Lower bound on the standard deviation of each scored unknown (:func:`truth`) [mm, 1, mm/kN].

    The bound is that of the simulated robot: over δM and :attr:`SweepData.true_blocks` — the
    compliance of an elastic robot too where the estimators calibrate it as a rigid one (their δM
    is then scored against the bound of the right model) — with the simulated noise and the true
    payloads; the scored unknowns' entries are returned.

    Tracker: the 42 parameters of the final δM (and the six stroke scales when they are
    unknown, the six compliances of an elastic robot). Constant parameters: the Cramér–Rao bound
    ``(AᵀA)⁻¹`` of the information matrix of these poses under the simulated noise (inf for a
    parameter the poses do not identify). Drifting parameters: the posterior (Bayesian) bound of
    the final value — the information recursion ``J_k = (J_{k−1}⁻¹ + q²Δt I)⁻¹ + A_kᵀA_k`` over
    the same whitened rows ``A_k``, from the estimators' prior ``J_0 = I / prior_sigma²``
    (Tichavský et al. 1998): with a random walk no estimator can beat the optimal filter of the
    linearised model.

    Outside instrument: the Cramér–Rao bound of δM in the gauge and the drive's blocks, with the
    frame and targets unknown too (:func:`stewart_calib.estimators.batch.cramer_rao`, at the
    truth, with the simulated σ) — of constant parameters: with drift it is optimistic.
    """
    drive = simulated_drive(data.platform, settings)
    blocks = drive.blocks
    if data.true_instrument is not None:
        delta, unknowns = truth_in_gauge(data.platform.drive, data.true_params[-1], data.true_instrument.unknowns)
        simulated = replace(
            data.platform,
            instrument=true_noise(data.platform, settings),
            elastic=None if data.true_elastic is None else elastic_table(settings),
        )
        problem = BatchProblem.of_log(simulated, data.log.strokes, data.log.readings, data.log.t_s, data.true_inputs)
        errors = [data.true_terms[block.key] - block.nominal for block in blocks]
        bound = cramer_rao(problem, np.concatenate([delta, *errors]), unknowns)
        stddev = np.sqrt(np.clip(np.diag(bound)[: drive.size], 0.0, None))
        return _scored_part(stddev, drive, data.scored)
    noise, poses = simulated_noise(settings), data.log.desired_poses
    if poses is None:
        raise ValueError("a sweep's simulated log holds its poses")
    rows = whitened_leg_jacobian(data.platform, poses, noise)
    if not blocks and settings["drift_mm_per_sqrt_s"] == 0:
        return identifiability_report(data.platform, poses, noise, paper_form=False).predicted_stddev_mm
    R, t = kin.pose_to_rt(poses)
    L = np.linalg.cholesky(residual_covariance(data.platform, R, t, noise))
    if blocks:  # ∂r_i/∂v_{b,i} = −g_b u_{b,i} of each term's own inputs, whitened as the rows of δM
        inputs = drive.inputs(data.log.strokes, data.true_inputs, R, t)
        rows = np.concatenate([rows, np.linalg.solve(L, -drive.extension_jacobian(inputs))], axis=2)
    n = rows.shape[2]
    if settings["drift_mm_per_sqrt_s"] == 0:
        return _scored_part(stddev_from_factor(rows.reshape(-1, n)), drive, data.scored)
    m = drive.n_params
    walk = np.zeros((n, n))
    walk[:m, :m] = settings["drift_mm_per_sqrt_s"] ** 2 / settings["rate_hz"] * np.eye(m)
    prior = [np.full(m, prior_sigma_mm**2), *(block.prior_sigma**2 for block in blocks)]
    covariance = np.diag(np.concatenate(prior))
    for k, A in enumerate(rows):
        predicted = covariance + walk if k else covariance
        covariance = np.linalg.inv(np.linalg.inv(predicted) + A.T @ A)
    return _scored_part(np.sqrt(np.diag(covariance)), drive, data.scored)


def _scored_part(stddev: np.ndarray, drive: DriveModel, scored: tuple[str, ...]) -> np.ndarray:
    """The entries of ``stddev`` over ``drive``'s ``[δM, blocks…]`` that belong to δM and the ``scored`` blocks."""
    keep = [np.arange(drive.n_params)]
    for k, block in enumerate(drive.blocks):
        if block.key in scored:
            keep.append(drive.n_params + drive.rows * k + np.arange(drive.rows))
    return stddev[np.concatenate(keep)]


def truth(data: SweepData) -> np.ndarray:
    """The scored unknowns' true values: δM at the last sample (in the gauge of
    :mod:`stewart_calib.instruments.gauge` for an outside instrument), then the scored blocks'
    (:attr:`SweepData.scored`: the stroke scales, the legs' compliance [mm/kN])."""
    if data.true_instrument is not None:
        delta, _ = truth_in_gauge(data.platform.drive, data.true_params[-1], data.true_instrument.unknowns)
    else:
        delta = data.true_error
    return np.concatenate([delta, *(data.true_terms[key] for key in data.scored)])


def nees_basis(data: SweepData, n: int) -> np.ndarray:
    """``(n, r)``: the directions the NEES is taken over — all of them for the tracker, and for
    an outside instrument the 30 of δM its gauge leaves free, then the drive's blocks."""
    if data.true_instrument is None:
        return np.eye(n)
    free = gauge.free_basis(data.platform.drive)
    (m, r), rest = free.shape, n - len(free)
    basis = np.zeros((n, r + rest))
    basis[:m, :r] = free
    basis[m:, r:] = np.eye(rest)
    return basis


def closed_loop_errors(data: SweepData, estimate: Estimate | None = None) -> dict[str, float]:
    """Mean position [mm] and orientation [deg] error at the validation poses when the
    controller commands encoder strokes by IK with the estimated drive (None: the nominal one) —
    its δM, stroke scales (``q = (L − l) / (1 + k)``) and, on an elastic robot, its compliance
    under the payload it knows of (0 where the log does not say); a block it did not identify at
    its nominal — and the true robot (:attr:`SweepData.true_drive`: parameters of the last
    sample, true scales, settling under its weight and the last sample's payload) executes them.

    Returns ``{"closed_loop_mm", "closed_loop_deg"}``: the pose reached in {J}, and
    ``{"closed_loop_motion_mm", "closed_loop_motion_deg"}``: the motion from the workspace's home
    (spec §15, :func:`~stewart_calib.model.rotations.motion_error`), the true robot commanded home and
    then to each pose — what an outside instrument sees (it leaves the robot's place in {J} open
    along directions the data barely see). Poses the commanded model cannot reach (a rotary drive's
    horn past its range) are left out, as the controller refuses them."""
    R_d, t_d = kin.pose_to_rt(data.validation_poses)
    known = {LOAD_KG: data.final_payload_kg} if LOAD_KG in data.log.inputs else {}
    payload = {LOAD_KG: data.final_payload_kg}
    drive = drive_model(data.platform)
    commanded = drive.calibrated_by(estimate) if estimate is not None else drive
    true = data.true_drive
    strokes = commanded.inverse_kinematics(R_d, t_d, channels=known)
    reached = np.all(np.isfinite(strokes), axis=-1)
    if not reached.all():
        R_d, t_d, strokes = R_d[reached], t_d[reached], strokes[reached]
    actual, _ = true.settled_kinematics(strokes, payload, guess=(R_d, t_d))
    position_mm, orientation_deg = kin.pose_error(R_d, t_d, actual.R, actual.t)
    R_h, t_h = kin.pose_to_rt(data.platform.required_workspace("a sweep's motion from home").home[None])
    home, _ = true.settled_kinematics(commanded.inverse_kinematics(R_h, t_h, channels=known), payload, guess=(R_h, t_h))
    motion_mm, motion_deg = motion_error((R_h[0], t_h[0]), (R_d, t_d), (home.R[0], home.t[0]), (actual.R, actual.t))
    return {
        "closed_loop_mm": float(position_mm.mean()),
        "closed_loop_deg": float(orientation_deg.mean()),
        "closed_loop_motion_mm": float(motion_mm.mean()),
        "closed_loop_motion_deg": float(motion_deg.mean()),
    }


def score(data: SweepData, estimate: Estimate, crb: np.ndarray) -> dict:
    """Scores of one estimate (see the module docstring), ``seconds`` left to the caller.

    The scored unknowns are :func:`truth`'s; where the estimate holds a scored block fixed (no
    such block), its value is the nominal with no variance, and the NEES and z² are taken over
    the unknowns it estimated.
    """
    found, columns = [estimate.error], [np.arange(len(estimate.error))]
    nominal = {term.key: term.nominal for term in drive_model(data.platform).terms}
    for key in data.scored:
        values, span = estimate.block_values(key), estimate.layout.slice(key)
        found.append(nominal[key] if values is None else values)
        columns.append(np.full(len(nominal[key]), -1) if span is None else np.arange(span.start, span.stop))
    e = np.concatenate(found) - truth(data)
    column = np.concatenate(columns)
    n = len(e)
    identified = np.isfinite(crb)
    nees = z2 = float("nan")
    dof = 0
    covariance = estimate.full_covariance if estimate.full_covariance is not None else estimate.covariance
    if covariance is not None:
        estimated = (column >= 0) & (column < len(covariance))
        basis = nees_basis(data, n)[estimated]
        basis = basis[:, np.linalg.norm(basis, axis=0) > 0]
        C = covariance[np.ix_(column[estimated], column[estimated])]
        reduced = basis.T @ e[estimated]
        dof = basis.shape[1]
        try:
            nees = float(reduced @ np.linalg.solve(basis.T @ C @ basis, reduced))
        except np.linalg.LinAlgError:
            pass
        variance = np.diag(C)
        if np.all(variance > 0):
            z2 = float(np.mean(e[estimated] ** 2 / variance))
    delta, angles = e[: len(estimate.error)], data.platform.drive.parameter_degrees
    return {
        "rms_mm": float(np.sqrt(np.mean(delta[~angles] ** 2))),
        "rms_deg": float(np.degrees(np.sqrt(np.mean(delta[angles] ** 2)))) if angles.any() else None,
        "rms_over_crb": float(np.sqrt(np.mean((e[identified] / crb[identified]) ** 2)))
        if identified.any()
        else float("nan"),
        "nees": nees,
        "nees_dof": dof,
        "z2": z2,
        **closed_loop_errors(data, estimate),
    }


def run_method(
    method: str, data: SweepData, cell: Cell, checkpoints: tuple[int, ...], refit: bool, crb: np.ndarray
) -> dict:
    """Run one method on the task's log; its scores, rejections and checkpoint ratios.

    With an outside instrument the method starts, as ``calibrate`` starts it, from the
    instrument registered on the log in closed form.
    """
    samples = list(data.log)
    platform = data.platform
    platform = registered(platform, data.log.strokes, data.log.readings)
    estimator = make_estimator(method, platform, cell.estimator_config)
    at_checkpoint = {}
    start, cpu_start = time.perf_counter(), time.process_time()
    if isinstance(estimator, BatchEstimator):  # the methods that are not online
        estimate = estimator.fit(samples)
        rejected = len(estimator.rejected)
        for n in checkpoints if refit else ():
            try:
                at_checkpoint[n] = fit_all(make_estimator(method, platform, cell.estimator_config), samples[:n]).error
            except CalibError:  # e.g. ls not converging on a short prefix: that checkpoint is NaN
                at_checkpoint[n] = np.full(platform.drive.n_params, np.nan)
    else:  # the refusals counted as calibrate counts them: late ones in, those taken back in out
        rejected = 0
        for k, sample in enumerate(samples, start=1):
            try:
                estimator.update(sample)
            except SampleRejected:
                rejected += 1
            rejected += len(take_late_rejections(estimator))
            if k in checkpoints:
                at_checkpoint[k] = estimator.current_error()
        estimate = accounted_estimate(estimator)
        rejected -= readmitted_count(estimate)
    seconds, cpu_seconds = time.perf_counter() - start, time.process_time() - cpu_start
    row = score(data, estimate, crb)
    row["seconds"], row["cpu_seconds"] = seconds, cpu_seconds
    row["samples_rejected"] = rejected
    crb_mm = crb[: platform.drive.n_params]
    for n in checkpoints:  # δM against the bound of the whole log (the benchmarks' convergence measure)
        error = at_checkpoint.get(n)
        z = (error - _truth_at(data, n)) / crb_mm if error is not None else np.full(len(crb_mm), np.nan)
        row[f"rms_over_crb_at_{n}"] = float(np.sqrt(np.mean(z[np.isfinite(crb_mm)] ** 2)))
    return row


def _truth_at(data: SweepData, n: int) -> np.ndarray:
    """δM in force at sample ``n`` (1-based), in the gauge for an outside instrument."""
    if data.true_instrument is not None:
        return truth_in_gauge(data.platform.drive, data.true_params[n - 1], data.true_instrument.unknowns)[0]
    return data.true_params[n - 1] - data.platform.drive.as_vector()


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

    The task computes with one BLAS thread wherever it runs: OpenBLAS's multi-threaded kernels
    (its Haswell and Zen ones among them) round differently from its one-thread kernels, and a
    Dask worker starts with one thread (``OPENBLAS_NUM_THREADS=1``) where the sweep's own process
    has the cores, so a task computed again on resume would not give the same row.
    """
    with threadpool_limits(limits=1):
        return _run_task(cell, seed, methods, checkpoints, refit_at_checkpoints)


def _run_task(
    cell: Cell,
    seed: int,
    methods: tuple[str, ...],
    checkpoints: tuple[int, ...],
    refit_at_checkpoints: tuple[str, ...],
) -> list[dict]:
    rng = task_rng(cell.id, seed)
    data = simulate(cell.settings, cell.platform, rng)
    crb = bound_stddev_mm(data, cell.settings, cell.estimator_config.noise.prior_sigma_mm)
    nominal = {key.replace("loop", "loop_nominal"): value for key, value in closed_loop_errors(data).items()}
    rows = []
    for method in methods:
        try:
            scores = run_method(method, data, cell, checkpoints, method in refit_at_checkpoints, crb)
            failure = ""
        except (CalibError, np.linalg.LinAlgError) as err:
            scores = {name: float("nan") for name in METRICS} | {"samples_rejected": None, "nees_dof": None}
            scores |= {f"rms_over_crb_at_{n}": float("nan") for n in checkpoints}
            failure = str(err).splitlines()[0] if str(err) else err.__class__.__name__
        scores |= nominal
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
