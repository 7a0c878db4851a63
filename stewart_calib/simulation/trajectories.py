"""Desired-pose generators: random static poses in the workspace and circles (paper §4.2–4.3).

Pure functions returning ``(N, 6)`` pose6 arrays ``[x, y, z [mm], roll, pitch, yaw [rad]]``.
"""

from __future__ import annotations

import numpy as np

from ..model import kinematics as kin
from ..model.platform import Platform

#: circle plane → (in-plane axis a, in-plane axis b) of the pose6 position
CIRCLE_PLANES = {"xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}


def in_range(platform: Platform, poses: np.ndarray, margin_mm: float) -> np.ndarray:
    """``(N,)`` mask: nominal strokes and tracker readings within their ranges shrunk by ``margin_mm``
    (a rotary drive's commanded angles within its angle range, spec §15).

    The margin leaves room for the few-mm difference between desired and actual pose.
    """
    R, t = kin.pose_to_rt(poses)
    ok = np.ones(len(poses), dtype=bool)
    if platform.drive.kind == "rotary":  # its IK is NaN where no horn reaches within the angle range
        ok &= np.all(np.isfinite(platform.drive.coordinates(R, t)), axis=1)
    for legs, bounds in ((platform.drive, platform.stroke_range), (platform.tracker, platform.reading_range)):
        if bounds is not None and legs is not None:
            s = legs.coordinates(R, t)
            ok &= np.all((s >= bounds[0] + margin_mm) & (s <= bounds[1] - margin_mm), axis=1)
    return ok


def random_static_poses(
    platform: Platform, n: int, rng: np.random.Generator, fraction: float, margin_mm: float
) -> np.ndarray:
    """``(n, 6)`` poses uniform in ``fraction`` of the workspace box about home (paper §4.1:
    ±200 mm, ±20°), keeping only poses that :func:`in_range` accepts (rejection sampling)."""
    ws = platform.required_workspace("random static poses")
    half = fraction * np.r_[[ws.translation_limit] * 3, [ws.rotation_limit] * 3]
    poses = np.empty((0, 6))
    while len(poses) < n:
        candidates = ws.home + rng.uniform(-1.0, 1.0, (2 * n, 6)) * half
        poses = np.vstack([poses, candidates[in_range(platform, candidates, margin_mm)]])
    return poses[:n]


def circle_poses(home: np.ndarray, radius_mm: float, plane: str, points: int, centre_offset_mm) -> np.ndarray:
    """``(points, 6)`` poses on a circle at home orientation (paper §4.3, Fig. 8).

    The circle of radius ``radius_mm`` lies in ``plane`` (``"xy"``, ``"xz"`` or ``"yz"`` of {J})
    about ``home + centre_offset_mm``, starting on the first in-plane axis and running
    counter-clockwise, one revolution, endpoint excluded.
    """
    a, b = CIRCLE_PLANES[plane]
    angle = 2.0 * np.pi * np.arange(points) / points
    poses = np.tile(np.asarray(home, dtype=float), (points, 1))
    poses[:, :3] += np.asarray(centre_offset_mm, dtype=float)
    poses[:, a] += radius_mm * np.cos(angle)
    poses[:, b] += radius_mm * np.sin(angle)
    return poses
