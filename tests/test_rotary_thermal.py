"""``[thermal]`` on rotary legs (spec §15, §17): a warm rod is a longer rod, not another servo angle.

The expansion term lengthens each leg from joint to joint; a rotary leg's coordinate is its crank
angle, so the drive model hands the growth ``α_i (T_i − T_ref) · 1e-6 · r_i`` to the leg model as the
rod's lengthening, while a prismatic leg's growth stays part of its extension. Checked here: the
rotary drive's residual against the rod lengthened by hand and its Jacobians (the α columns among
them) against central differences; inverse and forward kinematics at the legs' temperatures, each
the other's inverse; a prismatic drive's inputs, residuals, Jacobians and kinematics bit for bit what
the expansion folded into the extension by hand gives; and ``ls`` identifying each rod's expansion
from a simulated warm-up of a servo build under motion capture, within 4σ of its reported stddev.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from stewart_calib.instruments import outside_model
from stewart_calib.model import kinematics as kin
from stewart_calib.model.drive import THERMAL, drive_model
from stewart_calib.model.platform import Thermal
from stewart_calib.model.rotary import PARAMETER_FIELDS
from stewart_calib.samples import TEMPERATURE_C, Log
from stewart_calib.simulation import load_experiment
from stewart_calib.workflows.calibration import run_calibration
from tests.numdiff import numerical_jacobian, numerical_pose_jacobian, relative_error
from tests.synthetic import nim_stewart, random_error, random_poses

T_REF_C = 20.0
#: each leg's rod: aluminium, steel, and between (ppm/K)
ALPHA_PPM_PER_K = np.array([23.0, 11.5, 17.0, 23.0, 12.0, 20.0])
PER_LEG = len(PARAMETER_FIELDS)
ROD = [name for name, _ in PARAMETER_FIELDS].index("r")
TILTS = [PER_LEG * leg + column for leg in range(6) for column in (PER_LEG - 2, PER_LEG - 1)]


def servo_platform(alpha=None, sigma: float = 20.0):
    """The shipped servo build (configs/platforms/servo-hexapod.toml) with ``[thermal]`` about ``alpha``
    (None: 0)."""
    platform = load_experiment("servo").platform
    nominal = np.zeros(6) if alpha is None else np.asarray(alpha, dtype=float)
    return replace(platform, thermal=Thermal(T_REF_C, nominal, sigma))


def servo_poses(platform, n: int, rng: np.random.Generator, fraction: float = 0.8):
    """``(R, t)`` of ``n`` uniform poses in ``fraction`` of the workspace box that every leg reaches."""
    ws = platform.workspace
    half = fraction * np.r_[[ws.translation_limit] * 3, [ws.rotation_limit] * 3]
    R, t = kin.pose_to_rt(ws.home + rng.uniform(-1.0, 1.0, (3 * n, 6)) * half)
    ok = np.flatnonzero(np.all(np.isfinite(platform.drive.coordinates(R, t)), axis=-1))[:n]
    assert len(ok) == n
    return R[ok], t[ok]


def rotary_errors(rng: np.random.Generator, tilts: bool = True) -> np.ndarray:
    """A servo build's δM [mm, rad]: 0.3 mm joints, 0.2 mm horns and rods, 1° zero trim, 0.5° axis tilts."""
    sigma = np.tile(np.r_[[0.3] * 6, 0.2, 0.2, np.radians([1.0, 0.5, 0.5])], 6)
    delta = sigma * rng.standard_normal(66)
    if not tilts:  # a perturbed set's J_M turns its axes about its own u, w (RotaryLegs.tilt_reference)
        delta[TILTS] = 0.0
    return delta


def grown_rods(legs, alpha: np.ndarray, temperature_C: np.ndarray) -> np.ndarray:
    """``(..., 66)`` δM that lengthens each rod of ``legs`` by spec §17's ``α_i (T_i − T_ref) · 1e-6 · r_i``."""
    growth = alpha * (temperature_C - T_REF_C) * 1e-6 * legs.rod_lengths
    delta = np.zeros((*np.shape(growth)[:-1], 66))
    delta[..., ROD::PER_LEG] = growth
    return delta


