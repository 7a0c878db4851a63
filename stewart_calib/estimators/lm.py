"""``lm``: the factor graph of :mod:`.graph` solved in batch by Levenberg–Marquardt.

The gold standard for ``isam2``: it builds the same factors; with random walk 0 it uses one
parameter variable for the whole log (the exact constant-parameter problem), which ``isam2``
approximates with its near-hard chain. With a walk (and ``[robust] adapt_noise``) its rate is the
one ``isam2``'s front end measures on the same samples, not the configured one taken as given.

The solve takes full Gauss–Newton steps on gtsam's own linearisation while each one lowers the
cost, stops where a step changes it by less than a relative 1e-10 either way (or raises it where its
own linear model predicts a decrease below :data:`PREDICTED_TOLERANCE`: round-off, at the optimum), and
hands over to gtsam's ``LevenbergMarquardtOptimizer`` (multifrontal QR) at the first step that raises it
by more (or whose linear system Cholesky cannot solve). On a well-started graph GN
converges in 3–4 steps; gtsam's optimiser reaches the same optimum (to 1e-9 of the cost) but
takes ~3.4× the time on 500 samples (after convergence it keeps raising λ, an error evaluation of
every Python factor each time), which puts ``lm`` on a 10⁴–10⁵-sample log out of reach.

Gross errors: after each solve, every sample's measurement factors are tested together — their
χ² at the optimum against the gate's quantile (``[isam2] gate_probability``, the gate ``isam2``'s
front end applies) at the sample's share of the residual degrees of freedom, at a robust (median)
noise scale — and the samples beyond it are left out (:meth:`BatchLM.estimate`), as ``ekf``'s and
``isam2``'s gates leave them out. Kept in, a 5 % rate of 0.5 mm glitches put ``lm`` 4–50× its
Cramér–Rao bound from the truth, and its variance factor, inflated by them, could not make its
error bars honest where the glitches pulled (NEES in band in 1–3 of 5 drifting motion-capture
runs, sweep ``configs/sweeps/honesty.toml``).
"""

from __future__ import annotations

import dataclasses
import math

import gtsam
import numpy as np

from ..chi_square import chdtri
from ..config import EstimatorConfig
from ..errors import CalibError, SampleRejected, number
from ..estimate import Estimate
from ..factors import random_walk
from ..model.platform import Platform
from ..samples import Sample
from .base import BufferedFit, late_index
from .ekf import LegEKF
from .graph import ChainState, GraphBuilder, first_paragraph, params_key, pose_key
from .measurement import registered_start
from .robust import WALK_RAISING


