"""The pose algebra (stewart_calib.model.rotations), the package's one SO(3)/SE(3) module: against
its definitions (paper eq. 20–21), the group axioms, GTSAM's and scipy's conventions and central
differences.

Rotations are compared in local coordinates (the rotation angle of ``R_aᵀ R_b``), never by raw
Euler differences.
"""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from stewart_calib.model import rotations

from .numdiff import EPS_MM, EPS_RAD, numerical_jacobian, relative_error

#: central differences (steps of numdiff) agree to ~1e-10 relative; 1e-7 fails any wrong term
JACOBIAN_RTOL = 1e-7
#: a few flops on O(1) numbers
ROUND_OFF = 1e-14


def _random_poses(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return Rotation.random(n, random_state=rng).as_matrix(), rng.normal(0.0, 300.0, (n, 3))


# ----------------------------------------------------------------------------- rotations

angle = st.floats(min_value=-np.radians(179.0), max_value=np.radians(179.0))
pitch = st.floats(min_value=-np.radians(89.0), max_value=np.radians(89.0))
rpy_strategy = st.tuples(angle, pitch, angle).map(np.array)


def Rx(a):  # paper eq. 21
    return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])


def Ry(b):  # paper eq. 21
    return np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])


def Rz(g):  # paper eq. 21
    return np.array([[np.cos(g), -np.sin(g), 0], [np.sin(g), np.cos(g), 0], [0, 0, 1]])


@settings(max_examples=100, deadline=None)
@given(rpy=rpy_strategy)
def test_rpy_is_rz_ry_rx_and_round_trips(rpy):
    R = rotations.rpy_to_rotation(rpy)
    # eq. 20: R = Rz(γ) Ry(β) Rx(α); both are a few flops on O(1) numbers: 1e-15.
    np.testing.assert_allclose(R, Rz(rpy[2]) @ Ry(rpy[1]) @ Rx(rpy[0]), rtol=0, atol=1e-15)
    # atan2 recovery with |pitch| ≤ 89°: the conditioning 1/cos(89°) ≈ 57 costs ~2 digits.
    np.testing.assert_allclose(rotations.rotation_to_rpy(R), rpy, rtol=0, atol=1e-13)


def test_rotation_to_rpy_round_trips_random_rotations():
    R = Rotation.random(200, random_state=np.random.default_rng(2)).as_matrix()
    back = rotations.rpy_to_rotation(rotations.rotation_to_rpy(R))
    assert np.max(rotations.rotation_angle(np.swapaxes(R, -1, -2) @ back)) <= 1e-12


def test_pose_error_known_cases():
    eye, t0 = np.eye(3), np.array([10.0, -20.0, 1100.0])
    position_mm, angle_deg = rotations.pose_error(eye, t0, eye, t0 + [3.0, 4.0, 0.0])
    assert position_mm == pytest.approx(5.0, abs=1e-12) and angle_deg == pytest.approx(0.0, abs=1e-12)

    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    R_a = rotations.rpy_to_rotation(np.radians([5.0, -10.0, 30.0]))
    R_b = R_a @ rotations.so3_exp(np.radians(7.5) * axis)  # 7.5° about a body axis
    position_mm, angle_deg = rotations.pose_error(R_a, t0, R_b, t0)
    assert position_mm == 0.0 and angle_deg == pytest.approx(7.5, abs=1e-12)

    # Near 0 and π, where arccos(trace) would lose half the digits.
    tiny = rotations.so3_exp(1e-9 * axis)
    half_turn = rotations.so3_exp((np.pi - 1e-7) * axis)
    _, angle_deg = rotations.pose_error(
        np.stack([eye, eye]), np.zeros((2, 3)), np.stack([tiny, half_turn]), np.zeros((2, 3))
    )
    np.testing.assert_allclose(np.radians(angle_deg), [1e-9, np.pi - 1e-7], rtol=1e-9)


def test_so3_log_inverts_exp_and_its_jacobian():
    rng = np.random.default_rng(2)
    phi = rng.normal(0, 1.0, (50, 3))
    phi[0] = [0.0, 0.0, 1e-12]
    phi[1] = [np.pi - 1e-9, 0.0, 0.0]
    np.testing.assert_allclose(rotations.so3_log(rotations.so3_exp(phi)), phi, atol=1e-8)
    p = rng.normal(0, 0.8, 3)
    numeric = numerical_jacobian(
        lambda d: rotations.so3_log(rotations.so3_exp(p) @ rotations.so3_exp(d)), np.zeros(3), EPS_RAD
    )
    assert relative_error(rotations.so3_right_jacobian_inverse(p), numeric) < JACOBIAN_RTOL


def test_so3_log_at_half_a_turn_and_the_angle_and_axis():
    axes = Rotation.random(20, random_state=np.random.default_rng(5)).as_rotvec()
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    theta = np.r_[np.pi, np.pi - 1e-10, np.linspace(1e-8, 3.0, 18)]
    R = rotations.so3_exp(theta[:, None] * axes)
    phi = rotations.so3_log(R)
    # at π, φ and −φ are the same rotation: compare through Exp
    assert np.max(rotations.rotation_angle(np.swapaxes(R, -1, -2) @ rotations.so3_exp(phi))) < 1e-9
    np.testing.assert_allclose(np.linalg.norm(phi, axis=1), theta, rtol=1e-9)
    np.testing.assert_allclose(rotations.rotation_angle(R), theta, rtol=1e-9)
    np.testing.assert_allclose(rotations.rotation_axis_sin(R), np.sin(theta)[:, None] * axes, atol=ROUND_OFF)


