"""``isam2``: the factor graph of :mod:`.graph` solved online by iSAM2 in a fixed-lag smoother.

Bounded cost (docs/measured-facts.md): a single static parameter variable inside the fixed-lag
smoother keeps collecting marginal factors, so ``isam2`` always keeps a *chain* of parameter
variables and lets old ones be marginalised with the poses; the current variable's timestamp
is refreshed every update so it is never marginalised while in use.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable
from dataclasses import dataclass, replace

import gtsam
import numpy as np

from ..config import EstimatorConfig
from ..errors import CalibError, SampleRejected, number
from ..estimate import Estimate
from ..factors import pose_misfit
from ..factors.pose_misfit import misfit_key
from ..model.drive import PAYLOAD
from ..model.platform import Platform
from ..samples import Log, Sample
from .base import Refusals, payload_change_field, state_array, update_each
from .ekf import LegEKF
from .graph import ChainState, Epoch, GraphBuilder, first_paragraph, params_key
from .measurement import HeldForRegistration, check_sample, samples_from_arrays, samples_to_arrays
from .robust import WALK_RAISING

#: samples between the front end's anchor states (see :meth:`ISAM2Estimator.update`): a gtsam
#: failure replays at most this many front-end updates.
FRONT_ANCHOR_SAMPLES = 20

#: samples of a block the front end takes in one compiled run (:meth:`ISAM2Estimator.update_block`):
#: a run it must take back (a lock-out recovery, a gtsam failure) is replayed, so short enough that
#: this stays cheap, long enough that exporting the anchor state costs a small fraction of a sample's time.
FRONT_RUN_SAMPLES = 256


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
    couple of lags) up to ~1e-3 mm, a tenth of its σ. The same state is what
    :meth:`export_state` saves for checkpoints: the smoother itself cannot be serialised (its
    factors are Python callbacks).

    Cost: one 42×42 marginal covariance per window opened; a rebuild costs one update per
    buffered sample. A block of samples (:meth:`update_block`, what ``calibrate`` feeds) runs the
    front end in compiled runs and the graph after it, refusing what one by one would; where the
    estimate after each sample is not asked for and the tracker fixes every pose, the graph
    takes a parameter window's samples in one smoother update (:meth:`_add_window`): ~40 % of
    the cost, the estimate within the relinearisation threshold's error (~1e-6 mm).

    Robustness and noise levels: a leg-length EKF runs alongside as the front end
    (:class:`~stewart_calib.estimators.ekf.LegEKF` with ``[isam2] gate_probability``, so the
    shared :class:`~stewart_calib.estimators.robust.RobustFilter`). It decides which samples
    enter the graph — its robust start-up batch first, then its χ² gate. Once the start-up batch
    is decided, the samples it kept enter the graph as that batch's Gaussian (its MAP, relinearised
    to convergence, with its covariance at the graph's own noise) on the first parameter variable:
    fed one by one, each would be linearised at the smoother's estimate of the moment — from a
    handful of samples, millimetres off in the directions they do not yet determine — and
    marginalised seconds later with that linearisation (after large initial errors, an outside
    instrument's log at 1 Hz: 3–5 % worse on held-out data than the batch optimum,
    benchmarks/hobby.py). The graph's samples carry the noise ``s² R0`` at the scale ``s²`` the front
    end measured for their window, and the walk ``Q`` at its rate (:meth:`_window_walk`), between its
    windows' variables and, in each sample's drive-leg rows, from its window's variable to the sample
    (:meth:`GraphBuilder.epoch`): its marginal covariance is that of the noise and the walk. When the
    front end recovers from a lock-out, the smoother restarts from the front end's recovered
    Gaussian, as after a gtsam failure.

    An unannounced payload (``[elastic] payload_sigma_kg`` > 0, spec §10): the front end is ekf with
    its payload state, and the graph takes its layout, the payload mass its last entry (:mod:`.graph`).
    A step of the payload the front end takes (:class:`~.robust.RobustFilter`'s ``step``, once the
    samples after it confirm it) opens a parameter window at the sample it happened at, whose walk
    factor lets the payload move by its prior σ, from the front end's value after the step
    (:attr:`GraphBuilder.steps`, kept with the samples they open windows at through trims, rebuilds and
    checkpoints), and the samples the front end refused since (checkpointed too) are taken back into the graph; the
    result carries the steps taken as ``"payload_steps"``, as ekf's. Where the front end carries the in-situ
    tracker's misfit at a static pose (:attr:`LegEKF.pose_misfit <stewart_calib.estimators.ekf.LegEKF.pose_misfit>`),
    the graph holds one misfit variable a pose (:mod:`.graph`), marginalised with the lag once the pose is left;
    a snapshot taken within a pose holds the joint marginal of the window's variable and that pose's misfit,
    which a rebuild puts back as the parameters' prior and the misfit's conditional on them.
    """

    name = "isam2"
    # made anew by _rebuild
    _state: ChainState
    _snapshots: list[_Snapshot]
    _replay: list[Sample]

    def __init__(self, platform: Platform, config: EstimatorConfig):
        self._front = LegEKF(
            platform,
            dataclasses.replace(
                config, ekf=dataclasses.replace(config.ekf, gate_probability=config.isam2.gate_probability)
            ),
        )
        # the front end's unknown vector, an unannounced payload included: the graph starts from its Gaussians;
        # and the in-situ tracker's misfit at a static pose where the front end carries it
        self._builder = GraphBuilder(
            platform,
            config,
            chain=True,
            walk_in_windows=True,
            layout=self._front.layout,
            pose_misfit=self._front.pose_misfit,
        )
        payload = self._front.layout.slice(PAYLOAD)
        self._payload = None if payload is None else payload.start
        # The front end lowers the walk rate only where the window differences reject the configured
        # one at the same 5 % as it raises it (see _window_walk).
        self._front.robust.walk_lowering = WALK_RAISING
        self._pending: list[Sample] = []  # start-up samples the front end has not yet decided on
        # an unannounced payload's: the samples the front end's gate refused lately, which a step it takes
        # afterwards takes back in (_note_step)
        self._front_gated: list[Sample] = []
        # the samples the graph's payload steps left out (taken while the payload moved) and took back in
        self._step_dropped, self._step_readmitted = 0, 0
        #: ``{t_s: (s², q)}``: the noise scale and walk rate [mm²/s] of the walk factor each buffered
        #: window opened with (_window_walk)
        self._window_scales: dict[float, tuple[float, float]] = {}
        self._front_anchor: dict | None = None  # the front end's state before the samples in _front_since
        self._front_since: list[Sample] = []
        params = gtsam.ISAM2Params()
        params.setFactorization(config.isam2.factorization)
        mm, rad = config.isam2.relinearize_threshold_mm, config.isam2.relinearize_threshold_rad
        thresholds = gtsam.ISAM2ThresholdMap()  # per variable type: poses mix rad and mm
        thresholds.insert(("x", np.r_[[rad] * 3, [mm] * 3]))
        thresholds.insert(("p", np.full(self._builder.layout.size, mm)))
        if self._builder.misfit_size:
            thresholds.insert(("b", np.full(self._builder.misfit_size, mm)))
        params.setRelinearizeThreshold(thresholds)
        params.relinearizeSkip = 1
        # Reuse the slots of removed factors so the factor index stays bounded too.
        params.findUnusedFactorSlots = True
        self._params = params
        self._lag_s = config.isam2.lag_s
        builder = self._builder
        self._held = HeldForRegistration(platform, config.noise, builder.model, builder.layout)
        self._rebuild(None, [])

    def _current_params(self) -> np.ndarray:
        return self._smoother.calculateEstimateVector(params_key(self._state.window))

    def update(self, sample: Sample) -> None:
        """Add one epoch (pose variable and its factors) and run one iSAM2 update.

        Raises:
            SampleRejected: see :meth:`GraphBuilder.epoch`, or gtsam failed in the update
                (the smoother is rebuilt without the sample); the estimator is unchanged.

        An instrument registered on the data holds the first samples
        (:class:`~.measurement.HeldForRegistration`): once they register it, the unknown vector
        starts from the registration and they are replayed.
        """
        if self._held.active:
            self._hold(sample)
            return
        front = self._front.robust
        started, recoveries = front.started, front.recoveries
        # A gtsam failure below takes the sample back from the front end too: from its state at
        # an anchor and the samples fed to it since (replayed but this one), exporting the state
        # once every FRONT_ANCHOR_SAMPLES instead of every sample (an export every sample was a
        # sizeable share of the front end's time). Until its start-up batch is decided (a decision
        # that a replay would make again) the anchor is every sample.
        if not started or self._front_anchor is None or len(self._front_since) >= FRONT_ANCHOR_SAMPLES:
            self._front_anchor, self._front_since = self._front.export_state(), []
        self._front_since.append(sample)
        try:
            self._front_update(sample)
        except SampleRejected:
            self._follow_front(started, recoveries)
            raise
        if not started:
            self._pending.append(sample)
        if front.started:
            try:
                self._follow_front(started, recoveries, sample if started else None)
            except SampleRejected:
                self._take_back_from_front()
                raise

    def update_block(self, block: Log, errors_out: np.ndarray | None = None) -> tuple[Refusals, Refusals]:
        """:func:`~.base.update_each` over ``block``, the same result: once the front end is past its
        start-up, it takes runs of samples in compiled calls (:meth:`LegEKF.update_block
        <stewart_calib.estimators.ekf.LegEKF.update_block>`) and the graph follows it sample by
        sample (:meth:`_front_run`); anything else goes through :meth:`update`."""
        refused: Refusals = []
        late: Refusals = []
        j = 0
        while j < len(block):
            # an unannounced payload's samples go one by one: a step the front end takes after the samples
            # that confirm it has the graph take back those it had refused then (_note_step)
            if self._payload is None and not self._held.active and not self._pending and self._front.robust.started:
                j = self._front_run(block, j, refused, late, errors_out)
            else:
                j = self._one_by_one(block, j, j + 1, refused, late, errors_out)
        return refused, late

    def _one_by_one(
        self, block: Log, start: int, stop: int, refused: Refusals, late: Refusals, errors_out: np.ndarray | None
    ) -> int:
        """:meth:`update` with samples ``start:stop`` of ``block``; returns ``stop``."""
        one = update_each(
            self, block.select(slice(start, stop)), None if errors_out is None else errors_out[start:stop], first=start
        )
        refused += one[0]
        late += one[1]
        return stop

    def _front_run(
        self, block: Log, first: int, refused: Refusals, late: Refusals, errors_out: np.ndarray | None
    ) -> int:
        """Up to :data:`FRONT_RUN_SAMPLES` samples of ``block`` from ``first``: the front end takes
        them in one block, then the graph adds those it accepted, as :meth:`update` would one by one.
        Returns the index of the next sample to take.

        A run in which the front end recovered from a lock-out (the graph must restart from its
        state at that sample) is taken back and goes through :meth:`update` sample by sample; a
        sample gtsam fails on is rejected and the front end brought to the state before it (its
        anchor, then the run's earlier samples: the same state as the per-sample path's roll-back).
        """
        run = block.select(slice(first, first + FRONT_RUN_SAMPLES))
        front = self._front.robust
        recoveries = front.recoveries
        anchor = self._front.export_state()
        front_refused, front_late = self._front_block(run)
        if front.recoveries != recoveries or front_late:
            self._front_back_to(anchor, run.select(slice(0, 0)))
            return self._one_by_one(block, first, first + len(run), refused, late, errors_out)
        self._front_anchor, self._front_since = None, []  # update() anchors afresh
        rejected = dict(front_refused)
        if errors_out is None and self._builder.guess_at_windows_only:
            accepted = [i for i in range(len(run)) if i not in rejected]
            failed = self._add_in_windows([run[i] for i in accepted])
            stop = len(run) if failed is None else accepted[failed[0]]
            refused += [(first + i, rejected[i]) for i in range(stop) if i in rejected]
            if failed is None:
                return first + len(run)
            self._front_back_to(anchor, run.select(slice(0, stop)))
            refused.append((first + stop, failed[1]))
            return first + stop + 1
        for i in range(len(run)):
            if i in rejected:
                refused.append((first + i, rejected[i]))
            else:
                try:
                    self._add_or_reject(run[i])
                except SampleRejected as err:
                    self._front_back_to(anchor, run.select(slice(0, i)))
                    refused.append((first + i, err))
                    if errors_out is not None:
                        errors_out[first + i] = self.current_error()
                    return first + i + 1
            if errors_out is not None:
                errors_out[first + i] = self.current_error()
        return first + len(run)

    def _front_update(self, sample: Sample) -> None:
        """The front end's ``update``, noting a step of the unannounced payload it takes at ``sample``."""
        steps = self._front.robust.steps
        try:
            self._front.update(sample)
        except SampleRejected as err:
            if self._payload is not None and err.reason == SampleRejected.GATED:
                self._front_gated.append(sample)
            raise
        # a step the front end took at this sample without it: the graph takes the sample itself, as it takes
        # back the front end's refusals since the step began (_note_step), so it is no refusal of isam2's
        self._front.robust.take_step_refusals()
        self._note_step(sample, steps)

    def _note_step(self, sample: Sample, steps_before: int) -> None:
        """Where the front end took a payload step at ``sample`` (its count of steps moved from
        ``steps_before``), the graph opens a window with the payload it found (GraphBuilder.steps) at the
        sample the step happened at (the front end takes it once the samples after it agree), the graph
        rebuilt from the replay buffer with the window there and the samples since that the front end's
        gate had refused, which the step takes back in — where the buffer reaches back to it (else the
        window opens at ``sample``).

        The smoother is then rebuilt once more, from the newest snapshot of a window from the step's on
        (:class:`_Snapshot`; without one, from the snapshot the buffer starts at once the replay has
        trimmed it), so that it starts from the Gaussian every later rebuild and checkpoint starts from:
        rebuilt from the buffer's first snapshot alone, it holds pre-step samples that the replay then
        trims, relinearised by the step's samples, which no later rebuild re-creates (on
        tests/test_isam2_payload.py's check, its rebuilds and a resumed checkpoint 2.8 kg, 1.4σ, away).
        A snapshot of before the step would not do: it holds the samples before the step linearised at
        the estimate of then, which the step moves (the compliance by 6 %); from it the payload is
        26.6 kg after the check's 20 kg step and 42.7 kg at its 40 kg end (8 µm closed loop), from the
        step window's 23.8 and 40.2 kg (1.5 µm; ekf 20.0 and 39.7 kg).

        A step the front end took from the origin of a change that went on (:class:`~.robust.RobustFilter`'s
        ``step_origin_t_s``, a payload put on over seconds) left the samples between that origin and the step out:
        the rebuild leaves those the buffer holds out too (the paper's experiment, 20 s ramps, default
        configuration: 35.39 ± 0.45 kg on seed 3 with them, 39.69 ± 0.57 without).

        The front end's release of the payload it held (:meth:`_held_payload`) opens a window the same way,
        at the first sample the graph takes since: the payload's prior σ from its prior mean."""
        held_from = self._replay[0].t_s if self._replay else math.inf
        self._front_gated = [s for s in self._front_gated if s.t_s >= held_from]
        released_t_s = self._front.robust.payload_released_t_s
        if released_t_s > self._state.last_t_s:  # the first sample the graph takes since the front end released it
            self._builder.steps[sample.t_s] = float(self._front.filter.x[self._payload])
        if self._front.robust.steps == steps_before:
            return
        payload_kg = float(self._front.filter.x[self._payload])
        began_t_s = self._front.robust.step_t_s
        taken_back = [s for s in self._front_gated if s.t_s >= began_t_s]
        if min(began_t_s, self._state.last_t_s) < held_from:  # the buffer does not reach back to it
            self._builder.steps[sample.t_s] = payload_kg
        else:  # rebuilt, so that a checkpoint's replay or a gtsam-failure rebuild lands where this does
            self._builder.steps[began_t_s] = payload_kg
            origin_t_s = self._front.robust.step_origin_t_s
            kept = [s for s in self._replay if not origin_t_s < s.t_s < began_t_s]  # those taken back come after
            replay = sorted(kept + taken_back, key=lambda s: s.t_s)
            self._step_dropped += len(self._replay) - len(kept)
            self._step_readmitted += len(taken_back)
            self._rebuild(self._first_snapshot(), replay)
            # the Gaussian this smoother, and so every rebuild and checkpoint after it, starts from
            after = [s for s in self._snapshots if s.offset > 0 and s.state.window_start_s >= began_t_s]
            if after:
                self._rebuild(after[-1], self._replay[after[-1].offset :])
            elif len(self._replay) < len(replay):  # trimmed on the way
                self._rebuild(self._first_snapshot(), self._replay)
        self._front_gated = []

    def _front_block(self, run: Log) -> tuple[Refusals, Refusals]:
        """The front end over ``run`` (:meth:`LegEKF.update_block
        <stewart_calib.estimators.ekf.LegEKF.update_block>`); with an unannounced payload, which it
        takes one sample at a time anyway, sample by sample here so that its steps are noted."""
        if self._payload is None:
            return self._front.update_block(run)
        refused: Refusals = []
        late: Refusals = []
        for i in range(len(run)):
            steps = self._front.robust.steps
            one = update_each(self._front, [run[i]], first=i)
            self._front_gated += [run[i] for _, err in one[0] if err.reason == SampleRejected.GATED]
            self._note_step(run[i], steps)
            refused += one[0]
            late += one[1]
        return refused, late

    def _front_back_to(self, anchor: dict, since: Log) -> None:
        """The front end back at its state ``anchor``, then ``since`` fed again; the payload steps it
        noted on samples the graph does not hold are forgotten (those of ``since`` are noted again)."""
        self._front.import_state(anchor)
        self._forget_steps_after(self._state.last_t_s)
        self._front_block(since)

    def _forget_steps_after(self, t_s: float) -> None:
        self._builder.steps = {t: kg for t, kg in self._builder.steps.items() if t <= t_s}

    def _add_in_windows(self, samples: list[Sample]) -> tuple[int, SampleRejected] | None:
        """``samples`` into the graph a parameter window at a time (:meth:`_add_window`); the
        index of the first the graph refused and why (those before it are in), or None."""
        start = 0
        while start < len(samples):
            taken, err = self._add_window(samples[start:])
            if err is not None:
                return start + taken, err
            start += taken
        return None

    def _add_window(self, samples: list[Sample]) -> tuple[int, SampleRejected | None]:
        """The first of ``samples`` and those after it up to the next that opens a parameter
        window, in one smoother update (the root's re-elimination, the marginalisation and the
        relinearisation check once a window, not once a sample: ~40 % of isam2's cost, for
        estimates within ~1e-6 mm of one update a sample, where the relinearisation threshold
        leaves them). Returns how many went in and the error of the one that stopped them
        (its epoch refused it), or of one gtsam failed on: the smoother is then rebuilt without
        the window and its samples go in one by one, to find it (:meth:`_add_or_reject`)."""
        snapshot = self._window_snapshot(samples[0].t_s)
        state, factors, values, timestamps = self._state, gtsam.NonlinearFactorGraph(), gtsam.Values(), {}
        taken, refused = 0, None
        for sample in samples:
            if taken and self._builder.new_window(state, sample.t_s, self._window_fraction(state)):
                break
            try:
                epoch = self._epoch(state, sample)
            except SampleRejected as err:
                refused = err
                break
            factors.push_back(epoch.factors)
            values.insert(epoch.values)
            timestamps.update(epoch.timestamps)  # the window's variable keeps the latest time
            state, taken = epoch.state, taken + 1
        if not taken:
            return 0, refused
        try:
            self._smoother.update(factors, values, timestamps)  # type: ignore[arg-type]  # gtsam stubs: Mapping[SupportsInt, …] is invariant in its key
        except RuntimeError:  # half-updated: rebuilt, then sample by sample to find the one
            self._rebuild(self._first_snapshot(), self._replay)
            for k, sample in enumerate(samples[:taken]):
                try:
                    self._add_or_reject(sample)
                except SampleRejected as err:
                    return k, err
            return taken, refused
        self._state = state
        if snapshot is not None:
            self._snapshots.append(snapshot)
        self._replay.extend(samples[:taken])
        self._trim(samples[taken - 1].t_s)
        return taken, refused

    def _take_back_from_front(self) -> None:
        """The front end as if the last sample fed to it never came: its anchor state, then the
        samples fed since but that one (the front end is deterministic: the same state)."""
        replay, anchor = self._front_since[:-1], self._front_anchor
        if anchor is None:  # dropped by update_block, nothing fed since
            return
        self._front.import_state(anchor)
        self._forget_steps_after(self._state.last_t_s)
        # the samples fed since the anchor that its gate refused are noted again as they are fed again (and
        # the last one never came): kept as well, a step confirmed later took them into the graph twice
        self._front_gated = [s for s in self._front_gated if s.t_s < self._front_since[0].t_s]
        self._front_since = []
        for sample in replay:
            self._front_since.append(sample)
            try:
                self._front_update(sample)
            except SampleRejected:
                pass  # refused again, as the first time

    def _follow_front(self, started: bool, recoveries: int, sample: Sample | None = None) -> None:
        """Bring the graph where the front end now is: restart after its lock-out recovery,
        take the start-up samples it kept once it decided, then ``sample`` (accepted by it)."""
        front = self._front.robust
        if front.recoveries != recoveries:
            x, P = self._front.filter.x.copy(), self._held_payload(self._front.filter.P.copy())
            # the restart holds the samples of the front end's recovered Gaussian, no others
            state = dataclasses.replace(self._state, samples=self._front.filter.samples_used)
            self._rebuild(_Snapshot(state, x, P, 0), [])
        if not front.started:
            return
        batch = [] if sample is None else [sample]
        if not started:  # the start-up batch is decided: its kept samples enter as one Gaussian
            kept = [s for s, outlier in zip(self._pending, front.startup_outliers, strict=True) if not outlier]
            self._pending = []
            x, P = front.startup_gaussian(front.noise_scale2)
            P = self._held_payload(P)
            state = ChainState(
                samples=len(kept), window_start_s=kept[-1].t_s, window_samples=len(kept), last_t_s=kept[-1].t_s
            )
            self._rebuild(_Snapshot(state, x, P, 0), [])
        for sample in batch:
            self._add_or_reject(sample)

    def _held_payload(self, P: np.ndarray) -> np.ndarray:
        """``P`` of the front end's Gaussian with the payload it holds at its prior mean
        (:attr:`RobustFilter.payload_held <stewart_calib.estimators.robust.RobustFilter.payload_held>`)
        pinned there by the chain's floor σ, the tie of every constant block between windows: the graph's
        drive-leg factors have its column, and free at its prior beside a compliance the samples have not
        settled, it slid along the compliance–payload ridge as the front end's did (the paper's experiment,
        the tracker's geometry exact, readings white at 0.5 µm and told so: 62.8 ± 0.34 kg after a 40 kg
        step). The window that opens at the front end's release gives it the prior's σ (:meth:`_note_step`)."""
        if self._payload is None or not self._front.robust.payload_held:
            return P
        P = P.copy()
        P[self._payload, :], P[:, self._payload] = 0.0, 0.0
        P[self._payload, self._payload] = self._builder.graph.chain_sigma_floor_mm**2
        return P

    def _add_or_reject(self, sample: Sample) -> None:
        """:meth:`_add`; where gtsam fails, the smoother rebuilt without ``sample`` and
        :class:`SampleRejected` (the front end is the caller's to take back)."""
        try:
            self._add(sample)
        except RuntimeError as err:  # gtsam's C++ exceptions; the smoother may be half-updated
            self._rebuild(self._first_snapshot(), self._replay)
            raise SampleRejected(
                f"sample at t = {number(sample.t_s)} s: gtsam failed in the iSAM2 update ({first_paragraph(err)})",
                SampleRejected.SOLVER,
            ) from None

    def _hold(self, sample: Sample) -> None:
        check_sample(self._builder.platform, self._builder.model, sample)
        if self._held.samples and sample.t_s < self._held.samples[-1].t_s:
            raise SampleRejected(
                f"sample at t = {number(sample.t_s)} s is older than the last one "
                f"({number(self._held.samples[-1].t_s)} s)",
                SampleRejected.TIME_BACK,
            )
        self._held.hold_then_replay(sample, self._registered, self.update)

    def _registered(self, start: np.ndarray) -> None:
        self._builder.initial = start

    def _add(self, sample: Sample) -> None:
        """The update itself; the Python-side state changes only once the smoother has succeeded."""
        snapshot = self._window_snapshot(sample.t_s)
        epoch = self._epoch(self._state, sample)
        self._smoother.update(epoch.factors, epoch.values, epoch.timestamps)  # type: ignore[arg-type]  # gtsam stubs: Mapping[SupportsInt, …] is invariant in its key
        self._state = epoch.state
        if snapshot is not None:
            self._snapshots.append(snapshot)
        self._replay.append(sample)
        self._trim(sample.t_s)

    def _epoch(self, state: ChainState, sample: Sample) -> Epoch:
        """:meth:`GraphBuilder.epoch` of ``sample`` after ``state``, in its window's scale, walk and length."""
        scale2, rate = self._window_walk(state, sample)
        return self._builder.epoch(
            state, sample, self._current_params, 1.0, rate, self._window_fraction(state), measurement_scale2=scale2
        )

    def _window_fraction(self, state: ChainState) -> float:
        """The length of the window ``state`` is in, as a fraction of the configured one: where the
        walk ``q`` that window opened with is faster than the configured ``q₀``, ``q₀ / q``, so that
        the walk a window holds its variable constant over (``q T``) is at most the configured
        window's ``q₀ T₀``; else 1.

        A window's samples carry the walk from its variable as noise of their own (``Q τ / s²`` in each
        one's rows, :meth:`GraphBuilder.epoch`), but that walk is one path, common to them all
        (``Cov = Q min(τ_j, τ_k)``): taken as independent, its share of the rows is counted once a
        sample, and the longer the window against the walk's pace, the narrower the σ. On
        benchmarks/robustness.py's smooth-path drift log (a tracker at 1 µm, the walk 6.5× the
        default), told the true walk, isam2's mean z² was 1.76–1.87 with 1 s windows and 1.00–1.21
        with one variable a sample, where ekf's, which carries the walk sample by sample, is 1.00–1.10.
        The measured noise scale is left out of the ratio: a window is shortened for a walk faster
        than told, not for an instrument more precise than told (with ``q₀ s² / q`` the windows of
        tests/test_isam2_payload.py's elastic robot, its readings below the told noise, shortened at
        the configured walk and its closed loop at the end went from under 5 µm to 5.8)."""
        scales = self._window_scales.get(state.window_start_s)
        configured = self._builder.noise.random_walk_mm_per_sqrt_s**2
        if scales is None or scales[1] <= configured:
            return 1.0
        return configured / scales[1]

    def _window_walk(self, state: ChainState, sample: Sample) -> tuple[float, float | None]:
        """The measurement scale ``s²`` and the walk rate ``q`` [mm²/s] of the window ``sample`` is in
        (the walk factor of a window it opens, the walk from the window's first sample to it in its
        drive-leg rows; :meth:`GraphBuilder.epoch`): the front end's right after the window's first
        sample where the window is new (however far the front end has run ahead), the ones it had
        where a rebuild replays it (so a replay builds the factors of the uninterrupted run).

        The rate is the one the front end measures (with noise adaptation; the configured one
        without), above the configured one or below it. Above: at the configured rate, the graph's
        error bars on a robot drifting 3× faster were 1.3–1.9× too narrow (mean z² 1.7–3.7, 300-sample
        tracker logs, the default configuration, benchmarks/robustness.py's drift logs). Below: with
        the walk in every sample's rows, the configured rate on a robot drifting 3× slower widened
        the rows of a precise instrument far beyond its noise (0.3× the default: mean z² 0.27,
        σ ~2× too wide). The front end lowers the rate only where the window differences reject the
        configured one at 5 % (``RobustFilter.walk_lowering``), not its own 20 %: over the few
        windows of a short log its rate is noisy and, lowered at 20 %, isam2's NEES on the honesty
        study's drifting tracker cells (the walk matched) left the band in 6 of 60 runs (2 on main).

        The graph is in the units of the noise and the walk themselves: a window's samples carry
        ``s² R0`` at their window's ``s²``, the walk ``Q`` (:meth:`GraphBuilder.epoch`), and its marginal
        is the covariance, as ekf's ``P`` is. In units of one scale (``R0`` and ``Q / s²`` of each
        window, the marginal times the scale of the moment), a scale that moved over the lag weighed
        the walk of its earlier windows by the ratio of the two: on a robot drifting 10× faster than
        told, the readings at 0.3× the told noise, the scale falling from 12–20 at the start-up to
        0.1–2, mean z² 6.4 and NEES in band 25 % (benchmarks/robustness.py's honesty logs)."""
        opens = state.samples == 0 or self._builder.new_window(state, sample.t_s, self._window_fraction(state))
        start = sample.t_s if opens else state.window_start_s
        front = self._front.robust
        rate = front.walk_rate_at(start)
        return self._window_scales.setdefault(start, (front.noise_scale2_at(start), rate))

    def _window_snapshot(self, t_s: float) -> _Snapshot | None:
        """The current window's :class:`_Snapshot` where a sample at ``t_s`` opens the next, else None."""
        if not self._builder.new_window(self._state, t_s, self._window_fraction(self._state)):
            return None
        p = params_key(self._state.window)
        if self._state.misfit_inputs is None:
            covariance, mean = self._smoother.marginalCovariance(p), self._current_params()
        else:  # a pose held across the window: its misfit's joint marginal too (the next samples share it)
            b = misfit_key(self._state.misfits - 1)
            covariance = self._smoother.getISAM2().jointMarginalCovariance([p, b]).fullMatrix()
            mean = np.concatenate((self._current_params(), self._smoother.calculateEstimateVector(b)))
        return _Snapshot(self._state, mean, 0.5 * (covariance + covariance.T), len(self._replay))

    def _trim(self, t_s: float) -> None:
        """Drop what the newest snapshot at least one lag old makes redundant."""
        cutoff = t_s - self._lag_s
        # the snapshots' samples are in time order: the newest old one is the first old one from the end
        newest = next(
            (
                i
                for i in range(len(self._snapshots) - 1, -1, -1)
                if self._replay[self._snapshots[i].offset].t_s <= cutoff
            ),
            None,
        )
        if newest is None or self._snapshots[newest].offset == 0:
            return
        cut = self._snapshots[newest].offset
        del self._replay[:cut]
        first_t = self._replay[0].t_s
        self._window_scales = {t: walk for t, walk in self._window_scales.items() if t >= first_t}
        self._builder.steps = {t: kg for t, kg in self._builder.steps.items() if t >= first_t}
        self._snapshots = [replace(s, offset=s.offset - cut) for s in self._snapshots[newest:]]

    def _first_snapshot(self) -> _Snapshot | None:
        """The snapshot the replay buffer starts at; None while it starts at the first sample."""
        return self._snapshots[0] if self._snapshots and self._snapshots[0].offset == 0 else None

    def _rebuild(self, first: _Snapshot | None, samples: list[Sample]) -> None:
        """A fresh smoother holding ``first`` (the snapshot the samples follow; None: they start
        the log) as a prior, then ``samples`` replayed; snapshots and buffer are re-created."""
        self._smoother = gtsam.IncrementalFixedLagSmoother(self._lag_s, self._params)
        self._state, self._snapshots, self._replay = ChainState(), [], []
        if first is not None:
            p, n = params_key(first.state.window), self._builder.layout.size
            factors = self._builder.gaussian_prior(p, first.mean[:n], first.covariance[:n, :n])
            values, timestamps = gtsam.Values(), {p: first.state.last_t_s}
            values.insert(p, first.mean[:n])
            state = first.state
            if len(first.mean) > n:  # the misfit of the pose held across it, as b | p (pose_misfit.conditional)
                b = misfit_key(state.misfits - 1)
                factors.add(pose_misfit.conditional(p, b, first.mean, first.covariance, n))
                values.insert(b, first.mean[n:])
                timestamps[b] = state.last_t_s
            elif state.misfit_inputs is not None:  # a Gaussian without it (the front end's): a new pose next
                state = replace(state, misfit_inputs=None)
            self._smoother.update(factors, values, timestamps)  # type: ignore[arg-type]  # gtsam stubs, as below
            self._state = state
            self._snapshots = [replace(first, offset=0)]  # the buffer starts at it (checkpoints, rebuilds)
        for sample in samples:  # may be the old buffer: the attribute was rebound above, not cleared
            self._add(sample)

    def estimate(self) -> Estimate:
        """δM of the current parameter variable and its 42×42 marginal covariance [mm²], scaled
        by the measured noise (before the front end's start-up batch is decided: its estimate);
        with an unannounced payload, its result fields (:meth:`~.robust.RobustFilter.payload_details`)."""
        if self._pending:
            front = self._front.estimate()
            return dataclasses.replace(front, method=self.name)
        estimate = self._graph_estimate()
        if self._payload is None:
            return estimate
        return dataclasses.replace(
            estimate, details={**(estimate.details or {}), **self._front.robust.payload_details()}
        )

    def _graph_estimate(self) -> Estimate:
        """:meth:`estimate` from the graph (the front end's start-up decided)."""
        if self._state.samples == 0:
            return self._builder.prior_estimate(self.name)
        p = params_key(self._state.window)
        try:
            covariance = self._smoother.marginalCovariance(p)
        except RuntimeError as err:  # gtsam's C++ exceptions: a graph that does not determine δM
            raise CalibError(f"isam2: the marginal covariance failed: {first_paragraph(err)}") from None
        # the walk from the window's variable to the last sample, as lm adds it (GraphBuilder.window_walk_covariance)
        window = self._window_scales.get(self._state.window_start_s)
        walk = self._builder.window_walk_covariance(self._state, None if window is None else window[1])
        covariance = covariance + walk
        return Estimate.of_state(
            self._smoother.calculateEstimateVector(p),
            covariance,
            self._builder.layout,
            self.name,
            self._state.samples,
            self._state.last_t_s,
        )

    def samples_held(self) -> int:
        """Samples held to register the instrument, not yet used (:class:`HeldForRegistration`)."""
        return self._held.waiting()

    def relinearised(self, samples: Iterable[Sample]) -> Estimate | None:
        """:class:`~.base.Relinearising`: the MAP of ``samples`` by Gauss–Newton from the graph's estimate, its
        front end's passes (the same model, noise and unknown vector as the graph's factors)."""
        return self._front.optimum_from(self.estimate(), samples)

    def recovery_summary(self) -> dict | None:
        """Lock-out recoveries of its front end and the samples they dropped and readmitted."""
        return self._front.recovery_summary()

    def payload_change_summary(self) -> dict | None:
        """The samples the graph's payload steps left out and took back in (as :class:`RobustFilter`'s)."""
        return payload_change_field(self._step_dropped, self._step_readmitted)

    def take_late_rejections(self) -> list[SampleRejected]:
        """Start-up samples its front end left out once decided (they never entered the graph)."""
        return self._held.take_late() + self._front.take_late_rejections()

    def noise_scale(self) -> float | None:
        """The measurement noise its front end found in the data, as a multiple of the configured σ."""
        return self._front.noise_scale()

    def current_estimate(self) -> Estimate:
        """:meth:`estimate` without the marginal covariance (~2 ms a call at the paper's graph)."""
        if self._pending:
            return dataclasses.replace(self._front.current_estimate(), method=self.name)
        if self._state.samples == 0:
            return self._builder.prior_estimate(self.name)
        return Estimate.of_state(
            self._current_params(), None, self._builder.layout, self.name, self._state.samples, self._state.last_t_s
        )

    def current_error(self) -> np.ndarray:
        """δM of the current parameter variable [mm], without the marginal covariance."""
        if self._pending:
            return self._front.current_error()
        if self._state.samples == 0:
            return self._builder.prior_estimate(self.name).error
        return self._current_params()[: self._builder.drive.n_params]

    def graph_size(self) -> tuple[int, int]:
        """``(factors, variables)`` held by the smoother now."""
        return self._smoother.getFactors().nrFactors(), self._smoother.getLinearizationPoint().size()

    def export_state(self) -> dict:
        """The chain state, the snapshot the buffer starts at (none before the first trim; its
        covariance ``covariance_mm2``, the marginal itself) and the buffered samples, as arrays."""
        samples = self._replay
        state: dict[str, object] = {
            "chain": _chain_to_dict(self._state),
            "replay": samples_to_arrays(samples, self._builder.drive.rows, len(self._builder.model.columns)),
        }
        walks = np.array(list(self._window_scales.values()), dtype=float).reshape(-1, 2)
        state["window_scales"] = {
            "t_s": np.array(list(self._window_scales), dtype=float),
            "noise_scale2": walks[:, 0],
            "walk_rate_mm2_per_s": walks[:, 1],
        }
        first = self._first_snapshot()
        if first is not None:
            state["snapshot"] = {
                "chain": _chain_to_dict(first.state),
                "mean": first.mean,
                "covariance_mm2": first.covariance,
            }
        if self._payload is not None:  # the samples that open a window as a payload step, and its value there
            state["payload_steps"] = {
                "t_s": np.array(list(self._builder.steps), dtype=float),
                "payload_kg": np.array(list(self._builder.steps.values()), dtype=float),
            }
            # the samples the front end's gate refused while a candidate step was being tested, which the graph
            # takes back in once the step is confirmed (_note_step): without them, a checkpoint taken between a
            # step and its confirmation left the graph without the samples after the step
            state["front_gated"] = samples_to_arrays(
                self._front_gated, self._builder.drive.rows, len(self._builder.model.columns)
            )
            state["step_counts"] = np.array([self._step_dropped, self._step_readmitted], dtype=np.int64)
        if self._held.active:
            state["held"] = self._held.export_state()
        else:
            state["initial"] = self._builder.initial.copy()  # where the unknown vector started
        state["front"] = self._front.export_state()
        state["pending"] = samples_to_arrays(self._pending, self._builder.drive.rows, len(self._builder.model.columns))
        return state

    def import_state(self, state: dict) -> None:
        """Rebuild from :meth:`export_state` on a freshly built estimator (or from the state of a
        checkpoint whose snapshot holds ``covariance``: :func:`_snapshot_covariance`).

        Raises:
            CalibError: a missing key, a wrong shape, a non-positive-definite prior or a replay
                that does not end where the exported chain did (a corrupt state).
        """
        if self._state.samples:
            raise ValueError("import_state needs a freshly built estimator")
        self._held.restore(state, self.update)
        if self._held.active:  # still holding samples for the registration
            return
        if "initial" in state:
            self._builder.initial = state_array(state, "initial", (self._builder.layout.size,))
        replayed = samples_from_arrays(
            state.get("replay", {}), self._builder.drive.rows, len(self._builder.model.columns)
        )
        target = _chain_from_dict(state.get("chain", {}))
        self._front.import_state(state.get("front", {}))
        self._pending = samples_from_arrays(
            state.get("pending", {}), self._builder.drive.rows, len(self._builder.model.columns)
        )
        first = None
        if "snapshot" in state:
            snapshot = state["snapshot"]
            chain = _chain_from_dict(snapshot.get("chain", {}))
            n = self._builder.layout.size
            # with the misfit of a pose held across the snapshot, its joint marginal with it (_window_snapshot)
            size = n + (self._builder.misfit_size if chain.misfit_inputs is not None else 0)
            mean = state_array(snapshot, "mean", (size,))
            covariance = _snapshot_covariance(snapshot, size, self._front.robust.noise_scale2)
            if (
                not np.all(np.isfinite(covariance))
                or np.any(np.linalg.eigvalsh(self._builder.prior_covariance(covariance[:n, :n])) <= 0.0)
                or (size > n and np.any(np.linalg.eigvalsh(0.5 * (covariance + covariance.T)) <= 0.0))
            ):
                raise CalibError("estimator state: snapshot covariance is not positive definite")
            first = _Snapshot(chain, mean, covariance, 0)
        scales = state.get("window_scales", {})  # an older checkpoint has none: the front end's scale
        scale_t_s = state_array(scales, "t_s", np.shape(scales.get("t_s", ())))
        scale2 = state_array(scales, "noise_scale2", (len(scale_t_s),))
        if not np.all((scale2 > 0.0) & np.isfinite(scale2)):
            raise CalibError("estimator state: key 'window_scales.noise_scale2': expected finite scales > 0")
        if "walk_rate_mm2_per_s" in scales:
            rate = state_array(scales, "walk_rate_mm2_per_s", (len(scale_t_s),))
        else:  # an older checkpoint, without the measured rate: the graph walked at the configured one
            rate = np.full(len(scale_t_s), self._builder.noise.random_walk_mm_per_sqrt_s**2)
        if not np.all((rate >= 0.0) & np.isfinite(rate)):
            raise CalibError("estimator state: key 'window_scales.walk_rate_mm2_per_s': expected finite rates ≥ 0")
        self._window_scales = {
            t: (a, q) for t, a, q in zip(scale_t_s.tolist(), scale2.tolist(), rate.tolist(), strict=True)
        }
        if "payload_steps" in state:  # an unannounced payload's (see export_state)
            steps = state["payload_steps"]
            step_t_s = state_array(steps, "t_s", np.shape(steps.get("t_s", ())))
            step_kg = state_array(steps, "payload_kg", (len(step_t_s),))
            if not np.all(np.isfinite(step_kg)):
                raise CalibError("estimator state: key 'payload_steps.payload_kg': expected finite masses")
            self._builder.steps = dict(zip(step_t_s.tolist(), step_kg.tolist(), strict=True))
        if "step_counts" in state:  # an older checkpoint counted none
            self._step_dropped, self._step_readmitted = (int(v) for v in state_array(state, "step_counts", (2,)))
        if "front_gated" in state:  # an older checkpoint has none: a step confirmed after it takes back those since
            self._front_gated = samples_from_arrays(
                state["front_gated"], self._builder.drive.rows, len(self._builder.model.columns)
            )
        try:
            self._rebuild(first, replayed)
        except SampleRejected as err:
            raise CalibError(f"estimator state: a replayed sample was rejected ({err})") from None
        if (self._state.samples, self._state.window, self._state.last_t_s) != (
            target.samples,
            target.window,
            target.last_t_s,
        ):
            raise CalibError("estimator state: the replay does not end where the saved chain did")


