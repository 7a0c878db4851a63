"""EKF on the leg-length model: the same model and noise as the factor graph.

State ``X`` = the unknown vector (:mod:`stewart_calib.model.unknowns`): the drive's ``x_drive`` (δM, paper
order, 42 on the paper's 6-6 drive, then its unknown blocks where configured, :mod:`stewart_calib.model.drive`)
and the instrument model's own unknowns ``θ``. Observation per sample: the six drive-leg residuals
``r_i = ‖t + R d_i − j_i‖ − (l_i + e_i)`` of the drive model at the pose the instrument measured
(its model's loose pose: for the tracker, FK of the readings); the expected value is 0, so the
innovation is ``−r`` and ``H = ∂r/∂X``: the drive model's ``∂r/∂x_drive``, and ``J_x ∂ξ/∂θ`` on θ
(the measured pose moves with the instrument's unknowns); where the measurement holds more than
the pose (a points instrument's distances between its targets: ``PoseObservation.redundant``), those
rows too, on θ alone, with their own covariance. The filter names neither an instrument nor a block
of the drive.

Where the measurement does not fix a pose (a points instrument seeing fewer than three targets)
the observation is the instrument's own residual ``h(ξ(X), θ) − z`` at the pose ``ξ(X)`` the drive
model's forward kinematics gives, with ``∂ξ/∂X = −J_g⁻¹ ∂g/∂X`` by the implicit function theorem
on the drive-leg residuals ``g`` and the strokes' noise carried through ``J_g⁻¹``.

Measurement covariance: ``J_x Σ_x J_xᵀ + σ_q² I`` (full 6×6), with ``Σ_x`` the measured pose's
covariance (for the tracker propagated from i.i.d. reading noise σ_s) and ``J_x`` the
residuals' pose Jacobian — all six residuals share the one measured pose, so their errors are
correlated; with ``σ² I`` alone this filter diverges (docs/measured-facts.md). With
``noise.pose_misfit_sigma_mm = σ_m`` the tracker's readings are off, besides, by a misfit that stays while
the platform holds a pose (its geometry's residual seen through the pose) and is drawn afresh at the next:
``b ~ N(0, (σ_m/σ_s)² R_meas)`` rides beside the state over a pose's samples (the robust filter's
``pose_misfit``), so ``n`` samples of a static pose weigh as their mean, ``σ_s²/n + σ_m²`` a reading, not
as ``n`` independent readings; the samples then go one at a time (no compiled block path). Where an
unannounced payload's steps are tested and no ``σ_m`` is given, ``σ_m = σ_s``.

Process noise: a random walk of δM, ``Q = ρ² Δt`` on its entries with ``ρ`` =
``noise.random_walk_mm_per_sqrt_s`` and ``Δt`` between samples (``t_s``), as in the graph; the
other blocks are constant. Gauge: where the instrument's unknowns share the drive's gauge, the
prior and ``Q`` are conditioned on ``C X = 0`` (:func:`~stewart_calib.model.unknowns.gauge_conditioned`),
so every state holds the base and platform joints' mean rigid motion at nominal exactly.

An instrument whose kind is registered on the data (a frame far from nominal) is handled by
holding the first samples (:class:`~.measurement.HeldForRegistration`): once they register it,
its block starts at the registration and the held samples are replayed; until then the estimate
is the prior.

The recursion is a :class:`~stewart_calib.estimators.robust.RobustFilter` (robust start-up,
χ² gate with lock-out recovery, measurement and random-walk noise from the data, ``[robust]``);
its observation at a state is the loose one above, or the tight one where the measurement fixes
no pose there. A prepared sample is its drive inputs and the instrument's measurement, so the
start-up batch can relinearise it at any state. After the start-up each sample is linearised once, at
the state before it: relinearised at its own posterior (an iterated update, on the simulated
hobby hexapod with ``[elastic]``) it moves nothing held out, at 1.7–2.0× the CPU a sample on a pose
instrument; what keeps the filter off the batch optimum there is the earlier samples' linearisation,
which only a smoother revisits (BENCHMARKS.md, "The real data's stand-in"). Where the state moved far after
the start-up (an outside instrument's frame and encoder zeros 15 mm off: the README's example moved 23 mm), the
covariance so summed claims more than the log holds: ``calibrate`` asks the log's optimum from the final
estimate (:meth:`LegEKF.optimum_from`) and says so (:func:`~stewart_calib.analysis.accuracy.relinearised_summary`).

An unannounced payload (``[elastic] payload_sigma_kg`` > 0, spec §10): the payload mass ``m``
[kg] at ``[elastic] payload_com_mm`` on top of each sample's ``load_kg`` (0 where the log has
none) is the state's last entry, prior ``N(0, σ_m²)``. The leg forces are linear in the masses,
so the drive inputs are the forces at ``load_kg`` plus ``m`` times the forces per kg ``f_m``
(prepared with the sample) and ``∂r_i/∂m = −(∂e_i/∂f_i) f_{m,i} = c_i f_{m,i} / 1000``. Between
steps ``m`` is constant, so it averages over the samples; a step is tested by the samples after it
(the filter's ``step``, :meth:`~.robust.RobustFilter._test_steps`): a candidate, the filter with
``σ_m²`` added to ``m``'s process noise at one sample (that sample's update iterated, relinearised at its
own result: ``c_i f_{m,i} m`` is bilinear, and linearised where ``m`` has not stepped yet the update's
covariance loses the compliance–payload tie), runs beside the filter and replaces it once its samples'
likelihood beats the filter's, so the step moves ``m`` from the sample it happened at rather than 42
parameters over tens of samples — also where the configured δM walk takes most of what the step does
to one sample, or the payload is put on over a ramp. A random walk of ``m`` cannot do that: one slow
enough to let ``m`` average leaves a 20 kg step tens of σ outside the gate; one fast enough to pass it
makes ``m`` a per-sample nuisance that takes from every sample the information on the compliance it
carries. Where the compliance is an unknown too, ``m`` is held at its prior mean (its column out of
every observation, no step tested) until the compliance is known to within its own value on every leg
(:meth:`~.robust.RobustFilter._release_payload`): linearised at compliances the data have not settled, the
column ``c_i f_{m,i}`` puts ``m`` and ``c`` on a wrong point of the curved ridge ``c_i (f_{p,i} + m f_{m,i})``
the samples see. Not in the compiled block path (samples go one at a time).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable

import numpy as np

from ..config import EstimatorConfig
from ..errors import CalibError, SampleRejected, number
from ..estimate import Estimate
from ..instruments import instrument_model, instrument_theta, needs_registration
from ..model.drive import COMPLIANCE, PAYLOAD, payload_block
from ..model.platform import Platform
from ..model.unknowns import UnknownLayout, gauge_conditioned
from ..samples import Log, Sample, input_rows
from .base import Refusals, state_array, update_each
from .kalman import NO_POSES
from .measurement import (
    HeldForRegistration,
    LegSetPose,
    WarmFK,
    WarmPose,
    check_sample,
    drive_inputs,
    estimator_drive,
    unknown_layout,
)
from .robust import RobustFilter


class LegEKF:
    """Leg-length EKF; ``update(sample)`` then ``estimate()``.

    Attributes:
        filter: the :class:`FilterState` (``x``, ``P``, ``Q``, last NIS).
        robust: the :class:`RobustFilter` around it (noise scales, recoveries).
    """

    name = "ekf"

    def __init__(self, platform: Platform, config: EstimatorConfig):
        self.platform = platform
        self.noise = config.noise
        self.model = instrument_model(platform, config.noise)
        self.drive = estimator_drive(platform, config.noise)
        layout = unknown_layout(platform, config.noise, self.model)
        payload = payload_block(platform.elastic)
        self.layout = layout if payload is None else UnknownLayout((*layout.blocks, payload), n_params=layout.n_params)
        # an unannounced payload (see the module docstring): its column, and the per-kg leg forces in
        # each prepared sample after the drive inputs
        self._payload = self.layout.slice(PAYLOAD)
        self._per_kg = 0 if payload is None else self.drive.rows
        C = self.layout.gauge_rows(platform.drive)
        # Q per unit ρ²Δt: the walking entries, conditioned on the gauge (None: the plain diagonal).
        walks = self.layout.walks()
        scales = self.layout.walk_scales(self.drive.walk_sigmas(config.noise), config.noise.random_walk_mm_per_sqrt_s)
        if scales is None:
            unit_Q = None if walks.all() and len(C) == 0 else gauge_conditioned(np.diag(walks.astype(float)), C)
        else:  # δM's entries walk at their own rates (a rotary drive's angles)
            unit_Q = gauge_conditioned(np.diag(walks * scales**2), C)
        self._instrument = self.layout.slice("instrument")
        # an instrument that offers compiled kernels (a leg set of known geometry) is observed in compiled
        # code, and the robust filter's batch passes and its gated recursion over a block of samples
        # (update_block) run in one compiled call each — but for an unannounced payload, whose step test
        # the per-sample path alone makes
        self._leg_set = None
        if self.model.compiled_legs is not None and self.drive.legs.compiled:
            self._leg_set = LegSetPose(self.model, self.drive, self.noise.stroke_sigma_mm)
        self._coordinate_sigma = self.drive.coordinate_sigma(config.noise)
        self._pose = self._leg_set or WarmPose(self.model)
        pose_misfit = self._pose_misfit(config.noise, payload is not None)
        #: ``(κ, tolerance)`` of the in-situ tracker's misfit at a static pose it carries (κ = 0: none;
        #: :meth:`_pose_misfit`), which isam2's graph carries alike
        self.pose_misfit = pose_misfit
        compiled_rows = (
            self._leg_set.rows if self._leg_set is not None and payload is None and pose_misfit[0] == 0.0 else None
        )
        self._compiled = compiled_rows is not None
        # an instrument registered on the data starts far from the answer (frame, encoder zeros, scale):
        # its start-up batches are solved by Gauss–Newton, not one pass linearised at the prior
        far_start = self._instrument is not None and needs_registration(platform)
        self.robust = RobustFilter(
            self.name,
            self.drive.prior_sigmas(config.noise),
            config.noise.random_walk_mm_per_sqrt_s,
            config.ekf.gate_probability,
            self._observe,
            config.robust,
            self.drive.rows,
            layout=self.layout,
            C=C,
            unit_Q=unit_Q,
            relinearise=far_start,
            step=None
            if payload is None or self._payload is None
            else (self._payload.start, payload.prior_sigma[0] ** 2),
            step_factors=self._payload_factors(),
            compiled_rows=compiled_rows,
            pose_misfit=pose_misfit,
        )
        self._stroke_bounds = platform.stroke_range if platform.stroke_range is not None else (-np.inf, np.inf)
        self.filter = self.robust.filter
        self._drive_fk = WarmFK()
        self._held = HeldForRegistration(platform, config.noise, self.model, self.layout)
        self._forces_geometry: np.ndarray | None = None
        # An elastic drive measured from outside: the leg forces are taken at the pose the measurement
        # fixes through the STATE's instrument unknowns, at every linearisation (the log's payload rides
        # at the end of the prepared sample's inputs for that). The registered nominal frame is no place
        # for them: it maps nominal FK of strokes whose encoder zeros are 15 mm off, so its rotation is
        # degrees off (simulated hobby hexapod: 6° in roll) and gravity seen tilted as much — a fit whose
        # c·f is not validate's (benchmarks/hobby.py: plain held-out 0.50 mm against lm's 0.35).
        self._forces_at_state = self.drive.elastic is not None and self._instrument is not None
        self._packed_width = self.drive.packed_width if self._forces_at_state else 0

    def _pose_misfit(self, noise, payload_steps: bool) -> tuple[float, float]:
        """The robust filter's ``pose_misfit`` of ``noise.pose_misfit_sigma_mm``: its variance over the readings'
        ``reading_sigma_mm²``, as it enters the legs' residuals through the same pose (0: none), and the
        inputs' tolerance of one pose, 5 σ of a logged coordinate (a stroke's [mm], a servo's angle [rad]:
        a static pose's encoders read within it), which the step candidates begin at
        (:meth:`~.robust.RobustFilter._test_steps`) with or without a misfit.

        Where an unannounced payload's steps are tested (``payload_steps``) and none is given, the in-situ
        tracker's misfit is taken as large as its readings' σ_s: each static pose's samples then test a step
        as their mean does. The misfit cannot be measured from the data (the drive's unknowns take up what
        they can of it and the readings' scale shows the rest as noise), and were its samples independent a
        pose's own misfit, seen by every one of them, would be taken for a step."""
        sigma = noise.pose_misfit_sigma_mm  # another instrument's is refused by make_estimator
        if sigma == 0.0 and payload_steps and self.model.kind == "tracker":
            sigma = noise.reading_sigma_mm
        return sigma**2 / noise.reading_sigma_mm**2, 5.0 * self._coordinate_sigma  # a servo's angles in rad

    def _payload_factors(self):
        """``(columns, nominal)`` of the compliance the unannounced payload multiplies (the robust filter's
        ``step_factors``): drive row ``i``'s ``∂r_i/∂m = g_i f_{m,i}``, ``g`` the force gains, linear in
        the compliance ``nominal + x[columns]`` (``nominal = g_i / (∂g_i/∂c_i)`` at ``x = 0``); None without
        a payload or a compliance unknown."""
        compliance = self.layout.slice(COMPLIANCE)
        if (
            self._payload is None
            or compliance is None
            or compliance.stop - compliance.start != self.drive.rows
            or compliance.stop > self.drive.size
        ):
            return None
        columns = np.arange(compliance.start, compliance.stop)
        unit = np.zeros(self.drive.size)
        gains_at_zero = self.drive.force_gains(unit)
        unit[columns] = 1.0
        per_unit = self.drive.force_gains(unit) - gains_at_zero  # leg i's gain per unit of c_i
        return columns, gains_at_zero / per_unit

    def update(self, sample: Sample) -> None:
        """Fold in one sample; ``SampleRejected`` leaves the state untouched."""
        strokes, z = check_sample(self.platform, self.model, sample)
        last_t_s = self._held.samples[-1].t_s if self._held.active and self._held.samples else self.filter.t_s
        if sample.t_s < last_t_s:
            raise SampleRejected(
                f"ekf: sample at t = {number(sample.t_s)} s is older than the last one ({number(last_t_s)} s)",
                SampleRejected.TIME_BACK,
            )
        if not self._held.active:
            self.robust.update(sample.t_s, self._prepared(strokes, z, sample))
            return
        self._held.hold_then_replay(sample, self.robust.start_at, self._replay)

    def update_block(self, block: Log, errors_out: np.ndarray | None = None) -> tuple[Refusals, Refusals]:
        """:func:`~.base.update_each` over ``block``: the steady recursion in compiled calls for the
        runs of samples it accepts, any other sample (start-up, refused, window statistics due…)
        through :meth:`update` — the same result."""
        count = len(block)
        errors = np.zeros((0, self.drive.n_params)) if errors_out is None else errors_out
        refused, late = [], []
        rows: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        j = 0
        while j < count:
            if self._leg_set is not None and self._compiled and self.robust.started:
                if rows is None:
                    rows = self._prepared_rows(block, self._leg_set)
                prepared, poses, plain = rows
                j += self.robust.update_block(block.t_s[j:], prepared[j:], poses[j:], plain[j:], errors[j:])
                if j == count:
                    break
            one = update_each(self, [block[j]], None if errors_out is None else errors_out[j : j + 1], first=j)
            refused += one[0]
            late += one[1]
            j += 1
        return refused, late

    def _prepared_rows(self, block: Log, leg_set: LegSetPose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(prepared rows [u | z], their poses [R | t] where solved here (else none), the rows check_sample
        surely passes)`` of a block of the leg set's readings; the check is stricter than check_sample (any
        doubt: the row goes through :meth:`update`). An elastic drive's forces need the readings' poses:
        the recursion's Newton then starts at them instead of solving each pose again."""
        lo, hi = self._stroke_bounds
        strokes, readings = np.asarray(block.strokes, dtype=float), np.asarray(block.readings, dtype=float)
        with np.errstate(invalid="ignore"):
            plain = (
                np.isfinite(block.t_s)
                & np.isfinite(strokes).all(axis=1)
                & ((strokes >= lo) & (strokes <= hi)).all(axis=1)
                & self.model.surely_pass(readings)
            )
        poses = NO_POSES
        if not self.drive.needs_pose:
            inputs = self.drive.inputs(strokes, block.inputs)
        else:  # the forces at the tracker's poses and the state's geometry, as update() takes them
            # the block's samples in order: each FK from the sample before (~3 Newton steps, not ~5)
            fk = leg_set.legs.forward_kinematics(np.where(plain[:, None], readings, 0.0), strict=False, along=True)
            plain &= fk.converged
            R, t = fk.R[plain], fk.t[plain]
            inputs = np.zeros((len(strokes), self.drive.input_width))
            inputs[:, : strokes.shape[1]] = strokes
            inputs[plain] = self.drive.inputs(strokes[plain], input_rows(block.inputs, plain), R, t, self._forces_at())
            poses = np.column_stack((fk.R.reshape(-1, 9), fk.t))
        prepared = np.ascontiguousarray(np.column_stack((inputs, readings)), dtype=float)
        return prepared, poses, plain

    def _replay(self, held: Sample) -> None:
        strokes, z = check_sample(self.platform, self.model, held)
        self.robust.update(held.t_s, self._prepared(strokes, z, held))

    def _prepared(self, strokes: np.ndarray, z: np.ndarray, sample: Sample) -> np.ndarray:
        """A prepared sample ``[u | forces per kg (an unannounced payload) | the channels the forces read
        (forces taken at the state: :meth:`~stewart_calib.model.drive.DriveModel.packed_pose_channels`) | z]``."""
        inputs = drive_inputs(
            self.drive, self.model, strokes, z, sample.inputs, self._pose.guess, self._forces_at(), self._per_kg > 0
        )
        packed = self.drive.packed_pose_channels(sample.inputs) if self._forces_at_state else np.zeros(0)
        return np.concatenate((inputs, packed, np.ravel(z)))

    def _forces_at(self) -> np.ndarray | None:
        """The drive state whose geometry an elastic drive's leg forces are taken at: the one the
        robust start-up decided, fixed from then on (so that the compiled block path, whose rows are
        prepared ahead, and :meth:`update` take the same inputs); the nominal (None) before. The
        start-up's geometry is within micrometres of the final one, the nominal within millimetres:
        1e-3 of the moment arms, ~1 µm of a 60 kg platform's c·f at 1 mm/kN (benchmarks.elastic)."""
        if self._forces_geometry is None and self.drive.elastic is not None and self.robust.started:
            self._forces_geometry = self.filter.x[: self.drive.size].copy()
        return self._forces_geometry

    def _observe(self, prepared: np.ndarray, x: np.ndarray):
        """``(−r, H = ∂r/∂X, R_meas)`` of a prepared sample ``[u | z]`` at the state ``x``: the loose
        observation, or the tight one where the measurement fixes no pose at ``x``."""
        drive = self.drive
        width = drive.input_width
        inputs, per_kg = prepared[:width], prepared[width : width + self._per_kg]
        packed = self._packed_width
        z = prepared[width + self._per_kg + packed :]
        x_drive = x[: drive.size]
        theta = instrument_theta(self.model, None if self._instrument is None else x[self._instrument])
        observed = None
        if self._leg_set is None:
            observed = self._pose.solve(z, theta)
            if observed is not None and self._forces_at_state:
                channels = drive.unpacked_pose_channels(prepared[width + self._per_kg : width + self._per_kg + packed])
                inputs = drive.reposed(inputs, channels, observed.R, observed.t, self._forces_at())
                if self._per_kg:
                    per_kg = drive.payload_leg_forces(observed.R, observed.t, self._forces_at(), channels)
        dg_dm = None  # ∂r/∂m of the drive-leg residuals r on the unannounced payload m
        if self._payload is not None:
            inputs = drive.loaded_inputs(inputs, per_kg, float(x[self._payload][0]))
            dg_dm = -drive.force_gains(x_drive) * per_kg
        if self._leg_set is not None:  # the common case, in one compiled call from readings to (ν, H, R0)
            nu, H, R0 = self._leg_set.observe(x, prepared if dg_dm is None else np.concatenate((inputs, z)))
            if dg_dm is not None:
                H[:, self._payload] = dg_dm[:, None]
            return nu, H, R0
        if observed is None:
            return self._observe_tight(inputs, z, theta, x, dg_dm)
        residual, H_drive, R_meas, J_x = drive.observation(
            x_drive, observed.R, observed.t, inputs, observed.covariance, self._coordinate_sigma
        )
        H_instrument = None if self._instrument is None else J_x @ observed.J_instrument
        H = self._with_blocks(H_drive, H_instrument, dg_dm)
        redundant = observed.redundant
        if redundant is None or self._instrument is None:
            return -residual, H, R_meas
        # what the measurement holds beyond the pose: rows on the instrument's unknowns alone
        H_redundant = np.zeros((len(redundant.r), self.layout.size))
        H_redundant[:, self._instrument] = redundant.J_instrument
        R_all = np.zeros((len(H) + len(H_redundant),) * 2)
        R_all[: len(H), : len(H)], R_all[len(H) :, len(H) :] = R_meas, redundant.covariance
        return np.concatenate((-residual, -redundant.r)), np.vstack((H, H_redundant)), R_all

    def _with_blocks(
        self, H_drive: np.ndarray, H_instrument: np.ndarray | None, H_payload: np.ndarray | None = None
    ) -> np.ndarray:
        """``H`` over the whole unknown vector: the drive's ``∂r/∂x_drive``, ``H_instrument`` on θ,
        ``H_payload`` on the unannounced payload."""
        if H_instrument is None and H_payload is None and H_drive.shape[1] == self.layout.size:
            return H_drive
        H = np.zeros((len(H_drive), self.layout.size))
        H[:, : self.drive.size] = H_drive
        if H_instrument is not None:
            H[:, self._instrument] = H_instrument
        if H_payload is not None:
            H[:, self._payload] = H_payload[:, None]
        return H

    def _observe_tight(
        self, inputs: np.ndarray, z: np.ndarray, theta: np.ndarray, x: np.ndarray, dg_dm: np.ndarray | None
    ):
        """The instrument's residual at the drive model's pose (see the module docstring);
        ``SampleRejected`` when the drive model's FK fails."""
        drive = self.drive
        x_drive = x[: drive.size]
        R, t = self._drive_fk.solve_drive(drive, inputs, x_drive, "drive model")
        J_g, dg_dx = drive.jacobians(x_drive, R, t, inputs)
        J_g_inv = np.linalg.inv(J_g)
        channels = np.concatenate(self.model.groups(z))
        res = self.model.residual(R, t, theta, z, channels)
        moves = res.J_pose @ J_g_inv  # the drive model's pose moves with the drive's residuals
        H = -self._with_blocks(moves @ dg_dx, None, None if dg_dm is None else moves @ dg_dm)
        if self._instrument is not None:
            H[:, self._instrument] += res.J_instrument
        # a stroke moves the drive model's pose: ∂ξ/∂q = −J_g⁻¹ ∂r/∂q
        A = res.J_pose @ J_g_inv * -drive.stroke_gains(x_drive, R, t, inputs)
        R_meas = np.diag(self.model.channel_sigma[channels] ** 2) + self._coordinate_sigma**2 * (A @ A.T)
        return -res.r, H, 0.5 * (R_meas + R_meas.T)

    def samples_held(self) -> int:
        """Samples held to register the instrument, not yet used (:class:`HeldForRegistration`)."""
        return self._held.waiting()

    def recovery_summary(self) -> dict | None:
        """Lock-out recoveries and the samples they dropped and readmitted (see :class:`RobustFilter`)."""
        return self.robust.recovery_summary()

    def payload_change_summary(self) -> dict | None:
        """The samples its payload steps moved out of and into the estimate (see :class:`RobustFilter`)."""
        return self.robust.payload_change_summary()

    def take_late_rejections(self) -> list[SampleRejected]:
        """Start-up samples the robust batch left out once decided, and those an unannounced payload's step was
        taken at without them (see :class:`RobustFilter`)."""
        return self._held.take_late() + self.robust.take_late_rejections() + self.robust.take_step_refusals()

    def noise_scale(self) -> float | None:
        """The measurement noise found in the data as a multiple of the configured σ (None
        before the start-up batch has the redundancy to tell, or with fixed noise)."""
        return float(np.sqrt(self.robust.noise_scale2)) if self.robust.measured_noise else None

    def estimate(self) -> Estimate:
        """The unknown vector and ``P`` after the last accepted sample (with an unannounced payload,
        its result fields, :meth:`~.robust.RobustFilter.payload_details`)."""
        estimate = self.filter.estimate()
        if self._payload is None:
            return estimate
        return dataclasses.replace(estimate, details={**(estimate.details or {}), **self.robust.payload_details()})

    def relinearised(self, samples: Iterable[Sample]) -> Estimate | None:
        """:class:`~.base.Relinearising`: :meth:`optimum_from` the filter's estimate."""
        return self.optimum_from(self.estimate(), samples)

    def optimum_from(self, estimate: Estimate, samples: Iterable[Sample]) -> Estimate | None:
        """The MAP of this filter's prior and ``samples`` by Gauss–Newton from ``estimate`` (of this filter's
        unknown vector; :meth:`~.robust.RobustFilter.optimum_from`), as an estimate of this method; None where
        it does not settle.

        Raises:
            SampleRejected: a sample this filter would refuse (give those it used).
        """
        times, prepared = [], []
        for sample in samples:
            strokes, z = check_sample(self.platform, self.model, sample)
            times.append(sample.t_s)
            prepared.append(self._prepared(strokes, z, sample))
        at = np.concatenate((estimate.error, estimate.block_error))
        optimum = self.robust.optimum_from(np.array(times), np.array(prepared), at)
        if optimum is None:
            return None
        x, P = optimum
        n = estimate.layout.n_params
        return dataclasses.replace(estimate, error=x[:n], block_error=x[n:], covariance=P[:n, :n], full_covariance=P)

    def current_estimate(self) -> Estimate:
        """``estimate()``: the filter carries its covariance anyway."""
        return self.estimate()

    def current_error(self) -> np.ndarray:
        """δM [mm] after the last accepted sample."""
        return self.filter.x[: self.drive.n_params].copy()

    def export_state(self) -> dict:
        """Filter, pose warm start and samples held for registration as arrays (checkpoints;
        :meth:`import_state` restores). The warm start keeps its first key, ``tracker_fk``, so
        earlier checkpoints still load."""
        state: dict = {"robust": self.robust.export_state(), "tracker_fk": self._pose.export_state()}
        drive_fk = self._drive_fk.export_state()
        if drive_fk:
            state["drive_fk"] = drive_fk
        if self._held.active:
            state["held"] = self._held.export_state()
        if self._forces_geometry is not None:
            state["forces_at"] = self._forces_geometry.copy()
        return state

    def import_state(self, state: dict) -> None:
        """Restore :meth:`export_state` exactly. Raises ``CalibError`` on a bad key or shape."""
        self.robust.import_state(state.get("robust", {}))
        # a prepared row's layout follows the model (an elastic drive seen through an instrument with
        # unknowns adds the load column): rows of another layout would be misread, not refused
        width = self.drive.input_width + self._per_kg + self._packed_width + len(self.model.columns)
        if self.robust.buffered_width() not in (None, width):
            raise CalibError(
                f"estimator state: buffered samples of {self.robust.buffered_width()} columns, expected {width} "
                "for this platform and settings (a checkpoint of another version of the model)"
            )
        self._pose.import_state(state.get("tracker_fk", {}))
        self._drive_fk.import_state(state.get("drive_fk", {}))
        forces_at = state.get("forces_at")
        self._forces_geometry = None if forces_at is None else state_array(state, "forces_at", (self.drive.size,))
        # afresh, so a roll-back (isam2's front end) holds exactly the state's samples again
        self._held = HeldForRegistration(self.platform, self.noise, self.model, self.layout)
        self._held.restore(state, self.update)
