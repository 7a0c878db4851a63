"""The closed loop: a controller commands IK with the model it holds; the true robot settles.

Per sample k (paper Fig. 3 seen from the robot's side)::

    P_d (desired pose)
      → q = IK(controller.drive_model(), P_d)                   strokes, executed exactly
      → true params = M_base + δM_load(actual pose, payload)     FK ↔ compliance fixed point
      → actual pose = FK(true drive, q), warm-started at P_d
      → s = tracker readings (true tracker geometry, noise, 50 nm, range)
      → Sample(t, q + encoder noise, s, P_d, stage, load) → controller.observe(sample)

A **controller** is any object with two methods::

    controller.drive_model() -> LegModel      # model used for the IK of the next desired pose
    controller.observe(sample: Sample) -> None # called after each sample

and optionally ``controller.strokes(R_d, t_d, payload_kg) -> q``: its own IK where the model is
more than a leg geometry (an elastic drive under the payload, spec §10); on a tilting mount (an
experiment's stages' ``tilt_deg``, spec §17) it is called with ``gravity=`` the samples' unit vectors
of gravity in {J} too.

:class:`NominalController` (uncalibrated) and :class:`FrozenController` (a frozen batch
estimate, an elastic one's commanded under the payload as the online controller's are,
:func:`loaded_strokes`; or the true no-load geometry for a perfect calibration) never change their model;
they say so with ``adaptive = False``, and the samples are then settled in vectorised blocks
of :data:`BLOCK_SAMPLES` (identical results whatever the block size: each kind of noise is
drawn as by one call for all samples). Any other controller — :class:`EstimatorController`,
an online estimator in the loop (paper Fig. 3, step 4) — is run sample by sample.
:func:`simulate_blocks` hands the log and truth on a block at a time (``simulate`` writes them
so, holding none of them whole); :func:`run_experiment` joins them.

Randomness: ``np.random.default_rng(experiment.seed)`` spawns independent streams for the
robot's errors, the tracker residual, the pose sets, the measurement noise, the encoders'
scale and zero errors and an outside instrument (spec §7), so changing one part of an
experiment does not reshuffle the others.

With an instrument outside the robot (``[instrument] kind = "pose" | "points"``) the log holds
its readings instead of the tracker's; the encoders log ``(q − z_i) / (1 + k_i)`` for an
executed stroke q (scale errors k_i, zero errors z_i, spec §7), and the truth's initial lengths
are ``l_i + z_i``, what a model with the logged strokes must find.

A rotary drive (spec §15) logs the angles its controller commands, exactly; its servos turn the
horns by ``(1 + k_i) θ_i`` plus their own white error (``[robot] angle_noise_deg``), and the true
pose is the forward kinematics of the true drive (:meth:`TrueRobot.true_drive`: the leg model with
the experiment's errors and angle scale) there — rigid: no load moves it.

A warm-up (the experiment's ``[thermal]``, :class:`~.experiment.WarmUp`) gives each sample its legs'
temperatures ``T_i``: the true robot's legs grow joint to joint by ``1 + α_i (T_i − T_ref) · 1e-6`` with its
true expansion ``α`` (:meth:`~.load.Settling.settle`), the in-situ tracker (of a low-expansion material)
does not, the log carries the temperatures as its ``temperature_C`` channel and the truth ``α`` as its
``"thermal"`` drive term.
"""

from __future__ import annotations

import copy
import functools
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..errors import CalibError, SampleRejected, shown
from ..estimate import model_estimate
from ..model import kinematics as kin
from ..model.drive import STROKE_SCALE, THERMAL, DriveModel, drive_model, plain_drive
from ..model.legs import LegModel
from ..model.platform import LegGeometry, Platform
from ..progress import progress_bar
from ..samples import GRAVITY, LOAD_KG, TEMPERATURE_C, Log, Sample, Truth, with_payload
from .experiment import Experiment, RotaryRobotConfig, Schedule, schedule
from .instrument import SimulatedInstrument
from .load import LoadModel, Settling, elastic_of
from .robot import base_errors, encoder_readings, rotary_errors
from .tracker import Tracker


class Controller(Protocol):
    """What the closed loop needs of a controller (see the module docstring)."""

    def drive_model(self) -> LegModel: ...

    def observe(self, sample: Sample) -> None: ...


