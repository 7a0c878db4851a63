"""The predicted closed-loop error, and planning for outside instruments: against first principles,
brute force and the batch fit's own Jacobian, on geometries other than the shipped ones."""

from __future__ import annotations

import itertools
import json
import re
from dataclasses import replace

import numpy as np
import pytest

from benchmarks.plan_poses import wide_hexapod
from stewart_calib import io
from stewart_calib.analysis import accuracy
from stewart_calib.cli import main as cli_main
from stewart_calib.errors import CalibError
from stewart_calib.estimators import batch
from stewart_calib.instruments import gauge, outside_model, registration
from stewart_calib.instruments.points import visible_targets
from stewart_calib.io import read_pose_list
from stewart_calib.io.platform_file import parse_platform, platform_to_toml
from stewart_calib.model import kinematics as kin
from stewart_calib.model import rotations
from stewart_calib.model.drive import drive_model
from stewart_calib.model.platform import Instrument
from stewart_calib.workflows import planning


def _toml_doc(platform):
    import tomllib

    return tomllib.loads(platform_to_toml(platform))


THREE_SMRS = np.array([[100.0, 0.0, 20.0], [-50.0, 87.0, 20.0], [-50.0, -87.0, 35.0]])


@pytest.fixture(scope="module")
def wide_points():
    return wide_hexapod(
        Instrument("points", np.r_[900.0, 400.0, 1200.0, 0.0, 0.0, 0.0], np.zeros(6), THREE_SMRS, 0.015)
    )


@pytest.fixture(scope="module")
def wide_pose():
    return wide_hexapod(Instrument("pose", np.zeros(6), np.zeros(6), np.zeros((0, 3)), 0.2, np.radians(0.05)))


def test_closed_loop_jacobian_is_the_pose_change_of_ik_then_fk(wide_points):
    """FK(true drive, IK(estimate)) against the desired pose moves as −D·(estimate − truth)."""
    rng = np.random.default_rng(1)
    poses = accuracy.reachable_poses(wide_points, 5, rng)
    D = accuracy.closed_loop_jacobian(wide_points, poses)
    e = np.r_[rng.normal(0.0, 1.0, 42), rng.normal(0.0, 0.01, 6)] * 1e-4
    R, t = kin.pose_to_rt(poses)
    estimate, scale = wide_points.drive.perturbed(e[:42]), wide_points.stroke_scale + e[42:]
    strokes = kin.inverse_kinematics(estimate, R, t) / (1.0 + scale)  # what the controller commands
    reached = kin.forward_kinematics(wide_points.drive, strokes * (1.0 + wide_points.stroke_scale), guess=(R, t))
    omega = rotations.so3_log(np.swapaxes(R, -1, -2) @ reached.R)
    v = np.einsum("nji,nj->ni", R, reached.t - t)  # body tangent [ω, v]
    np.testing.assert_allclose(np.c_[omega, v], -D @ e, rtol=1e-3, atol=1e-9)


def test_expected_norm_of_an_isotropic_error_is_the_chi_mean():
    sigma = 0.3
    expected = sigma * 2.0 * np.sqrt(2.0 / np.pi)  # mean of a χ with 3 degrees of freedom, times σ
    value = accuracy._expected_norms(sigma**2 * np.eye(3)[None])[0]
    assert value == pytest.approx(expected, rel=0.05)  # 512 fixed draws: ~3 % (module docstring)


@pytest.mark.parametrize("n", [48, 54, 60])
def test_the_band_of_an_isotropic_error_holds_the_chi_quantiles(n):
    """One pose whose position error is the first three of ``n`` unknowns, each of σ 2 mm: its norm is σ
    times a χ with 3 degrees of freedom, so the band's ends sit at its 5 % and 95 %, within 0.5 % in
    probability (three standard errors of a quantile of 20 000 draws). The same draws serve every
    covariance, so their error is every band's alike, not averaged out over robots (1000 draws: 0.057 and
    0.9625 here)."""
    from scipy.stats import chi

    D = np.zeros((1, 3, n))
    D[0, :, :3] = np.eye(3)
    low, high = accuracy._position_band(D, 4.0 * np.eye(n))
    assert chi.cdf(low / 2.0, 3) == pytest.approx(0.05, abs=0.005)
    assert chi.cdf(high / 2.0, 3) == pytest.approx(0.95, abs=0.005)


