"""The rotary (servo-horn, 6-RSS) leg set of spec §15 (stewart_calib.model.rotary) against its
definitions, finite differences and its own inverse/forward kinematics.

The build is a plausible hobby servo platform: cranks on a 100 mm circle in pairs at 120k ± 15°,
horizontal axes tangential and alternately reversed (the mirrored servos of a pair), horns of
25 mm pointing outward at angle 0, rods of 150 mm, platform joints on a 75 mm circle at
120k ± 45°; the servos accept ±90°. Poses are compared in local coordinates (translation norm,
rotation angle of ``R_aᵀ R_b``).
"""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import gtsam
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from stewart_calib.errors import SampleRejected
from stewart_calib.model import RotaryLegs
from stewart_calib.model import kinematics as kin
from stewart_calib.model.rotary import PARAMETER_FIELDS, orthonormal_zero_directions
from stewart_calib.model.rotations import pose_error, pose_to_rt, so3_exp

from .numdiff import EPS_MM, EPS_RAD, numerical_jacobian, numerical_pose3_jacobian, relative_error

BASE_RADIUS_MM, PLATFORM_RADIUS_MM, HORN_MM, ROD_MM = 100.0, 75.0, 25.0, 150.0
#: the random poses about home: ±15 mm, ±10° per axis (about 70 % of them reachable within ±90°)
HALF_BOX = np.r_[15.0, 15.0, 15.0, np.radians([10.0, 10.0, 10.0])]

# Jacobian checks (tests/numdiff.py's steps): f is a rod length ≈ 150 mm. In mm, |f'''| ≲ 1/L² ≈ 4e-5
# mm⁻² and EPS_MM = 1e-2 mm give a truncation error ≈ eps² |f'''| / 6 ≈ 7e-10 on derivatives of order 1;
# in rad (ω, o, tu, tw), |f'''| ≲ L ≈ 150 mm and EPS_RAD = 1e-5 give ≈ 2.5e-9 plus round-off
# ε |f| / eps ≈ 3e-9 on derivatives of order h ≈ 25 mm/rad: ≈ 1e-9 relative either way. 1e-6 fails any
# wrong term (a sign, a missing factor, a wrong rotation order is an O(1) error) with a margin of 1000.
JACOBIAN_REL_TOL = 1e-6
# FK stops once every |residual| ≤ FK_TOL_MM; the pose is then off by ≤ ‖J_pose⁻¹‖₂ √6 FK_TOL_MM, and
# IK of it off by ≤ FK_TOL_MM / |J_e| per leg: the round trips below assert these bounds pose by pose.
FK_TOL_MM = 1e-11
# IK closes a rod up to rounding of |v|² ≈ 2e4 mm²: ε · |v|² / r ≈ 3e-14 mm a step, a few steps
IK_RESIDUAL_MM = 1e-11


def servo_build(angle_range_deg=(-90.0, 90.0), angle_offsets_deg=(0.0,) * 6) -> RotaryLegs:
    pair = np.repeat(np.arange(3), 2)
    side = np.tile([-1.0, 1.0], 3)
    base = np.radians(120.0 * pair + 15.0 * side)
    plat = np.radians(120.0 * pair + 45.0 * side)
    radial = np.c_[np.cos(base), np.sin(base), np.zeros(6)]
    tangent = np.c_[-np.sin(base), np.cos(base), np.zeros(6)]
    return RotaryLegs(
        crank_centres=BASE_RADIUS_MM * radial,
        crank_axes=side[:, None] * tangent,
        zero_directions=radial,
        horn_lengths=np.full(6, HORN_MM),
        rod_lengths=np.full(6, ROD_MM),
        platform_joints=PLATFORM_RADIUS_MM * np.c_[np.cos(plat), np.sin(plat), np.zeros(6)],
        angle_offsets=np.radians(angle_offsets_deg),
        angle_range=tuple(np.radians(angle_range_deg)),
    )