class NominalController:
    """Commands IK on the platform file's nominal drive: the uncalibrated robot."""

    adaptive = False

    def __init__(self, platform: Platform):
        self._drive: LegModel = platform.drive

    def drive_model(self) -> LegModel:
        return self._drive

    def observe(self, sample: Sample) -> None:
        """Nothing: the nominal model does not learn."""


def loaded_strokes(
    drive: DriveModel, R_d: np.ndarray, t_d: np.ndarray, payload_kg, gravity=None, unannounced_kg: float = 0.0
) -> np.ndarray:
    """IK of an elastic ``drive`` (its legs and terms: compliance, stroke scale, …) at the desired poses, its legs
    holding the platform's weight and ``payload_kg`` (None: not announced, taken as 0) plus ``unannounced_kg``,
    gravity along ``gravity`` (None: the platform's ``[elastic] gravity``): the strokes that reach the poses
    under that load (spec §10)."""
    announced: dict = {} if payload_kg is None else {LOAD_KG: payload_kg}
    if gravity is not None:
        announced[GRAVITY] = gravity
    return drive.inverse_kinematics(R_d, t_d, channels=with_payload(announced, unannounced_kg))


class FrozenController(NominalController):
    """Commands IK on a fixed drive geometry (e.g. a batch estimate frozen after calibration); an elastic
    calibration's with its compliance under each sample's payload.

    Args:
        drive: the legs whose IK gives the strokes.
        elastic: the calibrated elastic drive (``drive`` and its identified terms, :meth:`DriveModel.calibrated`)
            whose :func:`loaded_strokes` under the stage's announced payload give them instead: a rigid IK
            leaves the legs' give under the platform's weight and the payload uncompensated, or None.
    """

    def __init__(self, drive: LegModel, elastic: DriveModel | None = None):
        self._drive = drive
        self._elastic = elastic

    def strokes(self, R_d: np.ndarray, t_d: np.ndarray, payload_kg, gravity=None) -> np.ndarray:
        """IK of the frozen model: the elastic one's under ``payload_kg``, gravity along ``gravity``."""
        if self._elastic is None:
            return self.drive_model().coordinates(R_d, t_d)
        return loaded_strokes(self._elastic, R_d, t_d, payload_kg, gravity)


class EstimatorController:
    """Online calibration in the loop: each sample goes to ``estimator.update``, and the next
    IK uses the nominal drive plus the latest estimate δM (paper Fig. 3, step 4).

    The model is refreshed after every sample, from the mean alone (``current_error()``: isam2's
    marginal covariance would add ~0.3 ms to a ~0.6 ms update): a stale model would cost
    accuracy on the circle, where each point is a single sample.

    Attributes:
        estimator: any :class:`~stewart_calib.estimators.Estimator`.
        rejected: ``(t_s, reason)`` of the samples the estimator refused (SampleRejected); the
            model in force stays the last one.
    """

    adaptive = True

    def __init__(self, estimator, platform: Platform):
        self.estimator = estimator
        self.rejected: list[tuple[float, str]] = []
        self._nominal = platform.drive
        self._drive = platform.drive
        self._error = np.zeros(platform.drive.as_vector().shape)
        self._trace: list[np.ndarray] = []
        self._elastic = drive_model(platform) if platform.elastic is not None else None
        self.payload_known = True

    def drive_model(self) -> LegModel:
        return self._drive

    def observe(self, sample: Sample) -> None:
        """Fold ``sample`` in and refresh the model the next IK will use."""
        try:
            self.estimator.update(sample)
        except SampleRejected as err:
            self.rejected.append((sample.t_s, str(err)))
        else:
            self._error = self.estimator.current_error()
            self._drive = self._nominal.perturbed(self._error)
        self._trace.append(self._error)

    def strokes(self, R_d: np.ndarray, t_d: np.ndarray, payload_kg, gravity=None) -> np.ndarray:
        """IK of the model in force; an elastic one with its identified blocks, under ``payload_kg``
        (taken as 0 unless :attr:`payload_known`) and the payload the estimator found unannounced, gravity
        along ``gravity`` (None: the platform's ``[elastic] gravity``)."""
        if self._elastic is None:
            return self._drive.coordinates(R_d, t_d)
        estimate = model_estimate(self.estimator)
        values = {term.key: estimate.block_values(term.key) for term in self._elastic.terms}
        drive = self._elastic.calibrated(self._error, values)
        announced = payload_kg if self.payload_known else None
        return loaded_strokes(drive, R_d, t_d, announced, gravity, estimate.unannounced_payload_kg())

    def trace(self) -> np.ndarray:
        """``(N, 42)`` δM in force after each observed sample [mm] (paper Figs. 5–6)."""
        return np.array(self._trace).reshape(-1, self._error.size)


