"""``lm``: the factor graph of :mod:`.graph` solved in batch by Levenberg–Marquardt.

The gold standard for ``isam2``: it builds the same factors; with random walk 0 it uses one
parameter variable for the whole log (the exact constant-parameter problem), which ``isam2``
approximates with its near-hard chain.

The solve takes full Gauss–Newton steps on gtsam's own linearisation while each one lowers the
cost, and hands over to gtsam's ``LevenbergMarquardtOptimizer`` (multifrontal QR) at the first
step that does not (or whose linear system Cholesky cannot solve). On a well-started graph GN
converges in 3–4 steps; gtsam's optimiser reaches the same optimum (to 1e-9 of the cost) but
spent 3.4× the time on 500 samples (5.9 s against 1.7 s: after convergence it keeps raising λ, an
error evaluation of every Python factor each time), which put ``lm`` on a 10⁴–10⁵-sample log out
of reach (issue 15).
"""

from __future__ import annotations

import math

import gtsam
import numpy as np

from ..config import EstimatorConfig
from ..errors import CalibError, SampleRejected
from ..estimate import Estimate
from ..platform import Platform
from ..samples import Sample
from .base import BufferedFit
from .graph import ChainState, GraphBuilder, first_paragraph, params_key
from .measurement import registered_start


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
        self._graph = gtsam.NonlinearFactorGraph()
        self._values = gtsam.Values()
        self._state = ChainState()
        self._solved: Estimate | None = None
        #: ``(index in the graph, window, Δt [s])`` of every walk factor (:meth:`_solve_scaled`)
        self._walk_factors: list[tuple[int, int, float]] = []
        self._walk_scale2 = 1.0  # the measurement scale the walk factors carry
        #: ``(index in the fitted samples, SampleRejected)`` of samples :meth:`fit` skipped.
        self.rejected: list[tuple[int, SampleRejected]] = []

    def fit(self, samples) -> Estimate:
        """Register the instrument on ``samples`` where its kind asks for it (its unknowns then start
        from the closed-form registration, not a nominal frame far off), then fit them all."""
        samples = list(samples)
        if self._state.samples == 0:
            builder = self._builder
            builder.initial = registered_start(
                builder.platform, self._config.noise, builder.model, builder.layout, samples
            )
        return super().fit(samples)

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
        self._graph.push_back(epoch.factors)
        self._values.insert(epoch.values)
        self._state = epoch.state
        self._solved = None

    def estimate(self) -> Estimate:
        """Solve by LM; δM of the last parameter variable and its ``gtsam.Marginals`` covariance."""
        if self._state.samples == 0:
            return self._builder.prior_estimate(self.name)
        if self._solved is None:
            p = params_key(self._state.window)
            scale2 = self._solve_scaled()
            covariance = _marginal_covariance(self._graph, self._values, p)
            if self._config.robust.adapt_noise:
                covariance = covariance * scale2
            covariance = covariance + self._builder.window_walk_covariance(self._state)
            self._solved = Estimate.of_state(
                self._values.atVector(p),
                covariance,
                self._builder.layout,
                self.name,
                self._state.samples,
                self._state.last_t_s,
            )
        return self._solved

    def _solve_scaled(self) -> float:
        """Solve the graph; with noise adaptation, the variance factor ``s²`` it returns, and with a
        walk, the graph's walk factors carried at ``Q / s²`` until ``s²`` settles.

        The measurement factors keep the configured noise ``R0``; a graph of ``R0`` and ``Q / s²`` is
        that of ``s² R0`` and ``Q`` divided by ``s²`` (the same optimum), so ``s²`` × its marginal
        is the covariance of noise ``s² R0`` and walk ``Q``, and its variance factor is ``s²`` at the
        fixed point. Scaling the marginal of the graph of ``R0`` and ``Q`` scaled the walk's share too
        (NEES 1.5–2.6× its degrees of freedom on drifting robots whose readings were 0.2× the told
        noise, sweep configs/sweeps/honesty.toml). Each step moves ``s²`` by the walk's share of the
        residual degrees of freedom less than the last: a few solves, warm-started."""
        self._values = _solve(self._graph, self._values)
        if not self._config.robust.adapt_noise:
            return 1.0
        scale2, redundancy = variance_factor(self._graph, self._values, with_redundancy=True)
        for _ in range(MAX_SCALE_STEPS if self._walk_factors else 0):
            if abs(scale2 / self._walk_scale2 - 1.0) <= 0.1 * math.sqrt(2.0 / max(redundancy, 1.0)):
                break
            self._walk_scale2 = scale2
            for index, window, dt_s in self._walk_factors:
                self._graph.replace(index, self._builder.walk_factor(window, dt_s, scale2))
            self._values = _solve(self._graph, self._values)
            scale2, redundancy = variance_factor(self._graph, self._values, with_redundancy=True)
        return scale2


#: at most this many re-solves of :meth:`BatchLM._solve_scaled` (each one a tenth of the last's change, or less)
MAX_SCALE_STEPS = 8

#: the variance factor is taken from at least this many redundant residuals (its relative
#: σ is √(2 / redundancy): 5 % at 800); below, the noise model is taken as given.
MIN_REDUNDANCY = 100


def variance_factor(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, with_redundancy: bool = False):
    """The a-posteriori variance factor ``s² = χ² / (m − n)`` of the solved graph (Helmert):
    ``χ² = 2 × error`` over its ``m`` whitened residual rows, ``n`` the unknowns' dimension
    (priors and gauge ties count as rows, so the ``n`` they pin are paid for). 1 when the noise
    model is right; the covariance is scaled by it, as ``ekf`` and ``isam2`` adapt their noise
    from the data (``[robust] adapt_noise``). A reading noise 5× the model's left lm's NEES 25×
    its degrees of freedom on every instrument (sweep ``configs/sweeps/honesty.toml``).
    """
    rows = sum(graph.at(k).dim() for k in range(graph.size()) if graph.exists(k))
    redundancy = rows - values.dim()
    factor = 1.0 if redundancy < MIN_REDUNDANCY else 2.0 * graph.error(values) / redundancy
    return (factor, float(redundancy)) if with_redundancy else factor


#: Gauss–Newton stops when a step lowers the cost by less than this fraction of it.
RELATIVE_TOLERANCE = 1e-10
#: at most this many Gauss–Newton steps before LM takes over.
MAX_GN_STEPS = 20


def _solve(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> gtsam.Values:
    """The graph's optimum from ``values``: Gauss–Newton while it descends, then LM (module docstring).

    Raises:
        CalibError: LM fails too (a graph that does not determine δM).
    """
    cost = graph.error(values)
    for _ in range(MAX_GN_STEPS):
        try:
            candidate = values.retract(graph.linearize(values).optimize())
        except RuntimeError:  # Cholesky found the system indeterminate: LM's QR decides
            break
        new_cost = graph.error(candidate)
        if not new_cost <= cost:  # an overshoot (or nan): LM's damping takes it from here
            break
        values, converged = candidate, cost - new_cost <= RELATIVE_TOLERANCE * cost
        cost = new_cost
        if converged:
            return values
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
