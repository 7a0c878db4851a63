"""The simulator: statics, drift sign, tracker, closed loop, reproducibility, calibration to the paper."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from stewart_calib import kinematics as kin
from stewart_calib.errors import CalibError
from stewart_calib.samples import Sample
from stewart_calib.simulation.closed_loop import FrozenController, NominalController, run_experiment
from stewart_calib.simulation.experiment import load_experiment
from stewart_calib.simulation.load import G_N_PER_KG, gravity_wrench, leg_forces, loaded_params, settle, statics_matrix
from stewart_calib.simulation.trajectories import random_static_poses

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "configs" / "experiments" / "paper.toml"
QUICK = ROOT / "configs" / "experiments" / "quick.toml"


@pytest.fixture(scope="module")
def paper():
    return load_experiment(PAPER)


@pytest.fixture(scope="module")
def quick():
    return load_experiment(QUICK)


@pytest.fixture(scope="module")
def paper_runs(paper):
    """Uncalibrated run and a run frozen at the TRUE no-load geometry (a perfect no-load calibration)."""
    nominal = run_experiment(paper)
    frozen = run_experiment(paper, FrozenController(nominal.robot.drive_at(paper.platform.workspace.home, 0.0)))
    return nominal, frozen


# ----------------------------------------------------------------------------- statics


def test_leg_forces_balance_the_gravity_wrench(paper):
    rng = np.random.default_rng(0)
    poses = random_static_poses(paper.platform, 50, rng, 1.0, 0.0)
    R, t = kin.pose_to_rt(poses)
    masses = np.stack([np.full(50, 15.0), rng.uniform(0.0, 60.0, 50)], axis=-1)
    coms = np.array([[0.0, 0.0, -40.0], [80.0, -50.0, 120.0]])
    wrench = gravity_wrench(R, masses, coms)
    forces = leg_forces(paper.platform.drive, R, t, wrench)
    residual = np.einsum("kij,kj->ki", statics_matrix(paper.platform.drive, R, t), forces) + wrench
    # Relative to the largest wrench component (~1e5 N·mm): a 6×6 solve is good to ~1e-13.
    assert np.max(np.abs(residual) / np.max(np.abs(wrench), axis=-1, keepdims=True)) < 1e-9
    # and the forces' vertical components carry the whole weight
    n = kin.leg_unit_vectors(paper.platform.drive, R, t)
    np.testing.assert_allclose(np.sum(forces * n[..., 2], axis=-1), masses.sum(axis=-1) * G_N_PER_KG, rtol=1e-9)


def test_centred_load_on_the_threefold_symmetric_platform_shares_equally(paper):
    # nim-stewart's drive is 3-fold symmetric about z (up to 1 µm rounding of its coordinates).
    R, t = kin.pose_to_rt(paper.platform.workspace.home)
    forces = leg_forces(paper.platform.drive, R, t, gravity_wrench(R, np.array([40.0]), np.zeros((1, 3))))
    assert np.all(forces > 0)  # compression
    np.testing.assert_allclose(forces, forces.mean(), rtol=1e-5)


def test_compression_shortens_the_legs_and_the_platform_sinks(paper):
    load = paper.load
    base = paper.platform.drive.as_vector()
    home = paper.platform.workspace.home
    R, t = kin.pose_to_rt(home[None])
    params, forces = loaded_params(load, base, R, t, 40.0)
    assert np.all(forces > 0)
    delta = (params[0] - base).reshape(6, 7)
    assert np.all(delta[:, 6] < 0)  # δl_i = −f_i / k_leg
    # the effective leg (joint to joint) is shorter: holding the pose needs more stroke
    loaded = kin.inverse_kinematics(paper.platform.drive.perturbed(delta), R, t)
    assert np.all(loaded > kin.inverse_kinematics(paper.platform.drive, R, t))
    # and with the same strokes the platform sits lower
    sol, _ = settle(load, base, np.zeros((1, 6)), np.array([40.0]), (R, t))
    assert sol.t[0, 2] < home[2]


# ----------------------------------------------------------------------------- tracker, loop


def test_tracker_readings_are_ik_of_the_true_pose_before_noise(quick):
    exact = dataclasses.replace(quick, tracker=dataclasses.replace(quick.tracker, noise_mm=0.0, quantum_mm=0.0, geometry_residual_mm=0.0))
    result = run_experiment(exact)
    R, t = kin.pose_to_rt(result.actual_poses)
    np.testing.assert_allclose(result.log.readings, kin.inverse_kinematics(quick.platform.tracker, R, t), atol=1e-9)


def test_tracker_noise_and_quantisation(quick):
    result = run_experiment(quick)
    R, t = kin.pose_to_rt(result.actual_poses)
    true = result.robot.tracker.true_readings(R, t)
    quantum = quick.tracker.quantum_mm
    np.testing.assert_allclose(result.log.readings / quantum, np.round(result.log.readings / quantum), atol=1e-6)
    # within 6σ of noise plus half a quantum of rounding (6σ: ~1e-9 chance per reading)
    assert np.max(np.abs(result.log.readings - true)) <= 6 * quick.tracker.noise_mm + quantum / 2
    assert np.std(result.log.readings - true) > 0.5 * quick.tracker.noise_mm


def test_closed_loop_commands_ik_of_the_controller_model_and_observes_every_sample(quick):
    class Recording(FrozenController):
        adaptive = True  # forces the per-sample path

        def __init__(self, drive):
            super().__init__(drive)
            self.seen: list[Sample] = []

        def observe(self, sample):
            self.seen.append(sample)

    base = run_experiment(quick)
    drive = base.robot.drive_at(quick.platform.workspace.home, 0.0)
    recorder = Recording(drive)
    looped = run_experiment(quick, recorder)
    batched = run_experiment(quick, FrozenController(drive))
    assert len(recorder.seen) == len(looped.log)
    np.testing.assert_allclose(recorder.seen[5].strokes, looped.log.strokes[5])
    R_d, t_d = kin.pose_to_rt(looped.desired_poses)
    np.testing.assert_allclose(looped.log.strokes, kin.inverse_kinematics(drive, R_d, t_d), atol=1e-12)
    # per-sample and vectorised paths agree to the FK tolerance (1e-9 mm)
    np.testing.assert_allclose(looped.actual_poses, batched.actual_poses, atol=1e-8)
    np.testing.assert_allclose(looped.truth.params, batched.truth.params, atol=1e-8)
    # the true pose solves the true drive for the executed strokes
    for k in (0, len(looped.log) - 1):
        true = kin.inverse_kinematics(type(drive).from_params(looped.truth.params[k]), *kin.pose_to_rt(looped.actual_poses[k]))
        np.testing.assert_allclose(true, looped.log.strokes[k], atol=1e-8)


def test_load_ramps_in_and_drift_follows(quick):
    result = run_experiment(quick)
    stage = result.stages == "40kg"
    payload = result.payload_kg[stage]
    t = result.log.t_s[stage] - result.log.t_s[stage][0]
    np.testing.assert_allclose(payload, 40.0 * np.clip(t / 1.0, 0.0, 1.0))
    lengths = result.truth.params[:, 6::7]
    assert np.mean(lengths[stage][payload == 40.0]) < np.mean(lengths[result.stages == "no-load"])


def test_pose_sets_are_disjoint_and_in_range(paper, paper_runs):
    nominal, _ = paper_runs
    cal = np.unique(nominal.desired_poses[nominal.kinds == "calibration"], axis=0)
    val = np.unique(nominal.desired_poses[nominal.kinds == "validation"], axis=0)
    assert len(cal) == paper.poses.calibration and len(val) == paper.poses.validation
    assert np.min(np.linalg.norm(cal[:, None, :3] - val[None, :, :3], axis=-1)) > 1e-6
    lo, hi = paper.platform.reading_range
    assert np.all((nominal.log.readings >= lo) & (nominal.log.readings <= hi))


def test_same_seed_same_result_other_seed_other_result(quick):
    a, b = run_experiment(quick), run_experiment(quick)
    np.testing.assert_array_equal(a.log.readings, b.log.readings)
    np.testing.assert_array_equal(a.truth.params, b.truth.params)
    c = run_experiment(dataclasses.replace(quick, seed=quick.seed + 1))
    assert not np.array_equal(a.desired_poses, c.desired_poses)


# ----------------------------------------------------------------------------- the paper


def within(value: float, target: float, factor: float) -> bool:
    return target / factor <= value <= target * factor


def test_uncalibrated_errors_match_the_paper(paper_runs):
    nominal, _ = paper_runs
    position, orientation = nominal.mean_errors("validation", "no-load")
    assert within(position, 3.9243, 1.5), position  # Table 5, before calibration
    assert within(orientation, 0.8524, 1.5), orientation
    circle, _ = nominal.mean_errors("circle", "no-load")
    assert within(circle, 2.5334, 1.5), circle  # Table 6, before calibration


def test_a_model_frozen_at_no_load_loses_accuracy_with_load(paper_runs):
    _, frozen = paper_runs
    static = [frozen.mean_errors("validation", s)[0] for s in ("no-load", "20kg", "40kg")]
    circle = [frozen.mean_errors("circle", s)[0] for s in ("no-load", "20kg", "40kg")]
    assert static[0] < static[1] < static[2] and circle[0] < circle[1] < circle[2]
    assert static[2] >= 3 * static[0] and circle[2] >= 3 * circle[0]
    # "of the order of" the paper's LS at 40 kg (Table 5: 0.3854 mm, Table 6: 0.6223 mm)
    assert within(static[2], 0.3854, 2.0), static
    assert within(circle[2], 0.6223, 2.0), circle


def test_tracker_pose_accuracy_is_of_the_papers_order(paper, paper_runs):
    nominal, _ = paper_runs
    m = nominal.kinds == "validation"
    sol = kin.forward_kinematics(paper.platform.tracker, nominal.log.readings[m], guess=kin.pose_to_rt(nominal.desired_poses[m]))
    position, orientation = kin.pose_error(*kin.pose_to_rt(nominal.actual_poses[m]), sol.R, sol.t)
    # paper §4.1: 0.036 mm / 0.022°; a 42-value random residual sets the split between the two,
    # so position is matched (1.5×) and orientation only in order (3×).
    assert within(position.mean(), 0.036, 1.5), position.mean()
    assert within(orientation.mean(), 0.022, 3.0), orientation.mean()


def test_paper_experiment_is_fast(paper):
    import time

    start = time.perf_counter()
    result = run_experiment(paper, NominalController(paper.platform))
    elapsed = time.perf_counter() - start
    assert len(result.log) > 3000 and elapsed < 5.0  # "a few seconds" for ~3000 samples


# ----------------------------------------------------------------------------- experiment files


MINIMAL = 'seed = 1\nplatform = "nim-stewart"\n'
STAGE = '[[stages]]\nname = "no-load"\n'


@pytest.mark.parametrize(
    "text, key",
    [
        ("[robot]\nerrors = 'bogus'\n" + STAGE, "robot.errors"),
        ("[load]\nleg_stiffness = 3.0\n" + STAGE, "load.leg_stiffness"),
        ("[load]\nleg_N_per_mm = 'stiff'\n" + STAGE, "load.leg_N_per_mm"),
        ("[poses]\ncalibration = -1\n" + STAGE, "poses.calibration"),
        ("colour = 'red'\n" + STAGE, "colour"),
        ("[[stages]]\nname = 'x'\nsegments = ['dance']\n", "stages[0].segments"),
        ("[[stages]]\nname = 'x'\nload = 40\n", "stages[0].load"),
        ("", "stages"),
    ],
)
def test_bad_experiment_keys_are_refused_naming_file_and_key(tmp_path, text, key):
    path = tmp_path / "bad.toml"
    path.write_text(MINIMAL + text)
    with pytest.raises(CalibError) as info:
        load_experiment(path)
    assert str(path) in str(info.value) and f"'{key}'" in str(info.value)


def test_missing_seed_is_refused(tmp_path):
    path = tmp_path / "noseed.toml"
    path.write_text('platform = "nim-stewart"\n' + STAGE)
    with pytest.raises(CalibError, match="'seed'"):
        load_experiment(path)


def test_platform_by_name_or_relative_path(quick, paper):
    assert quick.platform.name == paper.platform.name == "nim-stewart"
    np.testing.assert_array_equal(quick.platform.drive.as_vector(), paper.platform.drive.as_vector())
