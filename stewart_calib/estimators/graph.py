"""The factor graph that ``isam2`` (:mod:`.isam2`) and ``lm`` (:mod:`.lm`) both solve.

Variables: one ``Pose3`` ``x_k`` per sample (the platform {D} in {J}, mm and rad) and one
unknown vector ``p_w`` per parameter window: the drive's ``x_drive`` (δM, paper eq. 9, paper order,
[mm], and its unknown blocks) followed by the instrument's unknowns (:mod:`stewart_calib.model.unknowns`).
Factors of sample k (all from :mod:`stewart_calib.factors`):

* six drive-leg factors on ``(x_k, p_w)``: the drive model's ``‖t + R d_i − j_i‖ − (l_i + e_i)``,
  σ_q (:mod:`stewart_calib.factors.drive_leg`, :mod:`stewart_calib.model.drive`); in ``isam2``'s graph
  (``walk_in_windows``) widened by the walk from the window's first sample to sample k;
* tight coupling: the instrument's factors (:mod:`stewart_calib.factors.instrument`), one per
  channel group of its model — for the tracker one per ruler, ``‖t + R h_i − z_i‖ − (ls_i + s_i)``, σ_s;
  loose coupling: one pose prior on ``x_k`` from the model's loose pose and its covariance
  (:mod:`stewart_calib.factors.instrument_pose`) where the measurement fixes a pose and the
  instrument has no unknowns (a prior could not follow them); otherwise the tight factors;
* per window: a random-walk between factor ``p_w → p_{w+1}``, σ = random_walk·√Δt on δM (at
  least ``chain_sigma_floor_mm``, the floor alone on constant blocks); on ``p_0`` the prior
  N(0, diag(σ²)) (``prior_sigma_mm`` on δM, each block's own); where a block shares the drive's
  gauge, the constraint ``C p_w = 0`` on every ``p_w`` (:mod:`stewart_calib.factors.gauge`).

An unannounced payload (``[elastic] payload_sigma_kg`` > 0, ``isam2`` only): the payload mass ``m``
[kg] is the unknown vector's last entry, as in ekf's state (``isam2`` takes its front end's layout),
and enters each drive-leg factor (:mod:`stewart_calib.factors.drive_leg`). Between windows it is
tied by the floor σ alone, so it averages over the samples; the sample a step of it happened at, as
the front end found it (:attr:`GraphBuilder.steps`), opens a new window whose walk factor lets ``m``
move by the prior's σ_m, so the step moves ``m`` at that sample (the front end's value after the step
its initial value), not δM over tens of samples.

The in-situ tracker's misfit at a static pose (``pose_misfit``, where the front end carries it: an unannounced
payload's steps tested on the tracker, or ``noise.pose_misfit_sigma_mm``): one variable ``b`` a static pose
(inputs within the tolerance of the pose's first sample's), prior ``N(0, κ R0)``, added to every measurement
row of the pose's samples (:mod:`stewart_calib.factors.pose_misfit`), so they weigh as their mean, as in ekf.

Measurement factors may carry a Huber or Cauchy kernel (``[isam2] robust``). The initial value
of ``x_k`` is the instrument's loose pose (the tracker's FK) warm-started from the previous
sample's pose, or the drive model's FK where the measurement does not fix a pose.

Parameter layout: one 42-vector per window, not six 7-vectors per leg. Smoother update alone,
1000 noisy samples, window 10 samples, lag 3 s, QR: median 0.48 ms (42-vector) against 0.56 ms
(per leg) with relinearisation threshold 1e-2, and 1.8 against 7.7 ms with 1e-3, where the
parameters are relinearised at almost every update; RMS errors vs truth agree to 1e-7 mm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import gtsam
import numpy as np

from ..config import EstimatorConfig
from ..errors import SampleRejected, number
from ..estimate import Estimate
from ..factors import diagonal_noise, drive_leg, gauge, instrument, instrument_pose, pose_misfit, random_walk
from ..instruments import instrument_model, instrument_theta
from ..model.drive import PAYLOAD
from ..model.platform import Platform
from ..model.unknowns import UnknownLayout
from ..samples import Sample
from .measurement import check_sample, estimator_drive, unknown_layout


def pose_key(k: int) -> int:
    """Key of the pose variable of sample k (0-based)."""
    return gtsam.symbol("x", k)


def params_key(w: int) -> int:
    """Key of the δM variable of parameter window w (0-based)."""
    return gtsam.symbol("p", w)


@dataclass(frozen=True)
class ChainState:
    """Where the graph stands after the accepted samples (immutable: replaced, never edited).

    Attributes:
        samples: samples accepted so far.
        window: index of the current parameter variable.
        window_start_s: time of the first sample of the current window [s].
        window_samples: samples in the current window.
        last_t_s: time of the last accepted sample [s].
        last_pose: ``(R, t)`` of the last tracker FK, the warm start of the next.
        misfits: the static poses' misfit variables made so far (:mod:`~stewart_calib.factors.pose_misfit`;
            the current one's key ``misfit_key(misfits − 1)``).
        misfit_inputs: the first inputs of the pose the last sample was at, whose misfit the next sample
            shares where its inputs are within the tolerance of them; None: the next sample is at a new pose.
    """

    samples: int = 0
    window: int = 0
    window_start_s: float = math.nan
    window_samples: int = 0
    last_t_s: float = -math.inf
    last_pose: tuple[np.ndarray, np.ndarray] | None = None
    misfits: int = 0
    misfit_inputs: np.ndarray | None = None


@dataclass
class Epoch:
    """What one sample adds: new factors, initial values, smoother timestamps, the next state."""

    factors: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    timestamps: dict[int, float]
    state: ChainState


def robust_noise(base: gtsam.noiseModel.Base, kind: str, k: float) -> gtsam.noiseModel.Base:
    if kind == "huber":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(k), base)
    if kind == "cauchy":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(k), base)
    return base


def first_paragraph(err: Exception) -> str:
    """gtsam's messages run to a paragraph of advice; the first says what failed, on one line."""
    return " ".join(str(err).strip().split("\n\n")[0].split()) or err.__class__.__name__


