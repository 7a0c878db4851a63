"""Estimator settings: typed dataclasses with documented defaults, loaded from TOML.

``configs/estimators/default.toml`` mirrors these defaults with comments. Every estimator
takes the whole :class:`EstimatorConfig`; the ``[noise]`` section is shared so that the
EKFs and the factor graph use the same process and measurement noise.
"""

from __future__ import annotations

import dataclasses
import sys
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from .errors import CalibError, did_you_mean, shown
from .inputs import check_document, implausible_sigma_mm
from .resources import read_toml


@dataclass(frozen=True)
class NoiseConfig:
    """Noise model shared by ``ekf``, ``isam2`` and ``lm``.

    Attributes:
        reading_sigma_mm: σ_s of one tracker grating reading [mm]: ruler noise plus the
            tracker's residual geometry error, taken as white. The default 2 µm suits a tracker
            whose geometry is known to a few µm; the simulated nim-stewart tracker (15 µm
            geometry residual) needs ~0.02 mm where its geometry is taken as exact
            (``configs/estimators/paper.toml``), or every reported covariance is far too small —
            ``estimate_tracker_geometry`` identifies the geometry instead, and the white σ stays.
        stroke_sigma_mm: σ_q of one executed drive stroke [mm] (encoder).
        random_walk_mm_per_sqrt_s: parameter random walk [mm/√s]: over Δt each parameter's
            variance grows by ``random_walk² Δt`` (paper eq. 15's Q; graph between-factors).
        prior_sigma_mm: prior σ of each δM component [mm] (manufacturing tolerance).
        stroke_scale_sigma: prior σ of each stroke scale k_i (dimensionless; drive leg
            ``l_i + (1 + k_i) q_i``, spec §7); 0 leaves the scale out of the unknowns (the
            encoders' nominal scale is taken as exact) with the tracker, and means 0.05 with an
            instrument outside the robot (whose encoders are rarely known better; ``ls`` has
            its own ``stroke_scale`` switch).
        tracker_geometry_sigma_mm: prior σ of the in-situ tracker's own 42 values [mm]: with it
            positive they are identified with the drive under N(nominal, σ²) (spec §7), as the
            platform file's ``[tracker] geometry_sigma_mm`` asks, which wins where it is given;
            0 takes the tracker's geometry as exact, unless ``estimate_tracker_geometry`` finds it off.
        estimate_tracker_geometry: ``calibrate`` with the in-situ tracker and a method that identifies its
            geometry (``ekf``, ``isam2``, ``lm``), where neither the platform file nor
            ``tracker_geometry_sigma_mm`` gives its σ: measure the σ of the tracker's own geometry error on
            the log (:mod:`stewart_calib.workflows.tracker_geometry`: the readings' residuals after a drive
            fit, split into white noise and what an error of the 42 values moves) and, where the log shows
            one, identify the geometry with the drive under that σ, the readings at the white σ measured
            beside it (``reading_sigma_mm``, which would otherwise count the error twice) — the reported
            covariance then holds what a tracker's geometry error does to the result. A tracker the log
            shows as exact keeps its geometry fixed, and nothing changes. false: the geometry as the
            settings give it.
        pose_misfit_sigma_mm: σ of the in-situ tracker's reading error that stays while the platform
            holds a pose [mm] — its geometry's residual seen through the pose, less what the drive's
            parameters take up of it — besides the white noise ``reading_sigma_mm``: ekf (and isam2's front
            end) carry it as a misfit drawn afresh at each pose (the ``pose_misfit`` of
            :class:`~stewart_calib.estimators.robust.RobustFilter`), so the samples of a static pose count
            as their mean, not as independent readings; 0: every reading independent — but where ekf tests
            an unannounced payload's steps, which it then takes as large as ``reading_sigma_mm``.
        angle_prior_sigma_deg: a rotary drive's (spec §15) prior σ of each angle of δM — zero
            offsets ``o_i`` and axis tilts ``tu_i``, ``tw_i`` [deg]; its lengths take ``prior_sigma_mm``.
        angle_sigma_deg: σ of one commanded servo angle [deg]: the rotary leg's analog of
            ``stroke_sigma_mm``, entering the measurement covariance through ``∂r_i/∂e_i``.
        angle_random_walk_deg_per_sqrt_s: a rotary drive's random walk of those angles [deg/√s].
    """

    reading_sigma_mm: float = 0.002
    stroke_sigma_mm: float = 0.001
    random_walk_mm_per_sqrt_s: float = 1e-3
    prior_sigma_mm: float = 5.0
    stroke_scale_sigma: float = 0.0
    tracker_geometry_sigma_mm: float = 0.0
    estimate_tracker_geometry: bool = True
    pose_misfit_sigma_mm: float = 0.0
    angle_prior_sigma_deg: float = 2.0
    angle_sigma_deg: float = 0.05
    angle_random_walk_deg_per_sqrt_s: float = 1e-3


