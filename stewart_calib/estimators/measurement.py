"""From one sample to what the estimators observe (paper Fig. 3, steps 1–2).

* :func:`check_sample` — refuse an unusable sample (non-finite, outside the platform's
  stroke range, refused by the instrument model) with
  :class:`~stewart_calib.errors.SampleRejected` before any state is touched.
* :func:`estimator_drive`, :func:`unknown_layout` — the drive model an estimator identifies and
  its unknown vector: δM, then the drive's unknown blocks, then the instrument model's own unknowns.
* :class:`WarmFK` — forward kinematics of one leg set, warm-started from the previous
  solution (2 Newton iterations instead of 4–5 on a smooth trajectory), falling back to
  a cold start before giving up; FK failure becomes ``SampleRejected``.
* :class:`WarmPose` — the same for an instrument model's loose pose; :class:`LegSetPose` — and the
  EKF's observation through it, compiled, for an instrument that offers compiled kernels.
* :func:`pose_difference` — ``P_v − P_m`` as the paper's ``δE = [δh, δθ]`` (eq. 9).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from ..config import EstimatorConfig, NoiseConfig
from ..errors import CalibError, SampleRejected, number
from ..instruments import (
    InstrumentModel,
    PoseObservation,
    instrument_kind,
    instrument_model,
    instrument_theta,
    needs_registration,
    registered,
)
from ..model import _kernels
from ..model import kinematics as kin
from ..model.drive import DriveModel, drive_model
from ..model.legs import LegModel
from ..model.platform import Platform
from ..model.unknowns import UnknownLayout
from ..samples import CHANNEL_SHAPES, Sample
from .base import state_array
from .kalman import leg_set_filter_rows, leg_set_observation


def check_sample(platform: Platform, model: InstrumentModel, sample: Sample) -> tuple[np.ndarray, np.ndarray]:
    """Strokes and the instrument's measurement of ``sample`` as float arrays, or :class:`SampleRejected`.

    Refuses a non-finite time, non-finite strokes or strokes outside ``platform.stroke_range``
    (inclusive bounds, spec §3), then whatever ``model.check`` refuses.
    """
    strokes = np.asarray(sample.strokes, dtype=float)
    legs = platform.drive.n_legs
    lo, hi = platform.stroke_range if platform.stroke_range is not None else (-math.inf, math.inf)
    # One compiled check for the common, valid sample (the wording below costs several times more).
    if not (
        strokes.shape == (legs,) and math.isfinite(sample.t_s) and _kernels.all_within(strokes, float(lo), float(hi))
    ):
        if not np.isfinite(sample.t_s):
            raise SampleRejected(f"sample at t = {number(sample.t_s)} s: non-finite time", SampleRejected.NON_FINITE)
        if strokes.shape != (legs,):
            raise SampleRejected(
                f"sample at t = {number(sample.t_s)} s: expected {legs} stroke q values, got shape {strokes.shape}",
                SampleRejected.NON_FINITE,
            )
        bad = np.flatnonzero(~np.isfinite(strokes))
        if bad.size:
            raise SampleRejected(
                f"sample at t = {number(sample.t_s)} s: stroke q{bad[0] + 1} is not finite", SampleRejected.NON_FINITE
            )
        i = int(np.flatnonzero((strokes < lo) | (strokes > hi))[0])
        raise SampleRejected(
            f"sample at t = {number(sample.t_s)} s: stroke q{i + 1} = {strokes[i]:.6g} mm outside [{lo}, {hi}] mm",
            SampleRejected.OUT_OF_RANGE,
        )
    return strokes, model.check(sample.readings, sample.t_s)


def estimator_drive(platform: Platform, noise: NoiseConfig) -> DriveModel:
    """The drive an estimator identifies: its unknown terms as ``noise`` asks, and
    the encoders' scale always with an instrument outside the robot (:func:`~stewart_calib.model.drive.drive_model`)."""
    return drive_model(platform, noise, outside_instrument=instrument_kind(platform).outside)