def test_an_error_off_its_mean_has_the_noncentral_chi_mean_and_quantiles():
    """An error ``N(μ, σ² I)`` (an online method's estimate off the log's optimum by a known step): its norm
    is σ times a noncentral χ with 3 degrees of freedom and ``ν = ‖μ‖/σ``, whose mean is
    ``σ (√(2/π) e^{−ν²/2} + (ν + 1/ν) erf(ν/√2))`` and whose square's quantiles are the noncentral χ²'s. The
    mean within 5 % (512 draws), the band's ends within 0.5 % in probability (20 000 draws). Before: no mean
    (a zero-mean error's 3.19 mm and band 1.17–5.59 mm where ν = 2 gives 4.99 mm, 2.18–8.00 mm)."""
    from scipy.special import erf
    from scipy.stats import ncx2

    sigma, mean = 2.0, np.array([3.0, 0.0, -np.sqrt(7.0)])  # ‖μ‖ = 4 mm, ν = 2
    nu = np.linalg.norm(mean) / sigma
    expected = sigma * (np.sqrt(2.0 / np.pi) * np.exp(-(nu**2) / 2.0) + (nu + 1.0 / nu) * erf(nu / np.sqrt(2.0)))
    value = accuracy._expected_norms(sigma**2 * np.eye(3)[None], mean[None])[0]
    assert value == pytest.approx(expected, rel=0.05)
    n = 48
    D = np.zeros((1, 3, n))
    D[0, :, :3] = np.eye(3)
    low, high = accuracy._position_band(D, sigma**2 * np.eye(n), np.r_[mean, np.zeros(n - 3)])
    assert ncx2.cdf((low / sigma) ** 2, 3, nu**2) == pytest.approx(0.05, abs=0.005)
    assert ncx2.cdf((high / sigma) ** 2, 3, nu**2) == pytest.approx(0.95, abs=0.005)


def test_prediction_matches_the_spread_of_simulated_estimates(wide_points):
    """Draws of the estimate from its covariance, driven through IK/FK: the mean position error
    over the poses equals the prediction (the linearisation holds at micrometre errors)."""
    rng = np.random.default_rng(2)
    A = np.r_[[0.01] * 42, [1e-5] * 6][:, None] * rng.normal(0.0, 1.0, (48, 48))
    covariance = A @ A.T
    poses = accuracy.reachable_poses(wide_points, 40, rng)
    predicted = accuracy.predicted_error(wide_points, covariance, poses)
    R, t = kin.pose_to_rt(poses)
    errors = []
    for e in rng.multivariate_normal(np.zeros(48), covariance, 300):
        strokes = kin.inverse_kinematics(wide_points.drive.perturbed(e[:42]), R, t) / (1.0 + e[42:])
        reached = kin.forward_kinematics(wide_points.drive, strokes, guess=(R, t))
        errors.append(kin.pose_error(R, t, reached.R, reached.t)[0].mean())
    assert predicted.position_mm == pytest.approx(np.mean(errors), rel=0.1)
    assert not predicted.workspace and predicted.n_poses == 40
    # one calibration is one draw: 90 % of them within the band (300 draws: ±1.7 %, here ±4σ)
    low, high = predicted.position_band_mm
    assert 0.83 <= np.mean((low <= np.array(errors)) & (np.array(errors) <= high)) <= 0.97