@dataclass(frozen=True)
class LSConfig:
    """The paper's batch least squares (Gauss–Newton on ``P_v − P_m = J_p δM``).

    Attributes:
        tolerance_mm: stop when the largest step component is below this [mm]. FK solves
            lengths to 1e-9 mm, which puts a ~1e-8 mm noise floor under the step (× the
            conditioning), so much tighter values never converge on inconsistent data.
        max_iterations: Gauss–Newton iteration cap.
        weighting: how the in-situ tracker's pose rows ``P_v − P_m`` are weighed. ``noise``:
            each sample's six rows whitened by their covariance, the readings' and strokes' noise
            (``[noise]``) through both forward kinematics — generalised least squares, the
            maximum-likelihood fit to first order, at the Cramér–Rao bound that ``identifiability``
            and ``plan`` predict. ``paper``: the paper's pose-form fit, the rotation rows scaled by
            ``rotation_weight_mm`` (the paper reproduction's ``configs/estimators/paper.toml``); on
            planned poses it leaves 1.3–1.4× the bound's error.
        rotation_weight_mm: with ``weighting = "paper"``, the rotation rows of ``δE`` [rad] are
            multiplied by this length [mm] so that both halves of the residual are in mm and weigh
            alike (about the platform radius; it also lowers the condition number ~4×,
            docs/measured-facts.md). 1.0 is the paper's unweighted form.
        robust_k: instruments outside the robot (spec §7): Huber threshold on a reading's RMS
            whitened residual [σ]; 0 = plain least squares. At 3 σ a Gaussian reading is almost
            never down-weighted (RMS of 6 normals > 3: p ≈ 1e-11), a glitch is; a reading 4× past
            the threshold is a gross error and gets no weight.
        estimate_noise: instruments outside the robot: re-estimate the σ of position and
            orientation from the residuals (the platform file's σ is only the start), so their
            relative weight is the data's own and the reported covariance is honest.
        stroke_scale: ``auto`` (identify k1..k6 where the strokes make them identifiable),
            ``on`` or ``off`` (held at the platform file's ``[drive] stroke_scale``).
    """

    tolerance_mm: float = 1e-7
    max_iterations: int = 20
    weighting: str = "noise"
    rotation_weight_mm: float = 300.0
    robust_k: float = 3.0
    estimate_noise: bool = True
    stroke_scale: str = "auto"

    #: the ``[ls]`` key of :attr:`drive_blocks`, for the messages that suggest it
    DRIVE_BLOCKS_KEY: ClassVar[str] = "stroke_scale"

    @property
    def drive_blocks(self) -> str:
        """Whether the fit identifies the drive model's unknown blocks (``auto``, ``on``, ``off``):
        the ``stroke_scale`` switch, named when the stroke scale was the drive's only block."""
        return self.stroke_scale


@dataclass(frozen=True)
class PaperEKFConfig:
    """The paper's EKF (eq. 14–19, §4.1).

    Attributes:
        process_noise: diagonal of Q per update (paper: 1e-5) [mm² / rad²-mixed, as the paper].
        measurement_noise: diagonal of R (paper: 4e-2).
        adaptive: innovation-based adaptive Q/R (paper ref. [28]).
        adaptive_window: innovations averaged by the adaptive update.
        adaptive_min_variance: floor on the eigenvalues of the adapted R (keeps it positive
            definite when the windowed innovation covariance falls below ``H P Hᵀ``).
        gate_probability: χ² innovation gate (0 = off); samples beyond it are rejected.
        angle_unit: ``rad`` or ``deg``, the unit of the orientation rows of Y = P_v − P_m that
            ``measurement_noise`` applies to (the paper does not say).
    """

    process_noise: float = 1e-5
    measurement_noise: float = 4e-2
    adaptive: bool = False
    adaptive_window: int = 50
    adaptive_min_variance: float = 1e-12
    gate_probability: float = 0.9999
    angle_unit: str = "rad"


@dataclass(frozen=True)
class EKFConfig:
    """EKF on the leg-length model (same noise as the graph, from ``[noise]``).

    Attributes:
        gate_probability: χ² innovation gate (0 = off); samples beyond it are rejected.
    """

    gate_probability: float = 0.9999


