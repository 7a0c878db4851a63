"""The leg-model protocol (stewart_calib.model.legs): the drive model's generic (numpy) path, taken
for legs without compiled kernels, equals its compiled path on the same prismatic legs — the EKF's
observation, the drive-leg factor's rows and the kinematics — and ``with_terms`` scales a term's
columns by the leg model's ``J_e = ∂r_i/∂e_i`` (central differences on legs whose ``J_e`` is not −1)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import pytest

from stewart_calib.errors import CalibError
from stewart_calib.factors import drive_leg
from stewart_calib.model import kinematics as kin
from stewart_calib.model.drive import DriveModel, drive_model, stroke_term
from stewart_calib.model.legs import LEG_KINDS, LegModel
from stewart_calib.model.platform import Elastic, LegGeometry
from tests.numdiff import numerical_jacobian, relative_error
from tests.synthetic import nim_stewart, random_error, random_poses


@dataclass(frozen=True)
class NumpyLegs:
    """Prismatic legs whose compiled kernels the drive model must not take: every answer the
    wrapped :class:`LegGeometry`'s, ``compiled`` False (``kind`` as given)."""

    legs: LegGeometry
    kind: str = "prismatic"
    compiled = False

    def __getattr__(self, name: str):
        return getattr(self.legs, name)

    def perturbed(self, delta: np.ndarray) -> NumpyLegs:
        return replace(self, legs=self.legs.perturbed(delta))


@dataclass(frozen=True)
class ScaledLegs(NumpyLegs):
    """Legs whose coordinate is ``e_i / s_i`` of the prismatic extension: ``r_i(e) = r⁰_i(s_i e_i)``,
    so ``J_e,i = −s_i``, not −1."""

    scale: np.ndarray = field(default_factory=lambda: np.ones(6))

    def residuals(self, R, t, e, *, lengthening=None):
        return self.legs.residuals(R, t, self.scale * np.asarray(e), lengthening=lengthening)

    def residual_jacobians(self, R, t, e, *, lengthening=None):
        J_pose, J_M, J_e = self.legs.residual_jacobians(R, t, self.scale * np.asarray(e), lengthening=lengthening)
        return J_pose, J_M, J_e * self.scale


@pytest.fixture(scope="module")
def setting():
    platform = nim_stewart()
    rng = np.random.default_rng(42)
    R, t = kin.pose_to_rt(random_poses(platform, 3, rng))
    terms = (stroke_term(np.full(6, 0.01), 0.05),)
    compiled = DriveModel(platform.drive, terms)
    generic = DriveModel(NumpyLegs(platform.drive), terms)
    x = np.r_[random_error(rng, 0.5), rng.normal(0.0, 0.01, 6)]
    return platform, rng, R, t, compiled, generic, x


def test_prismatic_legs_are_a_leg_model():
    legs: LegModel = nim_stewart().drive
    assert LEG_KINDS[legs.kind] is LegGeometry and legs.compiled and legs.coordinate_unit == "mm"
    assert not legs.parameter_degrees.any() and legs.parameter_degrees.shape == (legs.n_params,)
    base, platform = legs.gauge_columns
    values = legs.as_vector()
    np.testing.assert_array_equal(values[base], legs.base_joints)
    np.testing.assert_array_equal(values[platform], legs.platform_joints)


def test_the_generic_observation_equals_the_compiled_one(setting):
    _, rng, R, t, compiled, generic, x = setting
    A = rng.normal(size=(6, 6))
    covariance = 1e-4 * (A @ A.T + np.eye(6))
    inputs = rng.uniform(-20.0, 20.0, 6)
    for k in range(len(R)):
        ours = generic.observation(x, R[k], t[k], inputs, covariance, 0.001)
        theirs = compiled.observation(x, R[k], t[k], inputs, covariance, 0.001)
        assert ours[1].shape == (6, compiled.size)
        for a, b in zip(ours, theirs, strict=True):
            np.testing.assert_allclose(a, b, rtol=0.0, atol=1e-9)


def test_the_generic_factor_rows_equal_the_compiled_ones(setting):
    _, rng, R, t, compiled, generic, x = setting
    unknowns = np.r_[x, rng.normal(size=12)]  # an instrument's block after x_drive: zero columns
    inputs = rng.uniform(-20.0, 20.0, 6)
    for legs in (np.arange(6), np.array([4])):
        ours, theirs = drive_leg.DriveLegs.of(legs, generic), drive_leg.DriveLegs.of(legs, compiled)
        assert ours.generic is generic and theirs.generic is None
        for k in range(len(R)):
            pose = np.eye(4)
            pose[:3, :3], pose[:3, 3] = R[k], t[k]
            for a, b in zip(ours.rows(pose, unknowns, inputs), theirs.rows(pose, unknowns, inputs), strict=True):
                np.testing.assert_allclose(a, b, rtol=0.0, atol=1e-9)