@dataclass(frozen=True)
class _Snapshot:
    """The filtered marginal of parameter variable ``state.window`` just before the next window
    opened: everything the samples up to then say about δM, as one Gaussian.

    Attributes:
        state: the chain state at that moment. mean: δM [mm]. covariance: [mm²]. Where the platform
            held a pose across the window (``state.misfit_inputs``), both of ``[δM; b]``, ``b`` that
            pose's misfit (:mod:`~stewart_calib.factors.pose_misfit`), which the next samples share.
        offset: index in the replay buffer of the first sample of the next window.
    """

    state: ChainState
    mean: np.ndarray
    covariance: np.ndarray
    offset: int


def _snapshot_covariance(snapshot: dict, size: int, noise_scale2: float) -> np.ndarray:
    """The covariance [mm²] of a checkpoint's :class:`_Snapshot`: ``covariance_mm2`` as it is, or a
    ``covariance`` times ``noise_scale2``, the front end's ``s²`` when the checkpoint was written.

    A checkpoint that holds ``covariance`` was written while the graph kept the configured noise
    ``R0`` (each window's walk ``Q / s²``) and its marginal was that times the front end's ``s²`` of
    the moment: the graph of now is in the units of the noise and the walk (:meth:`ISAM2Estimator._window_walk`),
    and taken as it was that prior would be ``1 / s²`` too wide or too narrow."""
    if "covariance_mm2" in snapshot:
        return state_array(snapshot, "covariance_mm2", (size, size))
    return state_array(snapshot, "covariance", (size, size)) * noise_scale2