@dataclass(frozen=True)
class TrueRobot:
    """The simulated machine: unloaded drive parameters, load model, tracker, encoder noise.

    Attributes:
        base_params: ``(n_params,)`` nominal + δM_base (paper order; a rotary drive's 66, spec §15) [mm, rad].
        load: the load model.
        tracker: the simulated tracker (true geometry incl. residual), or None (no [tracker]).
        encoder_noise_mm: σ of the logged strokes' noise [mm]; a rotary drive's: of the angle each servo
            holds about its command [rad] (its log holds the commands).
        stroke_scale: ``(6,)`` true k_i: the encoders log ``q / (1 + k_i)`` (rotary: a servo turns ``(1 + k_i) θ``).
        encoder_zero_mm: ``(6,)`` true zero errors z_i [mm]: the encoders log ``q − z_i``.
        instrument: the simulated outside instrument, or None (the tracker measures).
        nominal: a rotary robot's nominal legs (its true drive is built from them), else None.
        expansion_ppm_per_K: ``(6,)`` the legs' true thermal expansion α_i [ppm/K], or None (no warm-up).
        reference_temperature_C: ``T_ref`` [°C], where ``base_params`` hold.
    """

    base_params: np.ndarray
    load: LoadModel
    tracker: Tracker | None
    encoder_noise_mm: float
    stroke_scale: np.ndarray
    encoder_zero_mm: np.ndarray
    instrument: SimulatedInstrument | None = None
    nominal: LegModel | None = None
    expansion_ppm_per_K: np.ndarray | None = None
    reference_temperature_C: float = 20.0

    @property
    def rotary(self) -> bool:
        """A rotary drive (spec §15): commanded angles logged, the robot rigid."""
        return self.nominal is not None and self.nominal.kind == "rotary"

    def logged_strokes(self, strokes: np.ndarray, unit_noise: np.ndarray) -> np.ndarray:
        """What the encoders log for executed strokes [mm]: zero and scale errors, then noise; a rotary
        drive logs the commanded angles as they are."""
        if self.rotary:
            return np.array(strokes, dtype=float)
        return encoder_readings(
            (strokes - self.encoder_zero_mm) / (1.0 + self.stroke_scale), self.encoder_noise_mm, unit_noise
        )

    @property
    def unloaded_params(self) -> np.ndarray | None:
        """``(n_params,)`` the drive with no force on its legs, its initial lengths those of the logged strokes'
        zero (the truth's ``params`` are this drive loaded, spec §10), or None for a rigid robot (a rotary drive,
        a massless platform: no ``[elastic]``, :func:`~.load.elastic_of`)."""
        if self.rotary or elastic_of(self.load) is None:
            return None
        return self.at_logged_zero(self.base_params)

    def at_logged_zero(self, params: np.ndarray) -> np.ndarray:
        """Prismatic drive parameters ``(..., n_params)`` with their initial lengths at the logged strokes' zero:
        the model's ``l_i`` of a log whose encoders read ``q − z_i`` (a copy)."""
        params = np.array(params, dtype=float)
        params[..., 6::7] += self.encoder_zero_mm
        return params

    @functools.cached_property
    def true_drive(self) -> DriveModel:
        """The true drive of a rotary robot: its legs with the true errors and its true angle scale."""
        if self.nominal is None:
            raise ValueError("the true drive is built from the nominal legs (a rotary robot's)")
        return plain_drive(self.nominal).true_drive(
            self.base_params - self.nominal.as_vector(), {STROKE_SCALE: self.stroke_scale}
        )

    def growth(self, temperature_C: np.ndarray | None) -> np.ndarray | None:
        """``(..., 6)`` each leg's relative growth ``α_i (T_i − T_ref) · 1e-6`` at ``temperature_C`` (``(..., 6)``
        or a scalar for all legs [°C]); None without a warm-up or a temperature."""
        if self.expansion_ppm_per_K is None or temperature_C is None:
            return None
        return self.expansion_ppm_per_K * (np.asarray(temperature_C, dtype=float) - self.reference_temperature_C) * 1e-6

    def settle(
        self,
        strokes: np.ndarray,
        payload_kg: np.ndarray,
        guess,
        unit_noise: np.ndarray,
        gravity=None,
        temperature_C: np.ndarray | None = None,
    ) -> tuple[kin.FKSolution, np.ndarray]:
        """``(poses, true parameters (N, n_params))`` the robot reaches with the commanded ``strokes (N, 6)``:
        the loaded fixed point of the load model (:class:`~.load.Settling`) under gravity along ``gravity``
        (``(N, 3)``; None: the load model's) with its legs at ``temperature_C`` (``(N, 6)`` [°C]; None: at
        the reference), or a rotary robot's forward kinematics of its servos' angles (``unit_noise``: the
        standard normal draws of their white error)."""
        if not self.rotary:
            return self.settling.settle(strokes, payload_kg, guess, gravity, self.growth(temperature_C))
        held = strokes + self.encoder_noise_mm * unit_noise / (1.0 + self.stroke_scale)
        sol = self.true_drive.forward_kinematics(held, guess=guess)
        return sol, np.tile(self.base_params, (len(strokes), 1))

    def reached(
        self, logged: np.ndarray, guess, payload_kg=0.0, temperature_C: np.ndarray | float | None = None
    ) -> kin.FKSolution:
        """Where this prismatic robot settles when its controller commands the strokes ``logged (N, 6)``
        (in the encoders' units: executed as ``(1 + k_i) q_i + z_i``) under ``payload_kg`` with its legs at
        ``temperature_C`` (a scalar or ``(N, 6)`` [°C]; None: the reference), from ``guess = (R, t)``: what
        a check commands with a calibrated model's ``compensate`` and measures."""
        strokes = np.asarray(logged, dtype=float) * (1.0 + self.stroke_scale) + self.encoder_zero_mm
        n = len(strokes)
        growth = self.growth(None if temperature_C is None else np.broadcast_to(temperature_C, (n, strokes.shape[-1])))
        sol, _ = self.settling.settle(strokes, np.broadcast_to(payload_kg, n), guess, growth=growth)
        return sol

    def readings(
        self, R: np.ndarray, t: np.ndarray, reading_noise: np.ndarray, instrument_draws: np.ndarray
    ) -> np.ndarray:
        """What the measuring instrument logs at the true poses ``(R, t)``."""
        if self.instrument is not None:
            return self.instrument.read(R, t, instrument_draws)
        if self.tracker is None:
            raise ValueError("a robot without an outside instrument is measured by its tracker: it needs one")
        return self.tracker.read(R, t, reading_noise)

    def drive_at(self, pose6: np.ndarray, payload_kg: float = 0.0, gravity=None) -> LegGeometry:
        """True drive geometry in force at a pose ``[mm, rad]`` under a payload [kg], gravity along
        ``gravity`` ``(3,)`` (None: the load model's).

        ``drive_at(home, 0.0)`` is what a perfect no-load calibration would find.
        """
        R, t = kin.pose_to_rt(np.asarray(pose6, dtype=float)[None])
        params, _ = self.settling.loaded_params(R, t, payload_kg, gravity)
        return LegGeometry.from_params(params[0])

    @functools.cached_property
    def settling(self) -> Settling:
        """The load model on this robot's drive, as :func:`~.load.settle` takes it (made once)."""
        return Settling.of(self.load, self.base_params)