LEGS = servo_build()
FIELDS = [
    field.name for field in dataclasses.fields(RotaryLegs) if field.name not in ("tilt_reference", "reach_margin")
]


def servo_errors(rng: np.random.Generator) -> np.ndarray:
    """A δM of a real servo build: 0.5 mm joints, 0.2 mm horns and rods, zero trim of a spline tooth's
    fraction (≈ 3°), axis tilt ≈ 1° [mm, rad]."""
    sigma = np.tile(np.r_[[0.5] * 6, 0.2, 0.2, np.radians([3.0, 1.0, 1.0])], 6)
    return sigma * rng.standard_normal(66)


# nothing aligned: every term of J_M is non-zero; its own tilt reference (a platform file's set), so
# its tilt columns are about its own axes
ROUGH = dataclasses.replace(LEGS.perturbed(servo_errors(np.random.default_rng(7))), tilt_reference=None)


def home(legs: RotaryLegs = LEGS) -> tuple[np.ndarray, np.ndarray]:
    solution = legs.forward_kinematics(np.zeros(6), tol_mm=FK_TOL_MM)
    return solution.R, solution.t


def reachable_poses(legs: RotaryLegs, n: int, seed: int):
    """``(R, t, e)`` of random poses about home that every leg reaches inside its range."""
    R_home, t_home = home(legs)
    rng = np.random.default_rng(seed)
    R, t = pose_to_rt(np.r_[t_home, 0.0, 0.0, 0.0] + HALF_BOX * rng.uniform(-1.0, 1.0, (4 * n, 6)))
    R = R_home @ R
    e = legs.coordinates(R, t)
    ok = np.flatnonzero(np.all(np.isfinite(e), axis=-1))[:n]
    assert len(ok) == n
    return R[ok], t[ok], e[ok]


# ----------------------------------------------------------------------------- the set and its vector


def test_construction_normalises_and_freezes():
    raw = LEGS.crank_axes * 3.0
    tilted = LEGS.zero_directions + np.tan(np.radians(0.5)) * LEGS.crank_axes  # 0.5° off orthogonal
    legs = RotaryLegs(
        LEGS.crank_centres, raw, 2.0 * tilted, LEGS.horn_lengths, LEGS.rod_lengths, LEGS.platform_joints,
        LEGS.angle_offsets, LEGS.angle_range,
    )  # fmt: skip
    np.testing.assert_allclose(legs.crank_axes, LEGS.crank_axes, atol=1e-15)
    np.testing.assert_allclose(legs.zero_directions, LEGS.zero_directions, atol=1e-15)
    for name in ("crank_centres", "crank_axes", "zero_directions", "horn_lengths", "rod_lengths"):
        assert not getattr(legs, name).flags.writeable
    _, _, off_deg = orthonormal_zero_directions(raw, tilted)
    np.testing.assert_allclose(off_deg, 0.5, rtol=1e-12)


def test_degenerate_rows_are_nan_and_refused():
    axes, zero = LEGS.crank_axes.copy(), LEGS.zero_directions.copy()
    axes[1], zero[3], zero[4] = 0.0, 0.0, 2.0 * LEGS.crank_axes[4]
    n, u, off_deg = orthonormal_zero_directions(axes, zero)
    assert np.flatnonzero(np.isnan(off_deg)).tolist() == [1, 3, 4]
    assert np.isnan(u[[1, 3, 4]]).all() and np.isnan(n[[1, 3, 4]]).all() and np.isfinite(u[[0, 2, 5]]).all()
    with pytest.raises(ValueError, match="leg 2"):
        RotaryLegs(
            LEGS.crank_centres, axes, zero, LEGS.horn_lengths, LEGS.rod_lengths, LEGS.platform_joints,
            LEGS.angle_offsets, LEGS.angle_range,
        )  # fmt: skip