@pytest.fixture(scope="module")
def rotary():
    """``(drive, x_drive = [δM | k | α], R, t, temperatures)``: the servo build with its scale and
    expansion unknown, at five poses and per-leg temperatures between 0 and 50 °C."""
    platform = servo_platform(ALPHA_PPM_PER_K)
    drive = drive_model(platform).identifying()
    assert [block.key for block in drive.blocks] == ["stroke_scale", THERMAL]
    rng = np.random.default_rng(17)
    x = np.r_[rotary_errors(rng, tilts=False), rng.normal(0.0, 0.01, 6), rng.normal(0.0, 5.0, 6)]
    R, t = servo_poses(platform, 5, rng)
    return drive, x, R, t, rng.uniform(0.0, 50.0, (5, 6))


def test_a_rotary_drive_takes_a_thermal_table_and_grows_its_rods(rotary):
    """The residual is the rod closure with each rod ``r_i + δr_i`` longer by ``α_i ΔT_i · 1e-6 · r_i``
    (the nominal rod's growth), and the servo angle is ``(1 + k_i) q_i`` whatever the temperature."""
    drive, x, R, t, temperature = rotary
    alpha = ALPHA_PPM_PER_K + x[-6:]
    angles = drive.inverse_kinematics(R, t, x) + 0.01
    inputs = drive.inputs(angles, {TEMPERATURE_C: temperature})
    np.testing.assert_array_equal(drive.extensions(inputs, x), (1.0 + x[66:72]) * angles)
    nominal = drive.legs
    growth = alpha * (temperature - T_REF_C) * 1e-6 * nominal.rod_lengths
    np.testing.assert_allclose(drive.lengthening(inputs, x), growth, rtol=1e-14, atol=0.0)
    assert np.max(np.abs(growth)) > 0.05  # mm: 23 ppm/K over 30 K on a 150 mm rod is 0.1 mm
    for k in range(len(R)):
        by_hand = nominal.perturbed(x[:66] + grown_rods(nominal, alpha, temperature[k]))
        expected = by_hand.residuals(R[k], t[k], (1.0 + x[66:72]) * angles[k])
        np.testing.assert_allclose(drive.residual(x, R[k], t[k], inputs[k]), expected, rtol=0.0, atol=1e-11)


def test_the_rotary_thermal_jacobians_match_central_differences(rotary):
    """``∂r/∂ξ`` and ``∂r/∂x_drive`` (δM, angle scale, and the α columns ``−(T_i − T_ref) · 1e-6 · r_i``)
    against central differences at every pose."""
    drive, x, R, t, temperature = rotary
    angles = drive.inverse_kinematics(R, t, x) + 0.01
    inputs = drive.inputs(angles, {TEMPERATURE_C: temperature})
    thermal = slice(72, 78)
    # α's step of 1 ppm/K: the residual is linear in α, and a step of 1e-6 would leave round-off of a
    # 150 mm rod's closure (~1e-14 · 150 mm / 2e-6) at 1e-5 of its 2e-3 mm per ppm/K
    eps = np.r_[np.full(72, 1e-6), np.full(6, 1.0)]
    for k in range(len(R)):
        J_pose, J_x = drive.jacobians(x, R[k], t[k], inputs[k])
        numeric = numerical_jacobian(lambda v, k=k: drive.residual(v, R[k], t[k], inputs[k]), x, eps=eps)
        assert relative_error(J_x, numeric) < 1e-6
        assert relative_error(J_x[:, thermal], numeric[:, thermal]) < 1e-9
        expected = -(temperature[k] - T_REF_C) * 1e-6 * drive.legs.rod_lengths
        np.testing.assert_allclose(np.diag(J_x[:, thermal]), expected, rtol=1e-12)
        numeric_pose = numerical_pose_jacobian(lambda R_, t_, k=k: drive.residual(x, R_, t_, inputs[k]), R[k], t[k])
        assert relative_error(J_pose, numeric_pose) < 1e-6
        # the EKF's observation and the drive-leg factor take the same rows
        r_obs, H_obs, _, _ = drive.observation(x, R[k], t[k], inputs[k], 1e-4 * np.eye(6), np.radians(0.05))
        np.testing.assert_allclose(r_obs, drive.residual(x, R[k], t[k], inputs[k]), rtol=0.0, atol=1e-12)
        np.testing.assert_allclose(H_obs, J_x, rtol=0.0, atol=1e-12)


