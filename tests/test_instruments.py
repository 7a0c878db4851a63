"""Measurement models (stewart_calib.instruments) and the unknown vector (stewart_calib.model.unknowns)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from stewart_calib.config import NoiseConfig
from stewart_calib.errors import SampleRejected
from stewart_calib.instruments import MODELS, InstrumentModel, instrument_model, instrument_theta
from stewart_calib.instruments.tracker import TrackerModel
from stewart_calib.model import kinematics as kin
from stewart_calib.model.drive import stroke_term
from stewart_calib.model.platform import INSTRUMENT_KINDS, N_PARAMS
from stewart_calib.model.unknowns import UnknownLayout
from tests.numdiff import EPS_MM, numerical_jacobian, numerical_pose_jacobian, relative_error
from tests.synthetic import nim_stewart, random_poses

#: analytic vs central-difference Jacobians: the differences' own error is ~1e-10 (tests/numdiff.py).
JACOBIAN_RTOL = 1e-6


@pytest.fixture(scope="module")
def platform():
    return nim_stewart()


@pytest.fixture(scope="module")
def poses(platform):
    return kin.pose_to_rt(random_poses(platform, 4, np.random.default_rng(3)))


def _tracker(platform, geometry_sigma_mm=0.0):
    return TrackerModel(platform.tracker, 0.002, platform.reading_range, geometry_sigma_mm)


def test_the_registry_builds_the_tracker_as_a_protocol_instance(platform):
    model = instrument_model(platform, NoiseConfig(reading_sigma_mm=0.02))
    assert isinstance(model, InstrumentModel) and model.kind == "tracker" and model.unknowns is None
    np.testing.assert_array_equal(model.channel_sigma, np.full(6, 0.02))
    assert model.columns == tuple(f"s{i}_mm" for i in range(1, 7))


@pytest.mark.parametrize("geometry_sigma_mm", [0.0, 0.05])
def test_tracker_residual_and_jacobians_match_central_differences(platform, poses, geometry_sigma_mm):
    model = _tracker(platform, geometry_sigma_mm)
    theta = instrument_theta(model, None)
    channels = np.arange(6)
    for R, t in zip(*poses, strict=True):
        z = kin.inverse_kinematics(platform.tracker, R, t) - 0.05  # every ruler reads 50 µm short
        res = model.residual(R, t, theta, z, channels)
        np.testing.assert_allclose(res.r, 0.05, atol=1e-9)
        numeric = numerical_pose_jacobian(lambda R_, t_, z=z: model.residual(R_, t_, theta, z, channels).r, R, t)
        assert relative_error(res.J_pose, numeric) < JACOBIAN_RTOL
        if geometry_sigma_mm:
            numeric = numerical_jacobian(
                lambda th, R=R, t=t, z=z: model.residual(R, t, th, z, channels).r, theta, EPS_MM
            )
            assert relative_error(res.J_instrument, numeric) < JACOBIAN_RTOL
        else:
            assert res.J_instrument.shape == (6, 0)


def test_tracker_pose_is_fk_with_propagated_covariance_and_its_theta_jacobian(platform, poses):
    model = _tracker(platform, 0.05)
    theta = instrument_theta(model, None)
    R, t = poses[0][0], poses[1][0]
    z = kin.inverse_kinematics(platform.tracker, R, t)
    obs = model.pose(z, theta, None)
    assert np.max(np.abs(obs.R - R)) < 1e-9 and np.max(np.abs(obs.t - t)) < 1e-7
    np.testing.assert_allclose(obs.covariance, kin.pose_covariance_from_legs(platform.tracker, R, t, 0.002))

    def implied_xi(th):  # the FK pose at θ, as a body-tangent offset from the pose at θ₀
        fk = model.pose(z, th, (R, t))
        return np.r_[_log_so3(R.T @ fk.R), R.T @ (fk.t - t)]

    numeric = numerical_jacobian(implied_xi, theta, EPS_MM)
    assert relative_error(obs.J_instrument, numeric) < JACOBIAN_RTOL


def _log_so3(R: np.ndarray) -> np.ndarray:
    angle = kin.rotation_angle(R)
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return axis * (0.5 if angle < 1e-12 else angle / (2.0 * np.sin(angle)))


def test_tracker_check_refuses_with_the_reason(platform):
    model = _tracker(platform)
    good = np.full(6, np.mean(platform.reading_range))
    np.testing.assert_array_equal(model.check(good, 1.0), good)
    for z, reason, words in (
        (np.r_[good[:5], np.nan], SampleRejected.NON_FINITE, "reading s6 is not finite"),
        (np.r_[platform.reading_range[1] + 1.0, good[1:]], SampleRejected.OUT_OF_RANGE, "reading s1 ="),
        (good[:5], SampleRejected.NON_FINITE, "expected 6 reading s values"),
    ):
        with pytest.raises(SampleRejected, match=words) as err:
            model.check(z, 1.0)
        assert err.value.reason == reason


def test_layout_places_blocks_after_the_drive_and_reports_file_units(platform):
    tracker = _tracker(platform, 0.05)
    layout = UnknownLayout((stroke_term(np.zeros(6), 0.02).block(), tracker.unknowns), n_params=N_PARAMS)
    assert layout.size == N_PARAMS + 6 + N_PARAMS
    assert layout.slice("stroke_scale") == slice(42, 48) and layout.slice("instrument") == slice(48, 90)
    np.testing.assert_array_equal(layout.prior_sigma(5.0)[[0, 41, 42, 48]], [5.0, 5.0, 0.02, 0.05])
    entry = layout.block("stroke_scale").to_file(np.full(6, 0.01), np.full(6, 0.002))
    assert entry == {"names": ["k1", "k2", "k3", "k4", "k5", "k6"], "estimate": [0.01] * 6, "stddev": [0.002] * 6}


@pytest.mark.parametrize("holder", ["tracker", "drive"])
def test_gauge_rows_span_exactly_the_rigid_motions_of_the_joints(platform, holder):
    """The tracker's geometry block holds the gauge on its own joints; a block that does not (an
    outside instrument's) leaves it on the drive's."""
    block = _tracker(platform, 0.05).unknowns
    if holder == "drive":
        block = replace(block, holds_gauge=False)
    layout = UnknownLayout((block,), n_params=N_PARAMS)
    C = layout.gauge_rows(platform.drive)
    assert C.shape == (12, layout.size) and np.linalg.matrix_rank(C) == 12
    rng = np.random.default_rng(0)
    legs, start = (platform.tracker, N_PARAMS) if holder == "tracker" else (platform.drive, 0)
    joints = {"base": (legs.base_joints, 0), "platform": (legs.platform_joints, 3)}
    for points, offset in joints.values():
        a, omega = rng.normal(size=3), rng.normal(size=3) * 1e-3
        x = np.zeros(layout.size)
        for i, p in enumerate(points):  # δp_i = a + ω × (p_i − p̄): a rigid motion of these joints
            x[start + 7 * i + offset : start + 7 * i + offset + 3] = a + np.cross(omega, p - points.mean(axis=0))
        # a rigid motion is seen by the rows; what is left after removing the rows' span is not one
        assert np.linalg.norm(C @ x) > 0.1 * np.linalg.norm(x)
        residue = x - np.linalg.pinv(C) @ (C @ x)
        assert np.linalg.norm(residue) < 1e-9 * np.linalg.norm(x)
    assert UnknownLayout((stroke_term(np.zeros(6), 0.02).block(),), n_params=N_PARAMS).gauge_rows(
        platform.drive
    ).shape == (0, 48)


def test_estimate_of_a_generalised_state_adds_its_blocks_to_the_result(platform):
    from stewart_calib.estimate import Estimate
    from stewart_calib.io import result_dict, validate_result

    layout = UnknownLayout((stroke_term(np.zeros(6), 0.02).block(),), n_params=N_PARAMS)
    x = np.r_[np.full(N_PARAMS, 0.1), np.full(6, 0.01)]
    P = np.diag(np.r_[np.full(N_PARAMS, 0.04), np.full(6, 1e-4)])
    estimate = Estimate.of_state(x, P, layout, "ekf", 10, 1.0)
    np.testing.assert_array_equal(estimate.error, x[:N_PARAMS])
    np.testing.assert_allclose(estimate.stddev, 0.2)
    result = result_dict(estimate, platform)
    validate_result(result, "<test>")  # spec §5 unchanged
    assert result["stroke_scale"]["estimate"] == [0.01] * 6
    np.testing.assert_allclose(result["stroke_scale"]["stddev"], 0.01)
    assert "stroke_scale" not in result_dict(
        Estimate.of_state(x[:N_PARAMS], P[:N_PARAMS, :N_PARAMS], UnknownLayout(n_params=N_PARAMS), "ekf"), platform
    )


def test_the_platform_file_reads_the_kinds_the_registry_models():
    # the platform file's sections and the models are one list of kinds, in one order (the first the default)
    assert tuple(MODELS) == INSTRUMENT_KINDS