def build_robot(
    experiment: Experiment,
    robot_rng: np.random.Generator,
    tracker_rng: np.random.Generator,
    encoder_rng: np.random.Generator | None = None,
    instrument_rng: np.random.Generator | None = None,
) -> TrueRobot:
    """The true robot of an experiment (errors from ``robot_rng``, tracker residual from
    ``tracker_rng``, encoder scale and zero errors from ``encoder_rng``, the outside instrument's
    truth from ``instrument_rng``)."""
    e = experiment
    r = e.robot
    drive = e.platform.drive
    if isinstance(r, RotaryRobotConfig):
        return _rotary_robot(experiment, r, robot_rng, encoder_rng, instrument_rng)
    scales = (r.scale_base_joints, r.scale_platform_joints, r.scale_lengths)
    delta = base_errors(r.errors, scales, r.random_spread_mm, robot_rng, drive.n_params)
    tracker = None
    if e.platform.tracker is not None:
        tracker = Tracker.with_residual(
            e.platform.tracker,
            e.tracker.geometry_residual_mm,
            tracker_rng,
            noise_mm=e.tracker.noise_mm,
            quantum_mm=e.tracker.quantum_mm,
            reading_range_mm=e.platform.reading_range,
        )
    encoder_rng = encoder_rng or np.random.default_rng(0)
    legs = drive.n_legs
    scale = encoder_rng.normal(0.0, r.stroke_scale_spread, legs) if r.stroke_scale_spread > 0 else np.zeros(legs)
    zero = encoder_rng.normal(0.0, r.encoder_zero_spread_mm, legs) if r.encoder_zero_spread_mm > 0 else np.zeros(legs)
    instrument = None
    if e.instrument is not None:
        instrument = SimulatedInstrument.build(
            e.platform.instrument, e.instrument, instrument_rng or np.random.default_rng(0)
        )
    warm = e.warm_up
    return TrueRobot(
        drive.as_vector() + delta,
        e.load,
        tracker,
        r.encoder_noise_mm,
        scale,
        zero,
        instrument,
        expansion_ppm_per_K=None if warm is None else warm.true_expansion_ppm_per_K.copy(),
        reference_temperature_C=20.0 if warm is None else warm.reference_temperature_C,
    )


