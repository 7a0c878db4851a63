"""The factor graph: iSAM2 in a fixed-lag smoother (``isam2``) and batch LM (``lm``).

Variables: one ``Pose3`` ``x_k`` per sample (the platform {D} in {J}, mm and rad) and one
42-vector ``p_w`` per parameter window holding δM (paper eq. 9, paper order, [mm]).
Factors of sample k (all from :mod:`stewart_calib.factors`):

* six drive-leg factors on ``(x_k, p_w)``: ``‖t + R d_i − j_i‖ − (l_i + q_i)``, σ_q;
* tight coupling: six tracker-leg factors on ``x_k``: ``‖t + R h_i − z_i‖ − (ls_i + s_i)``, σ_s;
  loose coupling: one pose prior on ``x_k`` from tracker FK, covariance propagated from σ_s;
* per window: a random-walk between factor ``p_w → p_{w+1}``, σ = random_walk·√Δt (at least
  ``chain_sigma_floor_mm``); on ``p_0`` the manufacturing prior N(0, prior_sigma² I).

Measurement factors may carry a Huber or Cauchy kernel (``[isam2] robust``). The initial
value of ``x_k`` is tracker FK warm-started from the previous sample's pose.

Parameter layout: one 42-vector per window, not six 7-vectors per leg. Smoother update alone,
1000 noisy samples, window 10 samples, lag 3 s, QR: median 0.48 ms (42-vector) against 0.56 ms
(per leg) with relinearisation threshold 1e-2, and 1.8 against 7.7 ms with 1e-3, where the
parameters are relinearised at almost every update; RMS errors vs truth agree to 1e-7 mm.

Bounded cost (docs/measured-facts.md): a single static parameter variable inside the fixed-lag
smoother keeps collecting marginal factors, so ``isam2`` always keeps a *chain* of parameter
variables and lets old ones be marginalised with the poses; the current variable's timestamp
is refreshed every update so it is never marginalised while in use. ``lm`` builds the same
factors; with random walk 0 it uses one parameter variable for the whole log (the exact
constant-parameter problem), which ``isam2`` approximates with its near-hard chain.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import gtsam
import numpy as np

from .. import kinematics as kin
from ..errors import CalibError, SampleRejected
from ..factors import drive_leg, random_walk, tracker_leg, tracker_pose
from ..platform import N_LEGS, N_PARAMS, Platform
from ..samples import Sample
from .base import Estimate, feed, state_array
from .config import EstimatorConfig
from .measurement import check_sample, solve_fk


def pose_key(k: int) -> int:
    """Key of the pose variable of sample k (0-based)."""
    return gtsam.symbol("x", k)


def params_key(w: int) -> int:
    """Key of the δM variable of parameter window w (0-based)."""
    return gtsam.symbol("p", w)


@dataclass(frozen=True)
class _ChainState:
    """Where the graph stands after the accepted samples (immutable: replaced, never edited).

    Attributes:
        samples: samples accepted so far.
        window: index of the current parameter variable.
        window_start_s: time of the first sample of the current window [s].
        window_samples: samples in the current window.
        last_t_s: time of the last accepted sample [s].
        last_pose: ``(R, t)`` of the last tracker FK, the warm start of the next.
    """

    samples: int = 0
    window: int = 0
    window_start_s: float = math.nan
    window_samples: int = 0
    last_t_s: float = -math.inf
    last_pose: tuple[np.ndarray, np.ndarray] | None = None


@dataclass
class _Epoch:
    """What one sample adds: new factors, initial values, smoother timestamps, the next state."""

    factors: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    timestamps: dict[int, float]
    state: _ChainState


def _robust(base: gtsam.noiseModel.Base, kind: str, k: float) -> gtsam.noiseModel.Base:
    if kind == "huber":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(k), base)
    if kind == "cauchy":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(k), base)
    return base


def _first_paragraph(err: Exception) -> str:
    """gtsam's messages run to a paragraph of advice; the first says what failed, on one line."""
    return " ".join(str(err).strip().split("\n\n")[0].split()) or err.__class__.__name__