@pytest.mark.parametrize("kind", ["points", "pose"])
def test_information_rows_are_the_batch_fits_jacobian(kind, wide_points, wide_pose):
    platform = wide_points if kind == "points" else wide_pose
    poses = accuracy.reachable_poses(platform, 12, np.random.default_rng(3))
    model = outside_model(platform)
    rows, lift = model.information_rows(poses)
    R, t = kin.pose_to_rt(poses)
    readings = model.predicted_readings(model.nominal_unknowns(), R, t)
    drive = drive_model(platform).identifying()
    problem = batch.BatchProblem(
        drive, drive.inputs(drive.inverse_kinematics(R, t)), readings, model, np.arange(len(R), dtype=float)
    )
    unknowns = model.nominal_unknowns()
    covariance = batch.cramer_rao(problem, np.zeros(drive.size), unknowns)
    A = rows.reshape(-1, rows.shape[-1])
    tolerance = 1e-7 * np.abs(covariance).max()  # the inverse's round-off at its condition number
    np.testing.assert_allclose(lift @ np.linalg.inv(A.T @ A) @ lift.T, covariance, rtol=1e-6, atol=tolerance)
    np.testing.assert_allclose(planning.design_covariance(platform, poses), covariance, rtol=1e-6, atol=tolerance)


def test_information_rows_of_a_log_with_payloads_are_the_batch_fits_jacobian(wide_pose):
    """An elastic robot measured without and with a payload (spec §10): the rows at the log's payloads
    are the batch fit's, whose compliance the payload's forces tell from the leg lengths — identifiability
    --log took every pose under the platform's weight alone, a compliance σ several times the fit's."""
    from stewart_calib.model.platform import Elastic
    from stewart_calib.samples import LOAD_KG

    platform = replace(wide_pose, elastic=Elastic(20.0, np.array([0.0, 0.0, -30.0]), np.array([10.0, 0.0, 40.0])))
    poses = np.tile(accuracy.reachable_poses(platform, 12, np.random.default_rng(3)), (2, 1))
    channels = {LOAD_KG: np.repeat([0.0, 30.0], 12)}
    model = outside_model(platform)
    R, t = kin.pose_to_rt(poses)
    drive = drive_model(platform).identifying()
    inputs = drive.inputs(drive.inverse_kinematics(R, t, channels=channels), channels, R, t)
    readings = model.predicted_readings(model.nominal_unknowns(), R, t)
    problem = batch.BatchProblem(drive, inputs, readings, model, np.arange(len(R), dtype=float), channels)
    covariance = batch.cramer_rao(problem, np.zeros(drive.size), model.nominal_unknowns())
    tolerance = 1e-7 * np.abs(covariance).max()
    designed = planning.design_covariance(platform, poses, channels=channels)
    np.testing.assert_allclose(designed, covariance, rtol=1e-6, atol=tolerance)
    compliance = slice(48, 54)
    weight_only = planning.design_covariance(platform, poses)
    assert np.all(np.diag(weight_only)[compliance] > 4.0 * np.diag(designed)[compliance])


def test_information_rows_of_a_compliant_robot_are_the_batch_fits_settled_jacobian(wide_pose):
    """At a nominal compliance the leg forces move with the pose and the joints, and the batch fit's rows
    carry that (``settled_pose_jacobian``): the weight's deflection ``c f(ξ, M)`` tells some of the
    weak leg-length directions apart. The bound plan and identifiability state is the fit's only with
    those rows (without them, here, σ off by up to 2.6×; the hobby hexapod's three reflectors at 100 mm/kN
    and its 2 kg payload: δM 1.09× the fit's)."""
    from stewart_calib.model.platform import Elastic
    from stewart_calib.samples import LOAD_KG

    elastic = Elastic(20.0, np.array([0.0, 0.0, -30.0]), np.array([10.0, 0.0, 40.0]), np.full(6, 30.0))
    platform = replace(wide_pose, elastic=elastic)
    poses = np.tile(accuracy.reachable_poses(platform, 12, np.random.default_rng(3)), (2, 1))
    channels = {LOAD_KG: np.repeat([0.0, 30.0], 12)}
    model = outside_model(platform)
    drive = drive_model(platform).identifying()
    fk, inputs = drive.settled_kinematics(drive.inverse_kinematics(*kin.pose_to_rt(poses), channels=channels), channels)
    readings = model.predicted_readings(model.nominal_unknowns(), fk.R, fk.t)
    problem = batch.BatchProblem(drive, inputs, readings, model, np.arange(len(poses), dtype=float), channels)
    covariance = batch.cramer_rao(problem, np.zeros(drive.size), model.nominal_unknowns())
    designed = planning.design_covariance(platform, poses, channels=channels)
    sd = np.sqrt(np.diag(covariance))
    np.testing.assert_allclose(np.sqrt(np.diag(designed)), sd, rtol=1e-4, atol=1e-9 * sd.max())