def _rotary_robot(
    experiment: Experiment,
    config: RotaryRobotConfig,
    robot_rng: np.random.Generator,
    encoder_rng: np.random.Generator | None,
    instrument_rng: np.random.Generator | None,
) -> TrueRobot:
    """The true robot of a rotary drive's experiment (spec §15): its legs' errors from ``robot_rng``
    (:func:`~.robot.rotary_errors`), the angle scale from ``encoder_rng``, rigid, measured from outside."""
    e = experiment
    legs = e.platform.drive
    delta = rotary_errors(config, legs, robot_rng)
    encoder_rng = encoder_rng or np.random.default_rng(0)
    n = legs.n_legs
    scale = encoder_rng.normal(0.0, config.angle_scale_spread, n) if config.angle_scale_spread > 0 else np.zeros(n)
    if e.instrument is None:
        raise CalibError(
            f'{e.source}: key \'instrument\': expected an instrument outside the robot (kind = "pose" or "points"): '
            "a rotary drive is measured from outside (spec §15)"
        )
    instrument = SimulatedInstrument.build(
        e.platform.instrument, e.instrument, instrument_rng or np.random.default_rng(0)
    )
    return TrueRobot(
        legs.as_vector() + delta,
        e.load,
        None,
        np.radians(config.angle_noise_deg),
        scale,
        np.zeros(n),
        instrument,
        legs,
    )


