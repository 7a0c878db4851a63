"""Test data for the instruments outside the robot (spec §7), straight from the models.

A true drive ``nominal + δM``, true stroke scale k, a true instrument (frame, target(s)) and
poses in the workspace; strokes are the true drive's IK divided by ``1 + k`` (what encoders with
scale errors log), readings the simulated instrument's (:mod:`stewart_calib.simulation.instrument`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from stewart_calib.estimators.batch import BatchProblem
from stewart_calib.io.platform_file import load_platform
from stewart_calib.model import kinematics as kin
from stewart_calib.model.platform import Instrument, Platform
from stewart_calib.resources import CONFIGS
from stewart_calib.samples import Log
from stewart_calib.simulation import instrument as simulated
from stewart_calib.simulation.instrument import InstrumentTruth, SimulatedInstrument

HOBBY = CONFIGS / "platforms" / "hobby-hexapod.toml"


def hobby(instrument: Instrument | None = None) -> Platform:
    platform = load_platform(HOBBY)
    return platform if instrument is None else replace(platform, instrument=instrument)


@dataclass(frozen=True)
class InstrumentCase:
    platform: Platform
    log: Log
    true_params: np.ndarray  # (42,) absolute, simulator frame
    true_scale: np.ndarray  # (6,)
    true_instrument: SimulatedInstrument


#: fraction of the workspace box the poses fill: the hobby's strokes stay inside [0, 90] mm
WORKSPACE_FRACTION = 0.6


def workspace_poses(platform: Platform, n: int, rng: np.random.Generator) -> np.ndarray:
    ws = platform.workspace
    half = WORKSPACE_FRACTION * np.r_[[ws.translation_limit] * 3, [ws.rotation_limit] * 3]
    return ws.home + rng.uniform(-1.0, 1.0, (n, 6)) * half


def make_case(
    platform: Platform,
    n: int,
    seed: int,
    truth: InstrumentTruth,
    joint_spread_mm: float = 0.5,
    length_spread_mm: float = 3.0,
    scale_spread: float = 0.02,
    delta: np.ndarray | None = None,
    scale: np.ndarray | None = None,
) -> InstrumentCase:
    rng = np.random.default_rng(seed)
    if delta is None:
        delta = rng.normal(0.0, joint_spread_mm, 42)
        delta[6::7] = rng.normal(0.0, length_spread_mm, 6)
    if scale is None:
        scale = rng.normal(0.0, scale_spread, 6)
    true_drive = platform.drive.perturbed(delta)
    instrument = SimulatedInstrument.build(platform.instrument, truth, rng)
    R, t = kin.pose_to_rt(workspace_poses(platform, n, rng))
    strokes = kin.inverse_kinematics(true_drive, R, t) / (1.0 + scale)
    log = Log(np.arange(n) * 0.1, strokes, instrument.read(R, t, instrument.draw(n, rng)))
    return InstrumentCase(platform, log, true_drive.as_vector(), np.asarray(scale, dtype=float), instrument)


def truth_in_gauge(case: InstrumentCase) -> tuple[np.ndarray, object]:
    """``(δM (42) in the gauge of instruments.gauge, instrument unknowns moved alike)``."""
    return simulated.truth_in_gauge(case.platform.drive, case.true_params, case.true_instrument.unknowns)


def problem(case: InstrumentCase) -> BatchProblem:
    return BatchProblem.of_log(case.platform, case.log.strokes, case.log.readings, case.log.t_s)