class GraphBuilder:
    """Turns one sample into its factors; shared by ``isam2`` and ``lm`` so both solve one graph.

    Args:
        chain: start a new parameter variable every window (else one variable for the log).
        walk_in_windows: each sample's drive-leg factors carry the walk from its window's variable
            to the sample (:meth:`epoch`).
        layout: the unknown vector (None: :func:`~.measurement.unknown_layout`'s); ``isam2`` passes its
            front end's, which may end with an unannounced payload (see the module docstring).
        pose_misfit: ``(κ, tolerance)`` of the in-situ tracker's misfit at a static pose, as its front end
            carries it (:meth:`LegEKF._pose_misfit <stewart_calib.estimators.ekf.LegEKF._pose_misfit>`): each
            static pose (inputs within ``tolerance`` of its first sample's) has one misfit variable, prior
            ``N(0, κ R0)``, added to its samples' measurement rows (:mod:`~stewart_calib.factors.pose_misfit`);
            None or κ = 0: every sample independent.

    Attributes:
        steps: ``{t_s [s]: m [kg]}``: the samples (by time) that open a window as a step of the
            unannounced payload, with the payload's initial value there (the caller keeps it).
    """

    def __init__(
        self,
        platform: Platform,
        config: EstimatorConfig,
        chain: bool,
        walk_in_windows: bool = False,
        layout: UnknownLayout | None = None,
        pose_misfit: tuple[float, float] | None = None,
    ):
        self.platform = platform
        self.noise = config.noise
        self.graph = config.isam2
        self.chain = chain
        self.walk_in_windows = chain and walk_in_windows
        self.model = instrument_model(platform, config.noise)
        self.drive = estimator_drive(platform, config.noise)
        self.layout: UnknownLayout = unknown_layout(platform, config.noise, self.model) if layout is None else layout
        payload = self.layout.slice(PAYLOAD)
        self._payload = None if payload is None else payload.start
        self.steps: dict[float, float] = {}
        self._robust = (self.graph.robust, self.graph.robust_k)
        # Gaussian rows: one factor of the six legs (or of all the instrument's channels) is their
        # scalar factors exactly, at a sixth of the callbacks; a robust kernel weighs each alone.
        self._gaussian = self.graph.robust == "none"
        self._drive_legs = [
            (
                drive_leg.DriveLegs.of(legs, self.drive, self._payload),
                robust_noise(
                    gtsam.noiseModel.Isotropic.Sigma(len(legs), self.drive.coordinate_sigma(self.noise)), *self._robust
                ),
            )
            for legs in ([np.arange(self.drive.rows)] if self._gaussian else [[i] for i in range(self.drive.rows)])
        ]
        self._group_noise: dict[tuple[int, ...], gtsam.noiseModel.Base] = {}
        # the drive legs' and channel groups' noise at the last measurement scale other than 1 (a window's)
        self._scaled: tuple[float, list, dict] = (1.0, self._drive_legs, self._group_noise)
        # the channel groups of the last sample as factored (channels, noise): the tracker's groups
        # are one constant list, so a sample's are most often the very list of the one before
        self._groups: tuple[list[np.ndarray] | None, list[tuple], float] = (None, [], 1.0)
        # tight coupling to a leg set of known geometry: the pose's initial value is the readings'
        # FK alone (its covariance, which model.pose adds, is for loose coupling)
        self._fk_legs = self.model.compiled_legs if self.graph.coupling == "tight" else None
        self._instrument = self.layout.slice("instrument")
        self._prior_sigma = self.layout.prior_sigma(self.drive.prior_sigmas(self.noise))
        self._walks = self.layout.walks()
        self._walk_scales = self.layout.walk_scales(
            self.drive.walk_sigmas(self.noise), self.noise.random_walk_mm_per_sqrt_s
        )
        self._gauge = self.layout.gauge_rows(platform.drive)
        #: whether :meth:`epoch` asks for the current estimate only when a sample opens a window (no
        #: instrument unknowns, and the measurement always fixes the pose): then a window's samples
        #: can be built before the smoother has any of them (``isam2``'s update a window)
        self.guess_at_windows_only = self._instrument is None and self.model.compiled_legs is not None
        #: the unknown vector's first value (zeros, or the instrument block at its registration)
        self.initial = np.zeros(self.layout.size)
        self._kappa, self._pose_tolerance = (0.0, 0.0) if pose_misfit is None else pose_misfit
        # a misfit's rows: the instrument's (tight: its channels; loose: the pose prior's six), then the drive's legs
        self._misfit_offset = 6 if self.graph.coupling == "loose" else len(self.model.channel_sigma)
        #: rows of a static pose's misfit variable (0: no misfit)
        self.misfit_size = self._misfit_offset + self.drive.rows if self._kappa > 0.0 else 0

    def _noise(self, channels: np.ndarray, scale2: float = 1.0) -> gtsam.noiseModel.Base:
        """The (robust) noise model of one channel group at ``scale2`` × its variance, made once per
        distinct group (at one scale other than 1 at a time: :meth:`_at_scale`)."""
        key = tuple(int(c) for c in channels)
        noise = self._at_scale(scale2)[1]
        if key not in noise:
            sigma = self.model.channel_sigma[list(key)] * math.sqrt(scale2)
            noise[key] = robust_noise(diagonal_noise(sigma), *self._robust)
        return noise[key]

    def _at_scale(self, scale2: float) -> tuple[list, dict]:
        """``(the drive legs with their noise, the channel groups' noise)`` at ``scale2`` × the
        configured measurement covariance: made when the scale changes (a window's, in time order)."""
        if scale2 == 1.0:
            return self._drive_legs, self._group_noise
        if self._scaled[0] != scale2:
            sigma = self.drive.coordinate_sigma(self.noise) * math.sqrt(scale2)
            legs = [
                (legs, robust_noise(gtsam.noiseModel.Isotropic.Sigma(len(legs.legs), sigma), *self._robust))
                for legs, _ in self._drive_legs
            ]
            self._scaled = (scale2, legs, {})
        return self._scaled[1], self._scaled[2]

    def _merged(self, groups: list[np.ndarray]) -> list[np.ndarray]:
        """The model's channel groups, as one group where the noise is Gaussian."""
        return [np.concatenate(groups)] if self._gaussian and len(groups) > 1 else groups

    def _new_variable(self, factors: gtsam.NonlinearFactorGraph, key: int) -> None:
        """What every parameter variable carries: the gauge constraint, where a block shares it."""
        if len(self._gauge):
            factors.add(gauge.factor(key, self._gauge))

    def prior_covariance(self, covariance: np.ndarray) -> np.ndarray:
        """A filter's or a marginal's covariance of the unknown vector as :meth:`gaussian_prior`
        uses it: symmetric, and along the gauge the covariance's mean variance instead of its own.

        Along the gauge such a covariance is (near) singular: inverted as it is, the ~1e8
        information there swamps, in round-off, the ~0.1 mm⁻² of the directions the data barely
        determine (a filtered Gaussian put in as it was left isam2 several σ from the batch
        optimum after one more sample). With the mean variance the prior says nothing along the
        gauge, and the gauge factor holds ``C x = 0`` there.
        """
        covariance = 0.5 * (covariance + covariance.T)
        if not len(self._gauge):
            return covariance
        C = self._gauge
        C_plus = np.linalg.solve(C @ C.T, C).T
        free = np.eye(len(covariance)) - C_plus @ C
        covariance = free @ covariance @ free.T
        spread = np.trace(covariance) / (len(covariance) - len(C))
        return covariance + spread * (C_plus @ C_plus.T)

    def gaussian_prior(self, key: int, mean: np.ndarray, covariance: np.ndarray) -> gtsam.NonlinearFactorGraph:
        """``N(mean, covariance)`` on the unknown vector ``key`` (a filter's or a marginal's
        Gaussian, :meth:`prior_covariance`), with the gauge held as on every parameter variable."""
        factors = gtsam.NonlinearFactorGraph()
        noise = gtsam.noiseModel.Gaussian.Covariance(self.prior_covariance(covariance))
        factors.add(gtsam.PriorFactorVector(key, mean, noise))
        self._new_variable(factors, key)
        return factors

    def _walk_rate(self, walk_rate_mm2_per_s: float | None) -> float:
        """The walk's rate [mm²/s]: ``walk_rate_mm2_per_s``, or the configured one where it is None."""
        return self.noise.random_walk_mm_per_sqrt_s**2 if walk_rate_mm2_per_s is None else walk_rate_mm2_per_s

    def walk_factor(
        self,
        window: int,
        dt_s: float,
        noise_scale2: float = 1.0,
        walk_rate_mm2_per_s: float | None = None,
        payload_step: bool = False,
    ) -> gtsam.BetweenFactorVector:
        """The walk from parameter variable ``window`` to the next over ``dt_s`` [s] at the rate
        ``walk_rate_mm2_per_s`` (None: the configured one), in units of the measurement scale
        ``noise_scale2`` (see :meth:`epoch`); the first factor of the epoch that opens the window.
        With ``payload_step`` the unannounced payload steps by its prior's σ_m (as ekf adds σ_m² to
        its process noise), else it is tied by the floor like every constant block."""
        rate = self._walk_rate(walk_rate_mm2_per_s)
        sigma = random_walk.sigma_mm(math.sqrt(rate / noise_scale2), dt_s, self.graph.chain_sigma_floor_mm)
        floor = self.graph.chain_sigma_floor_mm
        if self._walk_scales is None:
            sigmas = np.where(self._walks, sigma, floor)
        else:  # δM's entries walk at their own rates (a rotary drive's angles)
            sigmas = np.where(self._walks, np.maximum(sigma * self._walk_scales, floor), floor)
        if payload_step and self._payload is not None:
            sigmas[self._payload] = self._prior_sigma[self._payload] / math.sqrt(noise_scale2)
        return random_walk.factor(params_key(window), params_key(window + 1), sigmas)

    def window_walk_covariance(self, state: ChainState, walk_rate_mm2_per_s: float | None = None) -> np.ndarray:
        """What the walk adds between the current parameter variable and the parameters at the
        last sample [code units²]: every sample of a window observes one variable, which so
        stands for the parameters over the window; the value at its last sample differs from
        that by a walk of variance ``q (t_last − t_start) / 3`` (the end of a walk less its mean
        over the span; ``q`` is ``walk_rate_mm2_per_s``, None: the configured rate). Small beside the
        parameters' σ, but not beside their best-determined combinations: left out, lm's NEES on a
        drifting robot was 1.7× its degrees of freedom. With ``walk_in_windows`` the variable is the
        parameters at the window's first sample, and the walk from it to the last sample, ``q T``,
        bounds what this should add; the window's samples, though, say where the parameters were
        over the window too, and ``q T / 3`` is kept: with ``q T`` isam2's mean z² on
        benchmarks/robustness.py's drift logs was the same to two decimals, and on the honesty study's
        tracker cells the same runs in band (108 of 120), the term small beside the σ of most
        parameters."""
        span = max(state.last_t_s - state.window_start_s, 0.0) if self.chain else 0.0
        return np.diag(np.where(self._walks, self._walk_rate(walk_rate_mm2_per_s) * span / 3.0, 0.0))

    def new_window(self, state: ChainState, t_s: float, fraction: float = 1.0) -> bool:
        """Whether ``sample`` at ``t_s`` opens a new parameter variable after ``state`` (a window's
        length, ``fraction`` of the configured one, or a step of the unannounced payload, :attr:`steps`)."""
        if not self.chain or state.samples == 0:
            return False
        if t_s in self.steps:
            return True
        if self.graph.window_samples > 0:
            return state.window_samples >= max(1, math.ceil(fraction * self.graph.window_samples))
        return t_s - state.window_start_s >= fraction * self.graph.window_s

    def epoch(
        self,
        state: ChainState,
        sample: Sample,
        params_guess,
        noise_scale2: float = 1.0,
        walk_rate_mm2_per_s: float | None = None,
        window_fraction: float = 1.0,
        measurement_scale2: float = 1.0,
    ) -> Epoch:
        """Factors, values and timestamps of ``sample`` and the state after it.

        Args:
            params_guess: callable returning the current unknown vector [code units], the
                initial value of a new parameter variable.
            noise_scale2: the measurement noise's scale ``s²`` (``R = s² R0``) where a graph keeps
                the configured ``R0`` and takes ``s²`` times its covariance: a new window's walk
                factor then carries ``Q / s²``, so that the graph is the problem of ``R`` and ``Q``
                divided by ``s²`` (the same optimum, covariance ``/ s²``).
            walk_rate_mm2_per_s: the walk's rate ``Q`` a new window's walk factor carries [mm²/s]
                (None: the configured one).
            window_fraction: the current window's length as a fraction of the configured one
                (:meth:`new_window`; ``isam2`` shortens it where the walk is fast beside the noise).
            measurement_scale2: the sample's measurement covariance in the graph, this × the configured
                ``R0`` (``isam2``: its window's ``s²``, the graph in the units of ``R`` and ``Q`` themselves;
                ``lm``: 1, one scale for the whole graph, ``noise_scale2``).

        With ``walk_in_windows``, ``noise_scale2`` and ``walk_rate_mm2_per_s`` are those of the window
        the sample is in, and its drive-leg rows carry, besides the stroke noise, the walk from the
        window's variable to the sample: the variable is the parameters at the window's first sample
        (the walk factor spans the windows' first samples), the sample's are a walk of ``Q τ`` from
        them (``τ`` its time since that sample), which adds ``H_w (Q τ / s²) H_wᵀ`` to the rows'
        covariance (``H_w`` their Jacobian on the walking unknowns). Left out, the graph had σ too
        narrow on a drifting robot unless its front end's noise scale took that walk for noise (one
        pass from its start-up's scale, not solved to its fixed point as ekf's): the default
        configuration on a robot drifting 3× faster than told, 0.3× the default noise, mean z² 2.06
        (benchmarks/robustness.py's drift logs, three seeds), 1.75 with it and the settled scale.
        Raises:
            SampleRejected: non-finite data, time going backwards, or FK failure; nothing is
                changed (the caller keeps ``state``).
        """
        strokes, z = check_sample(self.platform, self.model, sample)
        if sample.t_s < state.last_t_s:
            raise SampleRejected(
                f"sample at t = {number(sample.t_s)} s is older than the last one ({number(state.last_t_s)} s)",
                SampleRejected.TIME_BACK,
            )
        # The current estimate, asked for only where it is needed (isam2 pays a smoother query).
        wanted = state.samples > 0 and (
            self._instrument is not None or self.new_window(state, sample.t_s, window_fraction)
        )
        guess = (
            params_guess()
            if wanted
            else (self.initial if state.samples == 0 and self._instrument is not None else None)
        )
        if self._fk_legs is not None:
            observed, (R, t) = None, self._fk_legs.solve_fk(z, state.last_pose, "tracker")
        else:
            theta = instrument_theta(
                self.model, None if guess is None or self._instrument is None else guess[self._instrument]
            )
            observed = self.model.pose(z, theta, state.last_pose)
            if observed is not None:
                R, t = observed.R, observed.t
            else:  # the measurement alone does not fix a pose: start from the drive model's
                if guess is None and state.samples > 0:
                    guess = params_guess()
                x_drive = None if guess is None else guess[: self.drive.size]
                rest = self.drive.inputs_near(strokes, sample.inputs, state.last_pose)
                R, t = self.drive.solve_fk(rest, x_drive, state.last_pose)
        inputs = self.drive.inputs(strokes, sample.inputs, R, t)  # the forces at the pose found (spec §10)
        pose = gtsam.Pose3(gtsam.Rot3(R), t)

        factors, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        k, x = state.samples, pose_key(state.samples)
        values.insert(x, pose)
        loose = self.graph.coupling == "loose" and observed is not None and self._instrument is None
        misfit, misfits, misfit_inputs = None, state.misfits, state.misfit_inputs
        if self.misfit_size:
            pose_inputs = np.asarray(strokes, dtype=float)[: self.drive.rows]
            if misfit_inputs is None or np.max(np.abs(pose_inputs - misfit_inputs)) > self._pose_tolerance:
                # a new pose: its misfit drawn afresh, κ R0 in the graph's units (R0 / noise_scale2)
                misfits, misfit_inputs = misfits + 1, pose_inputs.copy()
                key = pose_misfit.misfit_key(misfits - 1)
                values.insert(key, np.zeros(self.misfit_size))
                factors.add(self._misfit_prior(key, None if not loose else observed.covariance, noise_scale2))  # type: ignore[union-attr]
            misfit = pose_misfit.misfit_key(misfits - 1)
        if k == 0:
            state = replace(state, window_start_s=sample.t_s)
            values.insert(params_key(0), self.initial)
            factors.add(random_walk.prior(params_key(0), self._prior_sigma))
            self._new_variable(factors, params_key(0))
        elif self.new_window(state, sample.t_s, window_fraction):
            w = state.window
            step = self.steps.get(sample.t_s)
            if step is not None:  # the payload starts from the front end's value after the step
                guess = np.array(guess, dtype=float)
                guess[self._payload] = step
            values.insert(params_key(w + 1), guess)  # type: ignore[arg-type]  # set: a new window is `wanted`
            dt_s = sample.t_s - state.window_start_s
            factors.add(self.walk_factor(w, dt_s, noise_scale2, walk_rate_mm2_per_s, step is not None))
            self._new_variable(factors, params_key(w + 1))
            state = replace(state, window=w + 1, window_start_s=sample.t_s, window_samples=0)
        p = params_key(state.window)

        if loose:
            covariance = observed.covariance * measurement_scale2  # type: ignore[union-attr]
            noise = robust_noise(gtsam.noiseModel.Gaussian.Covariance(covariance), *self._robust)
            rows = None if misfit is None else (misfit, np.arange(6))
            factors.add(instrument_pose.factor(x, pose, noise, rows))
        else:
            block, size = (None, 0) if self._instrument is None else (self._instrument, self.layout.size)
            for channels, noise, legs in self._factored_groups(z, measurement_scale2):
                rows = None if misfit is None else (misfit, channels)
                factors.add(
                    instrument.factor(self.model, x, z, channels, noise, p, block, size, legs=legs, misfit=rows)
                )
        walked = self._walk_since_window(sample.t_s - state.window_start_s, noise_scale2, walk_rate_mm2_per_s)
        for drive_legs, noise in self._at_scale(measurement_scale2)[0]:
            if walked > 0.0:
                noise = self._walked_noise(drive_legs, pose.matrix(), inputs, walked, measurement_scale2)
            rows = None if misfit is None else (misfit, self._misfit_offset + drive_legs.legs)
            factors.add(drive_leg.factor(x, p, drive_legs, inputs, noise, sample.inputs, rows))

        # The current parameter key is re-stamped every update so the smoother never
        # marginalises the variable new factors are about to touch (docs/measured-facts.md).
        timestamps = {x: sample.t_s, p: sample.t_s}
        if misfit is not None:  # and the pose's misfit, while its samples come
            timestamps[misfit] = sample.t_s
        state = ChainState(
            k + 1,
            state.window,
            state.window_start_s,
            state.window_samples + 1,
            sample.t_s,
            (R, t),
            misfits,
            misfit_inputs,
        )
        return Epoch(factors, values, timestamps, state)

    def _misfit_prior(self, key: int, pose_covariance: np.ndarray | None, noise_scale2: float):
        """A new pose's misfit ``N(0, κ R0 / noise_scale2)``: ``R0`` the configured covariance of the rows it
        joins (the instrument's channels, or the loose pose prior's ``pose_covariance``; the drive's legs)."""
        legs = np.full(self.drive.rows, self.drive.coordinate_sigma(self.noise) ** 2)
        scale = self._kappa / noise_scale2
        if pose_covariance is None:
            variances = np.concatenate((np.asarray(self.model.channel_sigma, dtype=float) ** 2, legs))
            return pose_misfit.prior(key, np.sqrt(scale * variances))
        covariance = np.zeros((self.misfit_size, self.misfit_size))
        covariance[:6, :6] = pose_covariance
        covariance[np.arange(6, self.misfit_size), np.arange(6, self.misfit_size)] = legs
        return gtsam.PriorFactorVector(
            key, np.zeros(self.misfit_size), gtsam.noiseModel.Gaussian.Covariance(scale * covariance)
        )

    def _walk_since_window(self, tau_s: float, noise_scale2: float, walk_rate_mm2_per_s: float | None) -> float:
        """The walk's variance ``Q τ / s²`` [code units²] a sample ``tau_s`` after its window's first
        sample carries in its drive-leg rows (0 without ``walk_in_windows``)."""
        if not self.walk_in_windows or tau_s <= 0.0:
            return 0.0
        return self._walk_rate(walk_rate_mm2_per_s) * tau_s / noise_scale2

    def _walked_noise(
        self, drive_legs: drive_leg.DriveLegs, pose: np.ndarray, inputs: np.ndarray, walked: float, scale2: float
    ) -> gtsam.noiseModel.Base:
        """The noise of ``drive_legs``'s rows, ``scale2`` × their configured variance, with a walk of
        variance ``walked`` from the window's variable."""
        covariance = walked * drive_leg.walk_covariance(drive_legs, pose, self.initial, inputs, self._walks)
        variances = np.diag(covariance) + scale2 * self.noise.stroke_sigma_mm**2
        # legs that share no walking unknown (δM's legs: each its own columns) stay independent rows
        if np.count_nonzero(covariance - np.diag(np.diag(covariance))) == 0:
            return robust_noise(diagonal_noise(np.sqrt(variances)), *self._robust)
        covariance[np.diag_indices_from(covariance)] = variances
        return robust_noise(gtsam.noiseModel.Gaussian.Covariance(covariance), *self._robust)

    def _factored_groups(
        self, z: np.ndarray, scale2: float = 1.0
    ) -> list[tuple[np.ndarray, gtsam.noiseModel.Base, np.ndarray | None]]:
        """The model's channel groups of ``z`` as factored (:meth:`_merged`), each with its noise at
        ``scale2`` × the configured variance and :func:`~stewart_calib.factors.instrument.known_legs`."""
        groups = self.model.groups(z)
        if groups is not self._groups[0] or scale2 != self._groups[2]:
            self._groups = (
                groups,
                [
                    (channels, self._noise(channels, scale2), instrument.known_legs(self.model, channels))
                    for channels in self._merged(groups)
                ],
                scale2,
            )
        return self._groups[1]

    def prior_estimate(self, method: str) -> Estimate:
        """The estimate before any sample: every error 0 with the prior's covariance."""
        return Estimate.of_state(np.zeros(self.layout.size), np.diag(self._prior_sigma**2), self.layout, method)