@dataclass(frozen=True)
class ISAM2Config:
    """Factor graph solved online by iSAM2 in a fixed-lag smoother.

    Attributes:
        gate_probability: χ² gate of the robust front end that decides which samples enter
            the graph (0 = off; :mod:`stewart_calib.estimators.robust`), and of ``lm``'s test of
            each sample's residuals at its solution, which leaves gross errors out (:mod:`.estimators.lm`).
        coupling: ``tight`` (one factor per tracker reading) or ``loose`` (tracker FK pose prior).
        window_s: a new parameter variable every ``window_s`` seconds [s]; ``isam2`` shortens a window
            to ``q₀ / q`` of it where the walk rate ``q`` its front end measures is above the configured
            ``q₀`` (``ISAM2._window_fraction``).
        window_samples: if > 0, a new parameter variable every this many samples instead (shortened alike).
        chain_sigma_floor_mm: least σ of the random walk between parameter variables [mm]; with
            random walk 0, ``isam2`` ties its chain of variables with this near-hard σ (a single
            static variable inside the fixed-lag smoother keeps growing), ``lm`` uses one variable.
        lag_s: smoother lag [s]; older variables are marginalised.
        robust: ``none``, ``huber`` or ``cauchy`` kernel on measurement factors.
        robust_k: kernel width in σ units.
        factorization: ``QR`` or ``CHOLESKY``.
        relinearize_threshold_mm: iSAM2 relinearises δM and pose translations whose step since
            the last linearisation exceeds this [mm]. 1e-2 mm: the linearisation error it
            leaves is ≈ δ²/L ≈ 1e-7 mm, while 1e-3 mm relinearised δM (and so every factor in
            the lag) at almost every update, 6× slower for the same estimate.
        relinearize_threshold_rad: the same for pose rotations [rad].
    """

    gate_probability: float = 0.9999
    coupling: str = "tight"
    window_s: float = 1.0
    window_samples: int = 0
    chain_sigma_floor_mm: float = 1e-5
    lag_s: float = 3.0
    robust: str = "none"
    robust_k: float = 3.0
    factorization: str = "QR"
    relinearize_threshold_mm: float = 1e-2
    relinearize_threshold_rad: float = 1e-5


@dataclass(frozen=True)
class RobustConfig:
    """Robust start-up, lock-out recovery and noise levels from the data, shared by ``ekf`` and
    ``isam2`` (:mod:`stewart_calib.estimators.robust`; their ``gate_probability`` is the gate).

    Attributes:
        startup_samples: the first samples solved as a robust batch (each one tested against
            the others at their median noise scale) before the gated recursion takes over. 30
            samples of 6 residuals leave 138 degrees of freedom over the 42 parameters.
        lockout_window_samples, lockout_gated_samples: when this many of the last window of
            samples are gated, the state is re-solved from the recent samples (clean data are
            gated once in 10⁴ at the default gate; 8 of 20 with 5 % glitches has odds ~1e-6).
        adapt_noise: estimate the scale of the measurement noise and of the random walk from
            the innovations (variance components); false: the ``[noise]`` values as given.
        noise_memory_samples: samples over which those estimates forget (exponential), counted
            in the windows they are taken from.
        noise_every_samples: once the first windows have given the random walk (12 differences),
            the noise estimates are taken every this many accepted samples (at least every window)
            from the window of the last ``max(startup_samples, lockout_window_samples)`` samples:
            a window's batch costs what the recursion does per sample, so taking one every window
            would double the cost of every sample.
    """

    startup_samples: int = 30
    lockout_window_samples: int = 20
    lockout_gated_samples: int = 8
    adapt_noise: bool = True
    noise_memory_samples: int = 300
    noise_every_samples: int = 240


@dataclass(frozen=True)
class EstimatorConfig:
    """All estimator settings; see ``configs/estimators/default.toml``."""

    noise: NoiseConfig = field(default_factory=NoiseConfig)
    ls: LSConfig = field(default_factory=LSConfig)
    paper_ekf: PaperEKFConfig = field(default_factory=PaperEKFConfig)
    ekf: EKFConfig = field(default_factory=EKFConfig)
    isam2: ISAM2Config = field(default_factory=ISAM2Config)
    robust: RobustConfig = field(default_factory=RobustConfig)


_CHOICES = {
    ("ls", "stroke_scale"): ("auto", "on", "off"),
    ("ls", "weighting"): ("noise", "paper"),
    ("paper_ekf", "angle_unit"): ("rad", "deg"),
    ("isam2", "coupling"): ("tight", "loose"),
    ("isam2", "robust"): ("none", "huber", "cauchy"),
    ("isam2", "factorization"): ("QR", "CHOLESKY"),
}

#: keys with a lower bound above 0, and why: a σ of 0 makes a noise model singular (gtsam
#: cannot factor it); the adaptive R is the covariance of a 6-vector, of full rank only over
#: at least 6 innovations; a window, lag or kernel of 0 is no window, lag or kernel.
_AT_LEAST = {
    ("noise", "reading_sigma_mm"): (0.0, "a positive σ"),
    ("noise", "stroke_sigma_mm"): (0.0, "a positive σ"),
    ("noise", "prior_sigma_mm"): (0.0, "a positive σ"),
    ("paper_ekf", "measurement_noise"): (0.0, "a positive variance"),
    ("paper_ekf", "adaptive_window"): (5, "at least 6 innovations (the covariance of a 6-vector)"),
    ("isam2", "window_s"): (0.0, "a positive window"),
    ("isam2", "lag_s"): (0.0, "a positive lag"),
    ("isam2", "robust_k"): (0.0, "a positive kernel width"),
    ("robust", "lockout_window_samples"): (0, "a window of at least one sample"),
    ("robust", "lockout_gated_samples"): (0, "at least one gated sample"),
    ("robust", "noise_memory_samples"): (1, "a memory of at least two samples"),
    ("robust", "noise_every_samples"): (0, "at least one sample"),
}