def test_exchanges_find_the_brute_force_optimum_of_small_designs():
    """Every 5 of 12 candidate blocks (3 rows, 5 unknowns), by I = −tr(W F⁻¹), for 20 random
    problems: DETMAX then Fedorov's swaps is a local search, so it may miss the exhaustive best;
    measured over 40 problems: 39 exact, the other 2 % off."""
    ratios = []
    for seed in range(20):
        rng = np.random.default_rng(seed)
        blocks = rng.normal(0.0, 1.0, (12, 3, 5))
        G = rng.normal(0.0, 1.0, (5, 5))
        weight = G @ G.T

        def variance(index, blocks=blocks, weight=weight):
            F = np.einsum("kri,krj->ij", blocks[list(index)], blocks[list(index)])
            return np.trace(weight @ np.linalg.inv(F))

        best = min(itertools.combinations(range(12), 5), key=variance)
        ratios.append(
            variance(planning.select_poses(blocks, 5, "I", weight=weight, criterion_greedy=True)) / variance(best)
        )
    assert np.mean(np.isclose(ratios, 1.0, rtol=1e-9)) >= 0.9
    assert max(ratios) < 1.03


def test_planned_poses_beat_random_poses_for_an_outside_instrument(wide_points):
    planned = planning.plan_poses(wide_points, 40, None, np.random.default_rng(0), 800)
    random = accuracy.reachable_poses(wide_points, 40, np.random.default_rng(1))
    error = lambda poses: accuracy.predicted_error(wide_points, planning.design_covariance(wide_points, poses))  # noqa: E731
    assert error(planned).position_mm < 0.7 * error(random).position_mm


def test_the_closed_loop_criterion_is_not_the_a_criterion_where_the_frame_is_unknown(wide_pose):
    """A weighs the 42 parameters alike, I by what they do to the pose the robot reaches: with
    the frame unknown they pick different poses, and I's leave less closed-loop error."""
    rng_seed = 4
    by_i = planning.plan_poses(wide_pose, 30, "I", np.random.default_rng(rng_seed), 600)
    by_a = planning.plan_poses(wide_pose, 30, "A", np.random.default_rng(rng_seed), 600)
    assert {tuple(p) for p in by_i} != {tuple(p) for p in by_a}
    error = lambda poses: accuracy.predicted_error(wide_pose, planning.design_covariance(wide_pose, poses))  # noqa: E731
    assert error(by_i).position_mm < error(by_a).position_mm


def test_extreme_poses_lie_in_the_box_and_the_stroke_range(wide_points):
    poses = planning.extreme_poses(wide_points)
    ws = wide_points.workspace
    assert len(poses) == 3**6
    assert np.all(np.abs(poses[:, :3] - ws.home[:3]) <= ws.translation_limit + 1e-9)
    assert np.all(np.abs(poses[:, 3:] - ws.home[3:]) <= ws.rotation_limit + 1e-12)
    assert np.all(accuracy.within_ranges(wide_points, poses))
    # a corner outside the strokes is pulled back to the range's edge, not to home
    strokes = kin.inverse_kinematics(wide_points.drive, *kin.pose_to_rt(poses))
    pulled = ~np.all(np.isclose(np.abs(poses - ws.home), np.r_[[ws.translation_limit] * 3, [ws.rotation_limit] * 3])
                     | np.isclose(poses, ws.home), axis=1)  # fmt: skip
    assert pulled.any()
    edge = np.min(np.abs(np.c_[strokes - wide_points.stroke_range[0], wide_points.stroke_range[1] - strokes]), axis=1)
    assert np.all(edge[pulled] < 1e-3)