@pytest.mark.parametrize(
    "change, message",
    [
        ({"crank_centres": np.zeros((5, 3))}, "crank_centres must have shape"),
        ({"horn_lengths": np.r_[0.0, np.ones(5)]}, "horn_lengths must be positive"),
        ({"rod_lengths": np.full(6, np.nan)}, "rod_lengths must be finite"),
        ({"angle_range": (1.0, -1.0)}, "angle_range"),
        ({"angle_range": (-4.0, 4.0)}, "angle_range"),
    ],
)
def test_bad_fields_are_refused(change, message):
    fields = {name: getattr(LEGS, name) for name in FIELDS}
    with pytest.raises(ValueError, match=message):
        RotaryLegs(**(fields | change))


def test_parameter_layout():
    assert (LEGS.kind, LEGS.n_legs, LEGS.n_params, LEGS.coordinate_unit, LEGS.compiled) == (
        "rotary",
        6,
        66,
        "deg",
        False,
    )
    names = LEGS.parameter_names
    assert names[:11] == ("a1x", "a1y", "a1z", "d1x", "d1y", "d1z", "h1", "r1", "o1", "tu1", "tw1")
    assert names[-1] == "tw6" and len(set(names)) == 66
    assert [names[k] for k in np.flatnonzero(LEGS.parameter_degrees)[:3]] == ["o1", "tu1", "tw1"]
    assert LEGS.parameter_degrees.sum() == 18
    M = ROUGH.as_vector()
    crank, joint = ROUGH.gauge_columns
    np.testing.assert_array_equal(M[crank], ROUGH.crank_centres)
    np.testing.assert_array_equal(M[joint], ROUGH.platform_joints)
    blocks = M.reshape(6, len(PARAMETER_FIELDS))
    np.testing.assert_array_equal(blocks[:, 6:9], np.c_[ROUGH.horn_lengths, ROUGH.rod_lengths, ROUGH.angle_offsets])
    np.testing.assert_array_equal(blocks[:, 9:], 0.0)


def test_priors_walks_and_the_coordinate_sigma_by_entry():
    # the keys of config.NoiseConfig that the rotary entries read (spec §15: priors and walks in degrees)
    noise = SimpleNamespace(
        prior_sigma_mm=0.5,
        angle_prior_sigma_deg=3.0,
        random_walk_mm_per_sqrt_s=1e-4,
        angle_random_walk_deg_per_sqrt_s=2e-3,
        angle_sigma_deg=0.05,
    )
    prior, walk = LEGS.prior_sigmas(noise), LEGS.walk_sigmas(noise)
    angle = LEGS.parameter_degrees
    np.testing.assert_array_equal(prior[~angle], 0.5)
    np.testing.assert_allclose(prior[angle], np.radians(3.0), rtol=1e-15)
    np.testing.assert_array_equal(walk[~angle], 1e-4)
    np.testing.assert_allclose(walk[angle], np.radians(noise.angle_random_walk_deg_per_sqrt_s), rtol=1e-15)
    assert LEGS.coordinate_sigma(noise) == pytest.approx(np.radians(noise.angle_sigma_deg), rel=1e-15)


# ----------------------------------------------------------------------------- perturbed


def _same_set(a: RotaryLegs, b: RotaryLegs, atol: float = 0.0) -> None:
    for name in FIELDS:
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=0.0, atol=atol, err_msg=name)


def test_zero_delta_is_the_same_set():
    _same_set(ROUGH.perturbed(np.zeros(66)), ROUGH)


def test_positions_lengths_and_offsets_add():
    delta = servo_errors(np.random.default_rng(3))
    delta.reshape(6, 11)[:, 9:] = 0.0
    moved = ROUGH.perturbed(delta)
    np.testing.assert_allclose(moved.as_vector(), ROUGH.as_vector() + delta, rtol=0.0, atol=1e-13)
    np.testing.assert_array_equal(moved.crank_axes, ROUGH.crank_axes)
    np.testing.assert_array_equal(moved.zero_directions, ROUGH.zero_directions)


def _tilt(leg: int, tu: float = 0.0, tw: float = 0.0) -> np.ndarray:
    delta = np.zeros((6, 11))
    delta[leg, 9:] = tu, tw
    return delta.reshape(-1)


