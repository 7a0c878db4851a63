"""Gravity along any direction (spec §17 "Tilt"): the statics of §10 with gravity's unit vector an
input, the drive reading it from the ``gravity`` channel, the simulator's tilting mount, and a
calibration of a tilted elastic robot against one that takes gravity along −z."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from stewart_calib.errors import CalibError
from stewart_calib.io.platform_file import load_platform
from stewart_calib.model import _kernels
from stewart_calib.model import kinematics as kin
from stewart_calib.model.drive import drive_model
from stewart_calib.model.platform import DOWN, G_N_PER_KG, LegGeometry
from stewart_calib.model.rotations import so3_exp
from stewart_calib.model.statics import gravity_leg_forces, gravity_wrench, leg_force_jacobians, leg_forces
from stewart_calib.resources import CONFIGS
from stewart_calib.samples import GRAVITY, LOAD_KG
from stewart_calib.simulation import load_experiment, run_experiment
from stewart_calib.simulation.experiment import tilted_gravity
from stewart_calib.simulation.load import elastic_of, settle

MASSES = np.array([60.0, 40.0])
COMS = np.array([[0.0, 0.0, -50.0], [120.0, -80.0, 150.0]])
#: gravity with the mount turned 50° about an axis in the base plane, and a little about z
TILTED = so3_exp(np.radians(50.0) * np.array([0.8, 0.6, 0.0])) @ so3_exp(np.array([0.0, 0.0, 0.2])) @ DOWN
TILTED_EXPERIMENT = CONFIGS / "experiments" / "tilted.toml"


@pytest.fixture(scope="module")
def drive():
    return load_platform("nim-stewart").drive


def _poses(rng, n=5):
    home = load_platform("nim-stewart").workspace.home
    offsets = np.concatenate([rng.uniform(-60, 60, (n, 3)), rng.uniform(-0.15, 0.15, (n, 3))], axis=-1)
    return kin.pose_to_rt(home + offsets)


def test_gravity_along_minus_z_gives_the_forces_of_the_upright_statics(drive):
    """``down = −z`` (the default, bit for bit the same call) solves the same ``Aᵀ f = −w`` as the statics
    that hard-code −z: the wrench built as ``(0, 0, W)`` and its moments ``(c_y W, −c_x W, 0)``, solved by
    the same LU."""
    R, t = _poses(np.random.default_rng(3), 8)
    given = gravity_leg_forces(drive, R, t, MASSES, COMS, np.broadcast_to(DOWN, (8, 3)))
    assert np.array_equal(given, gravity_leg_forces(drive, R, t, MASSES, COMS))
    reference = np.empty((8, 6))
    base, plat = drive.base_joints, drive.platform_joints
    for k in range(8):  # Aᵀ in the kernel's own order of operations, and the −z wrench written out
        Rk, tk = R[k], t[k]
        A_T, w = np.empty((6, 6)), np.zeros((6, 1))
        for i in range(6):
            p = [Rk[a, 0] * plat[i, 0] + Rk[a, 1] * plat[i, 1] + Rk[a, 2] * plat[i, 2] for a in range(3)]
            v = [tk[a] + p[a] - base[i, a] for a in range(3)]
            norm = np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
            n = [v[a] / norm for a in range(3)]
            A_T[:3, i] = n
            A_T[3:, i] = [p[1] * n[2] - p[2] * n[1], p[2] * n[0] - p[0] * n[2], p[0] * n[1] - p[1] * n[0]]
        for mass, com in zip(MASSES, COMS, strict=True):  # gravity (0, 0, −W) at R c, negated
            weight = mass * G_N_PER_KG
            c = [Rk[a, 0] * com[0] + Rk[a, 1] * com[1] + Rk[a, 2] * com[2] for a in range(2)]
            w[2, 0] += weight
            w[3, 0] += c[1] * weight
            w[4, 0] -= c[0] * weight
        assert _kernels._solve(A_T, w)  # the kernel's LU
        reference[k] = w[:, 0]
    # the kernel's own arithmetic, interpreted here: compiled code may contract a multiply-add (the
    # ahead-of-time build does), so the two agree to rounding, not to the bit
    np.testing.assert_allclose(given, reference, rtol=1e-13, atol=0)
    # the numpy wrench: the products of (0, 0, −g) exactly
    old = MASSES[:, None] * np.array([0.0, 0.0, -G_N_PER_KG])
    arms = np.einsum("kij,mj->kmi", R, COMS)
    wrench = np.concatenate([np.broadcast_to(old.sum(0), (8, 3)), np.cross(arms, old).sum(1)], -1)
    assert np.array_equal(gravity_wrench(R, MASSES, COMS), wrench)
    assert np.array_equal(gravity_wrench(R, MASSES, COMS, DOWN), wrench)


def test_tilted_statics_are_the_upright_statics_of_the_turned_robot(drive):
    """Turn the base joints, the pose and gravity together by ``Q``: the legs' forces are the same. With
    ``Q`` taking the tilted gravity to −z, the tilted statics are the −z statics of the turned robot."""
    R, t = _poses(np.random.default_rng(4), 10)
    tilted = gravity_leg_forces(drive, R, t, MASSES, COMS, TILTED)
    axis = np.cross(TILTED, DOWN)
    angle = np.arctan2(np.linalg.norm(axis), TILTED @ DOWN)
    Q = so3_exp(angle * axis / np.linalg.norm(axis))
    np.testing.assert_allclose(Q @ TILTED, DOWN, atol=1e-15)
    turned = LegGeometry(drive.base_joints @ Q.T, drive.platform_joints, drive.initial_lengths)
    upright = gravity_leg_forces(turned, Q @ R, t @ Q.T, MASSES, COMS)
    scale = np.abs(tilted).max()
    np.testing.assert_allclose(upright, tilted, rtol=0, atol=1e-12 * scale)
    # the numpy path (the wrench, then Aᵀ f = −w) agrees, and the tilted forces are not the upright ones
    np.testing.assert_allclose(
        leg_forces(drive, R, t, gravity_wrench(R, MASSES, COMS, TILTED)), tilted, rtol=0, atol=1e-9 * scale
    )
    assert np.abs(tilted - gravity_leg_forces(drive, R, t, MASSES, COMS)).max() > 0.2 * scale


def test_force_jacobians_under_a_tilted_gravity_match_central_differences(drive):
    R, t = _poses(np.random.default_rng(5), 3)
    masses = np.array([[60.0, 0.0], [60.0, 20.0], [15.0, 40.0]])
    down = np.stack([TILTED, DOWN, -np.roll(TILTED, 1)])  # one per pose: a wall mount's among them
    forces = gravity_leg_forces(drive, R, t, masses, COMS, down)
    df_dxi, df_dM = leg_force_jacobians(drive, R, t, forces, masses, COMS, down)
    upright_dxi, _ = leg_force_jacobians(drive, R, t, forces, masses, COMS)
    assert np.abs(df_dxi[0] - upright_dxi[0]).max() > 0.1 * np.abs(df_dxi[0]).max()  # the direction matters
    step = 1e-6
    for k in range(6):
        xi = np.zeros(6)
        xi[k] = step
        plus = gravity_leg_forces(drive, *kin.retract(R, t, xi), masses, COMS, down)
        minus = gravity_leg_forces(drive, *kin.retract(R, t, -xi), masses, COMS, down)
        np.testing.assert_allclose(df_dxi[..., k], (plus - minus) / (2 * step), rtol=1e-5, atol=1e-6)
    step = 1e-4
    for k in range(42):
        delta = np.zeros(42)
        delta[k] = step
        plus = gravity_leg_forces(drive.perturbed(delta), R, t, masses, COMS, down)
        minus = gravity_leg_forces(drive.perturbed(-delta), R, t, masses, COMS, down)
        np.testing.assert_allclose(df_dM[..., k], (plus - minus) / (2 * step), rtol=1e-5, atol=1e-6)


def test_the_drive_takes_gravity_from_the_channel_else_from_its_elastic_table():
    experiment = load_experiment(TILTED_EXPERIMENT)
    elastic = elastic_of(experiment.load)
    platform = dataclasses.replace(experiment.platform, elastic=dataclasses.replace(elastic, gravity=TILTED))
    drive = drive_model(platform)
    R, t = _poses(np.random.default_rng(6), 4)
    legs, masses = platform.drive, np.array([elastic.platform_mass_kg, 20.0])
    coms = np.stack([elastic.platform_com_mm, elastic.payload_com_mm])
    at_table = gravity_leg_forces(legs, R, t, masses, coms, TILTED)
    np.testing.assert_array_equal(drive.leg_forces(R, t, {LOAD_KG: 20.0}), at_table)
    rows = np.stack([DOWN, TILTED, [np.nan] * 3, DOWN])  # a buffer's sample without the channel: NaN
    expected = gravity_leg_forces(legs, R, t, masses, coms, np.stack([DOWN, TILTED, TILTED, DOWN]))
    np.testing.assert_array_equal(drive.leg_forces(R, t, {LOAD_KG: 20.0, GRAVITY: rows}), expected)
    per_kg = drive.payload_leg_forces(R, t, channels={GRAVITY: rows})
    np.testing.assert_allclose(per_kg * 20.0, expected - drive.leg_forces(R, t, {GRAVITY: rows}), atol=1e-9)
    # the EKF's packed channels: the payload, then gravity (the drive's own default where a sample has none)
    assert drive.pose_channels == (LOAD_KG, GRAVITY)
    np.testing.assert_array_equal(drive.packed_pose_channels({}), [0.0, *TILTED])
    np.testing.assert_array_equal(
        drive.unpacked_pose_channels(drive.packed_pose_channels({GRAVITY: DOWN}))[GRAVITY], DOWN
    )


def test_the_experiment_tilts_the_mount_and_refuses_what_is_no_direction(tmp_path):
    experiment = load_experiment(TILTED_EXPERIMENT)
    np.testing.assert_allclose(
        tilted_gravity(DOWN, np.array([1.0, 0.0, 0.0]), np.array([90.0])), [[0, -1, 0]], atol=1e-15
    )
    expected = tilted_gravity(experiment.load.gravity, experiment.load.tilt_axis, np.array([30.0, 45.0, 60.0]))
    assert [stage.tilt_deg for stage in experiment.stages] == [30.0, 45.0, 60.0]
    np.testing.assert_allclose(expected[:, 2], -np.cos(np.radians([30.0, 45.0, 60.0])), atol=1e-15)
    text = TILTED_EXPERIMENT.read_text()
    cases = {
        "gravity = [0.0, 0.0, -1.0]": ("gravity = [0.0, 0.0, 0.0]", r"key 'load\.gravity': expected a direction"),
        "tilt_axis = [1.0, 0.0, 0.0]": ("tilt_axis = [1.0, 0.0]", r"key 'load\.tilt_axis': expected a direction"),
        "tilt_deg = 60.0": ("tilt_deg = 200.0", r"key 'stages\[2\]\.tilt_deg': expected an angle within ±180"),
    }
    for old, (new, message) in cases.items():
        path = tmp_path / "bad.toml"
        path.write_text(text.replace(old, new))
        with pytest.raises(CalibError, match=rf"^[^\n]*{message}[^\n]*$"):
            load_experiment(path)
    # a mount tilted once: [load] gravity normalised, the log without the channel, [elastic] gravity set
    path = tmp_path / "fixed.toml"
    path.write_text(text.replace("gravity = [0.0, 0.0, -1.0]", "gravity = [0.0, -2.0, -2.0]").replace("tilt_deg", "#"))
    fixed = load_experiment(path)
    np.testing.assert_allclose(fixed.load.gravity, [0.0, -np.sqrt(0.5), -np.sqrt(0.5)], atol=1e-15)
    np.testing.assert_array_equal(elastic_of(fixed.load).gravity, fixed.load.gravity)


@pytest.fixture(scope="module")
def tilted_run():
    experiment = load_experiment(TILTED_EXPERIMENT)
    run = run_experiment(experiment)
    platform = dataclasses.replace(experiment.platform, elastic=elastic_of(experiment.load))
    return experiment, run, platform


def test_the_tilting_robot_settles_under_the_gravity_its_log_carries(tilted_run):
    _, run, _ = tilted_run
    gravity = run.log.inputs[GRAVITY]
    np.testing.assert_allclose(np.linalg.norm(gravity, axis=-1), 1.0, atol=1e-15)
    first = np.asarray(run.stages) == "30deg"
    np.testing.assert_allclose(
        gravity[first], np.broadcast_to([0.0, -0.5, -np.sqrt(0.75)], (first.sum(), 3)), atol=1e-15
    )
    # the true poses are where the robot settles under that gravity, not under −z
    rows = np.flatnonzero(np.asarray(run.stages) == "60deg")[:10]
    robot = run.robot
    executed = run.log.strokes[rows] * (1.0 + robot.stroke_scale) + robot.encoder_zero_mm
    guess = kin.pose_to_rt(run.desired_poses[rows])
    payload = run.log.inputs[LOAD_KG][rows]
    tilted, _ = settle(robot.load, robot.base_params, executed, payload, guess, gravity[rows])
    upright, _ = settle(robot.load, robot.base_params, executed, payload, guess)
    true = run.truth.true_poses[rows]
    np.testing.assert_allclose(tilted.t, true[:, :3], atol=1e-8)
    assert np.min(np.linalg.norm(upright.t - true[:, :3], axis=-1)) > 0.01  # the tilt moves each pose > 10 µm


@pytest.mark.parametrize("method", ["ls", "ekf"])
def test_a_tilted_elastic_robot_is_calibrated_and_compensated_better_than_by_a_model_of_minus_z(tilted_run, method):
    """The default config on the shipped tilted experiment: each leg's compliance within 4σ of the
    truth (σ the estimate's own), and fresh poses at 60° commanded by the calibrated model (told the
    tilt) land within 3× the error its covariance predicts plus the compliance's σ times the forces;
    the same method fitting a model that takes gravity along −z (the log without the channel) leaves
    ten times that at least: its forces are off by the weight's sideways part (0.87 of it at 60°)."""
    from stewart_calib.analysis.accuracy import predicted_error
    from stewart_calib.analysis.compensation import compensate
    from stewart_calib.workflows.calibration import run_calibration

    experiment, run, platform = tilted_run
    kinds, stages = np.asarray(run.kinds), np.asarray(run.stages)
    calibration = run.log.select(kinds == "calibration")
    upright_log = dataclasses.replace(calibration, inputs={LOAD_KG: calibration.inputs[LOAD_KG]})
    poses = run.desired_poses[(kinds == "validation") & (stages == "60deg")]
    down = tilted_gravity(experiment.load.gravity, experiment.load.tilt_axis, np.array([60.0]))[0]
    robot = run.robot
    R_d, t_d = kin.pose_to_rt(poses)

    def reached_um(estimate, inputs) -> float:
        strokes = compensate(estimate, poses, nominal=platform, inputs=inputs)
        executed = strokes * (1.0 + robot.stroke_scale) + robot.encoder_zero_mm
        sol, _ = settle(robot.load, robot.base_params, executed, np.full(len(poses), 20.0), (R_d, t_d), down)
        return 1e3 * float(np.sqrt(np.mean(np.sum((sol.t - t_d) ** 2, axis=-1))))

    truth = platform.elastic.true_compliance_mm_per_kN
    estimate = run_calibration(platform, calibration, method).estimate
    columns = estimate.layout.slice("compliance")
    sigma = np.sqrt(np.diag(estimate.full_covariance)[columns])
    assert np.all(np.abs(estimate.block_values("compliance") - truth) <= 4.0 * sigma), (
        estimate.block_values("compliance") - truth
    ) / sigma
    tilted_um = reached_um(estimate, {LOAD_KG: 20.0, GRAVITY: down})
    forces = drive_model(platform).leg_forces(R_d, t_d, {LOAD_KG: 20.0, GRAVITY: down})
    predicted_um = 1e3 * predicted_error(platform, estimate.covariance, poses).position_mm
    compliance_um = float(np.sqrt(np.mean((sigma * forces / 1000.0) ** 2))) * 1e3
    assert tilted_um <= 3.0 * (predicted_um + compliance_um), (tilted_um, predicted_um, compliance_um)
    upright = run_calibration(platform, upright_log, method).estimate
    upright_um = reached_um(upright, {LOAD_KG: 20.0})
    assert upright_um >= 10.0 * tilted_um, (upright_um, tilted_um)