def test_a_target_outside_its_cone_gives_no_information(wide_points):
    below = replace(wide_points.instrument, frame=np.r_[0.0, 0.0, -500.0, 0.0, 0.0, 0.0], visibility_cone_deg=60.0)
    above = replace(below, frame=np.r_[0.0, 0.0, 2000.0, 0.0, 0.0, 0.0], target_axes=np.tile([0.0, 0.0, 1.0], (3, 1)))
    home = wide_points.workspace.home
    R, t = kin.pose_to_rt(home[None])
    assert not visible_targets(below, R, t).any()
    assert visible_targets(above, R, t).all()
    rows, _ = outside_model(replace(wide_points, instrument=below)).information_rows(home[None])
    assert not rows.any()
    # tilted 40° about x, a target whose axis leans 30° the other way leaves a 60° cone
    tilted = replace(above, target_axes=np.array([[0.0, 0.0, 1.0], [0.0, 0.5, 0.866], [0.0, -0.5, 0.866]]))
    R, t = kin.pose_to_rt(np.r_[home[:3], np.radians(40.0), 0.0, 0.0][None])
    seen = visible_targets(tilted, R, t)[0]
    assert seen.tolist() == [True, True, False]


def test_the_visibility_keys_read_back_and_are_checked(wide_points, tmp_path):
    instrument = replace(wide_points.instrument, visibility_cone_deg=45.0, target_axes=np.tile([0.0, 0.2, 1.0], (3, 1)))
    again = parse_platform(_toml_doc(replace(wide_points, instrument=instrument)), "p.toml").instrument
    assert again.visibility_cone_deg == 45.0
    np.testing.assert_array_equal(again.target_axes, instrument.target_axes)
    doc = _toml_doc(replace(wide_points, instrument=instrument))
    for key, value, words in (
        ("visibility_cone_deg", 0.0, r"half-angle in \(0, 180\]"),
        ("target_axes", [[0.0, 0.0, 0.0]] * 3, "nonzero"),
        ("target_axes", [[0.0, 0.0, 1.0]] * 2, "shape"),
    ):
        bad = {**doc, "instrument": {**doc["instrument"], key: value}}
        with pytest.raises(CalibError, match=rf"instrument\.{key}.*{words}"):
            parse_platform(bad, "p.toml")
    axes_alone = {**doc, "instrument": {k: v for k, v in doc["instrument"].items() if k != "visibility_cone_deg"}}
    with pytest.raises(CalibError, match=r"instrument\.target_axes"):
        parse_platform(axes_alone, "p.toml")


def test_planned_poses_keep_a_margin_from_the_stroke_limits(wide_points):
    """The true robot needs other strokes for the same pose: plan stays 2 prior σ inside the range."""
    noise = planning.NoiseConfig(prior_sigma_mm=4.0)
    poses = planning.plan_poses(wide_points, 20, None, np.random.default_rng(4), 300, noise)
    R, t = kin.pose_to_rt(poses)
    strokes = drive_model(wide_points).inverse_kinematics(R, t)
    low, high = wide_points.stroke_range
    assert strokes.min() >= low + 8.0 - 1e-6 and strokes.max() <= high - 8.0 + 1e-6
    # the extremes it picks sit at the narrowed limits, not inside them
    assert min(strokes.min() - low, high - strokes.max()) < 8.5


def test_o1_is_refused_for_an_outside_instrument(wide_pose):
    with pytest.raises(CalibError, match="O1 is of the paper's J_p form"):
        planning.plan_poses(wide_pose, 10, "O1", np.random.default_rng(0), 100)


