"""Identifiability report: null spaces of constructed degenerate pose sets, weakest directions,
and the Cramér–Rao prediction against the Monte-Carlo spread of least-squares estimates."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from stewart_calib.analysis.identifiability import (
    CONDITION_POOR,
    conditioning_summary,
    identifiability_report,
    name_direction,
    observability_indices,
    residual_covariance,
    scaled_paper_jacobian,
    warning_line,
    whitened_leg_jacobian,
)
from stewart_calib.cli import main as cli_main
from stewart_calib.config import NoiseConfig
from stewart_calib.io import write_log
from stewart_calib.model import kinematics as kin
from stewart_calib.model.platform import PARAMETER_NAMES
from tests.synthetic import make_log, nim_stewart, numpy_legs, random_error, random_poses

NOISE = NoiseConfig()
INDEX = {name: k for k, name in enumerate(PARAMETER_NAMES)}


def unit(*terms: tuple[str, float]) -> np.ndarray:
    v = np.zeros(42)
    for name, coef in terms:
        v[INDEX[name]] = coef
    return v / np.linalg.norm(v)


def assert_same_span(basis: np.ndarray, expected: np.ndarray) -> None:
    """Both ``(42, k)`` span one subspace: equal dimension and every expected vector inside."""
    assert basis.shape[1] == expected.shape[1]
    q, _ = np.linalg.qr(basis)
    inside = np.linalg.norm(q.T @ (expected / np.linalg.norm(expected, axis=0)), axis=0)
    np.testing.assert_allclose(inside, 1.0, atol=1e-8)  # round-off of the SVD, far below any real leakage


@pytest.fixture(scope="module")
def platform():
    return nim_stewart()


def test_translations_only_leave_the_18_dim_null_space_of_d_minus_j(platform):
    # With R = I for every pose, moving d_i and j_i by the same vector changes no leg: 3 per leg.
    rng = np.random.default_rng(1)
    poses = platform.workspace.home + np.c_[rng.uniform(-200, 200, (30, 3)), np.zeros((30, 3))]
    report = identifiability_report(platform, poses, NOISE)

    assert report.rank == 24 and report.null_space_dimension == 18
    assert report.verdict == "rank-deficient" and report.condition_number == np.inf
    A = whitened_leg_jacobian(platform, poses, NOISE).reshape(-1, 42)
    assert np.max(np.abs(A @ report.null_space)) < 1e-9 * report.singular_values[0]
    expected = np.column_stack(
        [unit((f"j{leg}{axis}", 1.0), (f"d{leg}{axis}", 1.0)) for leg in range(1, 7) for axis in "xyz"]
    )
    assert_same_span(report.null_space, expected)
    # The readable basis is exactly those pairs, and every j, d is reported as not identified.
    assert sorted(report.null_space_names()) == sorted(name_direction(v) for v in expected.T)
    assert np.all(np.isinf(report.predicted_stddev_mm[[INDEX[n] for n in PARAMETER_NAMES if n[0] in "jd"]]))
    assert np.all(np.isfinite(report.predicted_stddev_mm[[INDEX[f"l{leg}"] for leg in range(1, 7)]]))
    assert "18 unidentified directions" in warning_line(report)
    assert report.observability["O3"] == 0.0


def fixed_leg1_direction_poses(platform, n: int, rng, jitter_rad: float = 0.0) -> np.ndarray:
    """Rich rotations, but leg 1 always points along its home direction (± a small tilt)."""
    legs = platform.drive
    home_R, home_t = kin.pose_to_rt(platform.workspace.home)
    n_home = kin.leg_unit_vectors(legs, home_R, home_t)[0]
    poses = np.empty((n, 6))
    for k in range(n):
        rpy = rng.uniform(-0.3, 0.3, 3)
        R = kin.rpy_to_rotation(rpy)
        direction = kin.so3_exp(rng.normal(0.0, jitter_rad, 3)) @ n_home if jitter_rad else n_home
        t = legs.base_joints[0] + rng.uniform(950, 1150) * direction - R @ legs.platform_joints[0]
        poses[k] = np.r_[t, rpy]
    return poses


def leg1_along_axis_directions(platform) -> np.ndarray:
    """With leg 1's unit vector n fixed, r_1 sees j_1 only through nᵀj_1 − l_1: three directions."""
    home_R, home_t = kin.pose_to_rt(platform.workspace.home)
    n = kin.leg_unit_vectors(platform.drive, home_R, home_t)[0]
    perp = np.linalg.svd(n[None, :])[2][1:]  # two unit vectors ⊥ n
    vectors = np.zeros((42, 3))
    vectors[0:3, 0], vectors[0:3, 1] = perp
    vectors[0:3, 2], vectors[INDEX["l1"], 2] = n, -1.0
    return vectors