class _GraphBuilder:
    """Turns one sample into its factors; shared by ``isam2`` and ``lm`` so both solve one graph.

    Args:
        chain: start a new parameter variable every window (else one variable for the log).
    """

    def __init__(self, platform: Platform, config: EstimatorConfig, chain: bool):
        self.platform = platform
        self.noise = config.noise
        self.graph = config.isam2
        self.chain = chain
        self._nominal = platform.drive.params
        self._tracker = platform.tracker.params
        robust = (self.graph.robust, self.graph.robust_k)
        self._stroke_noise = _robust(gtsam.noiseModel.Isotropic.Sigma(1, self.noise.stroke_sigma_mm), *robust)
        self._reading_noise = _robust(gtsam.noiseModel.Isotropic.Sigma(1, self.noise.reading_sigma_mm), *robust)

    def _new_window(self, state: _ChainState, t_s: float) -> bool:
        if not self.chain or state.samples == 0:
            return False
        if self.graph.window_samples > 0:
            return state.window_samples >= self.graph.window_samples
        return t_s - state.window_start_s >= self.graph.window_s


    def epoch(self, state: _ChainState, sample: Sample, params_guess) -> _Epoch:
        """Factors, values and timestamps of ``sample`` and the state after it.

        Args:
            params_guess: callable returning the current δM estimate [mm], the initial value
                of a new parameter variable.
        Raises:
            SampleRejected: non-finite data, time going backwards, or tracker FK failure;
                nothing is changed (the caller keeps ``state``).
        """
        strokes, readings = check_sample(self.platform, sample)
        if sample.t_s < state.last_t_s:
            raise SampleRejected(
                f"sample at t = {sample.t_s} s is older than the last one ({state.last_t_s} s)", SampleRejected.TIME_BACK
            )
        R, t = solve_fk(self.platform.tracker, readings, state.last_pose, "tracker")
        pose = gtsam.Pose3(gtsam.Rot3(R), t)

        factors, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        k, x = state.samples, pose_key(state.samples)
        values.insert(x, pose)
        if k == 0:
            state = replace(state, window_start_s=sample.t_s)
            values.insert(params_key(0), np.zeros(N_PARAMS))
            factors.add(random_walk.prior(params_key(0), self.noise.prior_sigma_mm))
        elif self._new_window(state, sample.t_s):
            w = state.window
            sigma = random_walk.sigma_mm(
                self.noise.random_walk_mm_per_sqrt_s, sample.t_s - state.window_start_s, self.graph.chain_sigma_floor_mm
            )
            values.insert(params_key(w + 1), params_guess())
            factors.add(random_walk.factor(params_key(w), params_key(w + 1), sigma))
            state = replace(state, window=w + 1, window_start_s=sample.t_s, window_samples=0)
        p = params_key(state.window)

        if self.graph.coupling == "tight":
            for i in range(N_LEGS):
                factors.add(tracker_leg.factor(x, self._tracker[i], readings[i], self._reading_noise))
        else:
            cov = kin.pose_covariance_from_legs(self.platform.tracker, R, t, self.noise.reading_sigma_mm)
            noise = _robust(gtsam.noiseModel.Gaussian.Covariance(cov), self.graph.robust, self.graph.robust_k)
            factors.add(tracker_pose.factor(x, pose, noise))
        for i in range(N_LEGS):
            factors.add(drive_leg.factor(x, p, i, self._nominal[i], strokes[i], self._stroke_noise))

        # The current parameter key is re-stamped every update so the smoother never
        # marginalises the variable new factors are about to touch (docs/measured-facts.md).
        timestamps = {x: sample.t_s, p: sample.t_s}
        state = replace(
            state,
            samples=k + 1,
            window_samples=state.window_samples + 1,
            last_t_s=sample.t_s,
            last_pose=(R, t),
        )
        return _Epoch(factors, values, timestamps, state)

    def prior_estimate(self, method: str) -> Estimate:
        """The estimate before any sample: δM = 0 with the manufacturing prior's covariance."""
        return Estimate(np.zeros(N_PARAMS), self.noise.prior_sigma_mm**2 * np.eye(N_PARAMS), method)