@pytest.mark.parametrize("order", ["xyzw", "wxyz"])
def test_quaternions_are_scipys_rotations_in_either_order(order):
    rng = np.random.default_rng(6)
    xyzw = Rotation.random(30, random_state=rng).as_quat()  # scipy: scalar last
    q = xyzw if order == "xyzw" else np.roll(xyzw, 1, axis=1)
    expected = Rotation.from_quat(xyzw).as_matrix()
    np.testing.assert_allclose(rotations.quaternion_to_rotation(q, order), expected, atol=ROUND_OFF)
    # −q is the same rotation; a quaternion is normalised first; any leading shape
    scaled = -rng.uniform(0.5, 2.0, (30, 1)) * q
    np.testing.assert_allclose(rotations.quaternion_to_rotation(scaled, order), expected, atol=ROUND_OFF)
    batched = rotations.quaternion_to_rotation(q.reshape(5, 6, 4), order)
    np.testing.assert_allclose(batched, expected.reshape(5, 6, 3, 3), atol=ROUND_OFF)


def test_compose_and_inverse_obey_the_group_axioms():
    R, t = _random_poses(3, 7)
    (Ra, Rb, Rc), (ta, tb, tc) = R, t
    left = rotations.compose(*rotations.compose(Ra, ta, Rb, tb), Rc, tc)
    right = rotations.compose(Ra, ta, *rotations.compose(Rb, tb, Rc, tc))
    np.testing.assert_allclose(left[0], right[0], atol=ROUND_OFF)
    np.testing.assert_allclose(left[1], right[1], atol=1e-11)
    R_id, t_id = rotations.compose(Ra, ta, *rotations.inverse(Ra, ta))
    np.testing.assert_allclose(R_id, np.eye(3), atol=ROUND_OFF)
    np.testing.assert_allclose(t_id, 0.0, atol=1e-12)
    # the same product as gtsam's Pose3
    expected = gtsam.Pose3(gtsam.Rot3(Ra), ta).compose(gtsam.Pose3(gtsam.Rot3(Rb), tb))
    R_ab, t_ab = rotations.compose(Ra, ta, Rb, tb)
    np.testing.assert_allclose(R_ab, expected.rotation().matrix(), atol=ROUND_OFF)
    np.testing.assert_allclose(t_ab, expected.translation(), atol=1e-11)


def test_adjoint_is_gtsams_and_conjugates_the_tangent():
    R, t = _random_poses(4, 8)
    Ad = rotations.adjoint(R, t)
    for k in range(len(R)):
        T = gtsam.Pose3(gtsam.Rot3(R[k]), t[k])
        np.testing.assert_allclose(Ad[k], T.AdjointMap(), atol=1e-11)
        xi = np.random.default_rng(k).normal(0.0, 0.3, 6)  # [ω, v], gtsam's order
        conjugated = T.compose(gtsam.Pose3.Expmap(xi)).compose(T.inverse())
        np.testing.assert_allclose(gtsam.Pose3.Logmap(conjugated), Ad[k] @ xi, atol=1e-9)


def test_project_to_rotation_is_the_nearest_rotation():
    R, _ = _random_poses(10, 9)
    np.testing.assert_allclose(rotations.project_to_rotation(R), R, atol=ROUND_OFF)
    M = R + np.random.default_rng(10).normal(0.0, 0.05, R.shape)
    P = rotations.project_to_rotation(M)
    np.testing.assert_allclose(np.swapaxes(P, -1, -2) @ P, np.broadcast_to(np.eye(3), P.shape), atol=ROUND_OFF)
    np.testing.assert_allclose(np.linalg.det(P), 1.0, atol=ROUND_OFF)
    # nearest: no rotation a small turn away from P is closer to M in the Frobenius norm
    for omega in np.random.default_rng(11).normal(0.0, 1e-3, (20, 3)):
        turned = P @ rotations.so3_exp(omega)
        assert np.all(np.linalg.norm(turned - M, axis=(1, 2)) >= np.linalg.norm(P - M, axis=(1, 2)))
    # a mirror image is turned into the rotation nearest it, never a reflection
    assert np.linalg.det(rotations.project_to_rotation(-R[0])) == pytest.approx(1.0, abs=ROUND_OFF)


def test_pose6_tangent_jacobian_matches_central_differences():
    R, t = _random_poses(3, 12)
    pose6 = rotations.rt_to_pose(R, t)
    pose6[:, 4] = np.clip(pose6[:, 4], -1.2, 1.2)  # pitch away from ±90°, where rpy is singular
    steps = np.r_[[EPS_RAD] * 3, [EPS_MM] * 3]
    for p in pose6:
        R_p, t_p = rotations.pose_to_rt(p)
        numeric = numerical_jacobian(
            lambda xi, R_p=R_p, t_p=t_p: rotations.rt_to_pose(*rotations.retract(R_p, t_p, xi)), np.zeros(6), steps
        )
        assert relative_error(rotations.pose6_tangent_jacobian(p), numeric) < JACOBIAN_RTOL