@dataclass
class SimulationResult:
    """Everything a simulated run produced, N samples.

    Attributes:
        log: what the machine logged (spec §3): strokes with encoder noise, tracker readings,
            desired poses, stage labels, payload.
        truth: true drive parameters in force ``(N, 42)`` [mm] and true poses ``(N, 6)`` [mm, rad].
        desired_poses: ``(N, 6)`` [mm, rad]. actual_poses: ``(N, 6)`` [mm, rad] (= truth.true_poses).
        stages: ``(N,)`` stage names. kinds: ``(N,)`` ``"calibration"``/``"validation"``/``"circle"``.
        payload_kg: ``(N,)`` payload in force [kg]. pose_index: ``(N,)`` pose number within its segment.
        robot: the true robot (base parameters, load model, tracker).
    """

    log: Log
    truth: Truth
    desired_poses: np.ndarray
    actual_poses: np.ndarray
    stages: np.ndarray
    kinds: np.ndarray
    payload_kg: np.ndarray
    pose_index: np.ndarray
    robot: TrueRobot

    def pose_errors(self) -> tuple[np.ndarray, np.ndarray]:
        """Per sample ``(‖t_actual − t_desired‖ [mm], rotation angle of R_dᵀ R_a [deg])``."""
        Rd, td = kin.pose_to_rt(self.desired_poses)
        Ra, ta = kin.pose_to_rt(self.actual_poses)
        return kin.pose_error(Rd, td, Ra, ta)

    def mean_errors(self, kind: str, stage: str | None = None) -> tuple[float, float]:
        """Mean position [mm] and orientation [deg] error over the samples of one segment kind
        (and stage) — Table 5's metric for static poses, Table 6's position deviation for circles."""
        mask = self.kinds == kind
        if stage is not None:
            mask &= self.stages == stage
        if not np.any(mask):
            raise ValueError(f"no samples of kind {kind!r}" + (f" in stage {stage!r}" if stage else ""))
        position, orientation = self.pose_errors()
        return float(position[mask].mean()), float(orientation[mask].mean())


#: samples settled, measured and handed on at a time: the working arrays of a block (settle's
#: per-pose geometry and statics, the CSV text of its rows) stay a few MB whatever the run's length.
BLOCK_SAMPLES = 4096


@dataclass
class SimulationRun:
    """A run being simulated (:func:`simulate_blocks`): the true robot, the schedule, and the
    samples as ``(log, truth)`` blocks of at most :data:`BLOCK_SAMPLES` rows, in order (one
    pass; the blocks are simulated as they are taken)."""

    robot: TrueRobot
    plan: Schedule
    blocks: Iterator[tuple[Log, Truth]]


def simulate_blocks(
    experiment: Experiment, controller: Controller | None = None, progress: bool = False
) -> SimulationRun:
    """Simulate an experiment in closed loop a block at a time (see the module docstring); the
    blocks joined are :func:`run_experiment`'s log and truth, bit for bit.

    Args and raises: as :func:`run_experiment` (an unreachable stroke set raises when its block is taken).
    """
    controller = NominalController(experiment.platform) if controller is None else controller
    # spawn(6)'s first four streams are spawn(4)'s: adding streams reshuffles no older experiment
    robot_rng, tracker_rng, poses_rng, noise_rng, encoder_rng, instrument_rng = np.random.default_rng(
        experiment.seed
    ).spawn(6)
    robot = build_robot(experiment, robot_rng, tracker_rng, encoder_rng, instrument_rng)
    plan = schedule(experiment, poses_rng)
    n = len(plan.t_s)
    # the (n, legs) stroke noise, then the (n, rulers) reading noise of one stream, drawn a block at a
    # time; without a tracker the readings' noise is drawn all the same, as wide as the drive's legs
    legs = robot.stroke_scale.size
    rulers = legs if robot.tracker is None else robot.tracker.geometry.n_legs
    stroke_noise, reading_noise = _consecutive_draws(noise_rng, n, (legs, rulers))
    instrument_draws = robot.instrument.draw(n, instrument_rng) if robot.instrument is not None else np.zeros((n, 0))
    step = _settle_each if getattr(controller, "adaptive", True) else _settle_block

    def blocks() -> Iterator[tuple[Log, Truth]]:
        bar = progress_bar(total=n, desc=f"simulate {experiment.name}", show=progress)
        try:
            for lo in range(0, max(n, 1), BLOCK_SAMPLES):  # one empty block for an empty schedule
                rows = slice(lo, min(lo + BLOCK_SAMPLES, n))
                m = rows.stop - rows.start
                noise = (
                    stroke_noise.standard_normal((m, legs)),
                    reading_noise.standard_normal((m, rulers)),
                    instrument_draws[rows],
                )
                try:
                    block = step(robot, plan, rows, controller, noise)
                except Unreachable as err:
                    raise CalibError(f"{shown(experiment.source)}: {err}") from None
                yield block
                bar.update(m)
        finally:
            bar.close()

    return SimulationRun(robot, plan, blocks())