def test_a_fixed_leg_direction_leaves_exactly_its_joint_and_length_unidentified(platform):
    poses = fixed_leg1_direction_poses(platform, 40, np.random.default_rng(2))
    report = identifiability_report(platform, poses, NOISE)
    assert report.rank == 39
    assert_same_span(report.null_space, leg1_along_axis_directions(platform))
    assert np.max(np.abs(report.null_space[7:])) < 1e-8  # only leg 1's parameters (columns 0–6)


def test_a_nearly_fixed_leg_direction_is_named_as_the_weakest_direction(platform):
    # A 0.3° tilt makes those three directions weak instead of null: full rank, poorly
    # conditioned, and the weakest direction lies in their span (nothing else is that weak).
    poses = fixed_leg1_direction_poses(platform, 40, np.random.default_rng(3), jitter_rad=np.radians(0.3))
    report = identifiability_report(platform, poses, NOISE)
    assert report.rank == 42 and report.verdict == "poorly conditioned"
    assert report.condition_number > CONDITION_POOR
    q, _ = np.linalg.qr(leg1_along_axis_directions(platform))
    assert np.linalg.norm(q.T @ report.weakest[0][1]) > 0.999
    assert "j1" in warning_line(report) and conditioning_summary(report)["verdict"] == "poorly conditioned"


def test_random_rich_poses_are_identifiable_and_the_report_serialises(platform):
    report = identifiability_report(platform, random_poses(platform, 30, np.random.default_rng(4)), NOISE)
    assert report.verdict == "identifiable" and warning_line(report) is None
    doc = json.loads(json.dumps(report.to_dict(), allow_nan=False))
    assert doc["leg_length_form"]["rank"] == 42
    assert doc["leg_length_form"]["condition_number"] == pytest.approx(report.condition_number)
    summary = conditioning_summary(report)
    assert summary["rank"] == 42 and summary["null_space"] == [] and len(summary["weakest_directions"]) == 3
    assert "Cramér–Rao" in report.format_text()


def test_leaving_out_the_paper_form_leaves_the_leg_form_as_it_was(platform):
    poses = random_poses(platform, 12, np.random.default_rng(5))
    both = identifiability_report(platform, poses, NOISE)
    leg_only = identifiability_report(platform, poses, NOISE, paper_form=False)
    assert conditioning_summary(leg_only) == conditioning_summary(both)
    np.testing.assert_array_equal(leg_only.singular_values, both.singular_values)
    np.testing.assert_array_equal(leg_only.predicted_stddev_mm, both.predicted_stddev_mm)
    assert np.all(np.isnan(leg_only.paper_singular_values)) and np.isnan(leg_only.paper_condition_number)
    assert np.all(np.isfinite(both.paper_singular_values))


def test_observability_indices_on_known_singular_values():
    indices = observability_indices(np.array([4.0, 2.0, 1.0]), n_rows=4)
    assert indices["O1"] == pytest.approx(2.0 / 2.0)
    assert indices["O2"] == pytest.approx(0.25)
    assert indices["O3"] == pytest.approx(1.0)
    assert indices["O4"] == pytest.approx(0.25)
    assert indices["O5"] == pytest.approx(1.0 / 1.75)


def test_name_direction_lists_large_components_largest_first():
    v = unit(("j3z", 0.62), ("l3", -0.68), ("d1x", 0.05))
    assert name_direction(v) == "−0.74·l3 + 0.67·j3z"


def gauss_newton_leg_model(platform, log, noise, iterations: int = 4) -> np.ndarray:
    """Weighted least squares on r_i = ‖t + R d_i − j_i‖ − (l_i + q_i), poses from tracker FK."""
    fk = kin.forward_kinematics(platform.tracker, log.readings, kin.pose_to_rt(log.desired_poses))
    params = platform.drive.as_vector()
    for _ in range(iterations):
        drive = platform.drive.from_params(params)
        _, J_M = kin.leg_residual_jacobians(drive, fk.R, fk.t)
        chol = np.linalg.cholesky(residual_covariance(replace(platform, drive=drive), fk.R, fk.t, noise))
        A = np.linalg.solve(chol, J_M).reshape(-1, 42)
        b = np.linalg.solve(chol, kin.leg_residuals(drive, fk.R, fk.t, log.strokes)[..., None]).reshape(-1)
        params = params - np.linalg.lstsq(A, b, rcond=None)[0]
    return params