def test_a_tu_turns_the_axis_about_u_and_a_tw_turns_u_about_w():
    alpha, leg = 0.3, 2
    n, u, w = ROUGH.crank_axes[leg], ROUGH.zero_directions[leg], ROUGH.w_directions[leg]
    by_tu = ROUGH.perturbed(_tilt(leg, tu=alpha))
    np.testing.assert_allclose(by_tu.crank_axes[leg], np.cos(alpha) * n - np.sin(alpha) * w, atol=1e-15)
    np.testing.assert_allclose(by_tu.zero_directions[leg], u, atol=1e-15)
    by_tw = ROUGH.perturbed(_tilt(leg, tw=alpha))
    np.testing.assert_allclose(by_tw.zero_directions[leg], np.cos(alpha) * u - np.sin(alpha) * n, atol=1e-15)
    np.testing.assert_allclose(by_tw.w_directions[leg], w, atol=1e-15)
    others = np.arange(6) != leg
    np.testing.assert_array_equal(by_tu.crank_axes[others], ROUGH.crank_axes[others])


def test_tilts_compose_about_the_sets_own_axes():
    # Rot(u, a) Rot(w, b): the w turn first about the old w, then the u turn; as two calls, a tu
    # then a tw about the new w (= Rot(u, a) w) is the same rotation; the other order is not.
    a, b, leg = 0.4, -0.3, 4
    both = ROUGH.perturbed(_tilt(leg, a, b))
    _same_set(ROUGH.perturbed(_tilt(leg, tu=a)).perturbed(_tilt(leg, tw=b)), both, atol=1e-15)
    other = ROUGH.perturbed(_tilt(leg, tw=b)).perturbed(_tilt(leg, tu=a))
    assert np.linalg.norm(other.crank_axes[leg] - both.crank_axes[leg]) > 0.01  # vs 1e-15 above
    turn = so3_exp(a * ROUGH.zero_directions[leg]) @ so3_exp(b * ROUGH.w_directions[leg])
    np.testing.assert_allclose(both.crank_axes[leg], turn @ ROUGH.crank_axes[leg], atol=1e-15)
    np.testing.assert_allclose(ROUGH.perturbed(_tilt(leg, tu=a)).perturbed(_tilt(leg, tu=b)).crank_axes,
                               ROUGH.perturbed(_tilt(leg, tu=a + b)).crank_axes, atol=1e-15)  # fmt: skip


# ----------------------------------------------------------------------------- Jacobians


POSES = reachable_poses(ROUGH, 5, seed=11)


@pytest.mark.parametrize("k", range(5))
def test_pose_jacobian_against_pose3_retract(k):
    R, t, e = POSES[0][k], POSES[1][k], POSES[2][k]
    J_pose = ROUGH.residual_jacobians(R, t, e)[0]
    pose3 = gtsam.Pose3(gtsam.Rot3(R), t)
    numeric = numerical_pose3_jacobian(lambda p: ROUGH.residuals(p.rotation().matrix(), p.translation(), e), pose3)
    assert relative_error(J_pose, numeric) < JACOBIAN_REL_TOL


@pytest.mark.parametrize("k", range(5))
def test_coordinate_jacobian(k):
    R, t, e = POSES[0][k], POSES[1][k], POSES[2][k]
    J_e = ROUGH.residual_jacobians(R, t, e)[2]
    numeric = numerical_jacobian(lambda x: ROUGH.residuals(R, t, x), e, EPS_RAD)
    np.testing.assert_array_equal(numeric[~np.eye(6, dtype=bool)], 0.0)  # leg i's residual sees e_i only
    assert relative_error(J_e, np.diagonal(numeric)) < JACOBIAN_REL_TOL


