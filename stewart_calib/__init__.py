"""stewart-calib: online identification of the 42 kinematic parameter errors of a Stewart platform.

Modules: :mod:`platform` (geometry, 42-vector layout, TOML), :mod:`kinematics` (pure numpy
IK/FK/Jacobians), :mod:`io` (logs, truth, results), :mod:`simulation`, :mod:`estimators`,
:mod:`factors` (GTSAM custom factors), :mod:`pipelines` (commands), :mod:`viz` (rerun).
"""

__version__ = "0.1.0"
