"""``ls`` with an instrument outside the robot (spec §7) against the simulator's truth: errors of
all unknowns at the Cramér–Rao bound, convergence from large offsets without any setting
changed, glitches down-weighted."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stewart_calib.config import EstimatorConfig
from stewart_calib.estimators import make_estimator
from stewart_calib.estimators.batch import cramer_rao, identifiability
from stewart_calib.instruments import points
from stewart_calib.instruments.pose import PoseModel
from stewart_calib.model.platform import Instrument
from stewart_calib.simulation.instrument import InstrumentTruth
from tests.instrument_data import hobby, make_case, problem, truth_in_gauge

#: Monte Carlo runs per instrument; with 60–63 unknowns each, the mean of z² over all of them has a
#: relative standard deviation ≈ √(2 / (runs · p)) ≈ 0.1, so an RMS ratio of 1.2 (1.44 on z², the
#: issue's target) sits ≥ 4 standard deviations above the ideal 1.
RUNS = 3

POSE_TRUTH = InstrumentTruth(
    np.array([60.0, -40.0, 25.0, 20.0, -10.0, 150.0]), np.array([10.0, -5.0, 30.0, 0.0, 5.0, -90.0])
)
POINTS = Instrument(
    "points", np.zeros(6), np.zeros(6), np.array([[60.0, 0.0, 25.0], [-30.0, 50.0, 25.0], [-30.0, -50.0, 40.0]]), 0.05
)
POINTS_TRUTH = InstrumentTruth(
    np.array([-80.0, 50.0, 30.0, -15.0, 10.0, 60.0]), np.zeros(6), target_spread_mm=2.0, dropout_probability=0.15
)


def _normalised_errors(case, estimate) -> np.ndarray:
    """Errors of δM (42), k (6) and the instrument unknowns (file units), each over its CRB σ."""
    delta, unknowns = truth_in_gauge(case)
    bound = cramer_rao(problem(case), np.r_[delta, case.true_scale - case.platform.stroke_scale], unknowns)
    J = unknowns.file_jacobian()
    sigma = np.sqrt(np.r_[np.diag(bound)[:48], np.diag(J @ bound[48:, 48:] @ J.T)])
    truth = np.r_[delta, case.true_scale, unknowns.file_values()]
    blocks = estimate.block_results()
    found = np.r_[estimate.error, blocks["stroke_scale"]["estimate"], blocks["instrument"]["estimate"]]
    difference = found - truth
    if case.platform.instrument.kind == "pose":  # angles: the nearest turn
        for k in (51, 52, 53, 57, 58, 59):
            difference[k] = (difference[k] + 180.0) % 360.0 - 180.0
    return difference / sigma


@pytest.mark.parametrize("kind", ["pose", "points"])
def test_ls_reaches_the_cramer_rao_bound(kind):
    platform, truth, n = (hobby(), POSE_TRUTH, 80) if kind == "pose" else (hobby(POINTS), POINTS_TRUTH, 100)
    z = []
    for run in range(RUNS):
        case = make_case(platform, n, 100 + run, truth)
        estimate = make_estimator("ls", platform, EstimatorConfig()).fit(list(case.log))
        z.append(_normalised_errors(case, estimate))
    ratio = math.sqrt(np.mean(np.square(z)))
    assert ratio <= 1.2, f"RMS error / CRB = {ratio:.3f}"


def test_ls_converges_from_large_offsets_without_any_setting_changed():
    """Issue 13: a frame 100 mm and any rotation away, encoder zeros 20 mm off, scale 10 % off."""
    from dataclasses import replace

    platform = replace(hobby(), stroke_range=None)  # zeros 20 mm off push logged strokes past the hobby's range
    rng = np.random.default_rng(5)
    delta = rng.normal(0.0, 0.5, 42)
    delta[6::7] = rng.choice([-20.0, 20.0], 6)
    scale = rng.choice([-0.1, 0.1], 6)
    truth = InstrumentTruth(
        np.array([100.0, -100.0, 100.0, 170.0, -60.0, -120.0]), np.array([30.0, 40.0, -20.0, 90.0, 45.0, 180.0])
    )
    case = make_case(platform, 108, 6, truth, delta=delta, scale=scale)
    estimate = make_estimator("ls", platform, EstimatorConfig()).fit(list(case.log))
    z = _normalised_errors(case, estimate)
    assert np.max(np.abs(z)) < 5.0  # Gaussian max of 60 z-scores: 5 is p ≈ 3e-5


#: an instrument metres from the robot, as they stand: motion capture's origin on the floor, a laser
#: tracker on its stand (the frame's pose in {J}: mm, deg)
FAR_FRAME = np.array([1100.0, 2450.0, 400.0, 0.0, 0.0, 40.0])


@pytest.mark.parametrize("kind", ["pose", "points"])
def test_ls_converges_with_the_instrument_metres_from_the_robot(kind):
    """A frame 2.7 m away, encoder zeros ~15 mm and stroke scales ~3 % off (as the README's hobby
    session): the frame's turn about {I}'s origin and its shift nearly one column, where a fixed ×10 / ÷10
    damping did not converge in 200 evaluations (the laser tracker)."""
    platform = hobby() if kind == "pose" else hobby(POINTS)
    target = POSE_TRUTH.target_offset if kind == "pose" else np.zeros(6)
    case = make_case(platform, 108, 21, InstrumentTruth(FAR_FRAME, target), length_spread_mm=15.0, scale_spread=0.03)
    estimate = make_estimator("ls", platform, EstimatorConfig()).fit(list(case.log))
    z = _normalised_errors(case, estimate)
    assert np.max(np.abs(z)) < 5.0  # Gaussian max of 60 z-scores: 5 is p ≈ 3e-5


def test_conditioning_is_that_of_the_poses_not_of_where_the_instruments_origin_is():
    """The same poses and readings seen from a frame beside the robot and from one 2.7 m away:
    one condition number, one weakest direction's drive part."""
    platform = hobby()
    found = []
    for frame in (POSE_TRUTH.frame_offset, FAR_FRAME):
        case = make_case(platform, 60, 22, InstrumentTruth(frame, POSE_TRUTH.target_offset))
        unknowns = case.true_instrument.unknowns
        report = identifiability(
            problem(case), unknowns, PoseModel.names_of(platform.instrument), unknowns.file_jacobian()
        )
        found.append(report["condition_number_equilibrated"])
    assert found[1] == pytest.approx(found[0], rel=0.02)


