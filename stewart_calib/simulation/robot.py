"""The true robot: nominal drive parameters plus manufacturing/assembly errors δM_base.

The errors are the *unloaded* geometry; the load model (:mod:`.load`) adds the pose- and
load-dependent drift on top. Strokes are executed exactly as commanded; the encoders may
add white noise to what is logged (:func:`encoder_readings`).
"""

from __future__ import annotations

import numpy as np

from ..model.platform import params_to_vector, vector_to_params

#: Paper Table 4, EKF columns: identified no-load errors of the nim-stewart platform, per leg
#: ``[δj_x, δj_y, δj_z, δd_x, δd_y, δd_z, δl]`` [mm] (paper order, eq. 9).
TABLE4_EKF_ERRORS_MM = np.array(
    [
        [0.118, -1.374, -2.660, -2.285, -3.207, 0.281, -0.186],
        [0.427, 1.754, -0.219, -3.148, -3.205, 0.266, -2.631],
        [0.140, -0.140, -2.243, -3.251, 2.046, -0.463, -0.143],
        [0.195, -0.484, 1.876, -1.949, 3.756, -0.789, -0.531],
        [-0.472, -0.397, 1.514, 1.459, 1.399, 0.378, 0.126],
        [-0.797, -2.545, -0.861, 2.745, -0.729, -0.351, -2.352],
    ]
).reshape(-1)  # the per-leg rows in the paper's order
TABLE4_EKF_ERRORS_MM.setflags(write=False)


def base_errors(
    kind: str, block_scales: tuple[float, float, float], spread_mm: float, rng: np.random.Generator, n_params: int
) -> np.ndarray:
    """The true unloaded error δM_base, ``(n_params,)`` [mm] (42 for a 6-6 drive, Table 4's).

    Args:
        kind: ``"table4"`` (paper Table 4 EKF columns) or ``"random"`` (i.i.d. normal draws).
        block_scales: factors on the ``(δj_i, δd_i, δl_i)`` blocks of every leg (the documented
            calibration knobs of ``configs/experiments/paper.toml``).
        spread_mm: standard deviation of the random draws [mm] (``"random"`` only).
        rng: drawn from only for ``"random"``.
        n_params: entries of the drive's δM (``"random"`` only; Table 4 is the paper's 6-6 drive).
    """
    if kind == "table4":
        errors = TABLE4_EKF_ERRORS_MM
    elif kind == "random":
        errors = rng.normal(0.0, spread_mm, n_params)
    else:
        raise ValueError(f"unknown error kind {kind!r}")
    sj, sd, sl = block_scales
    return params_to_vector(vector_to_params(errors) * np.array([sj, sj, sj, sd, sd, sd, sl]))


def rotary_errors(config, legs, rng: np.random.Generator) -> np.ndarray:
    """The true error δM of a rotary drive (spec §15), ``(legs.n_params,)`` [mm, rad]: its zero offsets
    uniform in ± ``config.angle_offset_limit_deg``, every other entry normal with the
    :class:`~.experiment.RotaryRobotConfig`'s σ (crank centres and platform joints alike), drawn
    leg by leg in the order of the parameter vector."""
    spreads = {
        "a": config.joint_spread_mm,
        "d": config.joint_spread_mm,
        "h": config.horn_spread_mm,
        "r": config.rod_spread_mm,
        "tu": np.radians(config.axis_tilt_spread_deg),
        "tw": np.radians(config.axis_tilt_spread_deg),
    }
    prefixes = [name.rstrip("0123456789xyz") for name in legs.parameter_names]
    sigma = np.array([spreads.get(prefix, 0.0) for prefix in prefixes])
    offsets = np.array([prefix == "o" for prefix in prefixes])
    delta = rng.standard_normal(legs.n_params) * sigma
    limit = np.radians(config.angle_offset_limit_deg)
    delta[offsets] = rng.uniform(-limit, limit, int(offsets.sum()))
    return delta


def encoder_readings(strokes_mm: np.ndarray, noise_mm: float, unit_noise: np.ndarray) -> np.ndarray:
    """Logged strokes: the executed ones plus encoder noise σ·``unit_noise`` [mm] (standard
    normal draws made up front by the caller)."""
    return strokes_mm + noise_mm * unit_noise