def test_rotary_inverse_and_forward_kinematics_at_the_legs_temperatures(rotary):
    """IK at the legs' temperatures gives the angles the rods grown by hand need; FK of those angles at
    the same temperatures is the pose again (batch, one sample, and along a log); the growth moves the
    angles by ~1e-3 rad, far above the round trip's error."""
    drive, x, R, t, temperature = rotary
    channels = {TEMPERATURE_C: temperature}
    angles = drive.inverse_kinematics(R, t, x, channels=channels)
    cold = drive.inverse_kinematics(R, t, x, channels={TEMPERATURE_C: np.full((len(R), 6), T_REF_C)})
    assert np.max(np.abs(angles - cold)) > 1e-3
    alpha, scale = ALPHA_PPM_PER_K + x[-6:], 1.0 + x[66:72]
    for k in range(len(R)):
        by_hand = drive.legs.perturbed(x[:66] + grown_rods(drive.legs, alpha, temperature[k]))
        np.testing.assert_allclose(angles[k], by_hand.coordinates(R[k], t[k]) / scale, rtol=0.0, atol=1e-12)
    inputs = drive.inputs(angles, channels)
    fk = drive.forward_kinematics(inputs, x, tol_mm=1e-11)
    np.testing.assert_allclose(fk.t, t, rtol=0.0, atol=1e-8)
    np.testing.assert_allclose(kin.pose_error(R, t, fk.R, fk.t)[1], 0.0, atol=1e-8)
    R_one, t_one = drive.solve_fk(inputs[2], x, None)
    np.testing.assert_allclose(t_one, t[2], rtol=0.0, atol=1e-6)
    np.testing.assert_allclose(kin.pose_error(R[2], t[2], R_one, t_one)[1], 0.0, atol=1e-6)
    legs = drive.geometry(x)
    along = legs.forward_kinematics(
        drive.extensions(inputs, x), tol_mm=1e-11, along=True, lengthening=drive.lengthening(inputs, x)
    )
    np.testing.assert_allclose(along.t, t, rtol=0.0, atol=1e-8)
    # without the growth (the legs at the reference) FK puts the platform ~0.1 mm off
    assert np.max(np.abs(drive.forward_kinematics(drive.inputs(angles), x).t - t)) > 0.02


def test_a_prismatic_drive_folds_its_growth_into_the_extension_bit_for_bit():
    """The expansion of a prismatic leg is part of its extension ``(1 + k) q + α u``: the drive's inputs,
    residuals, Jacobians, FK and IK are bit for bit the compiled kinematics of that extension by hand,
    and the drive has no separate lengthening."""
    platform = nim_stewart()
    platform = replace(platform, thermal=Thermal(T_REF_C, ALPHA_PPM_PER_K, 20.0))
    drive = drive_model(platform).identifying()
    rng = np.random.default_rng(3)
    R, t = kin.pose_to_rt(random_poses(platform, 4, rng))
    x = np.r_[random_error(rng, 0.5), rng.normal(0.0, 0.01, 6), rng.normal(0.0, 5.0, 6)]
    temperature = rng.uniform(0.0, 50.0, (4, 6))
    channels = {TEMPERATURE_C: temperature}
    legs, nominal = drive.geometry(x), platform.drive
    k_nominal = np.asarray(platform.stroke_scale, dtype=float) * np.ones(6)
    scale, alpha = 1.0 + (k_nominal + x[42:48]), 0.0 + (ALPHA_PPM_PER_K + x[48:54])
    strokes = rng.uniform(-20.0, 20.0, (4, 6))

    inputs = drive.inputs(strokes, channels)
    u = (temperature - T_REF_C) * 1e-6 * (nominal.initial_lengths + strokes * (1.0 + k_nominal))
    np.testing.assert_array_equal(inputs, np.concatenate([strokes, u], axis=-1))
    assert drive.lengthening(inputs, x) is None
    e = scale * strokes + alpha * u
    np.testing.assert_array_equal(drive.extensions(inputs, x), e)
    np.testing.assert_array_equal(drive.residual(x, R, t, inputs), kin.leg_residuals(legs, R, t, e))
    J_pose, J_x = drive.jacobians(x, R, t, inputs)
    J_pose_hand, J_M = kin.leg_residual_jacobians(legs, R, t)
    columns = np.zeros((4, 6, 12))
    columns[:, np.arange(6), np.arange(6)] = -strokes
    columns[:, np.arange(6), 6 + np.arange(6)] = -u
    np.testing.assert_array_equal(J_pose, J_pose_hand)
    np.testing.assert_array_equal(J_x, np.concatenate([J_M, columns], axis=-1))
    fk, fk_hand = drive.forward_kinematics(inputs, x), kin.forward_kinematics(legs, e)
    np.testing.assert_array_equal(fk.R, fk_hand.R)
    np.testing.assert_array_equal(fk.t, fk_hand.t)
    coordinates = kin.inverse_kinematics(legs, R, t)
    first = coordinates / scale
    u_ik = (temperature - T_REF_C) * 1e-6 * (nominal.initial_lengths + first * (1.0 + k_nominal))
    np.testing.assert_array_equal(
        drive.inverse_kinematics(R, t, x, channels=channels), (coordinates - alpha * u_ik) / scale
    )