class BatchLM(BufferedFit):
    """Batch Levenberg–Marquardt on the same graph: the gold standard for ``isam2``.

    :meth:`update` appends the sample's factors; :meth:`estimate` solves the whole graph
    (warm-started from the previous solution). With random walk 0 there is one parameter
    variable; otherwise the same chain of windows as ``isam2``, and the estimate is the last.
    """

    name = "lm"

    def __init__(self, platform: Platform, config: EstimatorConfig):
        self._config = config
        self._builder = GraphBuilder(platform, config, chain=config.noise.random_walk_mm_per_sqrt_s > 0)
        # The walk's rate from the data, as isam2's front end measures it for the same graph: the
        # configured rate unless the window differences reject it at 5 % either way. Taken as given, a
        # robot that stood still was fitted as one that walked at 1 µm/√s, and the last window's
        # estimate stood on its last seconds: 1.4–3.1 µm closed loop at 0 and 40 kg where isam2 and
        # ekf left 0.4–1.1 (benchmarks.elastic --geometry-seed 3 and 4, 3 noise seeds each).
        # Its cost: ~2 ms a sample, lm's CPU on the check's 900 samples 9.2 → 11.1 s.
        self._front: LegEKF | None = None
        if self._builder.chain and config.robust.adapt_noise:
            elastic = platform.elastic
            self._front = LegEKF(
                platform
                if elastic is None
                else dataclasses.replace(platform, elastic=dataclasses.replace(elastic, payload_sigma_kg=0.0)),
                dataclasses.replace(
                    config, ekf=dataclasses.replace(config.ekf, gate_probability=config.isam2.gate_probability)
                ),
            )
            self._front.robust.walk_lowering = WALK_RAISING
        self._walk_rate: float | None = None  # the walk factors' rate [mm²/s]; None: the configured one
        self._graph = gtsam.NonlinearFactorGraph()
        self._values = gtsam.Values()
        self._state = ChainState()
        self._solved: Estimate | None = None
        #: ``(index in the graph, window, Δt [s])`` of every walk factor (:meth:`_solve_scaled`)
        self._walk_factors: list[tuple[int, int, float]] = []
        self._walk_scale2 = 1.0  # the measurement scale the walk factors and the prior carry
        #: ``(t_s, index of its pose variable, indices of its measurement factors)`` of every sample
        #: in the graph (:meth:`_leave_out_gross_errors`)
        self._measurements: list[tuple[float, int, list[int]]] = []
        self._late: list[SampleRejected] = []  # samples the test has left out, not yet reported
        self._prior_index: int | None = None  # the prior factor on the first parameter variable
        self._noise_scale: float | None = None
        self._prior_sigma2 = self._builder.layout.prior_sigma(self._builder.drive.prior_sigmas(config.noise)) ** 2
        # the walk rows a parameter variable's gauge constraint pins (see _variance_factor)
        walks = self._builder.layout.walks()
        gauge = self._builder.layout.gauge_rows(platform.drive)
        self._pinned_walk_rows = int(np.linalg.matrix_rank(gauge[:, walks])) if len(gauge) else 0
        #: ``(index in the fitted samples, SampleRejected)`` of samples :meth:`fit` skipped.
        self.rejected: list[tuple[int, SampleRejected]] = []

    def fit(self, samples) -> Estimate:
        """Register the instrument on ``samples`` where its kind asks for it (its unknowns then start
        from the registration, not a nominal frame far off), then fit them all."""
        samples = list(samples)
        if self._state.samples == 0:
            builder = self._builder
            builder.initial = registered_start(
                builder.platform, self._config.noise, builder.model, builder.layout, samples
            )
        times = [sample.t_s for sample in samples]
        estimate = super().fit(samples)
        self.rejected.extend((late_index(times, late.t_s), late) for late in self.take_late_rejections())
        return estimate

    def take_late_rejections(self) -> list[SampleRejected]:
        """The samples the gross-error test of :meth:`estimate` has left out (each once)."""
        late, self._late = self._late, []
        return late

    def _last_params(self) -> np.ndarray:
        return self._values.atVector(params_key(self._state.window))

    def update(self, sample: Sample) -> None:
        """Append one sample's factors (solved at the next :meth:`estimate`).

        Raises:
            SampleRejected: see :meth:`GraphBuilder.epoch`; the estimator is unchanged.
        """
        epoch = self._builder.epoch(self._state, sample, self._last_params, self._walk_scale2)
        if epoch.state.window != self._state.window:  # its first factor is the walk to the new window
            dt_s = sample.t_s - self._state.window_start_s
            self._walk_factors.append((self._graph.size(), self._state.window, dt_s))
        first, x = self._graph.size(), pose_key(self._state.samples)
        if self._state.samples == 0:
            self._prior_index = first + next(  # the parameters' prior, not a pose misfit's
                j
                for j in range(epoch.factors.size())
                if isinstance(epoch.factors.at(j), gtsam.PriorFactorVector)
                and params_key(0) in epoch.factors.at(j).keys()
            )
        measured = [first + j for j in range(epoch.factors.size()) if x in epoch.factors.at(j).keys()]
        self._measurements.append((sample.t_s, x, measured))
        self._graph.push_back(epoch.factors)
        self._values.insert(epoch.values)
        self._state = epoch.state
        self._solved = None
        if self._front is not None:
            try:
                self._front.update(sample)
            except SampleRejected:  # the graph's own gross-error test decides what lm leaves out
                pass

    def estimate(self) -> Estimate:
        """Solve by LM; δM of the last parameter variable and its ``gtsam.Marginals`` covariance."""
        if self._state.samples == 0:
            return self._builder.prior_estimate(self.name)
        if self._solved is None:
            p = params_key(self._state.window)
            scale2 = self._solve_scaled()
            for _ in range(MAX_GROSS_ERROR_PASSES if self._builder.graph.gate_probability > 0.0 else 0):
                if not self._leave_out_gross_errors():
                    break
                scale2 = self._solve_scaled()
            covariance = _marginal_covariance(self._graph, self._values, p)
            if self._config.robust.adapt_noise:
                covariance = covariance * scale2
            covariance = covariance + self._builder.window_walk_covariance(self._state, self._walk_rate)
            self._solved = Estimate.of_state(
                self._values.atVector(p),
                covariance,
                self._builder.layout,
                self.name,
                len(self._measurements),  # the samples the gross-error test left out are not used
                self._state.last_t_s,
            )
        return self._solved

    def noise_scale(self) -> float | None:
        """The measurement noise the last solve found in the data as a multiple of the configured σ
        (``√s²``, :meth:`_variance_factor`); None before a solve, with fixed noise, or where the graph
        has too little redundancy to tell."""
        return self._noise_scale

    def _solve_scaled(self) -> float:
        """Solve the graph; with noise adaptation, the variance factor ``s²`` it returns, the graph's
        walk factors carried at ``Q / s²`` and its prior at ``P0 / s²`` until ``s²`` settles.

        The measurement factors keep the configured noise ``R0``; a graph of ``R0``, ``Q / s²`` and
        ``P0 / s²`` is that of ``s² R0``, ``Q`` and ``P0`` divided by ``s²`` (the same optimum), so
        ``s²`` × its marginal is the covariance of noise ``s² R0``, walk ``Q`` and prior ``P0``, and its
        variance factor is ``s²`` at the fixed point. Scaling the marginal of the graph of ``R0``, ``Q``
        and ``P0`` scaled the walk's and the prior's shares too: NEES 1.5–2.6× its degrees of freedom on
        drifting robots whose readings were 0.2× the told noise (sweep configs/sweeps/honesty.toml), and
        with an in-situ tracker's geometry identified under the σ its log shows (a prior the readings
        barely reach), a predicted error 0.47× the truth's (the quick experiment: s² 0.22, the strokes
        quieter than their configured σ). Each step moves ``s²`` by the walk's and the prior's share of
        the residual degrees of freedom less than the last: a few solves, warm-started."""
        rate = None if self._front is None else self._front.robust.walk_rate_mm2_per_s
        if rate != self._walk_rate:  # the front end's measured rate has moved since the factors were made
            self._walk_rate = rate
            self._replace_scaled_factors()
        self._values = _solve(self._graph, self._values)
        if not self._config.robust.adapt_noise:
            return 1.0
        scale2, redundancy = self._variance_factor()
        for _ in range(MAX_SCALE_STEPS):
            if abs(scale2 / self._walk_scale2 - 1.0) <= 0.1 * math.sqrt(2.0 / max(redundancy, 1.0)):
                break
            self._walk_scale2 = scale2
            self._replace_scaled_factors()
            self._values = _solve(self._graph, self._values)
            scale2, redundancy = self._variance_factor()
        return scale2

    def _replace_scaled_factors(self) -> None:
        """Every walk factor at the current measurement scale and walk rate, and the prior at that scale."""
        if self._prior_index is not None:
            sigmas = np.sqrt(self._prior_sigma2 / self._walk_scale2)
            self._graph.replace(self._prior_index, random_walk.prior(params_key(0), sigmas))
        for index, window, dt_s in self._walk_factors:
            self._graph.replace(index, self._builder.walk_factor(window, dt_s, self._walk_scale2, self._walk_rate))

    def _variance_factor(self) -> tuple[float, float]:
        """The a-posteriori variance factor ``s² = χ² / r`` of the solved graph (Helmert) and its
        redundancy ``r``: 1 when the noise model is right; the covariance is scaled by it, as ``ekf``
        and ``isam2`` adapt their noise from the data (``[robust] adapt_noise``). A reading noise 5×
        the model's left lm's NEES 25× its degrees of freedom on every instrument (sweep
        ``configs/sweeps/honesty.toml``).

        ``χ² = 2 × error`` over the graph's rows but the prior's, and ``r = E[χ²]`` the sum of those
        rows' ``1 − h`` (``h`` a row's leverage): ``m − n + h_prior − g``, with ``m`` the rows, ``n``
        the unknowns' dimension (the gauge's ties count as rows: the ``n`` they pin are paid for),
        ``h_prior = tr(Λ_prior Σ_p0)`` the leverage of the prior's rows — what the prior, not the data,
        determines — and ``g`` the walk factors' rows the gauge pins (``C p = 0`` on both of its
        variables: those rows' residuals are 0 exactly). The wide prior (5 mm, the manufacturing
        tolerance) is not a distribution the truth is drawn from: its rows add ~0 to χ², and counted
        in ``r`` with the pinned walk rows they put ``s²`` 25 % low on a drifting robot measured by
        motion capture (0.70–0.78 on data of exactly the configured noise, 6 seeds: NEES 1.27× its
        degrees of freedom)."""
        graph, values = self._graph, self._values
        rows = _rows(graph)
        chi2 = 2.0 * graph.error(values)
        if self._prior_index is not None:
            prior = graph.at(self._prior_index)
            rows -= prior.dim()
            chi2 -= 2.0 * prior.error(values)
        counted = rows - values.dim() - self._pinned_walk_rows * len(self._walk_factors)
        if counted + len(self._prior_sigma2) < MIN_REDUNDANCY:
            return 1.0, float(counted)
        covariance = _marginal_covariance(graph, values, params_key(0))
        # the prior's leverage, in the graph's units (its σ² carried at P0 / s², :meth:`_solve_scaled`)
        redundancy = counted + float(np.sum(np.diag(covariance) * self._walk_scale2 / self._prior_sigma2))
        if redundancy < MIN_REDUNDANCY:
            return 1.0, float(redundancy)
        self._noise_scale = math.sqrt(chi2 / redundancy)
        return chi2 / redundancy, float(redundancy)

    def _leave_out_gross_errors(self) -> bool:
        """Leave out the samples whose measurement factors fail the gross-error test at the current
        solution (module docstring); whether any did.

        A sample's factors' χ² (twice their error) is compared, in units of the noise scale ``s²``,
        with the χ² quantile ``[isam2] gate_probability`` of ``r_k × redundancy / rows`` degrees of
        freedom (``r_k`` its rows: the share of the residual degrees of freedom its rows carry).
        ``s²`` is robust: the median over the samples of each one's χ² over its distribution's
        median, as the robust filter's batches take it, so a few glitches do not inflate the scale they are
        tested at (the configured noise, ``s² = 1``, without ``adapt_noise``). Its factors are
        removed and its pose variable with them; nothing is left out when more than half of the
        samples would be (no majority: the model, not the samples, is then wrong)."""
        graph, values = self._graph, self._values
        rows_total = _rows(graph)
        redundancy = rows_total - values.dim()
        if redundancy < MIN_REDUNDANCY or not self._measurements:
            return False
        chi2 = np.array([2.0 * sum(graph.at(k).error(values) for k in factors) for _, _, factors in self._measurements])
        rows = np.array([sum(graph.at(k).dim() for k in factors) for _, _, factors in self._measurements], dtype=float)
        dof = np.maximum(rows * redundancy / rows_total, 0.5)
        median = np.array([chdtri(d, 0.5) for d in dof])
        scale2 = float(np.median(chi2 / median)) if self._config.robust.adapt_noise else 1.0
        tail = 1.0 - self._builder.graph.gate_probability
        outliers = chi2 > scale2 * np.array([chdtri(d, tail) for d in dof])
        if not outliers.any() or 2 * outliers.sum() > len(outliers):
            return False
        kept = []
        for (t_s, x, factors), out in zip(self._measurements, outliers, strict=True):
            if not out:
                kept.append((t_s, x, factors))
                continue
            for k in factors:
                graph.remove(k)
            values.erase(x)
            err = SampleRejected(
                f"lm: sample at t = {number(t_s)} s fails the gross-error test (χ² of its measurements at the "
                "batch's robust noise scale)",
                SampleRejected.GATED,
            )
            err.t_s = t_s
            self._late.append(err)
        self._measurements = kept
        return True


