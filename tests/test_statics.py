"""Statics (stewart_calib/model/statics.py): equilibrium, the forces' Jacobians against central
differences, and a singular pose refused in one line."""

from __future__ import annotations

import numpy as np
import pytest

from stewart_calib.io.platform_file import load_platform
from stewart_calib.model import kinematics as kin
from stewart_calib.model.platform import LegGeometry
from stewart_calib.model.statics import (
    G_N_PER_KG,
    SingularStatics,
    gravity_leg_forces,
    gravity_wrench,
    leg_force_jacobians,
    leg_forces,
    statics_matrix,
)

MASSES = np.array([60.0, 40.0])
COMS = np.array([[0.0, 0.0, -50.0], [120.0, -80.0, 150.0]])


@pytest.fixture(scope="module")
def drive():
    return load_platform("nim-stewart").drive


def _poses(rng, n=5):
    home = load_platform("nim-stewart").workspace.home
    offsets = np.concatenate([rng.uniform(-60, 60, (n, 3)), rng.uniform(-0.15, 0.15, (n, 3))], axis=-1)
    return kin.pose_to_rt(home + offsets)


def test_forces_balance_the_weight_in_both_frames(drive):
    R, t = _poses(np.random.default_rng(1), 20)
    wrench = gravity_wrench(R, MASSES, COMS)
    forces = gravity_leg_forces(drive, R, t, MASSES, COMS)  # compiled
    np.testing.assert_allclose(forces, leg_forces(drive, R, t, wrench), rtol=0, atol=1e-9)  # numpy
    residual = np.einsum("kij,kj->ki", statics_matrix(drive, R, t), forces) + wrench
    assert np.max(np.abs(residual) / np.max(np.abs(wrench), axis=-1, keepdims=True)) < 1e-12
    # the body-frame form Jᵀ f = −w_D (J the leg-length pose Jacobian, rotation first) gives the same f
    J = kin.leg_pose_jacobian(drive, R, t)
    g_D = np.einsum("kji,j->ki", R, [0.0, 0.0, -G_N_PER_KG])
    w_D = np.concatenate([np.cross(MASSES @ COMS, g_D), MASSES.sum() * g_D], axis=-1)
    np.testing.assert_allclose(np.einsum("kji,kj->ki", J, forces), -w_D, atol=1e-9 * np.abs(w_D).max())
    n = kin.leg_unit_vectors(drive, R, t)
    np.testing.assert_allclose(np.sum(forces * n[..., 2], axis=-1), MASSES.sum() * G_N_PER_KG, rtol=1e-12)


def test_force_jacobians_match_central_differences(drive):
    R, t = _poses(np.random.default_rng(2), 3)
    masses = np.array([[60.0, 0.0], [60.0, 20.0], [15.0, 40.0]])
    forces = gravity_leg_forces(drive, R, t, masses, COMS)
    df_dxi, df_dM = leg_force_jacobians(drive, R, t, forces, masses, COMS)
    step = 1e-6
    for k in range(6):
        xi = np.zeros(6)
        xi[k] = step
        plus = gravity_leg_forces(drive, *kin.retract(R, t, xi), masses, COMS)
        minus = gravity_leg_forces(drive, *kin.retract(R, t, -xi), masses, COMS)
        np.testing.assert_allclose(df_dxi[..., k], (plus - minus) / (2 * step), rtol=1e-5, atol=1e-6)
    step = 1e-4
    for k in range(42):
        delta = np.zeros(42)
        delta[k] = step
        plus = gravity_leg_forces(drive.perturbed(delta), R, t, masses, COMS)
        minus = gravity_leg_forces(drive.perturbed(-delta), R, t, masses, COMS)
        np.testing.assert_allclose(df_dM[..., k], (plus - minus) / (2 * step), rtol=1e-5, atol=1e-6)
    assert np.all(df_dM[..., 6::7] == 0)  # the initial lengths do not enter the statics


def test_a_singular_pose_is_refused_in_one_line():
    # every joint in the plane z = 0 and the platform in that plane: no leg has a vertical component
    def ring(radius, degrees):
        angles = np.radians(degrees)
        return radius * np.stack([np.cos(angles), np.sin(angles), np.zeros(6)], axis=-1)

    legs = LegGeometry(
        ring(300.0, [-10, 10, 110, 130, 230, 250]), ring(150.0, [-50, 50, 70, 170, 190, 290]), np.full(6, 300.0)
    )
    R, t = np.eye(3)[None].repeat(2, axis=0), np.array([[0.0, 0.0, 300.0], [0.0, 0.0, 0.0]])
    with pytest.raises(SingularStatics, match=r"^pose 2: the statics matrix .* singular[^\n]*$") as caught:
        leg_forces(legs, R, t, gravity_wrench(R, np.array([10.0]), np.zeros((1, 3))))
    assert caught.value.index == 1
    with pytest.raises(SingularStatics) as compiled:
        gravity_leg_forces(legs, R, t, np.array([10.0]), np.zeros((1, 3)))
    assert compiled.value.index == 1 and str(compiled.value).split(" (")[0] == str(caught.value).split(" (")[0]