def test_predicted_stddev_matches_monte_carlo_spread(platform):
    rng = np.random.default_rng(5)
    poses = random_poses(platform, 40, rng)
    truth = random_error(rng, 1.0)
    predicted = identifiability_report(platform, poses, NOISE).predicted_stddev_mm
    estimates = np.array(
        [
            gauss_newton_leg_model(
                platform,
                make_log(platform, truth, poses, rng, NOISE.reading_sigma_mm, NOISE.stroke_sigma_mm)[0],
                NOISE,
            )
            for _ in range(60)
        ]
    )
    spread = estimates.std(axis=0, ddof=1)
    ratio = spread / predicted
    # 60 runs: a sample std has ~9 % relative error per parameter, so the mean of the 42
    # ratios is well inside ±20 %; single parameters get ±45 % (≈ 5 of their own σ).
    assert np.mean(ratio) == pytest.approx(1.0, abs=0.2)
    assert np.all(np.abs(ratio - 1.0) < 0.45)
    # The estimates are unbiased around the truth (5 σ of the mean of 60).
    bias = estimates.mean(axis=0) - (platform.drive.as_vector() + truth)
    assert np.all(np.abs(bias) < 5 * predicted / np.sqrt(60))


def test_cli_reads_a_log_and_writes_json(platform, tmp_path, capsys):
    rng = np.random.default_rng(6)
    poses = random_poses(platform, 25, rng)
    log, _ = make_log(platform, random_error(rng, 0.5), poses, rng, NOISE.reading_sigma_mm, NOISE.stroke_sigma_mm)
    write_log(tmp_path / "log.csv", log)
    out = tmp_path / "id.json"
    code = cli_main(
        ["identifiability", "--platform", str(platform.source), "--log", str(tmp_path / "log.csv"), "--json", str(out)]
    )
    assert code == 0
    printed = capsys.readouterr().out
    assert "verdict: identifiable" in printed
    # the lines after the report, which judge it, name the command (as plan's and calibrate's do)
    (line,) = [line for line in printed.splitlines() if "predicted closed-loop pose error after calibration" in line]
    assert line.startswith("stewart-calib identifiability: predicted closed-loop pose error after calibration ("), line
    doc = json.loads(out.read_text())
    # Tracker FK poses differ from the true ones by µm: the report is that of the true poses.
    expected = identifiability_report(platform, poses, NOISE)
    np.testing.assert_allclose(doc["predicted_stddev_mm"], expected.predicted_stddev_mm, rtol=1e-4)


def test_cli_refuses_a_pose_list_without_pose_columns(platform, tmp_path, capsys):
    path = tmp_path / "poses.csv"
    path.write_text("t_s,x_mm,y_mm\n0,1,2\n")
    assert cli_main(["identifiability", "--platform", str(platform.source), "--poses", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and str(path) in err and "z_mm" in err


def test_any_leg_model_gets_the_compiled_rows_and_paper_jacobian():
    # whitened rows and J_p through the drive model's Jacobians (any leg model) equal the prismatic
    # kernels' to round-off: J_p from ∂ξ/∂M by δh = R v, δθ = E⁻¹ R ω
    platform = nim_stewart()
    poses = random_poses(platform, 20, np.random.default_rng(3))
    noise = NoiseConfig()
    rows, J_p = whitened_leg_jacobian(platform, poses, noise), scaled_paper_jacobian(platform, poses)
    generic = replace(platform, drive=numpy_legs(platform.drive))
    pairs = ((whitened_leg_jacobian(generic, poses, noise), rows), (scaled_paper_jacobian(generic, poses), J_p))
    for got, want in pairs:
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-14 * np.abs(want).max())


def test_another_leg_models_report_is_the_compiled_ones():
    platform = nim_stewart()
    poses = random_poses(platform, 12, np.random.default_rng(5))
    generic = replace(platform, drive=numpy_legs(platform.drive))
    report, compiled = (
        identifiability_report(generic, poses, NoiseConfig()),
        identifiability_report(platform, poses, NoiseConfig()),
    )
    assert report.parameters_per_leg == 7 and not report.parameter_degrees.any()
    np.testing.assert_allclose(report.predicted_stddev_mm, compiled.predicted_stddev_mm, rtol=1e-9)
    assert report.format_text().splitlines()[0] == compiled.format_text().splitlines()[0]