def unknown_layout(platform: Platform, noise: NoiseConfig, model: InstrumentModel) -> UnknownLayout:
    """δM, then the drive's unknown blocks (:func:`estimator_drive`), then ``model``'s unknowns."""
    drive = estimator_drive(platform, noise)
    blocks = drive.blocks
    return UnknownLayout(blocks if model.unknowns is None else (*blocks, model.unknowns), n_params=drive.n_params)


def drive_inputs(
    drive: DriveModel,
    model: InstrumentModel,
    strokes: np.ndarray,
    z: np.ndarray,
    channels,
    guess=None,
    x_drive=None,
    per_kg: bool = False,
) -> np.ndarray:
    """One sample's drive inputs (:meth:`~stewart_calib.model.drive.DriveModel.inputs`): its strokes and, for
    an elastic drive, the leg forces under its input ``channels`` (``Sample.inputs``) at the pose
    the measurement fixes with the instrument at its nominal (:meth:`InstrumentModel.pose`, from
    ``guess``), or where it fixes none at the drive's own forward kinematics; with ``per_kg``,
    followed by the leg forces per kg of payload at that pose
    (:meth:`~stewart_calib.model.drive.DriveModel.payload_leg_forces`, for an estimated payload)."""
    if not drive.needs_pose:
        return drive.inputs(strokes, channels)
    observed = model.pose(z, instrument_theta(model, None), guess)
    if observed is None:
        batch = {name: np.asarray(value)[None] for name, value in (channels or {}).items()}
        solution, settled = drive.settled_kinematics(np.asarray(strokes)[None], batch, strict=False)
        R, t, inputs = solution.R[0], solution.t[0], settled[0]
    else:
        R, t = observed.R, observed.t
        inputs = drive.inputs(strokes, channels, R, t, x_drive)
    return np.concatenate([inputs, drive.payload_leg_forces(R, t, x_drive, channels)]) if per_kg else inputs


