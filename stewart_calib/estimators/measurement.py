"""From one sample to what the estimators observe (paper Fig. 3, steps 1–2).

* :func:`check_sample` — refuse an unusable sample (non-finite, outside the platform's
  ranges) with :class:`~stewart_calib.errors.SampleRejected` before any state is touched.
* :class:`WarmFK` — forward kinematics of one leg set, warm-started from the previous
  solution (2 Newton iterations instead of 4–5 on a smooth trajectory), falling back to
  a cold start before giving up; FK failure becomes ``SampleRejected``.
* :func:`pose_difference` — ``P_v − P_m`` as the paper's ``δE = [δh, δθ]`` (eq. 9).
"""

from __future__ import annotations

import math

import numpy as np

from .. import _kernels
from .. import kinematics as kin
from ..errors import SampleRejected
from ..platform import LegGeometry, Platform
from ..samples import Sample
from .base import state_array


def check_sample(platform: Platform, sample: Sample) -> tuple[np.ndarray, np.ndarray]:
    """Strokes and readings of ``sample`` as float arrays, or :class:`SampleRejected`.

    Refuses non-finite values and values outside ``platform.stroke_range`` /
    ``platform.reading_range`` (inclusive bounds, spec §3).
    """
    strokes = np.asarray(sample.strokes, dtype=float)
    readings = np.asarray(sample.readings, dtype=float)
    # Fast path for the common, valid sample (~1 µs; the loop below costs ~8 µs): any doubt
    # falls through to it, which finds the offending value and words the rejection.
    if strokes.shape == (6,) and readings.shape == (6,) and math.isfinite(sample.t_s):
        s_lo, s_hi = platform.stroke_range if platform.stroke_range is not None else (-math.inf, math.inf)
        r_lo, r_hi = platform.reading_range if platform.reading_range is not None else (-math.inf, math.inf)
        if _kernels.all_within(strokes, float(s_lo), float(s_hi)) and _kernels.all_within(readings, float(r_lo), float(r_hi)):
            return strokes, readings
    if not np.isfinite(sample.t_s):
        raise SampleRejected(f"sample at t = {sample.t_s} s: non-finite time", SampleRejected.NON_FINITE)
    for values, bounds, what in (
        (strokes, platform.stroke_range, "stroke q"),
        (readings, platform.reading_range, "reading s"),
    ):
        if values.shape != (6,):
            raise SampleRejected(
                f"sample at t = {sample.t_s} s: expected 6 {what} values, got shape {values.shape}",
                SampleRejected.NON_FINITE,
            )
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            raise SampleRejected(f"sample at t = {sample.t_s} s: {what}{bad[0] + 1} is not finite", SampleRejected.NON_FINITE)
        if bounds is not None:
            bad = np.flatnonzero((values < bounds[0]) | (values > bounds[1]))
            if bad.size:
                i = int(bad[0])
                raise SampleRejected(
                    f"sample at t = {sample.t_s} s: {what}{i + 1} = {values[i]:.6g} mm outside "
                    f"[{bounds[0]}, {bounds[1]}] mm",
                    SampleRejected.OUT_OF_RANGE,
                )
    return strokes, readings


class WarmFK:
    """Forward kinematics for a stream of samples, warm-started from the last solution.

    Args:
        tol_mm: Newton tolerance on the leg lengths [mm].
    """

    def __init__(self, tol_mm: float = 1e-9):
        self.tol_mm = tol_mm
        self._guess: tuple[np.ndarray, np.ndarray] | None = None

    def solve(self, legs: LegGeometry, lengths: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
        """``(R, t)`` with ``‖t + R p_i − b_i‖ = initial_i + lengths_i`` (paper step 1).

        Tries the previous pose first, then the default cold guess (:func:`~stewart_calib.kinematics.solve_fk`).

        Raises:
            SampleRejected: neither start converges; ``what`` names the leg set.
        """
        self._guess = kin.solve_fk(legs, lengths, self._guess, what, self.tol_mm)
        return self._guess


    def export_state(self) -> dict:
        """The warm start ``{"R", "t"}`` (empty before the first solve): a resumed stream must
        start Newton from the same pose to reproduce the same solution bit for bit."""
        return {} if self._guess is None else {"R": self._guess[0].copy(), "t": self._guess[1].copy()}

    def import_state(self, state: dict) -> None:
        """Restore :meth:`export_state`'s warm start. Raises ``CalibError`` on a bad shape."""
        self._guess = (state_array(state, "R", (3, 3)), state_array(state, "t", (3,))) if state else None


def pose_difference(R_v: np.ndarray, t_v: np.ndarray, R_m: np.ndarray, t_m: np.ndarray) -> np.ndarray:
    """``Y = P_v − P_m`` as ``[δh [mm], δθ [rad]]`` (paper eq. 9 and Fig. 3 step 2).

    ``δθ`` is the difference of roll-pitch-yaw, wrapped to (−π, π], the coordinates in
    which :func:`~stewart_calib.kinematics.error_jacobian` is written.
    """
    shape = np.shape
    batch = np.broadcast_shapes(shape(R_v)[:-2], shape(t_v)[:-1], shape(R_m)[:-2], shape(t_m)[:-1])
    R_v, t_v, _ = kin._flat_poses(R_v, t_v, batch)
    R_m, t_m, _ = kin._flat_poses(R_m, t_m, batch)
    Y = np.empty((len(R_v), 6))
    _kernels.pose_difference(R_v, t_v, R_m, t_m, Y)  # per-pose loop: numpy's small-array overhead dominated
    return Y.reshape(batch + (6,))