def _rows(graph: gtsam.NonlinearFactorGraph) -> int:
    """The whitened residual rows of the factors left in ``graph`` (removed ones leave a hole)."""
    return sum(graph.at(k).dim() for k in range(graph.size()) if graph.exists(k))


#: at most this many rounds of :meth:`BatchLM._leave_out_gross_errors` and re-solves (glitches that
#: pulled the first solution hide others; 2–3 rounds settle it)
MAX_GROSS_ERROR_PASSES = 6

#: at most this many re-solves of :meth:`BatchLM._solve_scaled` (each one a tenth of the last's change, or less)
MAX_SCALE_STEPS = 8

#: the variance factor is taken from at least this many redundant residuals (its relative
#: σ is √(2 / redundancy): 5 % at 800); below, the noise model is taken as given.
MIN_REDUNDANCY = 100


#: Gauss–Newton stops when a step lowers the cost by less than this fraction of it.
RELATIVE_TOLERANCE = 1e-10
#: at most this many Gauss–Newton steps before LM takes over.
MAX_GN_STEPS = 20
#: LM takes over after more than this many Gauss–Newton steps in a row that raise the cost (:func:`_solve`)
MAX_GN_RISES = 2
#: a Gauss–Newton step whose linear model predicts a decrease of the cost (½ χ²) below this is at the
#: optimum: its parameters are within ~1e-3 σ of it
PREDICTED_TOLERANCE = 1e-6