@pytest.mark.parametrize("field", range(len(PARAMETER_FIELDS)))
def test_parameter_jacobian_through_perturbed(field):
    R, t, e = POSES
    J_M = ROUGH.residual_jacobians(R, t, e)[1]
    columns = field + 11 * np.arange(6)
    steps = np.where(ROUGH.parameter_degrees, EPS_RAD, EPS_MM)
    for column in columns:  # each kind on every leg, tilts too, all through perturbed()

        def moved(x, column=column):
            delta = np.zeros(66)
            delta[column] = x[0]
            return ROUGH.perturbed(delta).residuals(R, t, e)

        numeric = numerical_jacobian(moved, np.zeros(1), steps[column])[..., 0]
        assert relative_error(J_M[..., column], numeric) < JACOBIAN_REL_TOL, ROUGH.parameter_names[column]
    leg_of_column = np.arange(66) // 11
    np.testing.assert_array_equal(J_M[..., np.arange(6)[:, None] != leg_of_column], 0.0)  # block-diagonal


def test_tilt_jacobian_of_a_tilted_set_is_the_drives_derivative():
    # the drive perturbs its nominal legs by the whole δM: at a set tilted by 1° its tu, tw columns
    # must be ∂/∂δ of nominal.perturbed(δ), the derivative an estimator linearises with
    R, t, e = POSES
    delta = np.zeros(66)
    delta[_TILT_COLUMNS] = np.radians(1.0) * np.resize([1.0, -0.7, 0.4], len(_TILT_COLUMNS))
    tilted = ROUGH.perturbed(delta)
    J_M = tilted.residual_jacobians(R, t, e)[1]
    for column in _TILT_COLUMNS:

        def moved(x, column=column):
            step = delta.copy()
            step[column] += x[0]
            return ROUGH.perturbed(step).residuals(R, t, e)

        numeric = numerical_jacobian(moved, np.zeros(1), EPS_RAD)[..., 0]
        assert relative_error(J_M[..., column], numeric) < JACOBIAN_REL_TOL, ROUGH.parameter_names[column]


_TILT_COLUMNS = np.concatenate([9 + 11 * np.arange(6), 10 + 11 * np.arange(6)])


def test_jacobians_broadcast_over_batches():
    R, t, e = POSES
    J_pose, J_M, J_e = ROUGH.residual_jacobians(R.reshape(5, 1, 3, 3), t.reshape(5, 1, 3), e.reshape(5, 1, 6))
    assert J_pose.shape == (5, 1, 6, 6) and J_M.shape == (5, 1, 6, 66) and J_e.shape == (5, 1, 6)
    single = ROUGH.residual_jacobians(R[3], t[3], e[3])
    for batched, one in zip((J_pose, J_M, J_e), single, strict=True):
        np.testing.assert_allclose(batched[3, 0], one, rtol=1e-14, atol=1e-14)


# ----------------------------------------------------------------------------- IK and its branch rule


def test_ik_closes_every_rod():
    R, t, e = reachable_poses(ROUGH, 200, seed=5)
    assert np.max(np.abs(ROUGH.residuals(R, t, e))) < IK_RESIDUAL_MM
    low, high = ROUGH.angle_range
    assert np.all((e >= low) & (e <= high))


def test_mirrored_servos_turn_opposite_ways():
    # Raised 10 mm above home, every horn turns up by the same angle: the reversed axes of each pair
    # make that +θ on one servo and −θ on its mirror.
    R, t = home()
    e = LEGS.coordinates(R, t + [0.0, 0.0, 10.0])
    assert np.all(np.abs(e) > np.radians(5.0))
    np.testing.assert_allclose(e[0::2], -e[1::2], rtol=1e-12)
    np.testing.assert_allclose(e, e[0] * np.tile([1.0, -1.0], 3), rtol=1e-12)
    b = LEGS.horn_joints(e)
    assert np.all(b[:, 2] > 0.0)  # both branches of the rule turned the horns up, not down


