"""The one list of estimation methods: every other list (the CLI's choices, ``track``'s online
methods, the reproduction, the benchmarks) is derived from :data:`METHODS`.

Each entry says what the method is — online (updates per sample) or batch (fits the log),
checkpointable (``track`` can save and resume it), which instruments it can use — and where its
class lives, imported on first use so that naming a method does not load gtsam or numba.
Every class is built the same way, ``Class(platform, config)``.

Adding a method: write ``estimators/<module>.py`` implementing the protocols of
:mod:`.base`, and add one :class:`MethodSpec` below (docs/architecture.md).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

from ..config import EstimatorConfig
from ..errors import CalibError
from ..model.platform import Platform
from .base import BatchEstimator, Checkpointable, Estimator


@dataclass(frozen=True)
class MethodSpec:
    """One estimation method.

    Attributes:
        name: what users type (``--method``) and results carry.
        target: ``"module:Class"``; a module starting with ``.`` is in :mod:`stewart_calib.estimators`.
        online: updates per sample (``track``, the closed loop); otherwise it fits the whole log.
        checkpointable: its state can be saved and restored exactly (a :class:`Checkpointable`).
        instruments: the instrument kinds (``[instrument] kind``) it can calibrate with.
        summary: one line for ``--help`` and the docs.
        tracker_geometry: it identifies the in-situ tracker's own geometry with the drive
            (``noise.tracker_geometry_sigma_mm``); ``ls`` and ``paper-ekf`` fit the drive to the measured
            pose alone and refuse it.
        bytes_per_sample: the memory a batch method holds for each sample of the log [bytes]
            (:func:`~stewart_calib.memory.check_memory` says it before a run and refuses a log
            that would not fit); None for a method whose memory does not grow with the log.
    """

    name: str
    target: str
    online: bool
    checkpointable: bool
    instruments: tuple[str, ...]
    summary: str
    bytes_per_sample: int | None = None
    tracker_geometry: bool = True

    def build(self, platform: Platform, config: EstimatorConfig | None = None) -> Estimator:
        """The estimator for ``platform``, checked against the protocols this entry declares."""
        module_name, class_name = self.target.split(":")
        cls = getattr(importlib.import_module(module_name, __package__), class_name)
        estimator = cls(platform, config or EstimatorConfig())
        promised = [(Estimator, True), (BatchEstimator, not self.online), (Checkpointable, self.checkpointable)]
        missing = [protocol.__name__ for protocol, wanted in promised if wanted and not isinstance(estimator, protocol)]
        if missing:
            raise TypeError(f"{self.target} does not implement {', '.join(missing)} as the registry declares")
        return estimator


#: every method, in the order lists and tables show them.
METHODS: dict[str, MethodSpec] = {
    spec.name: spec
    for spec in (
        MethodSpec(
            "ls",
            ".ls:LeastSquares",
            online=False,
            checkpointable=False,
            instruments=("tracker", "pose", "points"),
            summary="the paper's batch least squares on the pose error (eq. 9–11)",
            # its compact rows and the log read whole: the peak RSS's slope of calibrate ls from
            # 10⁵ to 10⁶ samples of benchmarks/scale.py's log (290 → 720 MB)
            bytes_per_sample=500,
            tracker_geometry=False,
        ),
        MethodSpec(
            "paper-ekf",
            ".paper_ekf:PaperEKF",
            online=True,
            checkpointable=True,
            instruments=("tracker", "pose"),
            summary="the paper's EKF on the pose error (eq. 14–19)",
            tracker_geometry=False,
        ),
        MethodSpec(
            "ekf",
            ".ekf:LegEKF",
            online=True,
            checkpointable=True,
            instruments=("tracker", "pose", "points"),
            summary="EKF on the leg-length model, the factor graph's noise model",
        ),
        MethodSpec(
            "isam2",
            ".isam2:ISAM2Estimator",
            online=True,
            checkpointable=True,
            instruments=("tracker", "pose", "points"),
            summary="factor graph solved online by iSAM2 in a fixed-lag smoother",
        ),
        MethodSpec(
            "lm",
            ".lm:BatchLM",
            online=False,
            checkpointable=False,
            instruments=("tracker", "pose", "points"),
            summary="the same factor graph solved in batch by Levenberg–Marquardt",
            # every sample's factors and values in gtsam's graph: the peak RSS's slope from 10³ to 10⁴
            # samples of benchmarks/scale.py's log (197 → 332 MB)
            bytes_per_sample=15_000,
        ),
    )
}


def method_names(
    online: bool | None = None, checkpointable: bool | None = None, instrument: str | None = None
) -> tuple[str, ...]:
    """Names of the methods with the given properties (None: either), in :data:`METHODS` order."""
    return tuple(
        spec.name
        for spec in METHODS.values()
        if (online is None or spec.online == online)
        and (checkpointable is None or spec.checkpointable == checkpointable)
        and (instrument is None or instrument in spec.instruments)
    )


def method_spec(method: str, allowed: tuple[str, ...] | None = None, what: str = "method") -> MethodSpec:
    """The entry of ``method``.

    Args:
        allowed: the names acceptable here (default: all), e.g. ``method_names(online=True)``.
        what: how messages call the method (``online method``).
    Raises:
        CalibError: an unknown or not allowed method, listing the allowed ones.
    """
    allowed = tuple(METHODS) if allowed is None else allowed
    if method not in allowed:
        raise CalibError(f"unknown {what} '{method}': expected one of {', '.join(allowed)}")
    return METHODS[method]


def make_estimator(method: str, platform: Platform, config: EstimatorConfig | None = None) -> Estimator:
    """Build the estimator named ``method`` for ``platform``.

    Raises:
        CalibError: an unknown method, or one that does not take the platform's instrument.
    """
    spec = method_spec(method)
    kind = platform.instrument.kind
    if kind not in spec.instruments:
        raise CalibError(
            f"method '{method}' does not take the {kind} instrument of {platform.source}; "
            f"expected one of {', '.join(method_names(instrument=kind))}"
        )
    misfit = 0.0 if config is None else config.noise.pose_misfit_sigma_mm
    if misfit > 0.0 and kind != "tracker":
        raise CalibError(
            f"noise.pose_misfit_sigma_mm = {misfit:g} (--set or the config file): the in-situ tracker's misfit "
            f"at a pose, but the instrument of {platform.source} is '{kind}'; expected 0 (no such key) for it"
        )
    return spec.build(platform, config)
