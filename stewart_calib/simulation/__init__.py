"""The laboratory: true robot, load model, in-situ tracker, trajectories and the closed loop.

Public API (details in each module's docstring)::

    load_experiment(path) -> Experiment                          # experiment.py (TOML)
    run_experiment(experiment, controller=None, progress=False)  # closed_loop.py
        -> SimulationResult(log, truth, desired_poses, actual_poses, stages, kinds,
                            payload_kg, pose_index, robot)
    simulate_blocks(experiment, controller=None, progress=False)  # the same run, a block at a time
        -> SimulationRun(robot, plan, blocks)                     # blocks: (Log, Truth) of ≤ 4096 samples
    NominalController(platform), FrozenController(drive)         # controllers:
        .drive_model() -> LegGeometry, .observe(sample) -> None
    EstimatorController(estimator, platform)                     # online: update, then IK on M + δM
        .trace() -> (N, 42) δM after each sample, .rejected
    TrueRobot.drive_at(pose6, payload_kg) -> LegGeometry          # e.g. the true no-load geometry

Modules: :mod:`.robot` (δM_base, Table 4), :mod:`.load` (statics → forces → compliance),
:mod:`.tracker` (Table 2 tracker with residual, noise, 50 nm), :mod:`.trajectories`
(static poses, circles), :mod:`.experiment`, :mod:`.closed_loop`.
"""

from .closed_loop import (
    Controller,
    EstimatorController,
    FrozenController,
    NominalController,
    SimulationResult,
    SimulationRun,
    TrueRobot,
    run_experiment,
    simulate_blocks,
)
from .experiment import Experiment, load_experiment

__all__ = [
    "Controller",
    "EstimatorController",
    "Experiment",
    "FrozenController",
    "NominalController",
    "SimulationResult",
    "SimulationRun",
    "TrueRobot",
    "load_experiment",
    "run_experiment",
    "simulate_blocks",
]