def _consecutive_draws(rng: np.random.Generator, n: int, widths: tuple[int, ...]) -> list[np.random.Generator]:
    """Copies of ``rng`` at the starts of consecutive ``rng.standard_normal((n, width))`` calls, one
    per width: drawing ``(m, width)`` blocks from the k-th copy gives the k-th call's rows in order
    (a Generator fills its output value after value), without holding any of them whole."""
    starts = []
    for width in widths:
        starts.append(copy.deepcopy(rng))
        for lo in range(0, n, BLOCK_SAMPLES):  # past this call's draws
            rng.standard_normal((min(BLOCK_SAMPLES, n - lo), width))
    return starts


def _settle_block(robot: TrueRobot, plan: Schedule, rows: slice, controller: Controller, noise) -> tuple[Log, Truth]:
    """A model that never changes: the block's IK, settling and measurements in one vectorised pass
    (``noise``: the block's stroke and reading noise and instrument draws)."""
    R_d, t_d = kin.pose_to_rt(plan.desired_poses[rows])
    gravity = None if plan.gravity is None else plan.gravity[rows]
    strokes = _commanded(controller, R_d, t_d, plan.payload_kg[rows], plan, rows.start, gravity)
    temperature = None if plan.temperature_C is None else plan.temperature_C[rows]
    sol, params = robot.settle(strokes, plan.payload_kg[rows], (R_d, t_d), noise[0], gravity, temperature)
    log, truth = _measured(robot, plan, rows, strokes, sol.R, sol.t, params, noise)
    for sample in log:  # the protocol promises observe() after every sample
        controller.observe(sample)
    return log, truth


def _settle_each(robot: TrueRobot, plan: Schedule, rows: slice, controller: Controller, noise) -> tuple[Log, Truth]:
    """A model that may change after every sample: IK and settling one sample at a time."""
    stroke_noise, reading_noise, instrument_draws = noise
    R_d, t_d = kin.pose_to_rt(plan.desired_poses[rows])
    m = len(t_d)
    strokes, params = np.empty((m, len(robot.stroke_scale))), np.empty((m, robot.base_params.size))
    R, t = np.empty((m, 3, 3)), np.empty((m, 3))
    for i, k in enumerate(range(rows.start, rows.stop)):
        gravity = None if plan.gravity is None else plan.gravity[k]
        strokes[i] = _commanded(controller, R_d[i], t_d[i], plan.payload_kg[k], plan, k, gravity)
        sol, params[i : i + 1] = robot.settle(
            strokes[i : i + 1],
            plan.payload_kg[k : k + 1],
            (R_d[i : i + 1], t_d[i : i + 1]),
            stroke_noise[i : i + 1],
            None if gravity is None else gravity[None],
            None if plan.temperature_C is None else plan.temperature_C[k : k + 1],
        )
        R[i], t[i] = sol.R[0], sol.t[0]
        controller.observe(
            _sample(robot, plan, k, strokes[i], stroke_noise[i], R[i], t[i], reading_noise[i], instrument_draws[i])
        )
    return _measured(robot, plan, rows, strokes, R, t, params, noise)


class Unreachable(ValueError):
    """A desired pose the controller's model reaches with no drive coordinate (a rotary drive's
    inverse kinematics: no horn angle within the angle range, spec §15)."""


def _commanded(
    controller: Controller, R_d: np.ndarray, t_d: np.ndarray, payload_kg, plan: Schedule, first: int, gravity=None
):
    """The strokes ``controller`` commands for desired poses: its own ``strokes`` where it has one (told
    the samples' ``gravity`` where the mount tilts), else IK of its drive model (``plan``'s samples from
    ``first``: named where one is unreachable).

    Raises:
        Unreachable: a pose with a coordinate the IK leaves NaN, naming its sample.
    """
    command = getattr(controller, "strokes", None)
    if command is None:
        strokes = controller.drive_model().coordinates(R_d, t_d)
    elif gravity is None:
        strokes = command(R_d, t_d, payload_kg)
    else:
        strokes = command(R_d, t_d, payload_kg, gravity=gravity)
    bad = np.flatnonzero(~np.all(np.isfinite(np.reshape(strokes, (-1, np.shape(strokes)[-1]))), axis=1))
    if bad.size:
        k = first + int(bad[0])
        raise Unreachable(
            f"sample {k + 1} (t_s = {plan.t_s[k]:g} s, {plan.kinds[k]} pose {plan.pose_index[k] + 1}): the "
            "controller's model has no drive coordinate within range for its desired pose (a rotary drive's "
            "drive.angle_range_deg); expected poses within reach (a smaller workspace or trajectory)"
        )
    return strokes