class ISAM2Estimator:
    """Online: iSAM2 inside ``gtsam.IncrementalFixedLagSmoother`` (lag ``[isam2] lag_s``).

    Each :meth:`update` hands the smoother only that sample's new factors and values; poses
    and parameter variables older than the lag are marginalised, so the graph (and the cost
    of an update) stays bounded however long the log.

    Recovery: gtsam can throw inside an update (``IndeterminantLinearSystemException`` on a
    degenerate sample, surfacing as ``RuntimeError``) after it has already changed the
    smoother, which can be neither copied cheaply nor rolled back. So the estimator keeps
    what rebuilds the smoother without that sample, and a failed update rebuilds it and
    raises :class:`SampleRejected`. The parameter chain is Markov: given δM of window w, the
    samples before window w+1 say nothing more about later ones. So each time a window
    opens, the filtered marginal of the previous window's variable is kept
    (:class:`_Snapshot`) with the samples since; a rebuild puts that Gaussian on the variable
    as a prior and replays the samples, which re-creates the same keys, initial values,
    timestamps and marginalisations. Only the newest snapshot at least ``lag_s`` old is kept,
    so the replay covers every variable the smoother still holds and the buffer holds at most
    (lag + one window) of samples. The rebuilt smoother differs from the original only in how
    the information before the snapshot is linearised (one Gaussian at the estimate of then,
    instead of the marginal factors the original made later): ~1e-7 mm once the estimate has
    settled, which tests/test_online.py measures; while it still moves by ~1 mm (the first
    couple of lags) up to ~1e-3 mm, a tenth of its σ. :class:`ResumableISAM2` exports the
    same state for checkpoints.

    Cost: one 42×42 marginal covariance per window opened; a rebuild costs one update per
    buffered sample.
    """

    name = "isam2"

    def __init__(self, platform: Platform, config: EstimatorConfig | None = None):
        config = config or EstimatorConfig()
        self._builder = _GraphBuilder(platform, config, chain=True)
        params = gtsam.ISAM2Params()
        params.setFactorization(config.isam2.factorization)
        mm, rad = config.isam2.relinearize_threshold_mm, config.isam2.relinearize_threshold_rad
        thresholds = gtsam.ISAM2ThresholdMap()  # per variable type: poses mix rad and mm
        thresholds.insert(("x", np.r_[[rad] * 3, [mm] * 3]))
        thresholds.insert(("p", np.full(N_PARAMS, mm)))
        params.setRelinearizeThreshold(thresholds)
        params.relinearizeSkip = 1
        # Reuse the slots of removed factors so the factor index stays bounded too.
        params.findUnusedFactorSlots = True
        self._params = params
        self._lag_s = config.isam2.lag_s
        self._rebuild(None, [])

    def _current_params(self) -> np.ndarray:
        return self._smoother.calculateEstimateVector(params_key(self._state.window))

    def update(self, sample: Sample) -> None:
        """Add one epoch (pose variable and its factors) and run one iSAM2 update.

        Raises:
            SampleRejected: see :meth:`_GraphBuilder.epoch`, or gtsam failed in the update
                (the smoother is rebuilt without the sample); the estimator is unchanged.
        """
        try:
            self._add(sample)
        except RuntimeError as err:  # gtsam's C++ exceptions; the smoother may be half-updated
            self._rebuild(self._first_snapshot(), self._replay)
            raise SampleRejected(
                f"sample at t = {sample.t_s} s: gtsam failed in the iSAM2 update ({_first_paragraph(err)})",
                SampleRejected.SOLVER,
            ) from None

    def _add(self, sample: Sample) -> None:
        """The update itself; the Python-side state changes only once the smoother has succeeded."""
        snapshot = None
        if self._builder._new_window(self._state, sample.t_s):
            p = params_key(self._state.window)
            covariance = self._smoother.marginalCovariance(p)
            snapshot = _Snapshot(
                self._state, self._current_params(), 0.5 * (covariance + covariance.T), len(self._replay)
            )
        epoch = self._builder.epoch(self._state, sample, self._current_params)
        self._smoother.update(epoch.factors, epoch.values, epoch.timestamps)
        self._state = epoch.state
        if snapshot is not None:
            self._snapshots.append(snapshot)
        self._replay.append(sample)
        self._trim(sample.t_s)

    def _trim(self, t_s: float) -> None:
        """Drop what the newest snapshot at least one lag old makes redundant."""
        old = [i for i, s in enumerate(self._snapshots) if self._replay[s.offset].t_s <= t_s - self._lag_s]
        if not old or self._snapshots[old[-1]].offset == 0:
            return
        cut = self._snapshots[old[-1]].offset
        del self._replay[:cut]
        self._snapshots = [replace(s, offset=s.offset - cut) for s in self._snapshots[old[-1]:]]

    def _first_snapshot(self) -> _Snapshot | None:
        """The snapshot the replay buffer starts at; None while it starts at the first sample."""
        return self._snapshots[0] if self._snapshots and self._snapshots[0].offset == 0 else None

    def _rebuild(self, first: _Snapshot | None, samples: list[Sample]) -> None:
        """A fresh smoother holding ``first`` (the snapshot the samples follow; None: they start
        the log) as a prior, then ``samples`` replayed; snapshots and buffer are re-created."""
        self._smoother = gtsam.IncrementalFixedLagSmoother(self._lag_s, self._params)
        self._state, self._snapshots, self._replay = _ChainState(), [], []
        if first is not None:
            p = params_key(first.state.window)
            factors, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
            factors.add(gtsam.PriorFactorVector(p, first.mean, gtsam.noiseModel.Gaussian.Covariance(first.covariance)))
            values.insert(p, first.mean)
            self._smoother.update(factors, values, {p: first.state.last_t_s})
            self._state = first.state
        for sample in samples:  # may be the old buffer: the attribute was rebound above, not cleared
            self._add(sample)

    def estimate(self) -> Estimate:
        """δM of the current parameter variable and its 42×42 marginal covariance [mm²]."""
        if self._state.samples == 0:
            return self._builder.prior_estimate(self.name)
        p = params_key(self._state.window)
        try:
            covariance = self._smoother.marginalCovariance(p)
        except RuntimeError as err:  # gtsam's C++ exceptions: a graph that does not determine δM
            raise CalibError(f"isam2: the marginal covariance failed: {_first_paragraph(err)}") from None
        return Estimate(
            self._smoother.calculateEstimateVector(p),
            covariance,
            self.name,
            self._state.samples,
            self._state.last_t_s,
        )

    def current_error(self) -> np.ndarray:
        """δM of the current parameter variable [mm], without the marginal covariance."""
        if self._state.samples == 0:
            return self._builder.prior_estimate(self.name).error
        return self._smoother.calculateEstimateVector(params_key(self._state.window))

    def graph_size(self) -> tuple[int, int]:
        """``(factors, variables)`` held by the smoother now."""
        return self._smoother.getFactors().nrFactors(), self._smoother.getLinearizationPoint().size()


