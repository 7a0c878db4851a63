"""stewart-calib: online identification of the 42 kinematic parameter errors of a Stewart platform.

Packages: :mod:`model` (what a robot is: platform geometry, the 42-vector layout, TOML, leg models,
pure numpy IK/FK/Jacobians, statics, the drive model, the unknown vector, rotations, compiled
kernels), :mod:`instruments` (measurement models), :mod:`io` (logs, truth, results),
:mod:`analysis` (identifiability, accuracy, compensation, plausibility), :mod:`simulation`,
:mod:`estimators`, :mod:`factors` (GTSAM custom factors), :mod:`workflows` (calibration, online,
planning, diagnosis, validation), :mod:`pipelines` (commands), :mod:`viz` (rerun).
"""

__version__ = "0.1.0"