@pytest.fixture(scope="module")
def warm_up():
    """``(platform, log, true α, true δM)``: 200 static poses of the servo build under an instrument of
    0.02 mm and 0.005° (a laser tracker's 6-DOF probe; its frame and target at the platform file's,
    fitted like any; motion capture's 0.1 mm leaves α's σ at ~5 ppm/K over such a log), its rods of
    :data:`ALPHA_PPM_PER_K` warming from 8 to 42 °C over the log, each leg within ±2 K of the ambient.
    Simulated by hand: each sample's true rods ``(r_i + δr_i)(1 + α_i ΔT_i · 1e-6)``, the commanded
    angles the true legs' IK at the desired pose over ``1 + k_i``, plus the servos' 0.05° noise; the
    readings those of the pose the true legs reach with the commanded angles (their own FK), with
    the motion capture's noise."""
    platform = servo_platform()
    instrument = replace(platform.instrument, position_sigma_mm=0.02, orientation_sigma_rad=np.radians(0.005))
    platform = replace(platform, instrument=instrument)
    rng = np.random.default_rng(20261203)
    n = 200
    R_d, t_d = servo_poses(platform, n, rng)
    legs = platform.drive
    delta = rotary_errors(rng)
    true = legs.perturbed(delta)
    k = rng.normal(0.0, 0.02, 6)
    ambient = np.linspace(8.0, 42.0, n)[:, None]
    temperature = ambient + rng.uniform(-2.0, 2.0, 6) + rng.normal(0.0, 0.3, (n, 6))
    angles, R, t = np.empty((n, 6)), np.empty((n, 3, 3)), np.empty((n, 3))
    for i in range(n):
        grown = np.zeros(66)
        grown[ROD::PER_LEG] = true.rod_lengths * ALPHA_PPM_PER_K * (temperature[i] - T_REF_C) * 1e-6
        warm = true.perturbed(grown)  # the true set with its rods grown (no tilt: its axes as they are)
        commanded = warm.coordinates(R_d[i], t_d[i]) / (1.0 + k)
        angles[i] = commanded + np.radians(0.05) * rng.standard_normal(6)
        reached = warm.forward_kinematics((1.0 + k) * angles[i], guess=(R_d[i], t_d[i]), tol_mm=1e-11)
        R[i], t[i] = reached.R, reached.t
    model = outside_model(platform)
    draws = model.noise_draws(platform.instrument, n, rng)
    readings = model.simulated_readings(platform.instrument, model.nominal_unknowns(), R, t, draws, 0.0)
    log = Log(np.arange(n) * 0.5, angles, readings, inputs={TEMPERATURE_C: temperature})
    return platform, log, ALPHA_PPM_PER_K, delta


def test_ls_identifies_each_rods_expansion_from_a_warm_up(warm_up):
    """``ls`` with the default config on the warm-up: each rod's α within 4σ of the truth by its own
    reported stddev, that stddev below 2 ppm/K, a tenth of the prior (the log's 34 K span separates α
    from the rods' lengths)."""
    platform, log, alpha, _ = warm_up
    estimate = run_calibration(platform, log, "ls").estimate
    found = estimate.block_results()[THERMAL]
    value, sigma = np.asarray(found["estimate"]), np.asarray(found["stddev"])
    assert found["names"] == [f"alpha{i}" for i in range(1, 7)]
    assert np.all(sigma < 2.0), sigma
    assert np.all(np.abs(value - alpha) <= 4.0 * sigma), (value - alpha, sigma)