class BatchLM:
    """Batch Levenberg–Marquardt on the same graph: the gold standard for ``isam2``.

    :meth:`update` appends the sample's factors; :meth:`estimate` solves the whole graph
    (warm-started from the previous solution). With random walk 0 there is one parameter
    variable; otherwise the same chain of windows as ``isam2``, and the estimate is the last.
    """

    name = "lm"

    def __init__(self, platform: Platform, config: EstimatorConfig | None = None):
        config = config or EstimatorConfig()
        self._builder = _GraphBuilder(platform, config, chain=config.noise.random_walk_mm_per_sqrt_s > 0)
        self._graph = gtsam.NonlinearFactorGraph()
        self._values = gtsam.Values()
        self._state = _ChainState()
        self._solved: Estimate | None = None
        #: ``(index in the fitted samples, SampleRejected)`` of samples :meth:`fit` skipped.
        self.rejected: list[tuple[int, SampleRejected]] = []

    def _last_params(self) -> np.ndarray:
        return self._values.atVector(params_key(self._state.window))

    def update(self, sample: Sample) -> None:
        """Append one sample's factors (solved at the next :meth:`estimate`).

        Raises:
            SampleRejected: see :meth:`_GraphBuilder.epoch`; the estimator is unchanged.
        """
        epoch = self._builder.epoch(self._state, sample, self._last_params)
        self._graph.push_back(epoch.factors)
        self._values.insert(epoch.values)
        self._state = epoch.state
        self._solved = None

    def fit(self, samples) -> Estimate:
        """Append every usable sample and solve; skipped ones are listed in ``rejected``."""
        self.rejected.extend(feed(self, samples))
        return self.estimate()

    def estimate(self) -> Estimate:
        """Solve by LM; δM of the last parameter variable and its ``gtsam.Marginals`` covariance."""
        if self._state.samples == 0:
            return self._builder.prior_estimate(self.name)
        if self._solved is None:
            params = gtsam.LevenbergMarquardtParams()
            params.setLinearSolverType("MULTIFRONTAL_QR")
            params.setMaxIterations(100)
            params.setRelativeErrorTol(1e-12)
            params.setAbsoluteErrorTol(0.0)
            # LM may end on 'cost inf, giving up' at convergence with µm sigmas; the values are
            # still the optimum (docs/measured-facts.md), so the result is used as it stands.
            p = params_key(self._state.window)
            try:
                self._values = gtsam.LevenbergMarquardtOptimizer(self._graph, self._values, params).optimize()
                covariance = gtsam.Marginals(self._graph, self._values).marginalCovariance(p)
            except RuntimeError as err:  # gtsam's C++ exceptions: a graph that does not determine δM
                raise CalibError(f"lm: the solve failed: {_first_paragraph(err)}") from None
            self._solved = Estimate(
                self._values.atVector(p), covariance, self.name, self._state.samples, self._state.last_t_s
            )
        return self._solved