def _measured(robot: TrueRobot, plan: Schedule, rows: slice, strokes, R, t, params, noise) -> tuple[Log, Truth]:
    """What the machine logs for a block of settled samples, and its truth."""
    stroke_noise, reading_noise, instrument_draws = noise
    log = Log(
        t_s=plan.t_s[rows].copy(),
        strokes=robot.logged_strokes(strokes, stroke_noise),
        readings=robot.readings(R, t, reading_noise, instrument_draws),
        desired_poses=plan.desired_poses[rows].copy(),
        stages=list(plan.stages[rows]),
        inputs=_channels(plan, rows),
    )
    params = params.copy() if robot.rotary else robot.at_logged_zero(params)
    instrument = None
    if robot.instrument is not None:
        instrument = (robot.instrument.names(), robot.instrument.unknowns.file_values())
    elif robot.tracker is not None:  # an in-situ tracker's own values, where they are off its nominal ones
        instrument = robot.tracker.truth()
    truth = Truth(
        t_s=plan.t_s[rows].copy(),
        params=params,
        true_poses=kin.rt_to_pose(R, t),
        drive_terms=_true_terms(robot),
        instrument=instrument,
        unloaded=robot.unloaded_params,
    )
    return log, truth


def run_experiment(
    experiment: Experiment, controller: Controller | None = None, progress: bool = False
) -> SimulationResult:
    """Simulate an experiment in closed loop (see the module docstring), held whole.

    Args:
        experiment: from :func:`~stewart_calib.simulation.experiment.load_experiment`.
        controller: default :class:`NominalController` of the experiment's platform.
        progress: show a tqdm bar on stderr (when it is a terminal).
    Raises:
        kinematics.FKError: the robot cannot reach a commanded stroke set.
    """
    run = simulate_blocks(experiment, controller, progress)
    logs, truths = zip(*run.blocks, strict=True)
    log = Log.concatenate(list(logs))
    first = truths[0]
    joined = lambda name: np.concatenate([getattr(truth, name) for truth in truths])  # noqa: E731
    actual_poses = joined("true_poses")
    truth = Truth(joined("t_s"), joined("params"), actual_poses, first.drive_terms, first.instrument, first.unloaded)
    plan = run.plan
    return SimulationResult(
        log,
        truth,
        plan.desired_poses,
        actual_poses,
        plan.stages,
        plan.kinds,
        plan.payload_kg,
        plan.pose_index,
        run.robot,
    )


def _sample(robot: TrueRobot, plan, k: int, stroke, stroke_noise, R, t, reading_noise, instrument_draws) -> Sample:
    return Sample(
        t_s=float(plan.t_s[k]),
        strokes=robot.logged_strokes(stroke, stroke_noise),
        readings=robot.readings(R, t, reading_noise, instrument_draws),
        desired_pose=plan.desired_poses[k],
        stage=str(plan.stages[k]),
        inputs={name: value if np.ndim(value) else float(value) for name, value in _channels(plan, k).items()},
    )


def _channels(plan: Schedule, index) -> dict[str, np.ndarray]:
    """The input channels a log holds at ``plan``'s samples ``index`` (a slice or a sample): the payload,
    gravity's direction where the mount tilts, and a warm-up's leg temperatures."""
    channels = {LOAD_KG: np.array(plan.payload_kg[index])}
    if plan.gravity is not None:
        channels[GRAVITY] = np.array(plan.gravity[index])
    if plan.temperature_C is not None:
        channels[TEMPERATURE_C] = np.array(plan.temperature_C[index])
    return channels


def _true_terms(robot: TrueRobot) -> dict[str, np.ndarray]:
    """The truth's drive terms (:attr:`~stewart_calib.samples.Truth.drive_terms`): the stroke scale, and a
    warm-up's expansion."""
    terms = {STROKE_SCALE: robot.stroke_scale.copy()}
    if robot.expansion_ppm_per_K is not None:
        terms[THERMAL] = robot.expansion_ppm_per_K.copy()
    return terms
