"""Estimators sharing one protocol (:mod:`.base`): ``ls``, ``paper-ekf``, ``ekf``, ``isam2``, ``lm``."""

from __future__ import annotations

import importlib

from ..errors import CalibError
from .base import Estimate, Estimator, fit_all
from .config import EstimatorConfig, load_estimator_config

#: method name → "module:Class"; each class is built as ``Class(platform, config)``.
METHODS = {
    "ls": "ls:LeastSquares",
    "paper-ekf": "paper_ekf:PaperEKF",
    "ekf": "ekf:LegEKF",
    "isam2": "isam2:ISAM2Estimator",
    "lm": "isam2:BatchLM",
}


def make_estimator(method: str, platform, config: EstimatorConfig | None = None) -> Estimator:
    """Build the estimator named ``method`` for ``platform``.

    Raises:
        CalibError: an unknown method.
    """
    if method not in METHODS:
        raise CalibError(f"unknown method '{method}': expected one of {', '.join(METHODS)}")
    module_name, class_name = METHODS[method].split(":")
    module = importlib.import_module(f".{module_name}", __name__)
    return getattr(module, class_name)(platform, config or EstimatorConfig())


__all__ = ["Estimate", "Estimator", "EstimatorConfig", "METHODS", "fit_all", "load_estimator_config", "make_estimator"]