def _chain_to_dict(state: ChainState) -> dict:
    out: dict[str, np.ndarray | np.number] = {
        "samples": np.int64(state.samples),
        "window": np.int64(state.window),
        "window_start_s": np.float64(state.window_start_s),
        "window_samples": np.int64(state.window_samples),
        "last_t_s": np.float64(state.last_t_s),
    }
    if state.last_pose is not None:
        out["last_R"], out["last_t"] = state.last_pose
    if state.misfits:  # the static poses' misfits (pose_misfit): their count, the held pose's first inputs
        out["misfits"] = np.int64(state.misfits)
        if state.misfit_inputs is not None:
            out["misfit_inputs"] = state.misfit_inputs
    return out


def _chain_from_dict(d: dict) -> ChainState:
    integer = lambda key: int(state_array(d, key, ()))  # noqa: E731
    pose = (state_array(d, "last_R", (3, 3)), state_array(d, "last_t", (3,))) if "last_R" in d else None
    inputs = state_array(d, "misfit_inputs", np.shape(d["misfit_inputs"])) if "misfit_inputs" in d else None
    return ChainState(
        integer("samples"),
        integer("window"),
        float(state_array(d, "window_start_s", ())),
        integer("window_samples"),
        float(state_array(d, "last_t_s", ())),
        pose,
        integer("misfits") if "misfits" in d else 0,
        None if inputs is None else np.array(inputs, dtype=float).reshape(-1),
    )