def _solve(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> gtsam.Values:
    """The graph's optimum from ``values``: Gauss–Newton, then LM from the lowest cost it reached where it
    does not converge (module docstring).

    Gauss–Newton goes on through up to :data:`MAX_GN_RISES` steps in a row that raise the cost: from a
    start millimetres off along weak directions its first step overshoots and the next ones converge
    (the README's hobby log from its refined registration: cost 1.8e9, 2.5e10, 8.0e6, 577, 325.103, at the
    optimum in 4 steps), where LM taking over at the first rise stopped short of it after 11 s (332.42).

    Raises:
        CalibError: LM fails too (a graph that does not determine δM).
    """
    cost = graph.error(values)
    best, best_cost, rises = values, cost, 0
    for _ in range(MAX_GN_STEPS):
        try:
            linear = graph.linearize(values)
            step = linear.optimize()
        except RuntimeError:  # Cholesky found the system indeterminate: LM's QR decides
            break
        candidate = values.retract(step)
        new_cost = graph.error(candidate)
        # Converged either way: at the optimum a step may raise the cost by round-off (2.4e-13 of it on
        # benchmarks.scale's 10⁴-sample log), and taken for an overshoot it handed the optimum to LM,
        # whose one trial step there took 159 of that run's 174 s to end where it started (a GN step:
        # ~1 s). Driven from C++, every Python factor is handed its own copy of the values (3 ms for
        # that graph's 11 000) to linearise and again to evaluate: a cost quadratic in the log's length.
        if abs(cost - new_cost) <= RELATIVE_TOLERANCE * cost:
            found, found_cost = (candidate, new_cost) if new_cost <= cost else (values, cost)
            if found_cost <= best_cost * (1.0 + RELATIVE_TOLERANCE):
                return found
            break  # a stationary point above where it passed: LM from there
        # a rise where the linear model predicts less than PREDICTED_TOLERANCE to gain is round-off along
        # the weakest directions (a servo's tilts in rad beside 1e-4 mm gauge ties), not an overshoot
        if not new_cost <= cost and cost - linear.error(step) <= PREDICTED_TOLERANCE and cost <= best_cost:
            return values
        if not math.isfinite(new_cost):
            break
        rises = rises + 1 if new_cost > cost else 0
        values, cost = candidate, new_cost
        if cost < best_cost:
            best, best_cost = values, cost
        if rises > MAX_GN_RISES:
            break
    values = best  # LM's damping takes it from the lowest cost Gauss–Newton reached
    params = gtsam.LevenbergMarquardtParams()
    params.setLinearSolverType("MULTIFRONTAL_QR")
    params.setMaxIterations(100)
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(0.0)
    # LM may end on 'cost inf, giving up' at convergence with µm sigmas; the values are
    # still the optimum (docs/measured-facts.md), so the result is used as it stands.
    try:
        return gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    except RuntimeError as err:  # gtsam's C++ exceptions: a graph that does not determine δM
        raise CalibError(f"lm: the solve failed: {first_paragraph(err)}") from None


#: the dense QR fallback of :func:`_marginal_covariance` builds the whole Jacobian: up to this many columns
DENSE_MARGINAL_MAX_COLUMNS = 20_000


def _marginal_covariance(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, key: int) -> np.ndarray:
    """``key``'s marginal covariance: gtsam's (Cholesky) ``Marginals``, or where its normal equations
    are too ill-conditioned for Cholesky (whitened rows from 1e-4 mm gauge ties to 20 mm priors:
    "indeterminate"), the dense QR of the whitened Jacobian with ``key`` ordered last, whose last
    diagonal block ``R_pp`` gives ``Σ_p = (R_ppᵀ R_pp)⁻¹`` without squaring the condition number.

    Raises:
        CalibError: neither way determines the covariance.
    """
    try:
        return gtsam.Marginals(graph, values).marginalCovariance(key)
    except RuntimeError as err:
        failure = first_paragraph(err)
    linear = graph.linearize(values)
    ordering = gtsam.Ordering()
    for other in values.keys():
        if other != key:
            ordering.push_back(other)
    ordering.push_back(key)
    size = values.atVector(key).size
    if values.dim() > DENSE_MARGINAL_MAX_COLUMNS:
        raise CalibError(f"lm: the covariance failed: {failure}")
    A, _ = linear.jacobian(ordering)
    R: np.ndarray = np.linalg.qr(A, mode="r")  # type: ignore[assignment]  # numpy's stubs: QRResult; "r" gives R alone
    R_pp = R[-size:, -size:]
    try:
        R_inv = np.linalg.inv(R_pp)
    except np.linalg.LinAlgError:
        raise CalibError(f"lm: the covariance failed: {failure}") from None
    return R_inv @ R_inv.T