def test_cli_plans_for_a_motion_capture_platform(tmp_path, capsys, wide_pose):
    platform_file = tmp_path / "wide.toml"
    platform_file.write_text(platform_to_toml(wide_pose))
    out = tmp_path / "poses.csv"
    assert (
        cli_main(["plan", "--platform", str(platform_file), "--n", "20", "--out", str(out), "--candidates", "200"]) == 0
    )
    printed = capsys.readouterr().out
    assert "planned 20 poses (I from 200 candidates and 729 box extremes" in printed
    # the noise the prediction takes, named: calibrate re-estimates it, plan cannot
    sigma = (
        f"σ {wide_pose.instrument.position_sigma_mm:g} mm / {np.degrees(wide_pose.instrument.orientation_sigma_rad):g}°"
    )
    head = f"predicted closed-loop pose error after calibration (for the instrument's {sigma}, the platform file's "
    assert head + "[instrument]): expected mean over 200 workspace poses" in printed
    assert "(90% of such calibrations in each band): absolute place in {J}" in printed
    assert read_pose_list(out).shape == (20, 6)


def small_workspace_experiment() -> str:
    """tests/test_instrument_files.py's motion-capture experiment with 60 calibration poses within
    ±20 mm / ±8° of the hobby hexapod's home (issue 27's case)."""
    from tests.test_instrument_files import EXPERIMENT

    return EXPERIMENT.replace("calibration = 40", "calibration = 60").replace(
        "workspace_fraction = 0.5", "workspace_fraction = 0.67"
    )