class _WarmStart:
    """The last pose of a stream, the next solve's Newton start; exported for checkpoints, since a
    resumed stream must start Newton from the same pose to reproduce the same solution bit for bit."""

    _guess: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def guess(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The next solve's start: the last pose (None before the first)."""
        return self._guess

    def export_state(self) -> dict:
        """The warm start ``{"R", "t"}`` (empty before the first solve)."""
        return {} if self._guess is None else {"R": self._guess[0].copy(), "t": self._guess[1].copy()}

    def import_state(self, state: dict) -> None:
        """Restore :meth:`export_state`'s warm start. Raises ``CalibError`` on a bad shape."""
        self._guess = (state_array(state, "R", (3, 3)), state_array(state, "t", (3,))) if state else None


class WarmFK(_WarmStart):
    """Forward kinematics for a stream of samples, warm-started from the last solution."""

    def solve(self, legs: LegModel, coordinates: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
        """``(R, t)`` closing every leg of ``legs`` at its ``coordinates`` (paper step 1).

        Tries the previous pose first, then the default cold guess (the leg model's ``solve_fk``).

        Raises:
            SampleRejected: neither start converges; ``what`` names the leg set.
        """
        self._guess = legs.solve_fk(coordinates, self._guess, what)
        return self._guess

    def solve_drive(self, drive, inputs: np.ndarray, x_drive: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`solve` of a :class:`~stewart_calib.model.drive.DriveModel` at ``x_drive`` for one
        sample's drive ``inputs`` (its legs' coordinates and whatever else its terms give them)."""
        self._guess = drive.solve_fk(inputs, x_drive, self._guess, what)
        return self._guess


class WarmPose(_WarmStart):
    """An instrument model's loose pose for a stream of samples, warm-started from the last one."""

    def __init__(self, model: InstrumentModel):
        self.model = model

    def solve(self, z: np.ndarray, theta: np.ndarray) -> PoseObservation | None:
        """The pose ``z`` implies (:meth:`~stewart_calib.instruments.base.InstrumentModel.pose`),
        or None where it does not fix one. Raises ``SampleRejected`` as the model does."""
        observed = self.model.pose(z, theta, self._guess)
        if observed is not None:
            self._guess = (observed.R, observed.t)
        return observed


class LegSetPose(WarmPose):
    """:class:`WarmPose` of an instrument that offers compiled kernels: its readings are those of a
    prismatic leg set of known geometry (``model.compiled_legs``), and the drive's legs have compiled
    kernels too (``drive.legs.compiled``), so the EKF's observation of a prepared
    sample ``[u | z]`` through the pose they fix is one compiled call
    (:func:`~.kalman.leg_set_observation`), and so is the robust filter's recursion over rows of them
    (:meth:`rows`, :func:`~.kalman.leg_set_filter_rows`: the same observation). Both move the one warm start.

    Args:
        model: the instrument model (``compiled_legs`` not None).
        drive: the drive model the EKF identifies (its unknown terms: columns of the state after δM;
            its legs compiled).
        stroke_sigma_mm: σ_q of a stroke [mm].
    """

    def __init__(self, model: InstrumentModel, drive: DriveModel, stroke_sigma_mm: float):
        super().__init__(model)
        legs = model.compiled_legs
        if legs is None:
            raise TypeError(f"the {model.kind} instrument's model offers no compiled kernels")
        self.legs = legs
        starts, gains, offsets, values, columns = drive.kernel_terms()  # compiled legs only
        self._observation = (
            drive.prismatic().kernel_geometry(),
            legs.kernel_geometry(),
            (starts, gains, np.ascontiguousarray(offsets[:, None] + values), columns),
            (float(model.channel_sigma[0]) ** 2, float(stroke_sigma_mm) ** 2),
            (kin.FK_TOLERANCE_MM, kin.FK_MAX_ITERATIONS),
        )

    def observe(self, x: np.ndarray, row: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(ν = −r, H = ∂r/∂x, R0 = R_meas)`` of the drive's leg residuals at the pose the readings of
        ``row = [u | z]`` fix, at the state ``x`` (δM, then the drive's unknown terms, then any other
        unknowns, whose columns of ``H`` are 0). Raises ``SampleRejected`` where FK fails."""
        R, t = kin.start_pose(self._guess)
        residual, nu, H, R0 = leg_set_observation(x, row, self._observation, R, t, self._guess is not None)
        if not residual <= kin.FK_TOLERANCE_MM:
            raise kin.fk_failed(self.model.kind, residual)
        self._guess = (R, t)
        return nu, H, R0

    def rows(self, x, P, Q, unit_Q, S_last, t_s, prepared, poses, use, last_t, walk, noise_scale2, gate, skip, *window):
        """:func:`~.kalman.leg_set_filter_rows` from this warm start (moved to the last pose it found),
        with the observation's fixed arguments; ``walk``: the walk rate, ``gate``: the NIS gate; ``poses``: each
        row's pose where the caller knows it, Newton's start there (``(0, 12)``: none); ``window`` = the sample
        window's arrays and span,
        ``since_window``, ``window``, ``errors_out``, ``components``. Returns ``(rows done, why it stopped,
        rows taken, last taken t_s, its NIS, since_window)``."""
        R, t = kin.start_pose(self._guess)
        done, why, taken, last_t, nis, since_window, warm = leg_set_filter_rows(
            x,
            P,
            Q,
            unit_Q,
            S_last,
            np.ascontiguousarray(t_s),  # a track's block may hand a strided view: one specialisation
            np.ascontiguousarray(prepared),
            np.ascontiguousarray(poses),
            use,
            float(last_t),
            self._observation,
            float(walk),
            float(noise_scale2),
            float(gate),
            skip,
            R,
            t,
            self._guess is not None,
            *window,
        )
        if warm:
            self._guess = (R, t)
        return done, why, taken, last_t, nis, since_window


def pose_difference(R_v: np.ndarray, t_v: np.ndarray, R_m: np.ndarray, t_m: np.ndarray) -> np.ndarray:
    """``Y = P_v − P_m`` as ``[δh [mm], δθ [rad]]`` (paper eq. 9 and Fig. 3 step 2).

    ``δθ`` is the difference of roll-pitch-yaw, wrapped to (−π, π], the coordinates in
    which :func:`~stewart_calib.model.kinematics.error_jacobian` is written.
    """
    shape = np.shape
    batch = np.broadcast_shapes(shape(R_v)[:-2], shape(t_v)[:-1], shape(R_m)[:-2], shape(t_m)[:-1])
    R_v, t_v, _ = kin._flat_poses(R_v, t_v, batch)
    R_m, t_m, _ = kin._flat_poses(R_m, t_m, batch)
    Y = np.empty((len(R_v), 6))
    _kernels.pose_difference(R_v, t_v, R_m, t_m, Y)  # per-pose loop: numpy's small-array overhead dominated
    return Y.reshape(batch + (6,))


def registered_start(
    platform: Platform, noise: NoiseConfig, model: InstrumentModel, layout: UnknownLayout, samples: list[Sample]
) -> np.ndarray:
    """The unknown vector to start from: zeros, but for an instrument registered on the data
    (:func:`~stewart_calib.instruments.registry.needs_registration`) its block at the registration
    on ``samples`` (the closed form refined by least squares) — a frame 100 mm and any rotation from
    nominal, or metres away, is then within the linearisation of every method.

    Raises:
        CalibError: the samples cannot register the instrument (the reason says why).
    """
    start = np.zeros(layout.size)
    columns, block = layout.slice("instrument"), layout.block("instrument")
    if columns is None or block is None or not needs_registration(platform):
        return start
    width, legs = len(model.columns), platform.drive.n_legs
    usable = [s for s in samples if np.shape(s.strokes) == (legs,) and np.shape(s.readings) == (width,)]
    strokes = np.array([s.strokes for s in usable], dtype=float).reshape(-1, legs)
    readings = np.array([s.readings for s in usable], dtype=float).reshape(-1, width)
    theta = instrument_theta(instrument_model(registered(platform, strokes, readings), noise), None)
    start[columns] = theta - block.nominal
    return start


#: samples an online method holds before it registers an instrument that asks for it: the
#: closed-form registration wants several distinct poses (three at the very least).
REGISTRATION_SAMPLES = 10


class HeldForRegistration:
    """The samples an online method holds until its instrument can be registered on them
    (:func:`registered_start`); then it starts from the registration and replays them.

    Attributes:
        active: still holding (False from the start for an instrument without registration).
    """

    def __init__(self, platform: Platform, noise: NoiseConfig, model: InstrumentModel, layout: UnknownLayout):
        self._args = (platform, noise, model, layout)
        self.active = layout.slice("instrument") is not None and needs_registration(platform)
        self.samples: list[Sample] = []
        #: held samples the replay refused, not yet reported (``err.t_s``: the sample's time)
        self.late: list[SampleRejected] = []

    def waiting(self) -> int:
        """Samples held, not yet registered and replayed."""
        return len(self.samples) if self.active else 0

    def take_late(self) -> list[SampleRejected]:
        """The held samples the replay refused (each once): they were taken when held, so their
        refusal comes late, for the caller's count (see :func:`~.base.take_late_rejections`)."""
        late, self.late = self.late, []
        return late

    def hold(self, sample: Sample) -> np.ndarray | None:
        """Hold ``sample``; once :data:`REGISTRATION_SAMPLES` are held and they register the
        instrument, the start vector (and holding ends: the caller replays :attr:`samples`)."""
        self.samples.append(sample)
        if len(self.samples) < REGISTRATION_SAMPLES:
            return None
        try:
            start = registered_start(*self._args, self.samples)
        except CalibError:  # not yet: e.g. the poses held so far are not distinct enough
            return None
        self.active = False
        return start

    def hold_then_replay(
        self, sample: Sample, start: Callable[[np.ndarray], None], replay: Callable[[Sample], None]
    ) -> None:
        """:meth:`hold` ``sample``; once the held samples register the instrument, ``start(vector)``
        and ``replay`` each of them (one it refuses is left out, as it would have been, and reported
        by :meth:`take_late`)."""
        vector = self.hold(sample)
        if vector is None:
            return
        start(vector)
        for held in self.samples:
            try:
                replay(held)
            except SampleRejected as err:
                err.t_s = held.t_s
                self.late.append(err)

    def export_state(self) -> dict:
        """The held samples as arrays, while holding (a checkpoint without them has ended holding)."""
        return samples_to_arrays(self.samples, self._args[0].drive.n_legs, len(self._args[2].columns))

    def restore(self, state: dict, update) -> None:
        """Restore a checkpoint's ``state`` of the estimator: its ``"held"`` samples are held again
        (through ``update``); without them, holding had ended. Raises ``CalibError`` on a bad shape."""
        if "held" not in state:
            self.active = False
            return
        for sample in samples_from_arrays(state["held"], self._args[0].drive.n_legs, len(self._args[2].columns)):
            update(sample)


def samples_to_arrays(samples: list[Sample], n_legs: int, n_columns: int) -> dict[str, np.ndarray]:
    """Samples as arrays for a checkpoint (the samples an online method holds, has pending or replays):
    ``n_legs`` strokes and ``n_columns`` readings each, and every input channel one of them carries by
    its name (``load_kg``, …), NaN where a sample has none."""
    arrays = {
        "t_s": np.array([s.t_s for s in samples], dtype=float),
        "strokes": np.array([s.strokes for s in samples], dtype=float).reshape(-1, n_legs),
        "readings": np.array([s.readings for s in samples], dtype=float).reshape(len(samples), n_columns),
    }
    for name, shape in CHANNEL_SHAPES.items():
        if any(name in s.inputs for s in samples):
            missing = np.full(shape, np.nan)
            arrays[name] = np.array([s.inputs.get(name, missing) for s in samples], dtype=float).reshape(-1, *shape)
    return arrays


def samples_from_arrays(arrays: dict, n_legs: int, n_columns: int) -> list[Sample]:
    """:func:`samples_to_arrays` back; a channel a checkpoint lacks is absent from its samples."""
    t_s = state_array(arrays, "t_s", np.shape(arrays.get("t_s", ())))
    strokes = state_array(arrays, "strokes", (len(t_s), n_legs))
    readings = state_array(arrays, "readings", (len(t_s), n_columns))
    channels = {
        name: state_array(arrays, name, (len(t_s), *shape)) for name, shape in CHANNEL_SHAPES.items() if name in arrays
    }

    def inputs(k: int) -> dict:
        return {name: values[k] for name, values in channels.items() if not np.all(np.isnan(values[k]))}

    return [Sample(float(t_s[k]), strokes[k], readings[k], inputs=inputs(k)) for k in range(len(t_s))]


def drive_only_model(
    method: str, platform: Platform, config: EstimatorConfig, drive_blocks: bool = False
) -> InstrumentModel:
    """The instrument model of a method that identifies the drive from the measured pose ``P_v``
    alone (``ls``, ``paper-ekf``): δM and, where ``drive_blocks``, the drive's own
    unknown terms (stroke scale, compliance).

    Raises:
        CalibError: the configuration asks for more unknowns (the instrument's own; the drive's
            blocks unless ``drive_blocks``).
    """
    model = instrument_model(platform, config.noise)
    layout = unknown_layout(platform, config.noise, model)
    drive = {block.key for block in estimator_drive(platform, config.noise).blocks}
    extra = [block.key for block in layout.blocks if not (drive_blocks and block.key in drive)]
    if extra:
        parameters = f"the {layout.n_params} drive parameters"
        allowed = f"{parameters} and the drive's own blocks" if drive_blocks else parameters
        raise CalibError(f"{method} identifies {allowed} only, not {', '.join(extra)}; use ekf, isam2 or lm")
    return model


def measured_pose(
    pose: WarmPose, z: np.ndarray, t_s: float, theta: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``P_v``: the pose the instrument (its unknowns at ``θ``; default none) measured (paper Fig. 3
    step 1), or ``SampleRejected``."""
    observed = pose.solve(z, np.zeros(0) if theta is None else theta)
    if observed is None:
        raise SampleRejected(
            f"sample at t = {number(t_s)} s: the measurement does not fix a pose", SampleRejected.NO_POSE
        )
    return observed.R, observed.t