def test_ls_downweights_a_glitch_and_is_not_pulled_by_it():
    platform = hobby()
    case = make_case(platform, 80, 9, POSE_TRUTH)
    clean = make_estimator("ls", platform, EstimatorConfig()).fit(list(case.log))
    case.log.readings[7, :3] += 25.0  # a swapped marker: the body jumps 43 mm
    fitted = make_estimator("ls", platform, EstimatorConfig()).fit(list(case.log))
    assert fitted.details["readings_downweighted"] >= 1
    sd = np.sqrt(np.diag(clean.covariance))
    # the glitch costs the fit less than its own uncertainty
    assert np.max(np.abs(fitted.error - clean.error) / np.maximum(sd, 1e-9)) < 1.0


def test_points_with_one_target_per_row_missing():
    case = make_case(hobby(POINTS), 60, 12, POINTS_TRUTH)
    seen_rows = np.isfinite(case.log.readings).reshape(60, 3, 3).all(axis=2)
    assert not seen_rows.all()
    estimate = make_estimator("ls", case.platform, EstimatorConfig()).fit(list(case.log))
    assert tuple(estimate.block_results()["instrument"]["names"]) == points.unknown_names(3)
    assert estimate.samples_used == 60 - int(np.sum(~seen_rows.any(axis=1)))


def test_a_block_the_log_cannot_see_is_held_and_the_others_are_still_fitted():
    """A log at one temperature says nothing of the legs' expansion (its columns are 0): ls holds the
    expansion at nominal and fits the stroke scale as it does without [thermal], to the bit."""
    from dataclasses import replace

    from stewart_calib.model.platform import Thermal
    from stewart_calib.samples import TEMPERATURE_C

    case = make_case(hobby(), 60, 302, POSE_TRUTH)
    results = []
    for thermal in (None, Thermal()):
        platform = replace(case.platform, thermal=thermal)
        log = (
            case.log
            if thermal is None
            else replace(case.log, inputs={TEMPERATURE_C: np.full((len(case.log), 6), 20.0)})
        )
        estimator = make_estimator("ls", platform, EstimatorConfig())
        for sample in log:
            estimator.update(sample)
        results.append(estimator.estimate())
    rigid, thermal = results
    assert thermal.details["stroke_scale_identified"] and not thermal.details["thermal_identified"]
    np.testing.assert_array_equal(thermal.error, rigid.error)
    np.testing.assert_array_equal(thermal.block_values("stroke_scale"), rigid.block_values("stroke_scale"))
    np.testing.assert_array_equal(thermal.block_values("thermal"), np.zeros(6))


def test_ls_noise_of_each_channel_is_unbiased_where_one_channel_pins_most_unknowns():
    """The σ ls re-estimates for position and orientation, each over the degrees of freedom the fit
    takes from that channel (the trace of its rows of the hat matrix), not a share by the number of
    rows: a pose instrument of 1 mm / 0.005° over 20 poses takes ~40 of its 48 unknowns from the
    orientation's 60 rows, ~8 from the position's. Shared by the rows (24 each) σ̂² came out 0.52× the
    truth for orientation, 1.51× for position (the covariance then ~2× too confident along what the
    orientation pins); per run σ̂²/σ² spreads as χ²_ν/ν, ν ≈ 20 and 52, so the mean of 20 runs is within
    3 σ of 1: ±3 √(2 / (20 ν)), 0.21 and 0.13."""
    from dataclasses import replace

    platform = hobby()
    platform = replace(
        platform,
        instrument=replace(platform.instrument, position_sigma_mm=1.0, orientation_sigma_rad=math.radians(0.005)),
    )
    ratios = []
    for run in range(20):
        case = make_case(platform, 20, 100 + run, POSE_TRUTH)
        noise = make_estimator("ls", platform, EstimatorConfig()).fit(list(case.log)).details["noise_estimated"]
        ratios.append([noise["orientation_rad"] / math.radians(0.005), noise["position_mm"] / 1.0])
    orientation, position = np.mean(np.square(ratios), axis=0)
    assert abs(orientation - 1.0) <= 3.0 * math.sqrt(2.0 / (20 * 20)), orientation
    assert abs(position - 1.0) <= 3.0 * math.sqrt(2.0 / (20 * 52)), position