def test_a_small_workspace_calibration_warns_in_one_line_and_validate_says_what_it_cannot_see(tmp_path, capsys):
    """Issue 27's case: 60 motion-capture poses within ±20 mm / ±8° of the hobby hexapod. The frame's
    height trades against the leg lengths: calibrate warns in one line with the predicted error,
    the result and the report hold it, identifiability calls the poses poorly conditioned, and
    validate (through the refitted frame, near the noise floor) says it cannot see that error."""
    from tests.test_instrument_files import _simulated_fit_and_held_out

    platform_path = _simulated_fit_and_held_out(tmp_path, small_workspace_experiment())
    out, report = tmp_path / "r.json", tmp_path / "report"
    capsys.readouterr()
    args = ["--platform", str(platform_path), "--log", str(tmp_path / "fit.csv")]
    assert cli_main(["calibrate", *args, "--method", "ls", "--out", str(out), "--report", str(report)]) == 0
    err = capsys.readouterr().err.splitlines()
    warnings = [line for line in err if "predicted closed-loop" in line]
    # the same verdict on the poses' conditioning as identifiability's below, then the prediction
    assert len(warnings) == 1 and warnings[0].startswith("stewart-calib calibrate: warning: poorly conditioned")
    assert "; predicted closed-loop pose error after calibration: expected mean over 200 workspace poses" in warnings[0]
    predicted = json.loads(out.read_text())["predicted_closed_loop"]
    assert predicted["position_mm"] > accuracy.NOISE_FLOOR_FACTOR * predicted["noise_floor_mm"]
    assert predicted["warning"].removeprefix("warning: ") in warnings[0]
    assert f"{predicted['position_mm']:.3g} mm" in warnings[0]
    assert "Predicted closed-loop error" in (report / "index.html").read_text()

    assert cli_main(["identifiability", *args]) == 0
    assert "poorly conditioned" in capsys.readouterr().out.splitlines()[0]

    held = ["--log", str(tmp_path / "held.csv"), "--out", str(tmp_path / "V.csv")]
    assert cli_main(["validate", "--platform", str(platform_path), "--result", str(out), *held]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 3 and "cannot see the robot's closed-loop (absolute) pose error" in lines[1]
    assert lines[2].startswith("stewart-calib validate: verdict: ")
    # through the calibration's frame and target(s), not fitted again: not "after registration"
    measured = "validate measured the error as the instrument sees it through the calibration's frame and target(s)"
    assert measured in lines[1] and measured in lines[2]
    assert (
        "sees it after registration" not in lines[1]
        and "validate measured the error as the instrument sees it after" not in lines[2]
    )
    # the prediction printed once, in the verdict, in the words and order of calibrate's prediction line
    prediction = accuracy.PredictedError.from_dict(predicted)
    assert lines[1].endswith(f"the verdict's absolute place in {{J}}, limited by {predicted['absolute_limited_by']}")
    assert prediction.expected_words() in lines[2] and prediction.expected_words() in warnings[0]
    assert all(line.count("motion from home") == (i == 2) for i, line in enumerate(lines)), lines
    low, high = predicted["position_band_mm"]
    assert low < predicted["position_mm"] < high
    assert f"absolute place in {{J}} {predicted['position_mm']:.3g} mm / " in lines[2]
    # with the frame fitted again: the registered error measured, beside the registered prediction
    assert (
        cli_main(["validate", "--platform", str(platform_path), "--result", str(out), *held, "--register-instrument"])
        == 0
    )
    verdict = capsys.readouterr().out.strip().splitlines()[-1]
    registered = predicted["registered_position_mm"]
    r_low, r_high = predicted["registered_position_band_mm"]
    assert r_low < registered < predicted["motion_position_mm"]
    assert f"as the instrument sees it after registration {registered:.3g} mm" in verdict
    assert f"({r_low:.3g}–{r_high:.3g} mm)" in verdict.replace("90 %: ", "").replace("90%: ", "")
    refitted = "(its frame and target(s) fitted again to this log): position RMS"
    assert f"validate measured the error as the instrument sees it after registration {refitted}" in verdict
    assert re.search(
        r"beyond it [0-9.e-]+ mm \(90%: [0-9.e-]+–[0-9.e-]+ mm\) / [0-9.e-]+° \(90%: [0-9.e-]+–[0-9.e-]+°\)\), "
        r"(its interval meets|above|below) the predicted registered",
        verdict,
    )


def test_identifiability_reports_the_prediction_of_a_pose_list(tmp_path, capsys, wide_pose):
    platform_file = tmp_path / "wide.toml"
    platform_file.write_text(platform_to_toml(wide_pose))
    poses = planning.plan_poses(wide_pose, 30, None, np.random.default_rng(0), 300)
    io.write_pose_list(tmp_path / "p.csv", poses, 1.0)
    argv = ["identifiability", "--platform", str(platform_file), "--poses", str(tmp_path / "p.csv")]
    assert cli_main([*argv, "--json", str(tmp_path / "i.json")]) == 0
    printed = capsys.readouterr().out
    document = json.loads((tmp_path / "i.json").read_text())
    expected = accuracy.predicted_error(
        wide_pose, planning.design_covariance(wide_pose, read_pose_list(tmp_path / "p.csv"))
    )
    assert document["predicted_closed_loop"]["position_mm"] == pytest.approx(expected.position_mm, rel=1e-9)
    assert f"after calibration (for the instrument's σ {wide_pose.instrument.position_sigma_mm:g} mm" in printed
    assert f"[instrument]): {expected.describe()}" in printed
    assert document["verdict"] in ("identifiable", "poorly conditioned")
    # planned poses sit below the noise floor of as many poses at the box's extremes: no warning
    assert document["predicted_closed_loop"]["warning"] is None
    assert expected.position_mm < document["predicted_closed_loop"]["noise_floor_mm"]


def test_equilibrated_condition_number_does_not_depend_on_units_and_sets_the_verdict():
    rng = np.random.default_rng(5)
    A = rng.normal(0.0, 1.0, (40, 6))
    scaled = A * np.array([1.0, 1e3, 1e-3, 57.3, 1.0, 1e2])
    assert batch.equilibrated_condition_number(scaled) == pytest.approx(batch.equilibrated_condition_number(A))
    assert np.linalg.cond(scaled) > 1e4 * np.linalg.cond(A)
    assert batch._verdict(999.0) == "identifiable" and batch._verdict(1001.0) == "poorly conditioned"


def test_information_accumulator_covariance_is_the_inverse_information():
    from stewart_calib.analysis.identifiability import InformationAccumulator, whitened_leg_jacobian
    from stewart_calib.config import NoiseConfig
    from tests.synthetic import nim_stewart, random_poses

    platform, noise = nim_stewart(), NoiseConfig()
    poses = random_poses(platform, 30, np.random.default_rng(6))
    information = InformationAccumulator(platform, noise)
    information.add(poses)
    A = whitened_leg_jacobian(platform, poses, noise).reshape(-1, 42)
    np.testing.assert_allclose(information.covariance(), np.linalg.inv(A.T @ A), rtol=1e-6)
    few = InformationAccumulator(platform, noise)
    few.add(poses[:5])
    assert few.covariance() is None


@pytest.mark.parametrize("kind", ["points", "pose"])
def test_a_rigid_motion_of_either_joint_set_leaves_no_registered_error(kind, wide_points, wide_pose):
    """Moving all base joints by one rigid motion moves every pose by it in {J} (the frame absorbs it),
    the platform joints likewise in {D} (the target or the targets' places absorb it): a covariance
    spanned by those 12 directions leaves an absolute error but none as the instrument sees it."""
    platform = wide_points if kind == "points" else wide_pose
    values = platform.drive.as_vector()
    B = np.zeros((48, 12))
    for k, columns in enumerate(gauge.joint_columns(platform.drive)):
        B[columns, 6 * k : 6 * k + 6] = gauge.rigid_directions(values[columns].reshape(-1, 3))
    predicted = accuracy.predicted_error(platform, 0.01 * B @ B.T)
    assert predicted.position_mm > 0.01
    assert predicted.registered_position_mm < 1e-7 * predicted.position_mm
    assert max(predicted.registered_position_band_mm) < 1e-7 * predicted.position_mm


@pytest.mark.parametrize("kind", ["points", "pose"])
def test_the_registered_error_is_the_readings_error_after_the_best_registration(kind, wide_points, wide_pose):
    """One estimate error, driven through IK/FK: the instrument's readings of the poses the true robot
    reaches, registered to the desired poses by the instrument's own fit (frame and target(s), plain
    least squares), leave per pose the error the linear projection gives."""
    platform = wide_points if kind == "points" else wide_pose
    rng = np.random.default_rng(3)
    poses = accuracy.reachable_poses(platform, 30, rng)
    e = np.r_[rng.normal(0.0, 1e-3, 42), np.zeros(6)]
    R, t = kin.pose_to_rt(poses)
    strokes = kin.inverse_kinematics(platform.drive.perturbed(e[:42]), R, t)
    reached = kin.forward_kinematics(platform.drive, strokes, guess=(R, t))
    model = outside_model(platform)
    measured = model.predicted_readings(model.nominal_unknowns(), reached.R, reached.t)
    fitted = registration.refine(model, model.nominal_unknowns(), measured, R, t, frame_only=False)
    position = model.prediction_errors(fitted, R, t, measured)[1]
    D_seen, _ = accuracy.registered_jacobian(platform, accuracy.closed_loop_jacobian(platform, poses), poses)
    rows = (D_seen @ -e).reshape(len(poses), -1, 3)
    linear = np.linalg.norm(rows[:, 1], axis=-1) if kind == "pose" else np.sqrt(np.mean(np.sum(rows**2, -1), -1))
    assert np.mean(linear) > 1e-4  # not all absorbed
    np.testing.assert_allclose(position, linear, rtol=1e-2, atol=1e-3 * np.mean(linear))


def test_the_registered_prediction_is_written_and_read_back(wide_points):
    predicted = accuracy.predicted_error(wide_points, 1e-4 * np.eye(48))
    field = json.loads(json.dumps(predicted.to_dict()))
    assert field["registered_orientation_deg"] is None  # points read no orientation
    read = accuracy.PredictedError.from_dict(field)
    assert read.registered_position_mm == predicted.registered_position_mm > 0
    assert read.registered_position_band_mm == predicted.registered_position_band_mm
    assert np.isnan(read.registered_orientation_deg)
    assert predicted.registered_words() in predicted.describe() and "°" not in predicted.registered_words()
    old = {k: v for k, v in field.items() if not k.startswith("registered_")}  # a result written before
    assert np.isnan(accuracy.PredictedError.from_dict(old).registered_position_mm)