def _both_branches(legs, R, t):
    """The two horn solutions e± of each leg as angles in (−π, π]."""
    v = R @ legs.platform_joints.T
    v = v.T + t - legs.crank_centres
    A, B = np.sum(v * legs.zero_directions, axis=-1), np.sum(v * legs.w_directions, axis=-1)
    C = (np.sum(v * v, axis=-1) + legs.horn_lengths**2 - legs.rod_lengths**2) / (2.0 * legs.horn_lengths)
    roots = np.arctan2(B, A)[None] + np.array([[1.0], [-1.0]]) * np.arccos(C / np.hypot(A, B))
    return np.angle(np.exp(1j * (roots - legs.angle_offsets)))


def test_both_branches_in_range_take_the_one_nearest_the_middle():
    R, t = home()
    t = t + [3.0, -2.0, 5.0]
    branches = _both_branches(LEGS, R, t)
    assert np.all(np.abs(branches[0] - branches[1]) > np.radians(60.0))  # two solutions far apart
    full = servo_build(angle_range_deg=(-180.0, 180.0))
    np.testing.assert_allclose(full.coordinates(R, t), branches[np.argmin(np.abs(branches), axis=0), np.arange(6)])
    shifted = servo_build(angle_range_deg=(-100.0, 260.0))  # middle 80°: the other branch is nearer for some legs
    expected = np.where(branches < np.radians(-100.0), branches + 2.0 * np.pi, branches)
    nearest = expected[np.argmin(np.abs(expected - np.radians(80.0)), axis=0), np.arange(6)]
    np.testing.assert_allclose(shifted.coordinates(R, t), nearest)
    assert not np.allclose(nearest, full.coordinates(R, t))


def test_range_across_180_degrees_takes_its_own_window():
    # A zero trim of 180° puts the outward horn at e ≈ ±180°: in (−180°, 180°] it would be near −180°
    # for some legs and near +180° for others; the range [90°, 270°] takes every one near +180°.
    R, t = home()
    t = t + [0.0, 0.0, 10.0]
    e_plain = LEGS.coordinates(R, t)
    flipped = servo_build(angle_range_deg=(90.0, 270.0), angle_offsets_deg=np.full(6, 180.0))
    e = flipped.coordinates(R, t)
    np.testing.assert_allclose(e, e_plain + np.pi, atol=1e-12)
    assert np.all(e > np.pi - np.radians(30.0)) and np.any(e > np.pi) and np.any(e < np.pi)
    np.testing.assert_allclose(flipped.residuals(R, t, e), 0.0, atol=IK_RESIDUAL_MM)


def test_unreachable_or_out_of_range_is_nan():
    R, t = home()
    assert np.isnan(LEGS.coordinates(R, t + [0.0, 0.0, 60.0])).all()  # rod + horn too short
    narrow = servo_build(angle_range_deg=(-5.0, 5.0))
    e = narrow.coordinates(np.stack([R, R]), np.stack([t, t + [0.0, 0.0, 10.0]]))
    assert np.isfinite(e[0]).all() and np.isnan(e[1]).all()
    assert np.isnan(narrow.unit_vectors(R, t + [0.0, 0.0, 10.0])).all()


def test_unit_vectors_are_the_rods():
    R, t, e = POSES
    m = ROUGH.unit_vectors(R, t)
    rods = kin.transform_points(R, t, ROUGH.platform_joints) - ROUGH.horn_joints(e)
    np.testing.assert_allclose(m * ROUGH.rod_lengths[:, None], rods, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(m, axis=-1), 1.0, rtol=1e-15)


# ----------------------------------------------------------------------------- FK


def _pose_bounds(legs, R, t, e, residual_mm):
    """Per pose: ‖J_pose⁻¹‖₂ √6 · residual — how far FK's pose may be from the true one (rad and mm
    mixed in one norm, so a bound on both) — and per leg residual / |J_e|, the bound on IK's angles."""
    J_pose, _, J_e = legs.residual_jacobians(R, t, e)
    worst = np.sqrt(6.0) * residual_mm / np.linalg.svd(J_pose, compute_uv=False)[..., -1]
    return worst, residual_mm[..., None] / np.abs(J_e)


