"""Estimators sharing the protocols of :mod:`.base`, listed once in :mod:`.registry`:
``ls``, ``paper-ekf``, ``ekf``, ``isam2``, ``lm``."""

from __future__ import annotations

from .base import BatchEstimator, Checkpointable, Estimator, KalmanFiltered, Relinearising, fit_all
from .registry import METHODS, MethodSpec, make_estimator, method_names, method_spec

__all__ = [
    "METHODS",
    "BatchEstimator",
    "Checkpointable",
    "Estimator",
    "KalmanFiltered",
    "MethodSpec",
    "Relinearising",
    "fit_all",
    "make_estimator",
    "method_names",
    "method_spec",
]