def test_the_generic_kinematics_equal_the_compiled_ones(setting):
    _, _, R, t, compiled, generic, x = setting
    strokes = compiled.inverse_kinematics(R, t, x)
    np.testing.assert_allclose(generic.inverse_kinematics(R, t, x), strokes, rtol=0.0, atol=1e-9)
    ours, theirs = generic.forward_kinematics(strokes, x), compiled.forward_kinematics(strokes, x)
    np.testing.assert_allclose(ours.R, theirs.R, rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(ours.t, theirs.t, rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(ours.t, t, rtol=0.0, atol=1e-6)
    R_one, t_one = generic.solve_fk(strokes[0], x, None)
    np.testing.assert_allclose(R_one, R[0], rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(t_one, t[0], rtol=0.0, atol=1e-6)
    np.testing.assert_allclose(
        generic.residual(x, R, t, strokes), compiled.residual(x, R, t, strokes), rtol=0.0, atol=1e-9
    )
    with pytest.raises(ValueError, match="prismatic"):
        generic.kernel_terms()


def test_with_terms_scales_a_term_by_the_leg_models_J_e(setting):
    platform, rng, R, t, _, _, x = setting
    scale = rng.uniform(0.5, 2.0, 6)
    drive = DriveModel(ScaledLegs(platform.drive, scale=scale), (stroke_term(np.full(6, 0.01), 0.05),))
    inputs = rng.uniform(-20.0, 20.0, 6)
    for k in range(len(R)):
        _, J_x = drive.jacobians(x, R[k], t[k], inputs)
        numeric = numerical_jacobian(lambda v, k=k: drive.residual(v, R[k], t[k], inputs), x)
        assert relative_error(J_x, numeric) < 1e-6
        np.testing.assert_allclose(np.diag(J_x[:, 42:]), -scale * inputs, rtol=1e-12)
        # the stroke's gain into the residual: J_e (1 + k)
        gains = drive.stroke_gains(x, R[k], t[k], inputs)
        np.testing.assert_allclose(gains, -scale * (1.0 + 0.01 + x[42:]), rtol=1e-12)


def test_an_elastic_drive_needs_prismatic_legs():
    platform = nim_stewart()
    elastic = Elastic(platform_mass_kg=20.0, platform_com_mm=np.zeros(3))
    rotary = replace(platform, drive=NumpyLegs(platform.drive, kind="rotary"), elastic=elastic, source="robot.toml")
    with pytest.raises(CalibError, match=r"^robot\.toml: \[elastic\].*rotary"):
        drive_model(rotary)


def test_a_rotary_drive_through_the_drive_model_and_its_factor():
    """RotaryLegs (spec §15) plugs into the drive model: its Jacobians (stroke = angle scale unknown)
    match central differences, the factor's rows are its residual over ``|J_e|``, FK inverts IK, and
    an outside instrument's gauge leaves 66 − 12 = 54 free directions."""
    from stewart_calib.instruments import gauge
    from tests.test_rotary_legs import reachable_poses, servo_build, servo_errors

    legs = servo_build()
    drive = DriveModel(legs, (stroke_term(np.full(6, 0.01), 0.05),))
    rng = np.random.default_rng(5)
    # tilts 0: a perturbed set's J_M turns its axes about its own u, w (RotaryLegs), which at tilts
    # of ~1° differ from the derivative of nominal.perturbed(δM) by ~1 % in the tilt columns
    tilts = np.r_[np.tile(np.r_[np.zeros(9), 1.0, 1.0], 6), np.zeros(6)] > 0.0
    x = np.where(tilts, 0.0, np.r_[servo_errors(rng), rng.normal(0.0, 0.01, 6)])
    R, t, _ = reachable_poses(legs, 3, 7)
    angles = drive.inverse_kinematics(R, t, x)
    fk = drive.forward_kinematics(angles, x, guess=(R, t))
    np.testing.assert_allclose(fk.t, t, rtol=0.0, atol=1e-6)
    inputs = angles[0] + 0.01
    J_pose, J_x = drive.jacobians(x, R[0], t[0], inputs)
    numeric = numerical_jacobian(lambda v: drive.residual(v, R[0], t[0], inputs), x, eps=1e-6)
    assert J_pose.shape == (6, 6)
    assert relative_error(J_x, numeric) < 1e-5
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = R[0], t[0]
    r, H_pose, H = drive_leg.DriveLegs.of(np.arange(6), drive).rows(pose, x, inputs)
    _, _, J_e = drive.geometry(x).residual_jacobians(R[0], t[0], drive.extensions(inputs, x))
    np.testing.assert_allclose(r, drive.residual(x, R[0], t[0], inputs) / np.abs(J_e), rtol=1e-12)
    np.testing.assert_allclose(H, J_x / np.abs(J_e)[:, None], rtol=1e-12)
    np.testing.assert_allclose(H_pose, J_pose / np.abs(J_e)[:, None], rtol=1e-12)
    basis = gauge.free_basis(legs)
    assert basis.shape == (66, 54)
    np.testing.assert_allclose(basis.T @ basis, np.eye(54), atol=1e-12)
    covariance = 1e-4 * np.eye(6)
    r_obs, H_obs, R_meas, _ = drive.observation(x, R[0], t[0], inputs, covariance, np.radians(0.05))
    np.testing.assert_allclose(r_obs, drive.residual(x, R[0], t[0], inputs), rtol=1e-12)
    assert H_obs.shape == (6, 72) and np.all(np.linalg.eigvalsh(R_meas) > 0.0)