def test_ik_fk_ik_round_trip():
    R, t, e = reachable_poses(ROUGH, 300, seed=2)
    solution = ROUGH.forward_kinematics(e, tol_mm=FK_TOL_MM)
    assert solution.converged.all() and solution.residual_mm.max() <= FK_TOL_MM
    bound, angle_bound = _pose_bounds(ROUGH, R, t, e, np.maximum(solution.residual_mm, 1e-13))
    position_mm, angle_deg = pose_error(R, t, solution.R, solution.t)
    assert np.all(position_mm <= bound + 1e-12) and np.all(np.radians(angle_deg) <= bound + 1e-13)
    again = ROUGH.coordinates(solution.R, solution.t)
    assert np.all(np.abs(again - e) <= angle_bound + 1e-12)
    assert np.max(np.abs(ROUGH.residuals(solution.R, solution.t, e))) <= FK_TOL_MM


@settings(max_examples=40, deadline=None)
@given(fraction=st.lists(st.floats(-1.0, 1.0, allow_nan=False), min_size=6, max_size=6).map(np.array))
def test_fk_of_ik_across_the_box(fraction):
    # hypothesis draws the box's faces and corners often: there the horns near ±90° and the rods
    # near their reach, where J_pose is worst conditioned (the bound below grows with it)
    R_home, t_home = home(ROUGH)
    R, t = pose_to_rt(np.r_[t_home, 0.0, 0.0, 0.0] + HALF_BOX * fraction)
    e = ROUGH.coordinates(R_home @ R, t)
    assume(np.all(np.isfinite(e)))
    solution = ROUGH.forward_kinematics(e, tol_mm=FK_TOL_MM)
    bound = _pose_bounds(ROUGH, R_home @ R, t, e, np.maximum(solution.residual_mm, 1e-13))[0]
    position_mm, angle_deg = pose_error(R_home @ R, t, solution.R, solution.t)
    assert position_mm <= bound + 1e-12 and np.radians(angle_deg) <= bound + 1e-13


def test_fk_batch_equals_per_sample():
    e = reachable_poses(ROUGH, 8, seed=4)[2]
    batch = ROUGH.forward_kinematics(e.reshape(2, 4, 6))
    assert batch.R.shape == (2, 4, 3, 3) and batch.iterations.shape == (2, 4)
    for k in range(8):
        one = ROUGH.forward_kinematics(e[k])
        np.testing.assert_array_equal(one.R, batch.R.reshape(8, 3, 3)[k])
        np.testing.assert_array_equal(one.t, batch.t.reshape(8, 3)[k])
        assert one.iterations == batch.iterations.reshape(8)[k]


def test_fk_strict_raises_and_lax_reports():
    R, t = home()
    e = np.stack([np.zeros(6), np.zeros(6), np.full(6, np.nan)])
    # rods of 10 mm cannot span the 50 mm between the horn joints' 125 mm circle and the platform's 75 mm
    short = LEGS.perturbed(np.tile(np.r_[np.zeros(7), 10.0 - ROD_MM, 0.0, 0.0, 0.0], 6))
    with pytest.raises(kin.FKError, match=r"pose \(2,\).*non-finite"):
        LEGS.forward_kinematics(e)
    lax = LEGS.forward_kinematics(e, strict=False)
    assert lax.converged.tolist() == [True, True, False] and lax.iterations[2] == 0 and np.isinf(lax.residual_mm[2])
    assert not short.forward_kinematics(e, strict=False).converged.any()
    with pytest.raises(kin.FKError, match=r"pose \(0,\).*residual"):
        short.forward_kinematics(e)
    with pytest.raises(SampleRejected, match="servo forward kinematics"):
        short.solve_fk(e[0], (R, t), "servo")


