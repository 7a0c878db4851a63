"""Robust, self-calibrating Kalman recursion that every estimator can share.

:class:`RobustFilter` wraps :class:`~stewart_calib.estimators.kalman.FilterState` and gives a
random-walk Kalman filter three things a new user should not have to tune:

**A robust start-up.** While the parameters are still uncertain by millimetres, an innovation
gate cannot tell a 1 mm glitch from the prior's own spread, and a glitch that gets in pins the
filter to a wrong value — after which the gate locks out the good samples. So the first
``startup_samples`` samples are solved as a batch, again after each new one, by consensus:
filter passes over a few deterministic subsets of the buffer (overlapping blocks, and all of
it) each propose an estimate; every buffered sample is tested at it with
``d_k = νᵀ (s² R0 + H P Hᵀ)⁻¹ ν`` against the χ² gate, ``s²`` being the subset's own robust
(median) scale of the configured measurement covariance ``R0``; the proposal most samples
agree with wins and is refined over its agreeing samples until the set no longer changes.
Nothing is refused while fewer than :data:`MIN_REDUNDANCY` residual degrees of freedom are
left, or when no proposal has a majority. Where the start may lie far from the answer (``relinearise``:
an instrument outside the robot, its frame registered in closed form, encoder zeros and scale
unknown), every pass of one solve linearises its samples at one point, the last solution (a
filter pass from the prior over observations linearised at ``x̄``, innovations
``ν(x̄) − H (x − x̄)``, is one Gauss–Newton step of the batch's MAP problem from ``x̄``), and the
winner is relinearised at its own result until a step is within :data:`RELINEARISE_TOLERANCE` of
its posterior σ: the batch is the MAP of its samples, not a single pass whose first samples were
linearised at a prior millimetres from the answer (after large initial errors — the frame,
encoder zeros 15 mm off — that one pass left the filter 10–30 % worse on held-out data than the
batch optimum, benchmarks/hobby.py). Elsewhere the decided batch alone is so relinearised, once
(:meth:`RobustFilter._relinearise_startup`).

**Gated recursion that recovers from a lock-out.** After the start-up each sample is gated on
its NIS (χ² with ``m`` degrees of freedom, ``gate_probability``). Clean data are gated once in
``1/(1 − p)``; when ``lockout_gated_samples`` of the last ``lockout_window_samples`` are gated,
the state no longer explains the data (a bad update got in, or the robot changed faster than
the random walk allows) and the recent samples are solved afresh by the same consensus —
adopted only when most of them agree with it, so a stream of glitches cannot take over. Where the
instrument's misfit held over a static pose is modelled (``pose_misfit``), the gated samples must span
two poses or more: one pose's samples share its misfit, and a pose whose misfit is beyond the
modelled one is refused whole without being a lock-out.

**Noise levels from the data** (``adapt_noise``). Every window of accepted samples
(``max(startup_samples, lockout_window_samples)``) until :data:`WALK_WINDOWS` differences are pooled,
then every ``noise_every_samples``, the window of the last samples is solved as a small batch from
the prior — not every window for ever: a window's batch costs what the recursion does per sample.
Its post-fit residuals give the measurement scale, ``s² = Σ νᵀ R0⁻¹ ν / redundancy`` (the random
walk barely moves the parameters within one window), the window solved again at the scale it says
until that settles (a pass's variance components are unbiased only at the true scale), and again
when the walk rate moves. The windows give the random-walk
rate: a window's pass walks at the rate in use, so its estimate is δM at the window's last sample,
and for a walk of rate ``q`` [mm²/s] the windows ending at ``b1`` and ``b2`` differ by a covariance
``q T W`` (``W`` the walk per unit rate, ``unit_Q``) with ``T = b2 − b1``, so two window estimates
differ by ``P_w + P_v + q T W``; each window's ``P_w`` is taken at the scale its
own residuals have just updated. The rate in use is the configured one unless the likelihood of
the last :data:`WALK_HISTORY` windows, every one against every other, rejects it
(:meth:`RobustFilter._pooled_walk_rate`): as too large, then the nearest one it does not reject; as
too small, their maximum-likelihood rate. Windows far apart tell a walk, whose spread keeps growing
with the time apart, from a stationary excess over the windows' covariance, which does not. Measurement
noise and parameter
motion are so told apart by their time scales, not by one innovation sequence that both shape.
A window whose walk in use could explain it within the noise (fewer than :data:`MIN_REDUNDANCY`
residual degrees of freedom left: a configured walk far faster than the robot's) is measured as a
static batch, where the components' fixed point would otherwise be the scale's floor
(:meth:`RobustFilter._measured_scale`).
Both estimates forget over ``noise_memory_samples``. Fixed noise stays available.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .._jit import F8_1, F8_2, FLOAT, njit
from ..chi_square import chdtri  # chi2.ppf(p, m) is chdtri(m, 1 - p); scipy.special costs ~0.2 s of import
from ..errors import CalibError, SampleRejected, number
from ..model.unknowns import UnknownLayout
from .base import payload_change_field, state_array
from .kalman import (
    NO_COMPONENTS,
    NO_POSES,
    ROWS_WINDOW_DUE,
    STEP_TAKEN,
    FilterState,
    fill_walk,
    filter_step,
    window_append,
    workspace_size,
)

#: residual degrees of freedom a batch needs before it refuses any sample or estimates a scale.
MIN_REDUNDANCY = 12.0
#: at most this many refinements of the winning proposal (the set of good samples usually settles in 2).
MAX_ITERATIONS = 6
#: a batch's Gauss–Newton iteration stops once its step is within this many posterior σ
#: (Mahalanobis, in every direction at once): the linearisation point is then the answer to a
#: small fraction of its own uncertainty.
RELINEARISE_TOLERANCE = 0.1
#: at most this many relinearisations of one batch (from the last solution it takes 1–3).
MAX_RELINEARISATIONS = 10
#: candidate steps of an unannounced payload run beside the filter at most (RobustFilter._test_steps)
MAX_STEP_CANDIDATES = 4
#: the samples the filter took lately whose NIS gives the dispersion a candidate step's ratio is read at
DISPERSION_SAMPLES = 100
#: window differences (successive windows) after which the windows come every ``noise_every_samples``.
WALK_WINDOWS = 12
#: the last windows the random-walk rate is measured over, all of them against each other.
WALK_HISTORY = 16
#: a walk rate is rejected as too large where the window differences' signed root deviance at it
#: falls below the normal's quantile at this probability, and as too small where it exceeds the
#: quantile at 1 − WALK_RAISING: see ``RobustFilter._pooled_walk_rate``.
WALK_REJECTION = 0.2
WALK_RAISING = 0.05
#: bisection steps of the walk rate's likelihood roots, and the relative width they stop at
WALK_BISECTIONS = 200
WALK_RELATIVE_WIDTH = 1e-6
#: at most this many passes of one window's batch, each at the scale the last one measured (see
#: ``RobustFilter._window_statistics``), until the scale changes by at most SCALE_TOLERANCE (relative).
SCALE_ITERATIONS = 10
SCALE_TOLERANCE = 0.02
#: the remembered scale sums are dropped where this window, measured alone at a walk the walk test has
#: moved to, rejects them at this probability (two-sided): see ``RobustFilter._remembered_at_walk``
SCALE_MEMORY_REJECTION = 0.05
#: changes of the noise scale kept for :meth:`RobustFilter.noise_scale2_at`: more than the samples a
#: caller runs the filter ahead of where it asks (isam2's front-end runs: 256 samples)
SCALE_HISTORY = 512
#: the walk rate never falls below this fraction of the configured rate [-].
MIN_WALK_FRACTION = 1e-4
#: the measured noise never falls below this fraction of the configured variance [-] (σ ≥ 0.1 × the
#: configured one): noise-free data would otherwise drive R to 0, where the filter's own
#: linearisation error gates every sample.
MIN_NOISE_SCALE2 = 1e-2

#: a batch pass's sample window in the compiled recursion: none (``_SampleWindow.arrays``, ``span``)
_NO_WINDOW = (np.zeros(0), np.zeros((0, 0)), np.zeros(0, dtype=bool), np.zeros(2, dtype=np.int64))

#: ``observe(prepared, x) -> (innovation ν (m,), H (m, n), R0 (m, m))`` at the state ``x``, or
#: None when the sample fixes no pose there.
Observe = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray] | None]


class RobustFilter:
    """A random-walk Kalman filter with robust start-up, lock-out recovery and noise scales.

    Args:
        method: names the estimator in messages.
        prior_sigma_mm: initial ``P = diag(σ²)`` on δM [code units]: one σ, or ``(n_params,)`` entry by entry.
        walk_mm_per_sqrt_s: configured random walk ρ [mm/√s] (``Q = ρ² Δt I`` unless adapted).
        gate_probability: χ² gate probability (0 = off: then also no start-up refusals).
        observe: the linearised observation of a prepared sample at a state (see :data:`Observe`).
        robust: the ``[robust]`` settings (:class:`~stewart_calib.config.RobustConfig`).
        m: rows of an observation as the gate and the batch's proposals count a sample: the drive's
            residuals (:attr:`~stewart_calib.model.drive.DriveModel.rows`). A batch's redundancy counts the
            rows each sample's observation has: ``m``, or an outside instrument's tight observation's
            (the channels it saw, :meth:`~stewart_calib.instruments.base.InstrumentModel.groups`).
        layout, C: the unknown vector and its gauge rows (as :class:`FilterState`).
        unit_Q: the process noise per unit ``ρ² Δt`` (None: the identity).
        compiled_rows: the recursion over rows of prepared samples in one compiled call, observing
            each as ``observe`` does (:meth:`LegSetPose.rows <.measurement.LegSetPose.rows>`,
            :func:`~.kalman.leg_set_filter_rows`): the batches' passes and :meth:`update_block` run
            through it (None: the passes observe sample by sample, :meth:`update_block` does nothing).
        relinearise: solve the start-up and recovery batches by Gauss–Newton (see the module
            docstring) rather than one pass linearised along its own way from the prior.
        step: ``(index, variance)`` of an unknown that may step (an unannounced payload), tested by
            the samples that follow a candidate step (:meth:`_test_steps`): a candidate is the filter
            with ``variance`` added to that unknown's process noise at one sample, run beside it, and
            is taken where its samples' likelihood exceeds the filter's by more than half the gate's
            χ² bound at one degree of freedom (a Bayes factor: the step's size is drawn from its
            prior). A candidate starts every ``lockout_window_samples`` samples and at any sample a
            step explains a significant part of (it lowers the NIS by more than that bound), so a
            ramp or a step too small for one sample is found from the evidence of many, and one
            sample's misfit is no step unless the samples after it agree. The samples buffered
            before a step taken are let go (a window across the step fits neither side). A step taken
            begins a change that may go on (a payload put on over seconds): until a candidate from the
            filter before it loses, the candidates begin there, so that the samples taken while the
            unknown moved leave the estimate.
        step_factors: ``(columns, nominal)`` of the unknowns a ``step`` unknown multiplies in the
            observation (an unannounced payload, the compliance: row ``k``'s residual is bilinear in it and
            ``x[columns[k]]``), whose values are ``nominal + x[columns]``: the ``step`` unknown is then held
            at its prior mean until those values are known to within themselves (:meth:`_release_payload`).
        pose_misfit: ``(κ, tolerance)``: the instrument's reading error holds, besides the white noise
            ``s² R0``, a misfit ``b ~ N(0, κ R0)`` that stays while the platform holds a pose (its first
            ``m`` inputs, the strokes, within ``tolerance`` of the sample before) and is drawn afresh at the
            next: ``b`` rides beside the state through every update at one pose (:meth:`_misfit_step`), so a
            static pose's samples tell the parameters what their mean does, ``(s² / n + κ) R0``, not ``n``
            independent readings; κ = 0 or None: no misfit (every sample independent). The step
            candidates begin at each new pose by the same tolerance (:meth:`_test_steps`).

    Attributes:
        started: the start-up batch is decided (the gated recursion runs).
        noise_scale2: ``s²``, the measurement covariance in use is ``s² R0``.
        walk_rate_mm2_per_s: the random walk's variance rate in use [mm²/s].
        recoveries: lock-outs recovered from.
        steps: steps of the ``step`` unknown taken.
        payload_held: the ``step`` unknown of ``step_factors`` is held at its prior mean, its column
            out of every observation (:meth:`_release_payload`).
        payload_released_t_s: the time [s] of the sample it was released at (NaN while held, or never held).
        walk_lowering: the probability at which the window differences reject a rate as too large
            (:meth:`_pooled_walk_rate`; :data:`WALK_REJECTION`, isam2's front end :data:`WALK_RAISING`).
    """

    def __init__(
        self,
        method: str,
        prior_sigma_mm: float | np.ndarray,
        walk_mm_per_sqrt_s: float,
        gate_probability: float,
        observe: Observe,
        robust,
        m: int,
        layout: UnknownLayout,
        C: np.ndarray | None = None,
        unit_Q: np.ndarray | None = None,
        compiled_rows=None,
        relinearise: bool = False,
        step: tuple[int, float] | None = None,
        step_factors: tuple[np.ndarray, np.ndarray] | None = None,
        pose_misfit: tuple[float, float] | None = None,
    ):
        self.method = method
        self._step_unknown = step
        self._step_factors = step_factors
        self.payload_held = step is not None and step_factors is not None
        self.payload_released_t_s = math.nan
        #: the time of the first sample offered [s] (NaN before any): the run a walk is measured over
        self.first_t_s = math.nan
        # a step is taken where it lowers the NIS beyond the gate's bound at one degree of freedom
        self._step_bound = float(chdtri(1, 1.0 - gate_probability)) if gate_probability > 0.0 else math.inf
        self.steps = 0
        #: the time of the sample the last step taken happened at (NaN before any)
        self.step_t_s = math.nan
        #: the time of the last sample the filter the last step taken began from held: those between it and
        #: ``step_t_s`` are out of the estimate, taken while the unknown moved (NaN before any)
        self.step_origin_t_s = math.nan
        # candidate steps run beside the filter (_test_steps), and the samples since the last one began
        self._candidates: list[_Candidate] = []
        self._since_candidate = 0
        # the filter before the last step taken began, while the change it began may go on (_test_steps)
        self._change_origin: _Origin | None = None
        # NIS per row of the samples the filter took lately: the dispersion the candidates' ratios are read at
        self._dispersions: deque = deque(maxlen=DISPERSION_SAMPLES)
        self.filter = FilterState(method, prior_sigma_mm, gate_probability, m, layout, C)
        # the misfit held over a pose (pose_misfit): its variance over R0, the inputs' tolerance of one pose,
        # the filter's misfit at the pose it holds, and that of the last batch pass and of the solved batch
        self._kappa, self._pose_tolerance = (0.0, 0.0) if pose_misfit is None else pose_misfit
        self._misfit: _Misfit | None = None
        self._pass_misfit: _Misfit | None = None
        self._solved_misfit: _Misfit | None = None
        # candidate steps begin at each new pose where the noise model is the user's or holds the pose's misfit
        # (_test_steps); the inputs of the last sample they saw tell a new pose
        self._candidates_per_pose = pose_misfit is not None and (self._kappa > 0.0 or not robust.adapt_noise)
        self._last_inputs = np.zeros(0)
        n = len(self.filter.x)
        self._P0 = self.filter.P.copy()
        self._x0 = np.zeros(n)  # the prior's mean: 0, or where a registration started the filter
        self._P0_pinv = np.linalg.pinv(self._P0)
        self._free = int(np.linalg.matrix_rank(self._P0))  # directions the gauge leaves free
        # onto the gauge rows' directions Cᵀ, where P is singular (see _mahalanobis2)
        self._gauge_projector = None if C is None or not len(C) else C.T @ np.linalg.solve(C @ C.T, C)
        self._relinearise = relinearise
        self._unit_Q = np.eye(n) if unit_Q is None else np.ascontiguousarray(unit_Q, dtype=float)
        # the unknowns that walk, where the walk is the identity on them and 0 elsewhere (a drive's own
        # and the compliance's: no gauge ties them); None: any other walk (an outside instrument's)
        diagonal = np.diag(self._unit_Q)
        plain = np.array_equal(self._unit_Q, np.diag(diagonal)) and np.all((diagonal == 0.0) | (diagonal == 1.0))
        self._walking: np.ndarray | None = diagonal == 1.0 if plain else None
        self._compiled_rows = compiled_rows
        self._configured_walk = walk_mm_per_sqrt_s**2
        self._observe_model = observe
        self._robust = robust
        self._n, self._m = n, m
        self._gate_on = gate_probability > 0.0
        self._gate_tail = 1.0 - gate_probability if self._gate_on else 0.5
        self.noise_scale2 = 1.0
        self.walk_rate_mm2_per_s = self._configured_walk
        self.walk_lowering = WALK_REJECTION
        # (time of the sample after which they held, s², walk rate): see noise_scale2_at, walk_rate_at
        self._scale_history: deque = deque([(-math.inf, 1.0, self.walk_rate_mm2_per_s)], maxlen=SCALE_HISTORY)
        self.recoveries = 0
        #: samples the recoveries took out of the estimate (used before, not in the re-solved state)
        #: and those they took back in after the gate had refused them
        self.recovery_dropped, self.recovery_readmitted = 0, 0
        # the samples the payload steps taken left out of the estimate, and those refused that they took in
        self.step_dropped, self.step_readmitted = 0, 0
        self.started = robust.startup_samples <= 0
        self._late: list[SampleRejected] = []
        # the samples a payload step was taken at that its state does not hold (take_step_refusals)
        self._step_refused: list[SampleRejected] = []
        #: ``noise_scale2`` was measured from the data (a batch had the redundancy)
        self.measured_noise = False
        #: the start-up batch's verdict on its samples (in order), once it is decided
        self.startup_outliers = np.zeros(0, dtype=bool)
        self._window = max(robust.startup_samples, robust.lockout_window_samples, 1)
        # accepted samples between two noise estimates (never closer than a window: they must not overlap)
        self._noise_every = max(robust.noise_every_samples, self._window)
        # the last samples (the start-up batch, then the window)
        self._buffer = _SampleWindow(self._window)
        self._since_window = 0
        # noise statistics: [Σ νᵀR0⁻¹ν, Σ redundancy] over windows, the last window's estimate,
        # and the walk test's windows (x, P, first and last t_s, whether it begins a run of windows)
        self._scale_sums = np.zeros(2)
        # Σ redundancy · log(walk rate) of the windows in the sums, decayed with them: the walk they were
        # measured at (_memory_walk)
        self._scale_walk = 0.0
        self._last_window: tuple[np.ndarray, np.ndarray, float, float] | None = None  # x, P, first and last t_s
        self._windows: deque = deque(maxlen=WALK_HISTORY)

    # ------------------------------------------------------------------ protocol

    def update(self, t_s: float, prepared: np.ndarray) -> None:
        """Fold in one prepared sample at time ``t_s`` [s] (not before the last one).

        Raises:
            SampleRejected: non-finite observation, gated, or a degenerate innovation
                covariance; the state is as if the sample never came. Start-up samples are
                never refused here: those the decided batch leaves out come from
                :meth:`take_late_rejections`.
        """
        prepared = np.asarray(prepared, dtype=float)
        if math.isnan(self.first_t_s):
            self.first_t_s = float(t_s)
        if not self.started:
            observation = self._observe(prepared, self.filter.x)  # SampleRejected from FK passes on
            if observation is None:
                raise SampleRejected(
                    f"{self.method}: sample at t = {number(t_s)} s: the measurement does not fix a pose",
                    SampleRejected.NO_POSE,
                )
            # its NIS against the state before it, as the recursion reports one per sample
            nu, H, R0 = observation
            S = H @ self.filter.P @ H.T + self.noise_scale2 * R0
            nis = float(nu @ np.linalg.solve(S, nu))
            # provisionally taken: the batch may still change its mind, so the samples it leaves
            # out are reported once it is decided (take_late_rejections)
            self._buffer.append(t_s, prepared, False)
            outliers = self._solve(adopt=True)
            self._buffer.gated[:] = outliers
            self.filter.nis, self.filter.S = nis, S
            if len(self._buffer) >= self._robust.startup_samples:
                self.started = True
                self.startup_outliers = outliers.copy()
                self._late = [self._late_rejection(float(t)) for t in self._buffer.t[outliers]]
                if not self._relinearise:
                    self._relinearise_startup()
                self._window_statistics()
            return
        try:
            self._step(t_s, prepared)
        except SampleRejected as err:
            if err.reason == SampleRejected.GATED:
                self._buffer.append(t_s, prepared, True)
                # a candidate step that explains the samples the filter refuses is given its window first, and
                # while a change goes on, the candidates from before it (the filter lags the moving unknown)
                if (
                    self._locked_out()
                    and self._change_origin is None
                    and not any(self._leads(c.ratio) or self._leads(c.start_ratio) for c in self._candidates)
                ):
                    self._recover()
            raise
        self._buffer.append(t_s, prepared, False)
        self._since_window += 1
        if self._since_window >= self._noise_due():
            self._window_statistics()

    def update_block(
        self, t_s: np.ndarray, prepared: np.ndarray, poses: np.ndarray, plain: np.ndarray, errors_out: np.ndarray
    ) -> int:
        """Fold in rows of prepared samples from the first, in compiled calls, for as long as each is
        one the gated recursion accepts; returns how many it took. The row it stops at is for
        :meth:`update` (nothing of the state has moved for it). Takes none before the start-up is
        decided or without ``compiled_rows``.

        Args:
            t_s: ``(K,)`` times [s]; prepared: ``(K, width)`` prepared samples.
            poses: ``(K, 12)`` each row's pose ``[R row-major | t]`` where the caller solved it already
                (Newton starts there), or ``(0, 12)``: unknown.
            plain: ``(K,)`` rows that pass every check of a sample (the others stop the block).
            errors_out: ``(K, n_params)``, δM [mm] after each row taken, or ``(0, n_params)``: not kept.
        """
        if self._compiled_rows is None or not self.started or not self._buffer.holds(prepared.shape[1]):
            return 0
        f = self.filter
        done = 0
        while done < len(t_s):
            window = self._noise_due()
            S_last, span = np.empty((self._m, self._m)), self._buffer.span()
            count, why, _, last_t, nis, self._since_window = self._compiled_rows(
                f.x,
                f.P,
                f.Q,
                self._unit_Q,
                S_last,
                t_s[done:],
                prepared[done:],
                poses[done:],
                plain[done:],
                f.t_s,
                self.walk_rate_mm2_per_s,
                self.noise_scale2,
                f.gate_nis,
                False,
                *self._buffer.arrays(),
                span,
                self._since_window,
                window if window < math.inf else 0,
                errors_out[done:],
                NO_COMPONENTS,
            )
            self._buffer.set_span(span)
            if count:
                f.t_s, f.nis, f.S = last_t, nis, S_last
                f.samples_used += count
            done += count
            if why != ROWS_WINDOW_DUE:
                break
            self._window_statistics()
        return done

    def start_at(self, x0: np.ndarray) -> None:
        """Centre the prior on ``x0`` (an instrument registered on the first samples) before any
        sample: the filter and every batch from the prior start there."""
        self._x0 = np.array(x0, dtype=float)
        self.filter.x[:] = self._x0

    def startup_gaussian(self, noise_scale2: float) -> tuple[np.ndarray, np.ndarray]:
        """The start-up batch as one Gaussian ``(x, P)`` with measurement covariance
        ``noise_scale2 · R0``: a pass over the samples it kept, linearised at its estimate (with
        ``relinearise``, their MAP to :data:`RELINEARISE_TOLERANCE`). Valid on the update that
        decides the batch, while the buffer holds exactly its samples (isam2 starts its graph from it)."""
        x, P, *_ = self._pass(
            ~self.startup_outliers, noise_scale2, linearised=self._linearise(self.filter.x.copy()), startup=True
        )
        return x, P

    def _relinearise_startup(self) -> None:
        """The decided start-up batch by Gauss–Newton from where its pass ended: that pass linearised its
        first samples at the prior, millimetres from the answer, and at 0.2× the told noise on the tracker
        the second-order error of those samples (~mm²/leg length) is several σ of the reading noise,
        a bias the recursion keeps (NEES/dof 1.65 where lm, on the same log, gives 0.97)."""
        f = self.filter
        (x, P, *_), _ = self._gauss_newton(
            ~self.startup_outliers, self.noise_scale2, self._linearise(f.x.copy()), startup=True
        )
        f.x, f.P = x, P
        self._misfit = self._pass_misfit

    def _late_rejection(self, t_s: float) -> SampleRejected:
        err = SampleRejected(
            f"{self.method}: sample at t = {number(t_s)} s is inconsistent with the start-up batch "
            "(χ² test at its robust noise scale)",
            SampleRejected.GATED,
        )
        err.t_s = t_s
        return err

    def recovery_summary(self) -> dict | None:
        """The result's ``"recovery"`` field (None before any recovery): lock-outs recovered from,
        the samples they dropped from the estimate and those they readmitted after a refusal."""
        if not self.recoveries:
            return None
        return {
            "count": self.recoveries,
            "samples_dropped": self.recovery_dropped,
            "samples_readmitted": self.recovery_readmitted,
        }

    def payload_change_summary(self) -> dict | None:
        """The result's ``"payload_change"`` field (None where the steps taken moved no sample in or out): the
        samples a step taken from a change's origin left out of the estimate (taken while the payload moved),
        and those the filter had refused that a step took in."""
        return payload_change_field(self.step_dropped, self.step_readmitted)

    def payload_details(self) -> dict:
        """The result fields of an unannounced payload: ``"payload_steps"``, the steps of it taken, and
        ``"payload_walk"``, the δM random walk in use ``mm_per_sqrt_s`` [mm/√s] and the run it had ``over_s`` [s]
        (first sample offered to the last taken) to carry a payload put on gradually
        (:func:`~stewart_calib.analysis.plausibility.payload_walk_warning`)."""
        run_s = self.filter.t_s - self.first_t_s
        walk = {"mm_per_sqrt_s": math.sqrt(self.walk_rate_mm2_per_s), "over_s": run_s if math.isfinite(run_s) else 0.0}
        return {"payload_steps": self.steps, "payload_walk": walk}

    def take_late_rejections(self) -> list[SampleRejected]:
        """The start-up samples the decided batch left out (each once), for the caller's count."""
        late, self._late = self._late, []
        return late

    def take_step_refusals(self) -> list[SampleRejected]:
        """The samples a step of the ``step`` unknown was taken at without taking them (each once; ``err.t_s``
        its time): the candidate taken refused the sample as the filter did (a step confirmed before its
        window, :meth:`_test_steps`), so the update that took the step returned and the sample is in no state."""
        refused, self._step_refused = self._step_refused, []
        return refused

    # ------------------------------------------------------------------ recursion

    def _observe(self, prepared: np.ndarray, x: np.ndarray):
        """The observation of a prepared sample at ``x`` (:data:`Observe`), the held payload's column
        out of it (:meth:`_release_payload`): the sample says nothing of that unknown yet."""
        observation = self._observe_model(prepared, x)
        if observation is None or not self.payload_held:
            return observation
        nu, H, R0 = observation
        return nu, self._without_payload(H), R0

    def _without_payload(self, H: np.ndarray) -> np.ndarray:
        """``H`` without the column of the ``step`` unknown of ``step_factors`` (as it is where there is none)."""
        if self._step_factors is None or self._step_unknown is None:
            return H
        H = H.copy()
        H[:, self._step_unknown[0]] = 0.0
        return H

    def _compliance_settled(self, x: np.ndarray, P: np.ndarray) -> bool:
        """Whether the values of ``step_factors`` are known to within themselves at ``(x, P)``,
        ``σ_{c_i} < |c_i|`` on every leg (True where there are none)."""
        if self._step_factors is None:
            return True
        columns, nominal = self._step_factors
        return bool(np.all(np.diag(P)[columns] < (nominal + x[columns]) ** 2))

    def _release_payload(self, t_s: float) -> None:
        """Releases the held payload (:attr:`payload_held`) at the sample at ``t_s`` [s] once the compliance
        it multiplies is known to within its own value, ``σ_{c_i} < |c_i|`` on every leg
        (:meth:`_compliance_settled`): the payload's column ``∂r_i/∂m = −c_i f_{m,i} / 1000`` is then
        linearised at compliances whose sign and size the samples have settled, and the payload is its
        prior (mean and σ, uncorrelated), as a step of the prior's σ from the prior's mean leaves it.

        Before, the column is linearised at a compliance the data have not seen — the nominal, 0 for a
        controller that believes its legs rigid, with a prior σ of 2 mm over the platform's weight (82 mm/kN
        on the paper's robot) — and the payload and the compliance trade along the curved ridge
        ``c_i (f_{p,i} + m f_{m,i})`` the samples see: a filter update puts a narrow Gaussian on the ridge's
        tangent at a wrong point of it, which the updates after it keep (the paper's experiment, the
        tracker's geometry exact, readings white at 0.5 µm and told so: ``m`` 7.75 ± 0.36 kg after the first
        pose past the start-up's four, truth 0; ``c`` 2–11 mm/kN, truth 2.33). The second-order variance of
        the product, ``(∂²r_i/∂c_i∂m)² (P_cc P_mm + P_cm²)`` added to each row's, in the start-up's solves
        alone leaves that to the recursion, and in every update keeps the filter's σ wide where the
        compliance stays uncertain (a fast δM walk), where the step test then finds no step. Held, the
        compliance is identified alone, linear in the samples. Batches from the prior hold the payload the same way,
        sample by sample (:meth:`_observed_pass`)."""
        if self.payload_held and self._compliance_settled(self.filter.x, self.filter.P):
            self.payload_held = False
            self.payload_released_t_s = t_s

    def _held(self, misfit: _Misfit | None, prepared: np.ndarray, m: int) -> bool:
        """Whether ``prepared`` is at the pose ``misfit`` was drawn at (its first inputs within the tolerance)."""
        return (
            misfit is not None
            and len(misfit.b) == m
            and bool(np.max(np.abs(prepared[: self._m] - misfit.inputs)) <= self._pose_tolerance)
        )

    def _innovation(self, nu: np.ndarray, misfit: _Misfit | None, prepared: np.ndarray) -> np.ndarray:
        """``ν`` of the parameters alone less the misfit the pose's samples so far put on it (``pose_misfit``)."""
        return nu - misfit.b if misfit is not None and self._held(misfit, prepared, len(nu)) else nu

    def _predicted(
        self, P: np.ndarray, H: np.ndarray, R0: np.ndarray, misfit: _Misfit | None, prepared: np.ndarray
    ) -> np.ndarray:
        """The innovation covariance of a sample at the parameters' covariance ``P``: ``H P Hᵀ + s² R0``, and the
        misfit's share (``pose_misfit``): its prior ``κ R0`` at a new pose, what the pose's samples left at one held."""
        S = H @ P @ H.T + self.noise_scale2 * R0
        if self._kappa <= 0.0:
            return S
        if misfit is not None and self._held(misfit, prepared, len(R0)):
            C = H @ misfit.P_xb
            return S + C + C.T + misfit.P_bb
        return S + self._kappa * R0

    def _misfit_step(
        self,
        x: np.ndarray,
        P: np.ndarray,
        misfit: _Misfit | None,
        Q: np.ndarray,
        H: np.ndarray,
        nu: np.ndarray,
        R0: np.ndarray,
        noise_scale2: float,
        gate_nis: float,
        components: np.ndarray,
        prepared: np.ndarray,
    ) -> tuple[int, float, np.ndarray, _Misfit | None]:
        """:func:`~.kalman.filter_step` of one sample, in place on ``(x, P)``, with the pose's misfit ``b``
        (``pose_misfit``) beside the parameters; returns ``(status, NIS, S, the misfit after it)``.

        The state is ``[x; b]`` with ``ν − b̂`` observed through ``[H I]``: at a new pose ``b`` is drawn afresh,
        ``N(0, κ R0)`` uncorrelated with ``x``; at the pose the last sample was taken at, it is what that left
        (``b̂``, its covariance and its cross-covariance with ``x``). A static pose's ``n`` samples so give the
        parameters the information of their mean, ``Hᵀ ((s²/n + κ) R0)⁻¹ H``, and each sample's NIS is against
        what the samples before it at the pose predict. Where the step is not taken, the misfit is as it was.
        Without ``pose_misfit``, :func:`filter_step` alone (the misfit None)."""
        if self._kappa <= 0.0:
            status, nis, S = filter_step(
                x, P, Q, H, nu, R0, noise_scale2, gate_nis, self.filter.workspace(len(nu)), components
            )
            return status, nis, S, None
        n, m = len(x), len(nu)
        if misfit is not None and self._held(misfit, prepared, m):
            b, P_xb, P_bb = misfit.b, misfit.P_xb, misfit.P_bb
            inputs = misfit.inputs  # the pose's first: a slow creep of the inputs leaves the pose in the end
        else:
            b, P_xb, P_bb = np.zeros(m), np.zeros((n, m)), self._kappa * R0
            inputs = prepared[: self._m].copy()
        xa = np.concatenate((x, b))
        Pa = np.block([[P, P_xb], [P_xb.T, P_bb]])
        Qa = np.zeros((n + m, n + m))
        Qa[:n, :n] = Q
        Ha = np.hstack((H, np.eye(m)))
        work = np.empty(workspace_size(n + m, m))
        status, nis, S = filter_step(xa, Pa, Qa, Ha, nu - b, R0, noise_scale2, gate_nis, work, components)
        if status != STEP_TAKEN:
            return status, nis, S, misfit
        x[:], P[:] = xa[:n], Pa[:n, :n]
        return status, nis, S, _Misfit(inputs, xa[n:].copy(), Pa[:n, n:].copy(), Pa[n:, n:].copy())

    def _fill_Q(self, Q: np.ndarray, dt_s: float, walk_rate_mm2_per_s: float | None = None) -> None:
        rate = self.walk_rate_mm2_per_s if walk_rate_mm2_per_s is None else walk_rate_mm2_per_s
        fill_walk(Q, self._unit_Q, rate * max(dt_s, 0.0))

    def _step(self, t_s: float, prepared: np.ndarray, test_steps: bool = True) -> None:
        """One sample of the gated recursion; with an unknown that steps (and ``test_steps``: not a refused
        sample fed again out of time order) the candidate steps take it too and may replace the filter."""
        f = self.filter
        self._release_payload(t_s)
        observation = self._observe(prepared, f.x)
        if observation is None:
            raise SampleRejected(
                f"{self.method}: sample at t = {number(t_s)} s: the measurement does not fix a pose",
                SampleRejected.NO_POSE,
            )
        nu, H, R0 = observation
        self._fill_Q(f.Q, 0.0 if math.isnan(f.t_s) else t_s - f.t_s)
        step = self._step_unknown
        # a held payload has no step to test: its column is not in the samples yet
        if (
            step is not None
            and test_steps
            and not self.payload_held
            and self._test_steps(step, t_s, prepared, nu, H, R0)
        ):
            return
        if self._kappa <= 0.0:
            f.update(H, nu, R0, t_s, noise_scale2=self.noise_scale2)  # SampleRejected: untouched
            return
        gate_nis = f.gate_for(len(nu))
        status, nis, S, misfit = self._misfit_step(
            f.x, f.P, self._misfit, f.Q, H, nu, R0, self.noise_scale2, gate_nis, NO_COMPONENTS, prepared
        )
        f.count_step(status, nis, S, t_s, gate_nis)  # SampleRejected: untouched, the misfit too
        self._misfit = misfit

    def _test_steps(
        self, step: tuple[int, float], t_s: float, prepared: np.ndarray, nu: np.ndarray, H: np.ndarray, R0: np.ndarray
    ) -> bool:
        """The candidate steps of the ``step`` unknown on one sample (see the class docstring); True where
        one is taken: the filter is then that candidate, this sample included.

        Each candidate is the filter's recursion from the sample it began at, with the step's variance
        added there (that sample's update iterated, :meth:`_iterated`), and it keeps the log-likelihood
        ratio ``Σ log N(ν_c; 0, S_c) − log N(ν; 0, S)`` of the samples after that one against the
        filter's: a sample the filter refuses and the candidate takes counts with the filter's NIS (a step
        the filter does not know gates its samples); one both refuse, not at all; one the candidate
        refuses and the filter takes ends the candidate. The step's prior enters the ratio through the
        candidate's larger ``S`` (an Occam factor of about ``log(σ_step / σ_after)``). The ratio is read
        at the dispersion of the filter's recent NIS (a quasi-likelihood: a noise model too tight makes
        every ratio larger), and a candidate is taken once it leads after ``lockout_window_samples``
        samples (while one leads, a lock-out waits for it): the sample a step begins at, and the few
        after it at the same pose, are no evidence that a fault or the pose's own misfit could not
        give.

        Where the pose's misfit is modelled (κ > 0), a candidate that begins at a pose whose misfit the filter
        has not taken yet (its first sample there, or every sample of a pose the filter refuses) cannot tell
        its step from that misfit: the pose's samples do not count in its ratio (``start_ratio`` keeps what
        they would add, so that it is not dropped for a candidate with a smaller ratio, and a lock-out waits
        while it leads) until the candidate takes a sample at another pose. The paper's experiment, no-load
        stage: at 8 of its 100 static poses the tracker's misfit is far beyond κ (first NIS above the 6-dof
        gate) and the filter refuses the whole pose, where counting the pose's 8 samples against a fresh misfit
        each took one pose's misfit for a step (ekf, seed 3, 40 kg put on at once: 14 steps; withheld, 2). A
        candidate that has left its start pose and leads is taken also where it refuses a sample the filter refuses,
        before its window: the unknown has moved past both (40 kg put on over 20 s, with the ratio withheld
        alone: the leading candidate stayed frozen while the filter refused every sample, and the lock-out
        waited for it: isam2, seed 3, 23.9 kg for 50 s).

        A candidate begins, too, at the first sample of each new pose (``pose_misfit``'s inputs tolerance)
        where the noise model is the user's (``adapt_noise`` off) or holds the pose's misfit (κ > 0): begun
        only every ``lockout_window_samples``, a step found began up to that many samples late, and a fast
        δM walk had taken what the step did to the samples between (the paper's experiment, ``--config
        paper``, a 40 kg step: 23.0 ± 4.0, 32.2 ± 6.8, 36.6 ± 7.4 kg, seeds 1–3; at each pose 39.0 ± 9.8,
        39.1 ± 9.5, 38.6 ± 8.4). Where the scale is measured and the misfit is not modelled, the windows
        take the samples for as white as one pose's are, and a candidate at a new pose takes that pose's
        misfit for a step (the default configuration there: 16–29 steps taken).

        A step taken begins a change that may go on: the unknown put on over seconds (the paper's payload, over
        20 s) is found as a run of steps, each taken ``lockout_window_samples`` after it began, and the samples
        between were taken at a value the filter had not caught up with; what they leave along the ridge the
        samples see (the payload's column is bilinear in it and the compliance) stays (ekf, default configuration,
        the paper's 0/20/40 kg experiment: 38.25 ± 0.31, 37.94 ± 0.34, 39.33 ± 0.51 kg, seeds 1–3; without the
        ramps' samples 40.20 ± 0.37, 39.74 ± 0.39, 40.45 ± 0.55). So while a change goes on the candidates begin
        from its origin, the filter before the sample the first step began at (walked to the sample, the step's
        variance added), and a candidate taken from there leaves out the samples between (the step that follows a
        ramp as far as it has come, not the sum of steps each taken at the value before). The change is over once a
        candidate from the origin has seen a window of samples and the filter explains them at least as well (its
        ratio ≤ 0: the samples the filter kept since tell the unknown no worse than the origin and one step); until
        then a lock-out waits for the candidates, since the filter lags the moving unknown by design (a recovery's
        batch there re-solved the compliance against a payload some kilograms behind)."""
        f = self.filter
        index, variance = step
        S = self._predicted(f.P + f.Q, H, R0, self._misfit, prepared)
        nu_raw, nu = nu, self._innovation(nu, self._misfit, prepared)
        filter_ll = _log_likelihood(nu, S)
        filter_takes = not filter_ll.nis > f.gate_nis
        self._dispersions.append(min(filter_ll.nis, f.gate_nis) / len(nu))
        candidates = []
        taking = []  # the candidates that take this sample
        change_over = False
        for c in self._candidates:
            from_change = self._change_origin is not None and c.origin is self._change_origin
            observation = self._observe_or_none(prepared, c.x)
            if observation is None:
                candidates.append(c)
                continue
            x, P = c.x.copy(), c.P.copy()
            status, nis, S_c, misfit = self._misfit_step(
                x, P, c.misfit, f.Q, observation[1], observation[0], R0, self.noise_scale2, f.gate_nis,
                NO_COMPONENTS, prepared,
            )  # fmt: skip
            if status == STEP_TAKEN:
                at_start = c.at_start and self._held(c.misfit, prepared, len(observation[0]))
                taken_ll = _log_likelihood(self._innovation(observation[0], c.misfit, prepared), S_c)
                gain = taken_ll.value - filter_ll.value
                withheld = at_start and c.at_new_pose
                ratio, start_ratio = (c.ratio, c.start_ratio + gain) if withheld else (c.ratio + gain, 0.0)
                taking.append(
                    _Candidate(
                        x, P, ratio, nis, c.taken + 1, c.readmitted + (not filter_takes), c.t_s, c.origin, misfit,
                        at_start, c.at_new_pose, start_ratio=start_ratio,
                    )
                )  # fmt: skip
                candidates.append(taking[-1])
                # a window of samples, and the filter's state explains them as well: the change was over
                change_over |= (
                    from_change and not at_start and c.taken + 1 >= self._robust.lockout_window_samples and ratio <= 0.0
                )
            elif not filter_takes:
                candidates.append(dataclasses.replace(c, refused_last=True))  # both refuse it: it tells neither apart
        self._since_candidate += 1
        new_pose = self._candidates_per_pose and not (
            len(self._last_inputs) == self._m
            and np.max(np.abs(prepared[: self._m] - self._last_inputs)) <= self._pose_tolerance
        )
        self._last_inputs = prepared[: self._m].copy()
        stepped = S + variance * np.outer(H[:, index], H[:, index])
        if (
            new_pose
            or self._since_candidate >= self._robust.lockout_window_samples
            or (filter_ll.nis - float(nu @ np.linalg.solve(stepped, nu)) > self._step_bound)
        ):
            self._since_candidate = 0
            origin, observed = self._change_origin, None
            if origin is None:  # from the filter as it is: its own observation of this sample is the origin's
                origin, observed = _Origin(f.x.copy(), f.P.copy(), self._misfit, f.t_s, f.samples_used), (nu_raw, H)
            stepped_Q = np.zeros_like(f.Q)  # the walk since the origin's last sample, and the step
            self._fill_Q(stepped_Q, 0.0 if math.isnan(origin.t_s) else t_s - origin.t_s)
            stepped_Q[index, index] += variance
            start = self._stepped_update(t_s, prepared, origin, R0, stepped_Q, filter_takes, observed)
            if start is not None:
                candidates.append(start)
                taking.append(start)
                if len(candidates) > MAX_STEP_CANDIDATES:  # the least likely of the older ones goes
                    candidates.pop(int(np.argmin([c.ratio + c.start_ratio for c in candidates[:-1]])))
        self._candidates = candidates
        if change_over:
            self._change_origin = None
        if not candidates:
            return False
        best = candidates[int(np.argmax([c.ratio for c in candidates]))]
        confirmed = best.taken >= self._robust.lockout_window_samples or (
            self._kappa > 0.0 and not best.at_start and not filter_takes and best.refused_last
        )
        if not (self._leads(best.ratio) and confirmed):
            return False
        f.x, f.P, f.nis, f.S = best.x, best.P, best.nis, S
        self._misfit = best.misfit
        # the origin's samples, the one the step began at and those it took after it (this one too, where it
        # took it): of the filter's samples since the origin (this one not yet), those the step did not take are
        # out (taken while the unknown moved), and those the filter refused before this one that it took are in
        takes = any(best is c for c in taking)
        self.step_readmitted += best.readmitted - (takes and not filter_takes)
        in_both = 1 + best.taken - best.readmitted - (takes and filter_takes)
        if not takes:  # the step refused it, as the filter did (or sees no pose in it): refused, said once
            self._step_refused.append(self._step_refusal(t_s, filter_takes))
        self.step_dropped += f.samples_used - best.origin.samples_used - in_both
        f.samples_used = best.origin.samples_used + 1 + best.taken
        self._change_origin = best.origin
        self.step_origin_t_s = best.origin.t_s
        f.t_s = t_s
        self.steps += 1
        self.step_t_s = best.t_s
        self._candidates, self._since_candidate = [], 0
        self._buffer.clear()
        self._since_window, self._last_window = 0, None
        return True

    def _step_refusal(self, t_s: float, filter_takes: bool) -> SampleRejected:
        """The refusal of the sample at ``t_s`` that a step was taken at without it (:meth:`take_step_refusals`):
        gated by the filter and the step, or, where the filter takes it, fixing no pose at the step's state."""
        if filter_takes:
            err = SampleRejected(
                f"{self.method}: sample at t = {number(t_s)} s: the measurement does not fix a pose at the payload "
                "step taken at it",
                SampleRejected.NO_POSE,
            )
        else:
            err = SampleRejected(
                f"{self.method}: sample at t = {number(t_s)} s is refused by the filter and by the payload step "
                "taken at it (χ² gate)",
                SampleRejected.GATED,
            )
        err.t_s = t_s
        return err

    def _leads(self, ratio: float) -> bool:
        """Whether a candidate step's ``ratio`` (or the one it withholds at its start pose, 0 once it has left it)
        is beyond its bound at the dispersion of the filter's NIS."""
        dispersion = max(1.0, float(np.mean(self._dispersions))) if self._dispersions else 1.0
        return ratio > 0.5 * self._step_bound * dispersion

    def _stepped_update(
        self,
        t_s: float,
        prepared: np.ndarray,
        origin: _Origin,
        R0: np.ndarray,
        Q: np.ndarray,
        filter_takes: bool,
        observed: tuple[np.ndarray, np.ndarray] | None = None,
    ):
        """A candidate step from the update of one sample at ``origin`` with the process noise ``Q`` of the step,
        iterated (:meth:`_iterated`); None where the update is degenerate or the sample fixes no pose there.
        ``observed``: the sample's ``(ν, H)`` at ``origin.x`` where the caller has it (None: observed here)."""
        observation = observed if observed is not None else self._observe_or_none(prepared, origin.x)
        if observation is None:
            return None
        nu, H = self._iterated(prepared, observation[0], observation[1], R0, Q, origin)
        x, P = origin.x.copy(), origin.P.copy()
        at_new_pose = self._kappa > 0.0 and not self._held(origin.misfit, prepared, len(nu))
        status, nis, _, misfit = self._misfit_step(
            x, P, origin.misfit, Q, H, nu, R0, self.noise_scale2, math.inf, NO_COMPONENTS, prepared
        )
        return (
            _Candidate(x, P, 0.0, nis, 0, int(not filter_takes), t_s, origin, misfit, self._kappa > 0.0, at_new_pose)
            if status == STEP_TAKEN
            else None
        )

    def _iterated(
        self, prepared: np.ndarray, nu: np.ndarray, H: np.ndarray, R0: np.ndarray, Q: np.ndarray, origin: _Origin
    ):
        """A step's sample as an iterated update: ``(ν, H)`` linearised at the update's own result, so
        that :meth:`FilterState.update` from the state before it is one Gauss–Newton step of that sample
        and the prior (to :data:`RELINEARISE_TOLERANCE` posterior σ), not a step linearised where the
        unknown has not stepped yet.

        The payload's pattern is bilinear, ``c_i f_{m,i} m``: linearised at the payload before the step,
        the compliance's column has the leg forces without the new payload, and the update's covariance
        misses the line that ties the payload to the compliance (they are −0.98 correlated after a
        40 kg step). The samples after it did not undo that: on benchmarks.elastic's table-3 robot
        with the tracker's geometry exact, five seeds, ekf ended with the compliances' common error
        at up to 5.6σ and the payload 0.1–0.34 kg low at up to 5.8σ (σ 0.05–0.08 kg); iterated, within
        1.6σ and 1.5σ (σ 0.15–0.24 kg)."""
        x_prior = origin.x
        at, linearised = x_prior, (nu, H)
        for _ in range(MAX_RELINEARISATIONS):
            x, P = x_prior.copy(), origin.P.copy()
            innovation = linearised[0] + linearised[1] @ (at - x_prior)
            status, *_ = self._misfit_step(
                x, P, origin.misfit, Q, linearised[1], innovation, R0, self.noise_scale2, math.inf, NO_COMPONENTS,
                prepared,
            )  # fmt: skip
            if status != STEP_TAKEN or _mahalanobis2(x - at, P, self._gauge_projector) <= RELINEARISE_TOLERANCE**2:
                break
            observation = self._observe_or_none(prepared, x)
            if observation is None:  # no pose at the result: the last linearisation stands
                break
            at, linearised = x, observation[:2]
        return linearised[0] + linearised[1] @ (at - x_prior), linearised[1]

    # ------------------------------------------------------------------ batches

    def optimum_from(
        self, t_s: np.ndarray, prepared: np.ndarray, at: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """``(x, P)``: the MAP of the prior and the prepared samples ``(t_s, prepared)`` by Gauss–Newton from the
        state ``at`` (:meth:`_gauss_newton`: passes from the prior, every sample observed at one point, at the
        noise scale and walk rate in use), or None where it does not settle in :data:`MAX_RELINEARISATIONS`.

        The recursion's own ``P`` sums each sample's information at the state before it; where that state moved
        by millimetres along the way (an outside instrument's frame and encoder zeros found over the samples),
        its covariance is not the information the samples hold, nor is its state their optimum."""
        samples = (np.asarray(t_s, dtype=float), np.asarray(prepared, dtype=float))
        use = np.ones(len(prepared), dtype=bool)
        solved, settled = self._gauss_newton(use, self.noise_scale2, self._linearise(at, prepared), samples=samples)
        return (solved[0], solved[1]) if settled else None

    def _observe_or_none(self, prepared: np.ndarray, x: np.ndarray):
        """:data:`Observe` in a batch: a sample that fixes no pose at ``x`` is skipped, not fatal."""
        try:
            return self._observe(prepared, x)
        except SampleRejected:
            return None

    def _linearise(self, at: np.ndarray, prepared: np.ndarray | None = None) -> tuple[np.ndarray, list]:
        """``(at, every buffered sample's observation there)`` (None where it fixes no pose; ``prepared``: those
        samples' instead): the linearisation a Gauss–Newton pass (:meth:`_pass`) reuses."""
        rows = self._buffer.prepared if prepared is None else prepared
        return at, [self._observe_or_none(row, at) for row in rows]

    def _pass(
        self,
        use: np.ndarray,
        noise_scale2: float,
        centre: np.ndarray | None = None,
        linearised: tuple[np.ndarray, list] | None = None,
        walk_rate_mm2_per_s: float | None = None,
        startup: bool = False,
        samples: tuple[np.ndarray, np.ndarray] | None = None,
    ):
        """A filter pass from the prior over the buffered samples ``use`` (``samples``: ``(t_s, prepared)`` of
        others, observed as ``linearised`` has them); returns
        ``(x, P, samples used, last t_s, residual degrees of freedom)``.

        ``centre``: the prior's mean (default the filter's prior: 0, the manufacturing prior, or a
        registration's start). The window batches
        centre it on the running estimate, so their first samples are linearised near where
        the parameters are rather than millimetres away; the prior's σ is the same.
        ``linearised``: :meth:`_linearise`'s observations at one state ``x̄``; each sample is then
        taken at ``x̄`` with the innovation ``ν(x̄) − H (x − x̄)`` at the running ``x`` — one
        Gauss–Newton step from ``x̄`` — instead of at the running ``x``.
        ``walk_rate_mm2_per_s``: the random walk within the pass (default the rate in use).
        ``startup``: the decided start-up batch's own solve (:meth:`_relinearise_startup`,
        :meth:`startup_gaussian`), which runs once the filter has started: an unknown that steps is
        solved with the rest there, from its prior, as in every start-up pass.
        """
        walk = self.walk_rate_mm2_per_s if walk_rate_mm2_per_s is None else walk_rate_mm2_per_s
        x = (self._x0 if centre is None else centre).copy()
        P = self._P0.copy()
        if self._step_unknown is not None and self.started and not startup:
            # after the start-up, an unknown that steps is as the filter knows it in every batch (the
            # windows, a recovery): re-solved from its prior over a few samples it would trade against
            # its correlates (a payload against the compliance's scale), which a window would take
            # for parameter motion and a recovery adopt
            index = self._step_unknown[0]
            x[index] = self.filter.x[index]
            P[index, :], P[:, index], P[index, index] = 0.0, 0.0, self.filter.P[index, index]
        # variance components of the updates: e = R S⁻¹ ν has E[eᵀ R⁻¹ e] = tr(R S⁻¹), whatever
        # the walk (the residual is taken at the state right after the update)
        self._pass_components = np.zeros(2)
        buffer = self._buffer
        if linearised is not None:
            used, rows, last_t = self._observed_pass(x, P, use, noise_scale2, walk, linearised, samples)
        elif self._compiled_rows is not None:
            _, _, used, last_t, *_ = self._compiled_rows(
                x,
                P,
                np.empty((self._n, self._n)),
                self._unit_Q,
                np.empty((self._m, self._m)),
                buffer.t,
                buffer.prepared,
                NO_POSES,
                use,
                math.nan,
                walk,
                noise_scale2,
                math.inf,
                True,
                *_NO_WINDOW,
                0,
                0,
                np.empty((0, self._n)),
                self._pass_components,
            )
            rows = used * self._m  # a leg set of known geometry: the drive's rows, every sample
        else:
            used, rows, last_t = self._observed_pass(x, P, use, noise_scale2, walk)
        # the batch's hat-matrix trace, tr(P Σ Hᵀ R⁻¹ H) = n − tr(P P0⁻¹), is what the data
        # determine; the rest of the residual degrees of freedom are redundancy
        determined = self._free - float(np.sum(self._P0_pinv * P))  # tr(P0⁺ P), both symmetric
        return x, P, used, last_t, rows - determined

    def _observed_pass(
        self,
        x: np.ndarray,
        P: np.ndarray,
        use: np.ndarray,
        noise_scale2: float,
        walk_rate_mm2_per_s: float,
        linearised: tuple[np.ndarray, list] | None = None,
        samples: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> tuple[int, int, float]:
        """:meth:`_pass`'s recursion, observing each sample through ``observe`` (in place) at the
        pass's own state, or taking it from ``linearised``; returns ``(samples used, their
        observations' rows, last t_s)``. The ``step`` unknown of ``step_factors`` takes no part in a sample
        while the filter holds it or the pass's own compliance is not yet known to within itself
        (:meth:`_compliance_settled`; :meth:`_release_payload`). ``samples``: ``(t_s, prepared)`` of the
        samples ``use`` indexes (default the buffer's)."""
        Q = np.zeros((self._n, self._n))
        last_t, used, rows = math.nan, 0, 0
        times, prepared = (self._buffer.t, self._buffer.prepared) if samples is None else samples
        misfit = None
        for k in np.flatnonzero(use):
            observation = self._observe_or_none(prepared[k], x) if linearised is None else linearised[1][k]
            if observation is None:
                continue
            nu, H, R0 = observation
            # a batch from the prior re-solves the compliance from its prior: the payload waits for it there too
            if self.payload_held or not self._compliance_settled(x, P):
                H = self._without_payload(H)
            if linearised is not None:
                nu = nu - H @ (x - linearised[0])
            self._fill_Q(Q, 0.0 if math.isnan(last_t) else times[k] - last_t, walk_rate_mm2_per_s)
            status, _, _, misfit = self._misfit_step(
                x, P, misfit, Q, H, nu, R0, noise_scale2, math.inf, self._pass_components, prepared[k]
            )
            if status != STEP_TAKEN:
                continue  # degenerate: the step left x and P untouched
            last_t, used, rows = times[k], used + 1, rows + len(nu)
        self._pass_misfit = misfit
        return used, rows, last_t

    def _test(self, x: np.ndarray, P: np.ndarray, fitted: np.ndarray, redundancy: float, used: int):
        """``(d_k of every buffered sample, robust scale²)`` at the estimate ``(x, P)`` fitted to ``fitted``."""
        observations = [self._observe_or_none(prepared, x) for prepared in self._buffer.prepared]
        missing = np.array([o is None for o in observations])
        nu, H, R0 = _stacked(observations, self._m, self._n)
        unit = np.einsum("ki,ki->k", nu, np.linalg.solve(R0, nu[..., None])[..., 0])
        # post-fit residuals of the fitted samples have ~redundancy/used degrees of freedom each
        dof = max(redundancy / max(used, 1), 0.5)
        scale2 = max(float(np.median(unit[fitted & ~missing]) / chdtri(dof, 0.5)), MIN_NOISE_SCALE2)
        # a sample at the estimate, its pose's misfit too (pose_misfit)
        S = (scale2 + self._kappa) * R0 + H @ P @ np.swapaxes(H, 1, 2)
        tested = np.einsum("ki,ki->k", nu, np.linalg.solve(S, nu[..., None])[..., 0])
        tested[missing] = math.inf  # no pose at this estimate: not one of the good samples
        return tested, scale2

    def _proposals(self) -> list[np.ndarray]:
        """Deterministic subsets of the buffer: all of it, and overlapping blocks just large
        enough for :data:`MIN_REDUNDANCY` (so some of them miss any few glitches)."""
        count = len(self._buffer)
        block = math.ceil((self._n + MIN_REDUNDANCY) / self._m) + 2
        subsets = [np.ones(count, dtype=bool)]
        if count >= 2 * block:
            for start in range(0, count - block + 1, max(block // 2, 1)):
                subset = np.zeros(count, dtype=bool)
                subset[start : start + block] = True
                subsets.append(subset)
        return subsets

    def _solve(self, adopt: bool) -> np.ndarray:
        """Consensus batch over the buffered samples (see the module docstring); returns their
        outlier flags and keeps ``(x, P, samples, last t_s, scale², redundancy)`` in
        ``self._solved``; with ``adopt`` the filter takes that state."""
        count = len(self._buffer)
        gate = self.filter.gate_nis if self._gate_on else math.inf
        # the last solution: every proposal is a step from it
        linearised = self._linearise(self.filter.x.copy()) if self._relinearise else None
        best = None  # (agreeing samples, proposal outliers)
        if math.isfinite(gate):
            for subset in self._proposals():
                x, P, used, _, redundancy = self._pass(subset, self.noise_scale2, linearised=linearised)
                if redundancy < MIN_REDUNDANCY:
                    continue
                tested, _ = self._test(x, P, subset, redundancy, used)
                outliers = tested > gate
                if best is None or (~outliers).sum() > (~best).sum():
                    best = outliers
        outliers = np.zeros(count, dtype=bool) if best is None or best.sum() * 2 > count else best
        scale2 = self.noise_scale2
        solved = self._pass(~outliers, scale2, linearised=linearised)
        for _ in range(MAX_ITERATIONS if best is not None else 0):
            x, P, used, _, redundancy = solved
            if redundancy < MIN_REDUNDANCY:
                break
            tested, scale2 = self._test(x, P, ~outliers, redundancy, used)
            new = tested > gate
            if new.sum() * 2 > count:
                new[:] = False
            if np.array_equal(new, outliers):
                break
            outliers = new
            solved = self._pass(~outliers, scale2, linearised=linearised)
        if not self._robust.adapt_noise:
            scale2 = self.noise_scale2
        if linearised is not None:  # relinearising (self._relinearise), at the scale it will carry on with
            solved, _ = self._gauss_newton(~outliers, scale2, linearised)
        elif scale2 != self.noise_scale2:  # the state's P at the scale it will carry on with
            solved = self._pass(~outliers, scale2)
        x, P, used, last_t, redundancy = solved
        self._solved = (x, P, used, last_t, scale2, redundancy)
        self._solved_misfit = self._pass_misfit
        if adopt:
            self._adopt()
        return outliers

    def _gauss_newton(
        self,
        use: np.ndarray,
        noise_scale2: float,
        linearised: tuple[np.ndarray, list],
        startup: bool = False,
        samples: tuple[np.ndarray, np.ndarray] | None = None,
    ):
        """:meth:`_pass` over ``use`` relinearised at its own result until the step from the
        linearisation point is within :data:`RELINEARISE_TOLERANCE` posterior σ (the MAP of the
        prior and those samples); returns ``(the last pass, whether it settled so)`` (``startup``,
        ``samples``: as :meth:`_pass`)."""
        for _ in range(MAX_RELINEARISATIONS):
            solved = self._pass(use, noise_scale2, linearised=linearised, startup=startup, samples=samples)
            x, P = solved[0], solved[1]
            if _mahalanobis2(x - linearised[0], P, self._gauge_projector) <= RELINEARISE_TOLERANCE**2:
                return solved, True
            linearised = self._linearise(x, None if samples is None else samples[1])
        return solved, False

    def _adopt(self) -> None:
        x, P, used, last_t, scale2, redundancy = self._solved
        f = self.filter
        f.x, f.P, f.samples_used, f.t_s = x, P, used, last_t
        self._misfit = self._solved_misfit
        if self._robust.adapt_noise and redundancy >= MIN_REDUNDANCY:
            self.noise_scale2 = max(scale2, MIN_NOISE_SCALE2)
            self.measured_noise = True
            self._record_scale()

    # ------------------------------------------------------------------ noise from windows

    def _noise_due(self) -> float:
        """Accepted samples after which the next noise estimates are due (``inf``: never): every
        window until :data:`WALK_WINDOWS` differences are pooled (a short log's estimates as soon as
        they can be had), then every ``noise_every_samples``."""
        if not self._robust.adapt_noise:
            return math.inf
        return self._noise_every if self._walk_pooled() else self._window

    def _walk_pooled(self) -> bool:
        """Whether :data:`WALK_WINDOWS` window differences are pooled: past the start-up's windows, which
        come every window, the estimates are taken every ``noise_every_samples`` and only refreshed. There
        a window is passed again only where its measured scale moves beyond :data:`SCALE_TOLERANCE` (to
        its fixed point), and not when the walk rate moves (the next window measures the scale at the
        rate then in use): passed again at every window, as the start-up's are, a long log's windows took
        4 passes instead of 1–2, a third of ``calibrate ekf``'s time at 10⁵ samples. One pass at the
        scale measured, and no walk re-pass, biased the scale 19 % high on clean data (test_robust)."""
        return _differences(self._windows) >= WALK_WINDOWS

    def _window_statistics(self) -> None:
        """Measurement scale and random-walk rate from the window of recent good samples."""
        self._since_window = 0
        if not self._robust.adapt_noise:
            return
        good = ~self._buffer.gated
        x, P, used, last_t, redundancy = self._pass(good, self.noise_scale2, self.filter.x)
        if redundancy < MIN_REDUNDANCY:
            return
        refresh = self._walk_pooled()
        decay = math.exp(-used / self._robust.noise_memory_samples)
        remembered, remembered_walk = decay * self._scale_sums, decay * self._scale_walk
        x, P = self._measured_scale(good, remembered, x, P, refresh)
        self.measured_noise = True
        first_t = float(self._buffer.t[good][0])
        x, P, *_ = self._walk_window(good)
        if self._walk_difference(x, P, last_t) and not refresh:
            # the scale at the walk now in use: measured at the walk before, it had given that walk's
            # share of the residuals to the noise or taken it from it (a static robot at 0.2× the noise,
            # the default walk lowered at a window: the noise scale measured at the default walk, ~0.4 of
            # the truth, stood with the lowered walk and the gate refused 3 clean samples of 100)
            x, P, *_ = self._pass(good, self.noise_scale2, self.filter.x)
            kept = self._remembered_at_walk(good, remembered, remembered_walk, x, P)
            if not kept[1]:
                remembered, remembered_walk = kept, 0.0
            self._measured_scale(good, remembered, x, P)
            x, P, *_ = self._walk_window(good)
            self._windows[-1] = (x, P, last_t, last_t, self._windows[-1][4])
        # the window joins the sums at the walk it was measured at
        self._scale_walk = remembered_walk + (self._scale_sums[1] - remembered[1]) * _log_walk(self.walk_rate_mm2_per_s)
        self._last_window = (x, P, first_t, last_t)
        self._record_scale()

    def _remembered_at_walk(
        self, good: np.ndarray, remembered: np.ndarray, remembered_walk: float, x: np.ndarray, P: np.ndarray
    ) -> np.ndarray:
        """The ``remembered`` scale sums unless the walk they were measured at (:func:`_memory_walk` of
        them and ``remembered_walk``) is what parts them from the window ``good`` (its pass ``(x, P)`` at
        the scale and the walk in use), else none: where the window measured alone at the walk now in use
        rejects them beyond both spreads (``√(2 / redundancy)`` relative, each; as sure as the gate is)
        and measured alone at theirs does not, they hold the walk's share of the residuals that the rate
        then in use left out (or took) as noise.

        The start-up batch and the windows before the first difference measure the scale at the
        configured walk: on a robot drifting 10× faster than told, the readings at 0.3× the told noise
        (benchmarks/robustness.py's honesty logs), they put 12–20 where 0.09 is right, and over
        ``noise_memory_samples`` their sums outweighed every window measured at the walk the
        differences found (s² 7.8 at the log's end, the window alone 2–3). A window that rejects them
        at their own walk too differs from them by itself: a tracker's unmodelled geometry has the
        windows' scales scatter beyond their χ² spread by the poses each one holds. Dropped there (the
        walk raised by 20 %), the scale of tests/test_thermal.py's warm-up fell from 0.44 to 0.27 at a
        window and stood 10–35 % lower over the next 120 samples (main 0.38–0.42), and isam2, whose
        graph weighs each window's samples at its scale, took 0.06 ppm/K more of the temperature ramp
        into α."""
        if remembered[1] <= 0.0:
            return remembered
        held = (self.noise_scale2, self._pass_components.copy(), self.walk_rate_mm2_per_s)
        try:
            if not self._rejects(good, remembered, x, P):
                return remembered
            self.walk_rate_mm2_per_s = _memory_walk(remembered, remembered_walk)
            x_then, P_then, *_ = self._pass(good, held[0], self.filter.x)
            return remembered if self._rejects(good, remembered, x_then, P_then) else np.zeros(2)
        finally:
            self.noise_scale2, self._pass_components, self.walk_rate_mm2_per_s = held

    def _rejects(self, good: np.ndarray, remembered: np.ndarray, x: np.ndarray, P: np.ndarray) -> bool:
        """Whether the window ``good`` measured alone at the walk in use, from its last pass ``(x, P)``,
        rejects the ``remembered`` scale sums (:meth:`_remembered_at_walk`; the filter's scale is left at
        the window's)."""
        self._measured_scale(good, np.zeros(2), x, P)
        alone, redundancy = self.noise_scale2, max(float(self._scale_sums[1]), 1e-300)
        spread2 = 2.0 / redundancy + 2.0 / remembered[1]
        shift2 = math.log(alone * remembered[1] / max(remembered[0], 1e-300)) ** 2 / spread2
        return bool(shift2 > chdtri(1, SCALE_MEMORY_REJECTION))

    def _walk_window(self, use: np.ndarray):
        """The buffered samples ``use`` as a window of the walk test (:meth:`_pass`'s tuple): a pass from
        the prior at the scale in use, every sample linearised at the running estimate (one Gauss–Newton
        step from it).

        A pass that linearises each sample at its own state wanders, early on, by millimetres in the
        directions a few seconds of a smooth path leave open, and its result there disagrees with the
        window's samples by more than its σ: successive windows differ by up to 100× their covariance
        in a few directions, which the test took for a walk (a tracker drifting at 6.5 µm/√s along a
        10 Hz Lissajous path: the rate raised to 22–51 µm/√s, z² 0.1–0.3). The noise scale is measured
        on the other pass (:meth:`_measured_scale`): linearised at the running estimate, whose mean has
        seen the window's samples, it falls below its truth (test_robust's smooth path)."""
        return self._pass(use, self.noise_scale2, self.filter.x, self._linearise(self.filter.x.copy()))

    def _walk_difference(self, x: np.ndarray, P: np.ndarray, last_t: float) -> bool:
        """The window ``(x, P)`` whose last sample is at ``last_t`` [s] joins the walk test's windows and
        the walk rate in use is tested again. Returns whether the rate moved beyond
        :data:`SCALE_TOLERANCE` (False where there is no window before it to compare it with: the
        first window, or the first after a step or a jump, which begins a new run of windows).

        The window joins as an instant at its last sample (its span 0 in :func:`_window_terms`): its pass
        (:meth:`_walk_window`) walks at the rate in use from a prior wider than the window's samples, so
        ``x`` is the estimate of δM at the last sample and ``P`` its covariance, walk within the window
        included, not a mean over the window. Taken as the window's mean, two windows a span ``T`` apart
        differed by ``q · 2T/3`` and the rate came out up to 1.5× too high where the walk within a window
        exceeds its noise (a robot drifting 10× faster than told, readings at 0.3× the told noise: the
        walk 14–55 µm/√s against 10 with the true noise scale, NEES below the band)."""
        begins = self._last_window is None
        self._windows.append((x, P, last_t, last_t, begins))
        if begins:
            return False
        walk = max(self._pooled_walk_rate(), MIN_WALK_FRACTION * self._configured_walk)
        moved = abs(walk - self.walk_rate_mm2_per_s) > SCALE_TOLERANCE * max(walk, self.walk_rate_mm2_per_s)
        self.walk_rate_mm2_per_s = walk
        return moved

    def _measured_scale(
        self, good: np.ndarray, remembered: np.ndarray, x: np.ndarray, P: np.ndarray, refresh: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """Sets the noise scale from the last pass over the window ``good`` (its variance components,
        added to the ``remembered`` sums): passes at the scale the last one measured until it moves by
        at most :data:`SCALE_TOLERANCE`. One pass's components are unbiased only at the true scale, and
        the start-up's, which takes the walk within it for noise (its residuals are taken at one state),
        is 2–20× too high on a drifting robot: one step from it left the scale 2–4× too high and the walk
        test then rejected the configured rate (honesty study, tracker drifting at 0.2× the told noise:
        NEES in band 6 → 9 of 10). Returns the window's ``(x, P)`` at the scale in use, which the next
        window's is taken at: the walk test compares their difference with both. ``refresh``
        (:meth:`_walk_pooled`): no pass more where the scale moves within the tolerance (the last pass's
        ``(x, P)`` stands).

        Where the walk in use leaves the window's pass fewer than :data:`MIN_REDUNDANCY` expected
        residual degrees of freedom, it can explain the window within the noise and the window cannot
        tell the two apart: a walk faster than the robot's has the components take the samples for
        smoother than its noise, each pass lowers the scale and the next pass's walk fits still more
        (table 3 of benchmarks.elastic, a robot standing still, the configured walk 10⁴× its rate:
        24 of 180 rows left at the start-up's scale, 2.4 at the next, the scale at its floor 0.01
        against a static batch's 2.3, until the first window difference lowered the walk). There the
        window is measured as a static batch (the walk off within it): its residuals take any walk
        within the window for noise, an upper bound, exact for a robot that stood still over it;
        the window differences then test the walk against windows so measured."""
        scale2 = self.noise_scale2
        walk = None  # the rate in use
        for _ in range(SCALE_ITERATIONS):
            # (scale of the pass × observed, expected): their ratio is the scale the window says
            observed, expected = self._pass_components
            if expected < MIN_REDUNDANCY and walk is None and 0.0 < self.walk_rate_mm2_per_s <= self._configured_walk:
                walk = 0.0
                x, P, *_ = self._pass(good, scale2, self.filter.x, walk_rate_mm2_per_s=walk)
                continue
            self._scale_sums = remembered + [scale2 * observed, expected]
            measured = max(self._scale_sums[0] / self._scale_sums[1], MIN_NOISE_SCALE2)
            converged = abs(measured - scale2) <= SCALE_TOLERANCE * scale2
            if measured == scale2 or (refresh and converged):
                scale2 = measured
                break
            x, P, *_ = self._pass(good, measured, self.filter.x, walk_rate_mm2_per_s=walk)
            scale2 = measured
            if converged:
                break
        self.noise_scale2 = scale2
        return x, P

    def _record_scale(self) -> None:
        """Note a new noise scale or walk rate as holding from the last buffered sample on."""
        if (self.noise_scale2, self.walk_rate_mm2_per_s) != self._scale_history[-1][1:]:
            self._scale_history.append((float(self._buffer.t[-1]), self.noise_scale2, self.walk_rate_mm2_per_s))

    def _held_at(self, t_s: float) -> tuple[float, float, float]:
        """The entry of the scale history in force right after the sample at ``t_s`` [s]."""
        held = self._scale_history[0]
        for entry in self._scale_history:
            if entry[0] > t_s:
                break
            held = entry
        return held

    def noise_scale2_at(self, t_s: float) -> float:
        """The noise scale ``s²`` in use right after the sample at ``t_s`` [s] was folded in (the
        current one for the last sample): what a caller that ran the filter ahead of a sample — on
        a block of samples — sees as one that asks after every sample does."""
        return self._held_at(t_s)[1]

    def walk_rate_at(self, t_s: float) -> float:
        """The random walk's rate [mm²/s] in use right after the sample at ``t_s`` [s] was folded in,
        as :meth:`noise_scale2_at`."""
        return self._held_at(t_s)[2]

    def _pooled_walk_rate(self) -> float:
        """The configured rate ``q₀`` [mm²/s] unless the last :data:`WALK_HISTORY` windows reject it;
        rejected as too large, the rate nearest to it they do not reject; as too small, their
        maximum-likelihood rate ``q̂``. Their log-likelihood in the rate is
        ``L(q) = −½ Σ_j [log(λ_j + q) + p_j / (λ_j + q)]`` over the independent terms every window against
        every other one gives (:func:`_window_terms`): the windows' separations, not only their neighbours',
        tell a walk, whose spread keeps growing with the time apart, from a stationary excess of the
        windows over their own covariance (a tracker's unmodelled geometry, which each window's poses see
        their own way), which moves far windows no more than near ones. A rate is rejected as too large
        where its signed root deviance ``sign(q̂ − q) √(2 (L(q̂) − L(q)))`` (≈ N(0, 1) at the true rate)
        falls below the normal's ``walk_lowering`` quantile, as too small where it exceeds its
        ``1 −`` :data:`WALK_RAISING` quantile (:func:`_walk_rate_in_use`).

        The likelihood weighs each direction by what it says about the walk, ``1 / (λ + q)``:
        most of the 42–54 directions move less over a window than their windows' own σ and say
        nothing, and a test of the plain sum ``Σ p / (λ + q T)`` against its χ² drowned the few that
        do in their scatter. On a robot standing still under the in-situ tracker (benchmarks.elastic's
        check, 1 µm readings, 8 differences) that sum kept the configured 1 µm/√s at χ²'s 45 %
        quantile while the likelihood rejected it by 2ΔL = 69 (0.13 µm/√s its 20 % bound); the walk
        kept let a payload step's ``c_i Δf_i`` be taken for δM walking between the stages (the
        compliance 2.6 % off, closed loop 2.8 µm at 40 kg). Both tests hold the configured rate
        against a few windows' scatter: the plain root (``q̂`` itself) is 0 about half the time
        whatever the walk, and a filter told its parameters stood still while they walked reported σ
        too small (NEES 2–6× its degrees of freedom, sweep configs/sweeps/honesty.toml); above ``q₀``
        a rate raised where the differences did not reject ``q₀`` widened a still robot's σ for a
        walk that was not there. The test that raises the rate is the stricter: at 20 % a side the
        χ² test still raised a still robot's rate in 1 of 5 tests (honesty study, tracker: 107 → 108
        of 120 in band at 5 %); lowering at 5 % too, the rate after a 0.2 mm jump stayed where the
        noise scale took the jump (31×, NEES/dof 0.05; tests/test_robust.py). The bounds move
        continuously with the data, so blocks and single samples still agree.

        The nearest rate not rejected is a one-sided confidence bound: lowered, the rate in use stays
        at or above the truth but for the test's probability, σ on the wide side; raised, it would stay
        at or below it, σ on the narrow side whenever the robot drifts faster than it was told — the
        failure of the error bars the raising is there to prevent. Once the differences reject ``q₀``
        as too small, ``q̂`` is the rate they say: on benchmarks/robustness.py's smooth-path drift log
        (a tracker at 1 µm drifting 6.5× the default walk, 5 seeds) the bound raised the rate to
        4.2–6.2 µm/√s and ekf's mean z² was 1.22–2.56; ``q̂`` gives 4.6–6.8 µm/√s and 1.11–1.83."""
        lam, p = self._walk_terms(self._windows)
        # one-sided normal quantiles as χ² with one degree of freedom at twice the probability
        lowering = float(chdtri(1, 2.0 * self.walk_lowering))
        raising = float(chdtri(1, 2.0 * WALK_RAISING))
        return _walk_rate_in_use(lam, p, self._configured_walk, lowering, raising)

    def _walk_terms(self, windows) -> tuple[np.ndarray, np.ndarray]:
        """The walk test's windows as the independent terms of the rate's likelihood (:func:`_window_terms`),
        each run of windows on its own: the unknown a payload step moves, which steps and does not walk,
        left out."""
        walks = self._unit_Q.copy() if self._walking is None else self._walking.copy()
        index = None if self._step_unknown is None else self._step_unknown[0]
        if index is not None:
            if walks.dtype == bool:  # the mask of the unknowns that walk
                walks[index] = False
            else:
                walks[index, :], walks[:, index] = 0.0, 0.0
        runs: list[list] = []
        for window in windows:
            if window[4] or not runs:
                runs.append([])
            runs[-1].append(window)
        terms = [_window_terms(run, walks, index) for run in runs if len(run) > 1]
        if not terms:
            return np.zeros(0), np.zeros(0)
        return np.concatenate([t[0] for t in terms]), np.concatenate([t[1] for t in terms])

    def _rejected_as_too_large(self, windows: list, rate_mm2_per_s: float) -> bool:
        """Whether ``windows`` (of the walk test's) reject ``rate_mm2_per_s`` as too large at the
        gate's probability: as sure as the gate is when it refuses a sample."""
        lam, p = self._walk_terms(windows)
        bound = float(chdtri(1, 2.0 * self._gate_tail))
        return _walk_rate_in_use(lam, p, rate_mm2_per_s, bound, bound) < rate_mm2_per_s

    # ------------------------------------------------------------------ lock-out

    def _locked_out(self) -> bool:
        window = self._buffer.gated[-self._robust.lockout_window_samples :]
        if int(window.sum()) < self._robust.lockout_gated_samples:
            return False
        if self._kappa <= 0.0:
            return True
        inputs = self._buffer.prepared[-self._robust.lockout_window_samples :][window, : self._m]
        return bool(np.max(np.abs(inputs - inputs[0])) > self._pose_tolerance)

    def _recover(self) -> None:
        """Solve the recent samples afresh; adopt when most of them agree (a consensus). The samples
        used before that the new state leaves out are counted as dropped, the gated ones it takes
        back as readmitted: every sample stays accounted for."""
        used_before, gated_before = self.filter.samples_used, self._buffer.gated.copy()
        outliers = self._solve(adopt=False)
        if self._solved[5] < MIN_REDUNDANCY or outliers.sum() * 2 > len(outliers):
            return
        if self._walked(~outliers):
            return
        self._adopt()
        self._candidates, self._since_candidate = [], 0  # they were steps from the state it replaced
        self._change_origin = None
        self.recovery_dropped += used_before - int(np.sum(~gated_before & ~outliers))
        self.recovery_readmitted += int(np.sum(gated_before & ~outliers))
        self._buffer.gated[:] = outliers  # the batch's verdict replaces the lock-out's record
        self.recoveries += 1

    def _walked(self, agreeing: np.ndarray) -> bool:
        """Whether a walk faster than the rate in use explains the lock-out: the samples the recovery's
        batch agrees with since the last window are a window of the walk test (:meth:`_walk_window`),
        and where their difference from the last window raises the rate, the filter's covariance takes
        the walk the raised rate adds since that window and the refused samples are fed again. Taken
        (True) where fewer than ``lockout_gated_samples`` of them are refused again; else the filter is
        as it was and the recovery solves the recent samples afresh (a jump, or a stream of glitches),
        at the rate the test has raised.

        The walk test's windows come every ``max(startup_samples, lockout_window_samples)`` accepted
        samples, then every ``noise_every_samples``, and a robot drifting several times faster than its
        rate in use locks the gate out sooner: each recovery threw the filter's history away and,
        breaking the chain of windows, left the next window no difference to test (a tracker at 1 µm
        drifting 6.5× the default walk along a 10 Hz Lissajous path: 18 recoveries in 1 200 samples,
        562 rows dropped)."""
        if not self._robust.adapt_noise or self._last_window is None:
            return False
        since = agreeing & (self._buffer.t > self._last_window[3])
        if not since.any():
            return False
        rate_from = self._last_window[3]
        x, P, _, last_t, redundancy = self._walk_window(since)
        if redundancy < MIN_REDUNDANCY:
            return False
        before, pooled = self.walk_rate_mm2_per_s, list(self._windows)
        first_t = float(self._buffer.t[since][0])
        self._walk_difference(x, P, last_t)
        raised = self.walk_rate_mm2_per_s - before
        # a jump is one difference the windows before it reject as a walk: a robot drifting faster than
        # its rate in use moved between those windows too. The recovery then goes on as it would without
        # the test: no difference across the jump (the windows after it measure the walk afresh), the
        # rate as it was
        if raised > 0.0 and _differences(pooled) and self._rejected_as_too_large(pooled, self.walk_rate_mm2_per_s):
            self._windows = deque(pooled, maxlen=WALK_HISTORY)
            self.walk_rate_mm2_per_s, self._last_window = before, None
            return False
        self._last_window = (x, P, first_t, last_t)
        self._since_window = 0  # the next window's samples all come after these
        self._record_scale()
        if raised <= 0.0:
            return False
        f = self.filter
        saved = (f.x.copy(), f.P.copy(), f.t_s, f.samples_used)
        walk = np.zeros_like(f.P)
        fill_walk(walk, self._unit_Q, raised * max(f.t_s - rate_from, 0.0))
        f.P = f.P + walk
        refused = np.flatnonzero(self._buffer.gated)
        taken = np.zeros(len(self._buffer), dtype=bool)
        for k in refused:
            try:
                self._step(float(self._buffer.t[k]), self._buffer.prepared[k].copy(), test_steps=False)
                taken[k] = True
            except SampleRejected:
                pass
        if len(refused) - int(taken.sum()) >= self._robust.lockout_gated_samples:
            f.x, f.P, f.t_s, f.samples_used = saved
            return False
        # fed in time order among samples taken before: the filter's time stays its latest sample's
        f.t_s = max(f.t_s, saved[2])
        self._buffer.gated[taken] = False
        self.recovery_readmitted += int(taken.sum())
        return True

    # ------------------------------------------------------------------ checkpoints

    def _origins(self) -> list[_Origin]:
        """The candidates' origins and the change's, each once (the change's first where there is one)."""
        origins = [] if self._change_origin is None else [self._change_origin]
        for c in self._candidates:
            if _index_of(c.origin, origins) is None:
                origins.append(c.origin)
        return origins

    def export_state(self) -> dict:
        """Everything :meth:`update` reads or writes, as arrays."""
        windows = list(self._windows)
        origins = self._origins()
        state = {
            "filter": self.filter.export_state(),
            "prior_mean": self._x0.copy(),
            "noise": np.array([self.noise_scale2, self.walk_rate_mm2_per_s]),
            "scale_sums": self._scale_sums.copy(),
            "scale_walk": np.float64(self._scale_walk),
            "counters": np.array(
                [int(self.started), self.recoveries, self._since_window, int(self.measured_noise)], dtype=np.int64
            ),
            **self._buffer.export_state(),
            "recovery_counts": np.array([self.recovery_dropped, self.recovery_readmitted], dtype=np.int64),
            "step_counts": np.array([self.step_dropped, self.step_readmitted], dtype=np.int64),
            "steps": np.int64(self.steps),
            "first_t_s": np.float64(self.first_t_s),
            "step_candidates": {
                "x": np.array([c.x for c in self._candidates]).reshape(-1, self._n),
                "P": np.array([c.P for c in self._candidates]).reshape(-1, self._n, self._n),
                "ratio_nis_taken": np.array(
                    [(c.ratio, c.nis, c.taken, c.readmitted, c.t_s) for c in self._candidates], dtype=float
                ).reshape(-1, 5),
                # where the pose's misfit is modelled: each candidate at its start pose, that pose new to it, refused
                # last, and its ratio there withheld
                "at_start": np.array(
                    [(c.at_start, c.at_new_pose, c.refused_last, c.start_ratio) for c in self._candidates], dtype=float
                ).reshape(-1, 4),
                "since": np.int64(self._since_candidate),
                "last_step_t_s": np.float64(self.step_t_s),
                "dispersions": np.array(self._dispersions, dtype=float),
                "payload_held": np.array([float(self.payload_held), self.payload_released_t_s]),
                "last_inputs": self._last_inputs.copy(),
                "origin_x": np.array([o.x for o in origins]).reshape(-1, self._n),
                "origin_P": np.array([o.P for o in origins]).reshape(-1, self._n, self._n),
                "origin_t_s": np.array([o.t_s for o in origins], dtype=float),
                "origin_samples_used": np.array([o.samples_used for o in origins], dtype=np.int64),
                # each candidate's origin, and whether the first is the change's
                "origin_of": np.array([_index_of(c.origin, origins) for c in self._candidates], dtype=np.int64),
                "changing": np.int64(self._change_origin is not None),
            },
            "walk_windows": {
                "x": np.array([w[0] for w in windows]).reshape(-1, self._n),
                "P": np.array([w[1] for w in windows]).reshape(-1, self._n, self._n),
                "t_s": np.array([w[2:4] for w in windows], dtype=float).reshape(-1, 2),
                "begins": np.array([w[4] for w in windows], dtype=np.int64),
            },
            # a caller that takes the filter back to this state (isam2's front end, after a run a
            # sample failed in) still asks for the scales of samples before it
            "scale_history": np.array(self._scale_history, dtype=float).reshape(-1, 3),
        }
        if self._last_window is not None:
            x, P, first_t, last_t = self._last_window
            state["window"] = {"x": x, "P": P, "first_t_s": np.float64(first_t), "t_s": np.float64(last_t)}
        if self._kappa > 0.0:  # the misfit at the pose the filter and each candidate hold (None: a new pose next)
            misfits = [self._misfit, *(c.misfit for c in self._candidates), *(o.misfit for o in origins)]
            state["pose_misfits"] = {
                "held": np.array([m is not None for m in misfits], dtype=np.int64),
                **{
                    field: np.array([getattr(m, field) for m in misfits if m is not None]).reshape(-1, *shape)
                    for field, shape in self._misfit_shapes().items()
                },
            }
        return state

    def _misfit_shapes(self) -> dict[str, tuple[int, ...]]:
        """The shapes of a :class:`_Misfit`'s arrays, as a checkpoint holds them."""
        m = self._m
        return {"inputs": (m,), "b": (m,), "P_xb": (self._n, m), "P_bb": (m, m)}

    def _import_misfits(self, state: dict) -> None:
        """The misfits :meth:`export_state` wrote, the filter's, its candidates' and their origins' (none: a new
        pose next)."""
        kept = state.get("pose_misfits")
        origins = self._origins()
        misfits: list[_Misfit | None] = [None] * (1 + len(self._candidates) + len(origins))
        if kept is not None and self._kappa > 0.0:
            # an older checkpoint's origins (the filter at the import) hold none
            saved = len(misfits) if "origin_of" in state.get("step_candidates", {}) else 1 + len(self._candidates)
            held = state_array(kept, "held", (saved,)).astype(bool)
            fields = {f: state_array(kept, f, (int(held.sum()), *shape)) for f, shape in self._misfit_shapes().items()}
            for row, k in enumerate(np.flatnonzero(held)):
                misfits[k] = _Misfit(*(values[row] for values in fields.values()))
        self._misfit = misfits[0]
        n_candidates = len(self._candidates)
        restored = [dataclasses.replace(o, misfit=m) for o, m in zip(origins, misfits[1 + n_candidates :], strict=True)]
        self._candidates = [
            dataclasses.replace(c, misfit=m, origin=restored[_index_of(c.origin, origins)])
            for c, m in zip(self._candidates, misfits[1 : 1 + n_candidates], strict=True)
        ]
        if self._change_origin is not None:
            self._change_origin = restored[0]

    def _import_origins(self, kept: dict, candidates: int) -> tuple[_Origin | None, list[_Origin]]:
        """``(the change's origin (None: no change goes on), each candidate's)`` from ``step_candidates`` (their
        misfits come with :meth:`_import_misfits`)."""
        if "origin_of" not in kept:  # an older checkpoint's: the candidates as begun from the filter restored
            f = self.filter
            return None, [_Origin(f.x.copy(), f.P.copy(), None, f.t_s, f.samples_used)] * candidates
        t = state_array(kept, "origin_t_s", np.shape(kept["origin_t_s"])).ravel()
        xs = state_array(kept, "origin_x", (len(t), self._n))
        Ps = state_array(kept, "origin_P", (len(t), self._n, self._n))
        used = state_array(kept, "origin_samples_used", (len(t),))
        origins = [_Origin(x, P, None, float(when), int(u)) for x, P, when, u in zip(xs, Ps, t, used, strict=True)]
        of = state_array(kept, "origin_of", (candidates,)).astype(int)
        if np.any((of < 0) | (of >= len(origins))):
            raise CalibError("estimator state: key 'step_candidates.origin_of': expected indices of origin rows")
        changing = bool(state_array(kept, "changing", ())) and len(origins) > 0
        return (origins[0] if changing else None), [origins[k] for k in of]

    def buffered_width(self) -> int | None:
        """Columns of the prepared samples it holds, or None while it holds none."""
        return self._buffer.prepared.shape[1] if len(self._buffer) else None

    def import_state(self, state: dict) -> None:
        """Restore :meth:`export_state`. Raises ``CalibError`` on a bad key or shape."""
        self.filter.import_state(state.get("filter", {}))
        self._x0 = state_array(state, "prior_mean", (self._n,))
        self.noise_scale2, self.walk_rate_mm2_per_s = state_array(state, "noise", (2,))
        if "scale_history" in state:
            history = state_array(state, "scale_history", np.shape(state["scale_history"]))
            if history.ndim != 2 or history.shape[1] != 3 or not len(history):
                raise CalibError("estimator state: key 'scale_history': expected rows of (time, scale, walk rate)")
            self._scale_history = deque((tuple(row) for row in history.tolist()), maxlen=SCALE_HISTORY)
        else:  # a checkpoint without the history (an older format): the scales in use from its first sample on
            self._scale_history = deque(
                [(-math.inf, self.noise_scale2, self.walk_rate_mm2_per_s)], maxlen=SCALE_HISTORY
            )
        if not (0.0 < self.noise_scale2 < math.inf and 0.0 <= self.walk_rate_mm2_per_s < math.inf):
            raise CalibError(
                "estimator state: key 'noise': expected a finite positive noise scale and a finite walk rate ≥ 0"
            )
        self._scale_sums = state_array(state, "scale_sums", (2,))
        if "scale_walk" in state:
            self._scale_walk = float(state_array(state, "scale_walk", ()))
        else:  # an older checkpoint: its sums as measured at the walk in use
            self._scale_walk = self._scale_sums[1] * _log_walk(self.walk_rate_mm2_per_s)
        started, self.recoveries, self._since_window, measured = (int(v) for v in state_array(state, "counters", (4,)))
        self.started, self.measured_noise = bool(started), bool(measured)
        if "recovery_counts" in state:  # a checkpoint of an older format counts none
            self.recovery_dropped, self.recovery_readmitted = (
                int(v) for v in state_array(state, "recovery_counts", (2,))
            )
        self.steps = int(state_array(state, "steps", ())) if "steps" in state else 0  # none before steps counted
        # an older checkpoint's run is counted from its first sample after this one
        self.first_t_s = float(state_array(state, "first_t_s", ())) if "first_t_s" in state else math.nan
        self.step_dropped, self.step_readmitted = (
            (int(v) for v in state_array(state, "step_counts", (2,))) if "step_counts" in state else (0, 0)
        )
        self._candidates, self._since_candidate, self.step_t_s = [], 0, math.nan
        self._last_inputs = np.zeros(0)
        self.payload_held, self.payload_released_t_s = False, math.nan  # an older checkpoint's was never held
        self._dispersions = deque(maxlen=DISPERSION_SAMPLES)
        if "step_candidates" in state:  # an older checkpoint has none: they start afresh
            kept = state["step_candidates"]
            rows = state_array(kept, "ratio_nis_taken", np.shape(kept.get("ratio_nis_taken", ())))
            if rows.ndim != 2 or rows.shape[1] != 5:
                raise CalibError(
                    "estimator state: key 'step_candidates.ratio_nis_taken': expected rows of (ratio, NIS, "
                    "samples taken, readmitted, time)"
                )
            xs = state_array(kept, "x", (len(rows), self._n))
            Ps = state_array(kept, "P", (len(rows), self._n, self._n))
            self._change_origin, origins = self._import_origins(kept, len(rows))
            # an older checkpoint's: every sample counted as evidence
            flags = state_array(kept, "at_start", (len(rows), 4)) if "at_start" in kept else np.zeros((len(rows), 4))
            self._candidates = [
                _Candidate(
                    x,
                    P,
                    float(r),
                    float(q),
                    int(k),
                    int(a),
                    float(t),
                    origin,
                    at_start=bool(g[0]),
                    at_new_pose=bool(g[1]),
                    refused_last=bool(g[2]),
                    start_ratio=float(g[3]),
                )
                for x, P, (r, q, k, a, t), origin, g in zip(xs, Ps, rows, origins, flags, strict=True)
            ]
            self._since_candidate = int(state_array(kept, "since", ()))
            self.step_t_s = float(state_array(kept, "last_step_t_s", ()))
            dispersions = state_array(kept, "dispersions", np.shape(kept.get("dispersions", ())))
            self._dispersions = deque(dispersions.ravel().tolist(), maxlen=DISPERSION_SAMPLES)
            if "payload_held" in kept:
                held, self.payload_released_t_s = state_array(kept, "payload_held", (2,))
                self.payload_held = bool(held) and self._step_factors is not None
            if "last_inputs" in kept:  # an older checkpoint's: a new pose next
                self._last_inputs = state_array(kept, "last_inputs", np.shape(kept["last_inputs"])).ravel()
        self._buffer.import_state(state)
        self._windows = deque(maxlen=WALK_HISTORY)
        if "walk_windows" in state:  # an older checkpoint has none: its rate measured afresh from the next windows
            kept = state["walk_windows"]
            times = state_array(kept, "t_s", np.shape(kept.get("t_s", ())))
            if times.ndim != 2 or times.shape[1] != 2:
                raise CalibError("estimator state: key 'walk_windows.t_s': expected rows of (first, last) sample times")
            xs = state_array(kept, "x", (len(times), self._n))
            Ps = state_array(kept, "P", (len(times), self._n, self._n))
            begins = state_array(kept, "begins", (len(times),))
            for x, P, (first_t, last_t), begin in zip(xs, Ps, times, begins, strict=True):
                self._windows.append((x, P, float(first_t), float(last_t), bool(begin)))
        window = state.get("window")
        if window is None:
            self._last_window = None
        else:  # an older checkpoint, without first_t_s: the window as an instant at its end
            last_t = float(state_array(window, "t_s", ()))
            first_t = float(state_array(window, "first_t_s", ())) if "first_t_s" in window else last_t
            self._last_window = (
                state_array(window, "x", (self._n,)),
                state_array(window, "P", (self._n, self._n)),
                first_t,
                last_t,
            )
        self._import_misfits(state)


def _walk_directions(
    spread: np.ndarray, walks: np.ndarray, difference: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A window difference ``d ~ N(0, S + q T W)`` (``S`` the windows' spread, ``W`` the walk per unit
    rate, ``unit_Q``) as independent terms of the walk test: the directions ``g_i`` that diagonalise
    both, ``g_iᵀ S g_i = λ_i`` and ``g_iᵀ W g_i = 1``, so that ``(g_iᵀ d)² ~ (λ_i + q T) χ²₁``. Returns
    ``(λ (n,), g (n, n) as columns, (g_iᵀ d)² (n,))``, padded with ``λ = 0`` where a direction says
    nothing of the walk: held by the gauge (``S`` singular) or not walking (``W`` singular there —
    an instrument's frame, which does not walk, is the best determined direction of all, and
    taken for one that walks it rejected a matched rate: honesty study, motion capture at 0.2× the
    noise, the walk lowered from 2 to 0.02 µm/√s).

    ``walks`` is ``W``, or the mask of the unknowns that walk where ``W`` is the identity on them and 0
    elsewhere: then the part of ``d`` the walk moves is ``d_A − S_AB S_BB⁺ d_B`` (A those that walk,
    B the rest), of covariance ``S_A|B + q T I``, and one eigendecomposition of ``S_A|B`` gives the
    directions (an elastic drive's compliance does not walk: the general way's two of 48 × 48 cost
    ~0.3 s of ``calibrate ekf``'s 4.6 at 10⁵ samples)."""
    n = len(spread)
    lam, projection2, directions = np.zeros(n), np.zeros(n), np.zeros((n, n))
    if walks.dtype == bool:
        A, B = np.flatnonzero(walks), np.flatnonzero(~walks)
        if len(B):
            # g = [u; −S_BB⁺ S_BA u]: gᵀ d = uᵀ (d_A − S_AB S_BB⁺ d_B), gᵀ S g = uᵀ S_A|B u
            regression = np.linalg.pinv(spread[np.ix_(B, B)], hermitian=True) @ spread[np.ix_(B, A)]
            conditional = spread[np.ix_(A, A)] - spread[np.ix_(A, B)] @ regression
        else:  # every unknown walks (a drive's own): S itself, without an empty block's pinv (~40 µs a window)
            regression, conditional = np.zeros((0, n)), spread
        eigenvalues, vectors = np.linalg.eigh(0.5 * (conditional + conditional.T))
        informative = eigenvalues > 1e-12 * max(eigenvalues.max(initial=0.0), 1e-300)
        k = int(informative.sum())
        directions[A, :k] = vectors[:, informative]
        directions[B, :k] = -regression @ vectors[:, informative]
        lam[:k] = eigenvalues[informative]
    else:
        eigenvalues, vectors = np.linalg.eigh(spread)
        free = eigenvalues > 1e-12 * eigenvalues.max()
        whiten = vectors[:, free] / np.sqrt(eigenvalues[free])  # columns z with zᵀ S z = 1
        walk_share, rotation = np.linalg.eigh(whiten.T @ walks @ whiten)
        walking = walk_share > 1e-12 * max(walk_share.max(initial=0.0), 1e-300)
        k = int(walking.sum())
        directions[:, :k] = whiten @ rotation[:, walking] / np.sqrt(walk_share[walking])
        lam[:k] = 1.0 / walk_share[walking]
    projection2[:k] = (directions[:, :k].T @ difference) ** 2
    return lam, directions, projection2


def _log_walk(rate_mm2_per_s: float) -> float:
    """``log`` of a walk rate [mm²/s]; a rate of 0 (none configured, none measured) at the smallest double."""
    return math.log(max(rate_mm2_per_s, 5e-324))


def _memory_walk(sums: np.ndarray, walk_sum: float) -> float:
    """The walk rate [mm²/s] the windows of the scale ``sums`` were measured at: the geometric mean of
    theirs, weighted as the sums weigh them (``walk_sum``, Σ redundancy · log rate)."""
    return math.exp(walk_sum / sums[1])


def _differences(windows) -> int:
    """The walk test's window differences: successive windows within each run of windows."""
    return sum(1 for k, window in enumerate(windows) if k > 0 and not window[4])


def _window_terms(run: list, walks: np.ndarray, step_index: int | None) -> tuple[np.ndarray, np.ndarray]:
    """A run of ``K`` windows of the walk test (``(x, P, first t, last t, …)``, in time order) as the
    independent terms ``p_j ~ (λ_j + q) χ²₁`` of the walk rate's likelihood, every window against every
    other one: a stationary excess of the windows over their ``P_w`` (the same misfit, seen through each
    window's poses) moves windows far apart in time no more than neighbours, a walk of rate ``q`` moves
    them by ``q`` times their distance, so only spread that keeps growing with the time apart raises ``q``.

    Along the directions ``g_i`` that diagonalise the windows' mean spread and the walk
    (:func:`_walk_directions`, ``g_iᵀ W g_i = 1``), the window estimates ``y_w = g_iᵀ x_w`` are a walk's
    values at the windows plus errors of variance ``v_wi = g_iᵀ P_w g_i``; each window is an instant at
    its last sample (:meth:`RobustFilter._walk_difference`; so is an older checkpoint's, which spans its
    samples). Any ``K − 1`` contrasts of the ``y_w`` (free of the unknown mean) give the same terms, those
    of the pencil of their walk covariance and their error covariance; :func:`_contrast_terms` takes the
    successive differences, whose walk covariance is diagonal. Successive windows alone (the windows'
    neighbours) see a walk over one window's span; the runs' far pairs over the whole of it."""
    xs = np.array([w[0] for w in run])
    Ps = np.array([w[1] for w in run])
    times = np.array([w[3] for w in run], dtype=float)
    if step_index is not None:  # it steps, it does not walk: its marginal left out
        xs[:, step_index] = 0.0
        Ps[:, step_index, :], Ps[:, :, step_index] = 0.0, 0.0
    lam, directions, _ = _walk_directions(Ps.mean(axis=0), walks, np.zeros(xs.shape[1]))
    g = directions[:, lam > 0.0]
    y = xs @ g  # (K, k)
    # a window's own variance along the mean's directions, kept off 0 where its P is singular there
    v = np.maximum(np.einsum("wni,ni->wi", Ps @ g, g), 1e-9 * lam[lam > 0.0])
    terms_lam, terms_p = np.empty((g.shape[1], len(run) - 1)), np.empty((g.shape[1], len(run) - 1))
    if not _contrast_terms(times, v, y, terms_lam, terms_p):
        raise np.linalg.LinAlgError("walk test: the window contrasts' eigenvalues did not converge")
    # a term 10¹² times less sure of the walk than the surest says nothing (and λ = ∞, of windows at one instant)
    informative = terms_lam < 1e12 * terms_lam.min(initial=math.inf)
    return terms_lam[informative], terms_p[informative]


#: QL sweeps of one eigenvalue of a window run's contrasts before :func:`_contrast_terms` gives up (LAPACK's)
_QL_ITERATIONS = 30


@njit(entry=(F8_1, F8_2, F8_2, F8_2, F8_2), nogil=True, error_model="numpy")
def _contrast_terms(
    times_s: np.ndarray, variances: np.ndarray, estimates: np.ndarray, lam: np.ndarray, p: np.ndarray
) -> bool:
    """The walk test's terms of a run of ``K`` windows (:func:`_window_terms`), direction by direction:
    for each column ``i`` of ``variances`` and ``estimates`` (``(K, k)``: the windows' ``v_wi`` and
    ``y_wi``, the windows instants at ``times_s``, non-decreasing [s]), the ``K − 1`` terms
    ``p_j ~ (λ_j + q) χ²₁`` into ``lam[i]`` and ``p[i]``, in no particular order. Returns False where
    the QL iteration does not converge (:data:`_QL_ITERATIONS`).

    A walk's increments between the windows are independent: the successive differences
    ``d_j = y_{j+1} − y_j`` have the walk covariance ``q Δ``, ``Δ = diag(t_{j+1} − t_j)``, and an error
    covariance ``E`` that is tridiagonal (``v_j + v_{j+1}`` on its diagonal, ``−v_{j+1}`` beside it).
    Scaled by ``Δ^(−1/2)`` the walk is white, so the eigenvalues ``ν_j`` of the tridiagonal
    ``Δ^(−1/2) E Δ^(−1/2)`` and the scaled differences along its eigenvectors, ``c_j ~ N(0, ν_j + q)``,
    are the terms: ``λ_j = ν_j``, ``p_j = c_j²`` (:func:`_tridiagonal_ql`). Windows at one instant (a
    log's repeated times) are one window of their inverse-variance mean, and their contrast, which no
    walk moves, is a term ``λ = ∞``, ``p = 0``."""
    K, k = variances.shape
    t, mean, variance = np.empty(K), np.empty((K, k)), np.empty((K, k))
    n = 0  # the last instant's index: n contrasts
    t[0], mean[0], variance[0] = times_s[0], estimates[0], variances[0]
    for a in range(1, K):
        if times_s[a] > t[n]:
            n += 1
            t[n], mean[n], variance[n] = times_s[a], estimates[a], variances[a]
        else:
            for i in range(k):
                precision = 1.0 / variance[n, i] + 1.0 / variances[a, i]
                mean[n, i] = (mean[n, i] / variance[n, i] + estimates[a, i] / variances[a, i]) / precision
                variance[n, i] = 1.0 / precision
    gap = t[1 : n + 1] - t[:n]
    root_gap = np.sqrt(gap)
    d, e, c = np.zeros((K, k)), np.zeros((K, k)), np.zeros((K, k))
    for j in range(n):
        for i in range(k):
            d[j, i] = (variance[j, i] + variance[j + 1, i]) / gap[j]
            c[j, i] = (mean[j + 1, i] - mean[j, i]) / root_gap[j]
            if j + 1 < n:
                e[j, i] = -variance[j + 1, i] / (root_gap[j] * root_gap[j + 1])
    for i in range(k):
        # QL deflates from the top and converges in fewer sweeps with the large entries at the bottom
        # (as LAPACK's dsteqr chooses between QL and QR): reversed where they lie at the top
        if n > 1 and abs(d[0, i]) > abs(d[n - 1, i]):
            d[:n, i], c[:n, i] = d[:n, i][::-1].copy(), c[:n, i][::-1].copy()
            e[: n - 1, i] = e[: n - 1, i][::-1].copy()
    if n > 0 and not _tridiagonal_ql(d, e, c, n):
        return False
    for i in range(k):
        for j in range(K - 1):
            lam[i, j], p[i, j] = (d[j, i], c[j, i] * c[j, i]) if j < n else (math.inf, 0.0)
    return True


@njit(nogil=True, error_model="numpy")
def _tridiagonal_ql(d: np.ndarray, e: np.ndarray, y: np.ndarray, n: int) -> bool:
    """Eigenvalues of ``k`` symmetric tridiagonal ``n × n`` matrices, the columns of the diagonals ``d``
    and off-diagonals ``e`` (``(≥ n, k)``: ``e[j]`` between ``j`` and ``j + 1``, ``e[n − 1]`` unused),
    into ``d``, by implicit QL with Wilkinson's shift, each rotation applied to ``y``'s column, so that
    it ends as ``Zᵀ y`` (``Z`` the eigenvectors). False where an eigenvalue takes more than
    :data:`_QL_ITERATIONS` sweeps.

    Each matrix takes the rotations it takes alone, in its own order; the ``k`` matrices' sweeps are
    interleaved, a rotation of each in turn: a rotation waits on the last one's square root and
    division, and a matrix swept alone spent most of its time waiting (~7 µs a 15 × 15 matrix)."""
    k = d.shape[1]
    low, end, iterations = np.zeros(k, np.int64), np.zeros(k, np.int64), np.zeros(k, np.int64)
    s, c, p, g = np.empty(k), np.empty(k), np.empty(k), np.empty(k)
    sweeping = np.zeros(k, np.bool_)
    e[n - 1] = 0.0
    while True:
        longest = 0
        for i in range(k):  # each matrix's next sweep: from low to the first negligible off-diagonal
            sweeping[i] = False
            while low[i] < n:
                m = low[i]
                while m < n - 1:
                    dd = abs(d[m, i]) + abs(d[m + 1, i])
                    if abs(e[m, i]) + dd == dd:
                        break
                    m += 1
                if m != low[i]:
                    break
                low[i] += 1  # its eigenvalue there has converged
                iterations[i] = 0
            if low[i] == n:
                continue
            if iterations[i] == _QL_ITERATIONS:
                return False
            iterations[i] += 1
            top = low[i]
            shift = (d[top + 1, i] - d[top, i]) / (2.0 * e[top, i])
            r = math.hypot(shift, 1.0)
            g[i] = d[m, i] - d[top, i] + e[top, i] / (shift + math.copysign(r, shift))
            s[i], c[i], p[i] = 1.0, 1.0, 0.0
            end[i], sweeping[i] = m, True
            longest = max(longest, m - top)
        if longest == 0:
            return True
        for step in range(longest):
            for i in range(k):
                j = end[i] - 1 - step
                if not sweeping[i] or j < low[i]:
                    continue
                f, b, chased = s[i] * e[j, i], c[i] * e[j, i], g[i]
                r = math.sqrt(
                    f * f + chased * chased
                )  # no overflow: the entries are O(the windows' σ² over their gaps)
                e[j + 1, i] = r
                if r == 0.0:  # underflow: the matrix splits here, and its next sweep starts afresh
                    d[j + 1, i] -= p[i]
                    e[end[i], i] = 0.0
                    sweeping[i] = False
                    continue
                sine, cosine = f * (1.0 / r), chased * (1.0 / r)
                shifted = d[j + 1, i] - p[i]
                r = (d[j, i] - shifted) * sine + 2.0 * cosine * b
                rotated = sine * r
                d[j + 1, i] = shifted + rotated
                g[i], s[i], c[i], p[i] = cosine * r - b, sine, cosine, rotated
                f, h = y[j + 1, i], y[j, i]
                y[j + 1, i] = sine * h + cosine * f
                y[j, i] = cosine * h - sine * f
        for i in range(k):
            if sweeping[i]:
                d[low[i], i] -= p[i]
                e[low[i], i] = g[i]
                e[end[i], i] = 0.0


@dataclass(frozen=True)
class _Candidate:
    """A candidate step of :class:`RobustFilter`'s ``step`` unknown (:meth:`RobustFilter._test_steps`)."""

    x: np.ndarray
    P: np.ndarray
    ratio: float  #: log-likelihood ratio against the filter over the samples after the one it began at
    nis: float  #: NIS of its last sample
    taken: int  #: samples it took after the one it began at
    readmitted: int  #: samples it took that the filter refused, its first included
    t_s: float  #: the time of the sample it began at: where the step happened
    origin: _Origin  #: the filter it began from
    misfit: _Misfit | None = None  #: the misfit at the pose it holds (``pose_misfit``)
    at_start: bool = False  #: still at the pose it began at (``pose_misfit``)
    #: that pose's misfit unknown to the filter it began from: there the step and the misfit are one unknown, and
    #: the ratio of the pose's samples is withheld (``start_ratio``) until the candidate has left the pose
    at_new_pose: bool = False
    refused_last: bool = False  #: it refused the last sample it saw, as the filter did
    start_ratio: float = 0.0  #: the ratio withheld at its start pose (``at_new_pose``); 0 once it has left it


def _index_of(origin: _Origin, origins: list[_Origin]):
    """The index of ``origin`` itself (not an equal one: candidates share the object) in ``origins``, or None."""
    return next((k for k, o in enumerate(origins) if o is origin), None)


@dataclass(frozen=True)
class _Origin:
    """The filter a candidate step began from (:meth:`RobustFilter._test_steps`): the filter before the sample it
    began at, or, while a step taken may still go on, before the sample that step began at."""

    x: np.ndarray
    P: np.ndarray
    misfit: _Misfit | None  #: at the pose it held (``pose_misfit``)
    t_s: float  #: the time of its last sample (NaN before any)
    samples_used: int


@dataclass(frozen=True)
class _Misfit:
    """The instrument's misfit at a pose the platform holds (:class:`RobustFilter`'s ``pose_misfit``) as the
    samples taken there leave it (:meth:`RobustFilter._misfit_step`)."""

    inputs: np.ndarray  #: the first inputs (strokes) of the pose
    b: np.ndarray  #: its mean (m,) [the observation's units]
    P_xb: np.ndarray  #: its covariance with the state (n, m)
    P_bb: np.ndarray  #: its covariance (m, m)


class _Likelihood(NamedTuple):
    nis: float  #: νᵀ S⁻¹ ν
    value: float  #: log N(ν; 0, S)


def _log_likelihood(nu: np.ndarray, S: np.ndarray) -> _Likelihood:
    """An innovation's NIS and Gaussian log-density under its covariance ``S`` (Cholesky; −inf where
    ``S`` is not positive definite)."""
    try:
        L = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        return _Likelihood(math.inf, -math.inf)
    w = np.linalg.solve(L, nu)
    nis = float(w @ w)
    return _Likelihood(nis, -0.5 * (nis + len(nu) * math.log(2.0 * math.pi)) - float(np.sum(np.log(np.diag(L)))))


def _mahalanobis2(step: np.ndarray, P: np.ndarray, gauge_projector: np.ndarray | None) -> float:
    """``stepᵀ P⁺ step``: a step's size in the covariance's σ. With gauge rows ``C`` (``C P = 0``,
    ``C step = 0``), ``P`` is singular along ``Cᵀ``: adding a multiple of the projector onto them
    makes it invertible without touching the free directions, where the step lies (one LU
    solve; an eigendecomposition costs ~100× more on a shared machine)."""
    if gauge_projector is not None:
        P = P + np.trace(P) / len(P) * gauge_projector
    return float(step @ np.linalg.solve(P, step))


@njit(nogil=True, error_model="numpy")
def _walk_deviance(lam: np.ndarray, p: np.ndarray, q: float) -> float:
    """``−2 L(q)`` of the walk test's terms (see ``RobustFilter._pooled_walk_rate``) up to a constant:
    ``Σ log a + p / a``, ``a = λ + q``, over the terms with ``λ > 0`` (``λ = 0``: padding, no information
    either way)."""
    deviance = 0.0
    for j in range(lam.shape[0]):
        if lam[j] <= 0.0:
            continue
        a = lam[j] + q
        deviance += math.log(a) + p[j] / a
    return deviance


@njit(nogil=True, error_model="numpy")
def _walk_slope(lam: np.ndarray, p: np.ndarray, q: float) -> float:
    """``−2 dL/dq`` of the terms of :func:`_walk_deviance`: ``Σ (a − p) / a²``, apart from it (the root's
    bisection needs no logarithm)."""
    slope = 0.0
    for j in range(lam.shape[0]):
        if lam[j] <= 0.0:
            continue
        a = lam[j] + q
        slope += (a - p[j]) / (a * a)
    return slope


@njit(nogil=True, error_model="numpy")
def _narrowed(low: float, high: float) -> float:
    """The next bisection point of ``[low, high]``: geometric once ``low > 0`` (rates span decades),
    three decades down from ``high`` while it is 0."""
    return math.sqrt(low * high) if low > 0.0 else 1e-3 * high


@njit(entry=(F8_1, F8_1, FLOAT, FLOAT, FLOAT), nogil=True, error_model="numpy")
def _walk_rate_in_use(lam: np.ndarray, p: np.ndarray, configured: float, lowering: float, raising: float) -> float:
    """``configured`` where its deviance ``2 (L(q̂) − L(q))`` is at most ``lowering`` (it lies above the
    maximum-likelihood rate ``q̂``) or ``raising`` (below it); else, above, the rate ``q ≥ 0`` [mm²/s]
    nearest ``configured`` within that bound, below, ``q̂`` (χ²₁ quantiles: ``RobustFilter._pooled_walk_rate``)
    — of the independent terms ``p_j ~ (λ_j + q) χ²₁`` (:func:`_window_terms`). ``q̂`` is the root of the
    score between 0 and the largest single term's own root ``p − λ``, above which every term falls; the
    bound the deviance's root between ``q̂`` and ``configured``; all by bisection (compiled: called once a
    window on a few hundred terms)."""
    upper = 0.0
    for j in range(lam.shape[0]):
        if lam[j] > 0.0 and p[j] > lam[j]:
            upper = max(upper, p[j] - lam[j])
    best = 0.0
    if upper > 0.0 and _walk_slope(lam, p, 0.0) < 0.0:  # L still rises at q = 0
        low, high = 0.0, upper
        for _ in range(WALK_BISECTIONS):
            middle = _narrowed(low, high)
            if _walk_slope(lam, p, middle) < 0.0:
                low = middle
            else:
                high = middle
            if high - low <= WALK_RELATIVE_WIDTH * high:
                break
        best = 0.5 * (low + high)
    at_best = _walk_deviance(lam, p, best)
    lowered = configured >= best  # the configured rate is tested as too large, else as too small
    bound = lowering if lowered else raising
    if _walk_deviance(lam, p, configured) - at_best <= bound:
        return configured
    if not lowered:  # raised: the data's own rate (see RobustFilter._pooled_walk_rate)
        return best
    # the deviance rises from 0 at q̂ to beyond the bound at the configured rate
    low, high = best, configured
    for _ in range(WALK_BISECTIONS):
        middle = _narrowed(low, high)
        if _walk_deviance(lam, p, middle) - at_best <= bound:
            low = middle
        else:
            high = middle
        if high - low <= WALK_RELATIVE_WIDTH * high:
            break
    return low


def _stacked(observations: list, m: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(ν (K, M), H (K, M, n), R0 (K, M, M))`` of observations of up to ``M`` rows (at least ``m``),
    each padded with ``ν = 0``, ``H = 0`` and an identity block of ``R0`` (so any quadratic form
    ``νᵀ (s² R0 + H P Hᵀ)⁻¹ ν`` is unchanged); a missing one (None) is all padding."""
    size = max([m, *(len(o[0]) for o in observations if o is not None)])
    nu, H = np.zeros((len(observations), size)), np.zeros((len(observations), size, n))
    R0 = np.broadcast_to(np.eye(size), (len(observations), size, size)).copy()
    for k, observation in enumerate(observations):
        if observation is not None:
            rows = len(observation[0])
            nu[k, :rows], H[k, :rows], R0[k, :rows, :rows] = observation
    return nu, H, R0


class _SampleWindow:
    """The last ``capacity`` samples, oldest first.

    The arrays are twice ``capacity`` long and the live rows ``[span[0], span[1])`` a view into them:
    an append writes one row, and every ``capacity`` appends the rows slide back to the front
    (amortised O(1), where concatenating costs ~50 µs a sample); :func:`~.kalman.window_append`, which
    the compiled recursion runs too.
    """

    def __init__(self, capacity: int):
        self.capacity = capacity
        self._allocate(0)

    def _allocate(self, width: int) -> None:
        size = 2 * self.capacity
        self._t, self._prepared, self._gated = np.zeros(size), np.zeros((size, width)), np.zeros(size, dtype=bool)
        self._span = np.zeros(2, dtype=np.int64)

    def __len__(self) -> int:
        return int(self._span[1] - self._span[0])

    t = property(lambda self: self._t[self._span[0] : self._span[1]], doc="(K,) sample times [s]")
    prepared = property(lambda self: self._prepared[self._span[0] : self._span[1]], doc="(K, width) prepared samples")
    gated = property(lambda self: self._gated[self._span[0] : self._span[1]], doc="(K,) bool, writable: left out")

    def holds(self, width: int) -> bool:
        """Its rows are ``width`` wide (fixed by the first sample)."""
        return self._prepared.shape[1] == width

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The whole storage ``(t, prepared, gated)``, for a compiled append (with :meth:`span`)."""
        return self._t, self._prepared, self._gated

    def span(self) -> np.ndarray:
        """A copy of ``[start, end)`` of the live rows in :meth:`arrays`."""
        return self._span.copy()

    def clear(self) -> None:
        """Let every sample go (the width stays)."""
        self._span[0] = self._span[1]

    def set_span(self, span: np.ndarray) -> None:
        self._span[:] = span

    def append(self, t_s: float, prepared: np.ndarray, gated: bool) -> None:
        """Keep one sample, dropping the oldest beyond ``capacity``."""
        if self._prepared.shape[1] != prepared.shape[0]:
            self._allocate(prepared.shape[0])  # the first sample fixes the width
        window_append(self._t, self._prepared, self._gated, self._span, float(t_s), prepared, bool(gated))

    def export_state(self) -> dict:
        return {
            "buffer_t": self.t.copy(),
            "buffer_prepared": self.prepared.copy(),
            "buffer_gated": self.gated.astype(np.int64),
        }

    def import_state(self, state: dict) -> None:
        """Restore :meth:`export_state`. Raises ``CalibError`` on a bad key or shape."""
        t = state_array(state, "buffer_t", np.shape(state.get("buffer_t", ())))
        prepared = np.array(state.get("buffer_prepared", np.zeros((0, 0))), dtype=float)
        if t.ndim != 1 or prepared.ndim != 2 or len(prepared) != len(t) or len(t) > self.capacity:
            raise CalibError(
                "estimator state: keys 'buffer_t', 'buffer_prepared': expected one row per buffered sample"
            )
        self._allocate(prepared.shape[1])
        self._span[1] = len(t)
        self._t[: len(t)], self._prepared[: len(t)] = t, prepared
        self._gated[: len(t)] = state_array(state, "buffer_gated", (len(t),)).astype(bool)
