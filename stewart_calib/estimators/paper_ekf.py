"""The paper's EKF (§3.2, eq. 14–19; Q and R of §4.1; Fig. 3 steps 1–4).

State ``X = δM`` (the drive's ``n_params``, 42 in paper order), random-walk prediction
``P ← P + Q`` per update (eq. 14–15), observation ``Y = P_v − P_m = J_k X + E`` (eq. 16) with
``J_k = J_p`` (eq. 9–11). ``P_v`` is the measured pose (the tracker's: FK of the readings, step 1; or a
pose instrument's, through its frame and target). ``P_m`` is the pose
the *current* model ``M + X`` predicts for the executed strokes, and ``J_p`` is taken at
that model and pose: a true EKF, which at ``X = 0`` is exactly the paper's form and which
stays right when the controller already compensates with an earlier estimate.

The orientation rows of ``Y`` and ``J_p`` are in ``angle_unit`` (rad by default, or deg):
the paper gives ``R = 4e-2 I`` without units and reports orientation in degrees, and which
it meant decides how much the filter trusts the tracker's orientation.

With a ``pose`` instrument (motion capture) the state stays the paper's ``δM``: the instrument's
frame and target are fixed at their closed-form registration on the first samples (held, then
replayed, as in the leg-length EKF) and the strokes at the encoders' nominal scale — the paper's
model has neither unknown; ``ekf``, ``isam2`` and ``lm`` identify them. A platform with
``[elastic]`` (spec §10) keeps the paper's state too: each leg's compliance is held at its nominal
value, the leg forces taken at ``P_v`` under the sample's payload (its input channels).

Optional adaptive Q/R (paper ref. [28]; innovation-based, Mohamed & Schwarz 1999): over
the last ``adaptive_window`` updates, ``R = mean(ν νᵀ − H P⁻ Hᵀ)`` with its eigenvalues
floored at ``adaptive_min_variance`` (positive definite), and ``Q = mean(Δx Δxᵀ)`` with
``Δx = K ν`` (positive semidefinite). Both are used from the update after the window fills.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..config import EstimatorConfig
from ..errors import CalibError, SampleRejected
from ..estimate import Estimate
from ..instruments import instrument_kind, instrument_model, instrument_theta
from ..model import kinematics as kin
from ..model.drive import drive_model
from ..model.platform import Platform
from ..model.unknowns import UnknownLayout
from ..samples import Sample
from .base import checked_covariance, state_array
from .kalman import FilterState
from .measurement import (
    HeldForRegistration,
    WarmFK,
    WarmPose,
    check_sample,
    drive_only_model,
    measured_pose,
    pose_difference,
    unknown_layout,
)

#: rows of the observation ``Y = P_v − P_m``: a pose6 difference ``[mm, rad]``, whatever the leg set.
POSE_ROWS = 6


class PaperEKF:
    """The paper's pose-error EKF; ``update(sample)`` then ``estimate()``.

    Attributes:
        filter: the :class:`FilterState` (``x``, ``P``, ``Q``, last NIS).
        R: ``(POSE_ROWS, POSE_ROWS)`` measurement covariance in use (adapted when ``adaptive``).
    """

    name = "paper-ekf"

    def __init__(self, platform: Platform, config: EstimatorConfig):
        c = config.paper_ekf
        if platform.drive.kind != "prismatic":  # eq. 8–11: the error Jacobian of prismatic legs
            raise CalibError(
                f"{platform.source}: paper-ekf models the paper's prismatic legs, not a {platform.drive.kind} "
                "drive; use ekf, isam2, lm or ls"
            )
        if platform.elastic is not None:  # the paper's model identifies δM alone: c held at [elastic]'s nominal
            platform = replace(platform, elastic=replace(platform.elastic, compliance_sigma_mm_per_kN=0.0))
        self.platform = platform
        self.config = c
        self.model = _pose_error_model(platform, config)
        self._drive = drive_model(platform)
        self._layout = unknown_layout(platform, config.noise, self.model)
        self._held = HeldForRegistration(platform, config.noise, self.model, self._layout)
        self._theta = instrument_theta(self.model, None)  # the pose instrument's frame and target, once registered
        n_params = self._drive.n_params
        self.filter = FilterState(
            self.name, config.noise.prior_sigma_mm, c.gate_probability, POSE_ROWS, UnknownLayout(n_params=n_params)
        )
        self._noise = config.noise
        self.filter.Q[np.diag_indices(n_params)] = c.process_noise
        self.R = np.eye(POSE_ROWS) * c.measurement_noise
        # Y's orientation rows in the unit R is meant for: the paper states R = 4e-2 I without units.
        self._unit_scale = np.r_[np.ones(3), np.full(3, 1.0 if c.angle_unit == "rad" else np.degrees(1.0))]
        self._tracker_fk = WarmPose(self.model)
        self._model_fk = WarmFK()
        window = max(1, c.adaptive_window)
        self._innovations = np.zeros((window, POSE_ROWS))
        self._predicted = np.zeros((window, POSE_ROWS, POSE_ROWS))  # H P⁻ Hᵀ
        self._corrections = np.zeros((window, n_params))  # K ν
        self._filled = 0

    def update(self, sample: Sample) -> None:
        """Fold in one sample (Fig. 3 steps 1–3); ``SampleRejected`` leaves the state untouched.
        A pose instrument's first samples are held until they register it, then replayed."""
        strokes, z = check_sample(self.platform, self.model, sample)
        if not self._held.active:
            self._update(strokes, z, sample.t_s, sample.inputs)
            return
        self._held.hold_then_replay(sample, self._registered, self._replay)

    def samples_held(self) -> int:
        """Samples held to register the instrument, not yet used (:class:`HeldForRegistration`)."""
        return self._held.waiting()

    def take_late_rejections(self) -> list[SampleRejected]:
        """Held samples the replay after the registration refused (see :class:`HeldForRegistration`)."""
        return self._held.take_late()

    def _registered(self, start: np.ndarray) -> None:
        self._theta = instrument_theta(self.model, start[self._layout.slice("instrument")])

    def _replay(self, held: Sample) -> None:
        self._update(*check_sample(self.platform, self.model, held), held.t_s, held.inputs)

    def _update(self, strokes: np.ndarray, z: np.ndarray, t_s: float, channels=None) -> None:
        R_v, t_v = measured_pose(self._tracker_fk, z, t_s, self._theta)
        # the drive's nominal terms (spec §7; an elastic drive's forces at P_v, spec §10)
        strokes = self._drive.extensions(self._drive.inputs(strokes, channels, R_v, t_v))
        drive = self.platform.prismatic_drive("paper-ekf").perturbed(self.filter.x)
        R_m, t_m = self._model_fk.solve(drive, strokes, "drive model")
        Y = pose_difference(R_v, t_v, R_m, t_m) * self._unit_scale
        J_k = kin.error_jacobian(drive, R_m, t_m) * self._unit_scale[:, None]
        x_before = self.filter.x.copy()
        self.filter.update(J_k, Y, self.R, t_s)
        if self.config.adaptive and self.filter.S is not None:  # S: set by every update
            self._adapt(Y, self.filter.S - self.R, self.filter.x - x_before)

    def _adapt(self, innovation: np.ndarray, HPHt: np.ndarray, correction: np.ndarray) -> None:
        k = self._filled % len(self._innovations)
        self._innovations[k] = innovation
        self._predicted[k] = HPHt
        self._corrections[k] = correction
        self._filled += 1
        if self._filled < len(self._innovations):
            return
        nu = self._innovations
        R = (nu.T @ nu) / len(nu) - self._predicted.mean(axis=0)
        eigenvalues, vectors = np.linalg.eigh(0.5 * (R + R.T))
        self.R = (vectors * np.maximum(eigenvalues, self.config.adaptive_min_variance)) @ vectors.T
        dx = self._corrections
        self.filter.Q[:] = (dx.T @ dx) / len(dx)

    def estimate(self) -> Estimate:
        """``δM`` and ``P`` after the last accepted sample; with a pose instrument also the frame and
        target it was registered at (held fixed: their rows and columns of the covariance are 0),
        which ``validate`` and ``compensate`` need to read the drive in the same frame."""
        block = self._layout.block("instrument")
        if block is None:
            return self.filter.estimate()
        f, n_params = self.filter, self._drive.n_params
        n = n_params + block.size
        P = np.zeros((n, n))
        P[:n_params, :n_params] = f.P
        return Estimate.of_state(
            np.concatenate((f.x, self._theta - block.nominal)),
            P,
            UnknownLayout((block,), n_params=n_params),
            self.name,
            f.samples_used,
            f.t_s,
        )

    def current_estimate(self) -> Estimate:
        """``estimate()``: the filter carries its covariance anyway."""
        return self.estimate()

    def current_error(self) -> np.ndarray:
        """δM [mm] after the last accepted sample."""
        return self.filter.x.copy()

    def export_state(self) -> dict:
        """Filter, R, adaptive window, FK warm starts and the instrument's registration (or the
        samples held for it) as arrays (checkpoints)."""
        state = {
            "filter": self.filter.export_state(),
            "R": self.R.copy(),
            "innovations": self._innovations.copy(),
            "predicted": self._predicted.copy(),
            "corrections": self._corrections.copy(),
            "filled": np.int64(self._filled),
            "tracker_fk": self._tracker_fk.export_state(),
            "model_fk": self._model_fk.export_state(),
            "instrument_theta": self._theta.copy(),
        }
        if self._held.active:
            state["held"] = self._held.export_state()
        return state

    def import_state(self, state: dict) -> None:
        """Restore :meth:`export_state` exactly. Raises ``CalibError`` on a bad key or shape."""
        self.filter.import_state(state.get("filter", {}))
        self.R = checked_covariance(state_array(state, "R", (POSE_ROWS, POSE_ROWS)), "R")
        self._innovations = state_array(state, "innovations", self._innovations.shape)
        self._predicted = state_array(state, "predicted", self._predicted.shape)
        self._corrections = state_array(state, "corrections", self._corrections.shape)
        self._filled = int(state_array(state, "filled", ()))
        self._tracker_fk.import_state(state.get("tracker_fk", {}))
        self._model_fk.import_state(state.get("model_fk", {}))
        if "instrument_theta" in state:  # a tracker-only checkpoint may lack it: the tracker's θ is ()
            self._theta = state_array(state, "instrument_theta", self._theta.shape)
        self._held = HeldForRegistration(self.platform, self._noise, self.model, self._layout)
        self._held.restore(state, self.update)


def _pose_error_model(platform: Platform, config: EstimatorConfig):
    """The instrument model whose pose is ``P_v``: the tracker (its geometry known), or a pose
    instrument (the registry refuses the others). Raises ``CalibError`` for unknowns the
    configuration asks to identify beyond δM."""
    model = instrument_model(platform, config.noise)
    if not instrument_kind(platform).outside:
        return drive_only_model(PaperEKF.name, platform, config)
    drive = drive_model(platform, config.noise)
    extra = [block.key.replace("_", " ") for block in drive.blocks]
    if extra:
        raise CalibError(
            f"paper-ekf identifies the {drive.n_params} drive parameters only, not the {', '.join(extra)} "
            "(the [noise] settings ask for it); use ekf, isam2 or lm"
        )
    return model