def test_solve_fk_falls_back_to_the_cold_start():
    R, t, e = reachable_poses(ROUGH, 1, seed=9)
    lost = (R[0], np.full(3, np.nan))  # a start Newton cannot leave
    assert not ROUGH.forward_kinematics(e[0], lost, strict=False).converged
    R_k, t_k = ROUGH.solve_fk(e[0], lost, "drive")
    position_mm, angle_deg = pose_error(R[0], t[0], R_k, t_k)
    assert position_mm < 1e-8 and angle_deg < 1e-8
    R_w, t_w = ROUGH.solve_fk(e[0], (R[0], t[0] + 1.0), "drive")  # the warm start, converged: its pose
    assert pose_error(R[0], t[0], R_w, t_w)[0] < 1e-8


def test_along_follows_the_log_where_the_start_would_jump():
    # From a start below the base, Newton finds the mirrored assembly (platform under the cranks);
    # along a log, every sample after the first follows its predecessor on the real one.
    t_home = home()[1]
    s = np.linspace(0.0, 1.0, 40)[:, None]
    R, t = pose_to_rt(np.r_[t_home, 0.0, 0.0, 0.0] + s * np.r_[10.0, -5.0, 8.0, np.radians([5.0, -4.0, 6.0])])
    e = LEGS.coordinates(R, t)
    below = np.where(np.arange(40)[:, None] == 0, t_home, t_home * [1.0, 1.0, -1.0])
    starts = (np.broadcast_to(np.eye(3), (40, 3, 3)), below)
    cold = LEGS.forward_kinematics(e, starts, tol_mm=FK_TOL_MM)
    assert np.all(cold.t[1:, 2] < 0.0)
    followed = LEGS.forward_kinematics(e, starts, tol_mm=FK_TOL_MM, along=True)
    position_mm, angle_deg = pose_error(R, t, followed.R, followed.t)
    assert position_mm.max() < 1e-9 and angle_deg.max() < 1e-9
    plain = LEGS.forward_kinematics(e, tol_mm=FK_TOL_MM, along=True)  # nothing to follow: the default starts
    np.testing.assert_array_equal(plain.t, LEGS.forward_kinematics(e, tol_mm=FK_TOL_MM).t)


def test_a_reach_margin_refuses_poses_near_a_rods_full_stretch():
    # raise the platform until leg 1's rod is nearly in line with its horn: the exact IK still
    # reaches it, a plan's margin (the crank angle to where the two solutions meet) does not
    wide = dataclasses.replace(LEGS, angle_range=(-0.99 * np.pi, 0.99 * np.pi))  # only the reach bounds it
    R, t = home(wide)
    lifts = np.linspace(0.0, 60.0, 601)
    e = wide.coordinates(np.broadcast_to(R, (len(lifts), 3, 3)), t + lifts[:, None] * [0.0, 0.0, 1.0])
    last = np.flatnonzero(np.all(np.isfinite(e), axis=1))[-1]
    assert 0 < last < len(lifts) - 1  # the sweep leaves the reach
    edge = t + lifts[last] * np.array([0.0, 0.0, 1.0])
    margined = dataclasses.replace(wide, reach_margin=np.radians(4.0))
    assert np.all(np.isfinite(wide.coordinates(R, edge)))
    assert np.isnan(margined.coordinates(R, edge)).any()
    np.testing.assert_array_equal(margined.coordinates(R, t), wide.coordinates(R, t))  # home is far from it


def test_ekf_holds_a_servo_pose_within_five_sigma_of_its_angles():
    """The inputs' tolerance of one static pose (where the robust filter's step candidates begin) is in
    the logged coordinates' own unit: a servo's angles [rad], not the strokes' σ [mm]."""
    from stewart_calib.config import EstimatorConfig
    from stewart_calib.estimators.ekf import LegEKF
    from stewart_calib.io.platform_file import load_platform
    from stewart_calib.resources import CONFIGS

    config = EstimatorConfig()
    ekf = LegEKF(load_platform(CONFIGS / "platforms" / "servo-hexapod.toml"), config)
    assert ekf.robust._pose_tolerance == pytest.approx(5.0 * ekf.drive.coordinate_sigma(config.noise), rel=1e-12)
    assert ekf.drive.coordinate_sigma(config.noise) != config.noise.stroke_sigma_mm