@dataclass(frozen=True)
class _Snapshot:
    """The filtered marginal of parameter variable ``state.window`` just before the next window
    opened: everything the samples up to then say about δM, as one Gaussian.

    Attributes:
        state: the chain state at that moment. mean: δM [mm]. covariance: [mm²].
        offset: index in the replay buffer of the first sample of the next window.
    """

    state: _ChainState
    mean: np.ndarray
    covariance: np.ndarray
    offset: int


def _chain_to_dict(state: _ChainState) -> dict:
    out = {
        "samples": np.int64(state.samples), "window": np.int64(state.window),
        "window_start_s": np.float64(state.window_start_s), "window_samples": np.int64(state.window_samples),
        "last_t_s": np.float64(state.last_t_s),
    }
    if state.last_pose is not None:
        out["last_R"], out["last_t"] = state.last_pose
    return out


def _chain_from_dict(d: dict) -> _ChainState:
    integer = lambda key: int(state_array(d, key, ()))  # noqa: E731
    pose = (state_array(d, "last_R", (3, 3)), state_array(d, "last_t", (3,))) if "last_R" in d else None
    return _ChainState(
        integer("samples"), integer("window"), float(state_array(d, "window_start_s", ())),
        integer("window_samples"), float(state_array(d, "last_t_s", ())), pose,
    )


class ResumableISAM2(ISAM2Estimator):
    """``isam2`` whose state can be exported and rebuilt (checkpoints).

    The smoother itself cannot be serialised (its factors are Python callbacks), so the state
    exported is what :class:`ISAM2Estimator` keeps to rebuild it after a failed update: the
    snapshot the replay buffer starts at and the buffered samples.
    """

    def export_state(self) -> dict:
        """The chain state, the snapshot the buffer starts at (none before the first trim) and
        the buffered samples, as arrays."""
        samples = self._replay
        state = {
            "chain": _chain_to_dict(self._state),
            "replay": {
                "t_s": np.array([s.t_s for s in samples], dtype=float),
                "strokes": np.array([s.strokes for s in samples], dtype=float).reshape(-1, N_LEGS),
                "readings": np.array([s.readings for s in samples], dtype=float).reshape(-1, N_LEGS),
            },
        }
        first = self._first_snapshot()
        if first is not None:
            state["snapshot"] = {"chain": _chain_to_dict(first.state), "mean": first.mean, "covariance": first.covariance}
        return state

    def import_state(self, state: dict) -> None:
        """Rebuild from :meth:`export_state` on a freshly built estimator.

        Raises:
            CalibError: a missing key, a wrong shape, a non-positive-definite prior or a replay
                that does not end where the exported chain did (a corrupt state).
        """
        if self._state.samples:
            raise ValueError("import_state needs a freshly built estimator")
        replay = state.get("replay", {})
        t_s = state_array(replay, "t_s", np.shape(replay.get("t_s", ())))
        strokes = state_array(replay, "strokes", (len(t_s), N_LEGS))
        readings = state_array(replay, "readings", (len(t_s), N_LEGS))
        target = _chain_from_dict(state.get("chain", {}))
        first = None
        if "snapshot" in state:
            snapshot = state["snapshot"]
            mean = state_array(snapshot, "mean", (N_PARAMS,))
            covariance = state_array(snapshot, "covariance", (N_PARAMS, N_PARAMS))
            if not np.all(np.isfinite(covariance)) or np.any(np.linalg.eigvalsh(covariance) <= 0.0):
                raise CalibError("estimator state: snapshot covariance is not positive definite")
            first = _Snapshot(_chain_from_dict(snapshot.get("chain", {})), mean, covariance, 0)
        try:
            self._rebuild(first, [Sample(float(t_s[k]), strokes[k], readings[k]) for k in range(len(t_s))])
        except SampleRejected as err:
            raise CalibError(f"estimator state: a replayed sample was rejected ({err})") from None
        if (self._state.samples, self._state.window, self._state.last_t_s) != (target.samples, target.window, target.last_t_s):
            raise CalibError("estimator state: the replay does not end where the saved chain did")