#: the χ² gates' probabilities: the share of good samples a gate passes, so below 1 (a gate of
#: probability 1 has no finite threshold, ``chi_square.chi2_quantile``); 0 turns the gate off.
_PROBABILITY_SUFFIX = "_probability"


def _coerce(source: str, key: str, value: Any, default: Any) -> Any:
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise CalibError(f"{source}: key '{key}': expected true or false, got {value!r}")
        return value
    if isinstance(default, (int, float)):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise CalibError(f"{source}: key '{key}': expected a number, got {value!r}")
        if isinstance(default, int) and not isinstance(value, int):
            raise CalibError(f"{source}: key '{key}': expected a whole number, got {value!r}")
        if not value == value or not abs(value) <= sys.float_info.max or value < 0:  # NaN, ±inf, huge integers
            raise CalibError(f"{source}: key '{key}': expected a finite non-negative number, got {value!r}")
        return type(default)(value)
    if not isinstance(value, str):
        raise CalibError(f"{source}: key '{key}': expected a string, got {value!r}")
    return value


def config_from_dict(doc: dict, source: str = "<config>", base: EstimatorConfig | None = None) -> EstimatorConfig:
    """Overlay a ``{section: {key: value}}`` dict on ``base`` (default: the defaults).

    Raises:
        CalibError: an unknown section or key, a wrong type or a value outside its choices.
    """
    config = base or EstimatorConfig()
    sections = {f.name: f for f in dataclasses.fields(EstimatorConfig)}
    updates = {}
    for section, table in doc.items():
        if section not in sections:
            raise CalibError(
                f"{source}: unknown section '{section}'{did_you_mean(section, sections)}: expected one of "
                f"{', '.join(sections)}"
            )
        if not isinstance(table, dict):
            raise CalibError(f"{source}: key '{section}': expected a table")
        current = getattr(config, section)
        known = {f.name for f in dataclasses.fields(current)}
        changes = {}
        for key, value in table.items():
            full = f"{section}.{key}"
            if key not in known:
                hint = did_you_mean(key, known)
                raise CalibError(f"{source}: unknown key '{full}'{hint}: expected one of {', '.join(sorted(known))}")
            value = _coerce(source, full, value, getattr(current, key))
            bound = _AT_LEAST.get((section, key))
            if bound is not None and not value > bound[0]:
                raise CalibError(f"{source}: key '{full}': expected {bound[1]}, got {value!r}")
            if key.endswith(_PROBABILITY_SUFFIX) and not value < 1.0:
                raise CalibError(
                    f"{source}: key '{full}': expected a probability in (0, 1) (0: the gate off), got {value!r}"
                )
            if key.endswith(("_sigma_mm", "_mm_per_sqrt_s")) and value != 0 and implausible_sigma_mm(value):
                raise CalibError(f"{source}: key '{full}': expected {implausible_sigma_mm(value)}")
            choices = _CHOICES.get((section, key))
            if choices and value not in choices:
                raise CalibError(f"{source}: key '{full}': expected one of {', '.join(choices)}, got {value!r}")
            changes[key] = value
        updates[section] = dataclasses.replace(current, **changes)
    return dataclasses.replace(config, **updates)


def load_estimator_config(path: str | Path | None = None, overrides: list[str] | None = None) -> EstimatorConfig:
    """Defaults, then the TOML at ``path``, then ``section.key=value`` overrides (command line).

    Raises:
        CalibError: naming the file (or ``--set``) and the offending key.
    """
    config = EstimatorConfig()
    if path is not None:
        path, doc = read_toml(path, "estimators", "estimator config")
        config = config_from_dict(doc, shown(path), config)
    for item in overrides or []:
        key, sep, text = item.partition("=")
        section, dot, name = key.strip().partition(".")
        if not sep or not dot:
            raise CalibError(f"--set {item!r}: expected section.key=value, e.g. isam2.lag_s=5")
        try:
            value = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = text.strip()
        except (ValueError, RecursionError):  # tomllib's own limits (an integer of 5000 digits)
            raise CalibError(f"--set {shown(item)!r}: not a readable value") from None
        check_document({key.strip(): value}, "--set")
        config = config_from_dict({section: {name: value}}, "--set", config)
    return config
