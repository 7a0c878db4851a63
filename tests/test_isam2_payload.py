"""isam2's unannounced payload (``[elastic] payload_sigma_kg``, spec §10): the payload mass an entry of
the graph's unknown vector, each step its front end recognises a window whose walk lets it move.

Data: benchmarks.elastic's check, small (40 poses a stage at 0 / 20 / 40 kg, 1 µm tracker, legs of
1 mm/kN), logged without ``load_kg``.
"""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np
import pytest

from stewart_calib.config import RobustConfig
from stewart_calib.estimators import make_estimator
from stewart_calib.estimators.base import update_each
from stewart_calib.factors import drive_leg
from stewart_calib.io import result_dict
from stewart_calib.model import kinematics as kin
from stewart_calib.model.platform import Elastic
from stewart_calib.samples import LOAD_KG
from tests.numdiff import numerical_jacobian, relative_error
from tests.synthetic import nim_stewart, random_error, random_poses

#: the unannounced payload's prior σ [kg]: the largest payload the robot is expected to carry
PAYLOAD_SIGMA_KG = 50.0


def _estimating(platform, sigma_kg: float = PAYLOAD_SIGMA_KG):
    return replace(platform, elastic=replace(platform.elastic, payload_sigma_kg=sigma_kg))


@pytest.fixture(scope="module")
def check(tmp_path_factory):
    """The check's calibration samples without their ``load_kg``: the steps at samples 40 and 80."""
    from benchmarks.elastic import _subset, check_run

    _, run, platform = check_run(tmp_path_factory.mktemp("check"), 40, validation=20)
    calibration = np.asarray(run.kinds) == "calibration"
    log = replace(_subset(run.log, calibration), inputs={})
    return run, platform, log


def _payload(estimate) -> tuple[float, float]:
    """The unannounced payload found and its σ [kg]."""
    column = estimate.layout.slice("payload").start
    return estimate.unannounced_payload_kg(), float(np.sqrt(estimate.full_covariance[column, column]))


def test_the_drive_leg_factor_payload_column_is_the_numerical_derivative():
    """``∂r_i/∂m = c_i f_{m,i} / 1000`` in the factor's unknown-vector Jacobian, and the compliance
    columns under the forces at ``load_kg + m``, against central differences (the residual is bilinear
    in c and m; the forces do not depend on either), at c and m away from zero."""
    platform = nim_stewart()
    elastic = Elastic(
        60.0, np.array([8.0, -5.0, -60.0]), np.array([90.0, -60.0, 120.0]), np.full(6, 1.0), payload_sigma_kg=50.0
    )
    platform = replace(platform, elastic=elastic)
    builder = make_estimator("isam2", platform)._builder
    layout, drive = builder.layout, builder.drive
    payload, compliance = layout.slice("payload").start, layout.slice("compliance")
    rng = np.random.default_rng(3)
    unknowns = np.zeros(layout.size)
    unknowns[:42] = random_error(rng, 0.5)
    unknowns[compliance] = rng.uniform(-0.3, 0.3, 6)
    unknowns[payload] = 25.0
    X, P = gtsam.symbol("x", 0), gtsam.symbol("p", 0)
    for legs in (np.arange(6), [3]):
        spec = drive_leg.DriveLegs.of(legs, drive, payload)
        for pose6 in random_poses(platform, 3, rng):
            R, t = kin.pose_to_rt(pose6)
            pose = gtsam.Pose3(gtsam.Rot3(R), t)
            strokes = kin.inverse_kinematics(platform.drive, R, t) + 0.05
            load_kg = 10.0
            inputs = drive.inputs(strokes, {LOAD_KG: load_kg}, R, t)
            f = drive_leg.factor(X, P, spec, inputs, gtsam.noiseModel.Unit.Create(len(legs)), {LOAD_KG: load_kg})

            def error(u, f=f, pose=pose):
                values = gtsam.Values()
                values.insert(X, pose)
                values.insert(P, u)
                return f.unwhitenedError(values)

            values = gtsam.Values()
            values.insert(X, pose)
            values.insert(P, unknowns)
            A, _ = f.linearize(values).jacobian()
            H = A[:, 6:]
            numeric = numerical_jacobian(error, unknowns, 1.0)
            columns = np.r_[np.arange(layout.size)[compliance], payload]
            assert relative_error(H[:, columns], numeric[:, columns]) <= 1e-6
            c = elastic.compliance_mm_per_kN + unknowns[compliance]
            per_kg = drive.payload_leg_forces(R, t, unknowns)
            np.testing.assert_allclose(H[:, payload], (c * per_kg / 1000.0)[spec.legs], rtol=1e-12)
            assert np.abs(H[:, payload]).min() > 1e-4  # mm per kg: the column is there to be checked
            # the residual is the drive model's under load_kg + m
            loaded = drive.inputs(strokes, {LOAD_KG: load_kg + unknowns[payload]}, R, t, unknowns)
            expected = drive.residual(unknowns[: drive.size], R, t, loaded)
            np.testing.assert_allclose(error(unknowns), expected[spec.legs], rtol=0, atol=1e-9)


def test_isam2_finds_the_payload_ekf_finds_at_the_sample_of_each_step(check):
    """The 0 / 20 / 40 kg stages without ``load_kg``: isam2 takes each step as one (two, as ekf), once the
    window after the step's sample confirms it, and moves its payload by it there (to within 3σ); it
    ends within 3σ of 40 kg, ekf within 2σ, the two within 2.5σ of their difference (the same data). Its drive model
    follows the steps: from 10 samples after each, the closed loop at the true payload is at most
    3σ_m / m of isam2's without the payload state, which takes the steps for parameter motion (~80 µm
    after the first, ~200 µm at the end) — a payload missed by 3σ leaves that share of ignoring all of
    it — beyond isam2's with the payload known (``load_kg`` logged), and ≤ 5 µm at the end."""
    from benchmarks.elastic import _subset, closed_loop_um

    run, platform, log = check
    samples = list(log)
    known_log = list(_subset(run.log, np.asarray(run.kinds) == "calibration"))  # load_kg logged
    validation = run.desired_poses[np.asarray(run.kinds) == "validation"][:20]
    stage_kg = lambda k: 20.0 * (k // 40)  # noqa: E731
    found = {}
    window = RobustConfig().lockout_window_samples
    checked = (70, 79, 110, len(samples) - 1)  # after each step's window, and the end
    taken = []
    for sigma, fed in ((PAYLOAD_SIGMA_KG, samples), (0.0, samples), (None, known_log)):
        isam2 = make_estimator("isam2", _estimating(platform, sigma or 0.0))
        after, payload = {}, {}
        for k, sample in enumerate(fed):
            steps = isam2._front.robust.steps
            update_each(isam2, [sample])
            if sigma:
                payload[k] = _payload(isam2.estimate())
                if isam2._front.robust.steps != steps:
                    taken.append(k)
            if k in checked:
                after[k] = closed_loop_um(run, platform, isam2.estimate(), validation, stage_kg(k))
        found[sigma] = (isam2.estimate(), after, payload)  # None: the payload known
    estimate, after, payload = found[PAYLOAD_SIGMA_KG]
    assert estimate.details["payload_steps"] == 2
    result = result_dict(estimate, _estimating(platform))  # the result file's keys, as ekf's
    assert result["payload"]["names"] == ["payload_kg"] and result["payload_steps"] == 2
    for step, k in zip((40, 80), taken, strict=True):  # the payload moves by the stage's 20 kg once confirmed
        assert step + window <= k <= step + 2 * window, taken
        (before, _), (now, sigma_now) = payload[k - 1], payload[k]
        assert abs(now - before - 20.0) < 3.0 * sigma_now, (k, payload[k - 1], payload[k])
    _, ignored, _ = found[0.0]
    _, known, _ = found[None]
    for k in checked:  # with the payload known, less the share of it a 3σ miss leaves
        assert after[k] < known[k] + 3.0 * payload[k][1] / stage_kg(k) * ignored[k], (k, after, known, ignored)
    assert after[len(samples) - 1] < 5.0, after
    ekf = make_estimator("ekf", _estimating(platform))
    update_each(ekf, samples)
    assert ekf.estimate().details["payload_steps"] == 2
    (m_isam2, sigma_isam2), (m_ekf, sigma_ekf) = _payload(estimate), _payload(ekf.estimate())
    assert abs(m_isam2 - 40.0) < 3 * sigma_isam2 and sigma_isam2 < 2.0, (m_isam2, sigma_isam2)
    # the payload held until the compliance is known (RobustFilter._release_payload): ekf 39.6 ± 0.6, isam2 39.5 ± 0.5
    assert abs(m_ekf - 40.0) < 2 * sigma_ekf, (m_ekf, sigma_ekf)
    assert abs(m_isam2 - m_ekf) < 2.5 * np.hypot(sigma_isam2, sigma_ekf), (m_isam2, sigma_isam2, m_ekf, sigma_ekf)
    np.testing.assert_allclose(
        estimate.block_values("compliance"), platform.elastic.true_compliance_mm_per_kN, rtol=0.05
    )


def test_the_payload_and_its_steps_survive_a_checkpoint_and_a_rebuild(check):
    """Exported a few samples after the first step is taken (its window in the replay buffer), resumed and fed
    the rest: the payload, its steps and δM as the uninterrupted run's; a gtsam-failure rebuild right
    after the step replays the step's window (the payload as before, to the rebuild's linearisation);
    the step samples' record goes through the result's ``"payload_steps"`` and the checkpoint's arrays."""
    from stewart_calib.errors import CalibError

    _, platform, log = check
    estimating = _estimating(platform)
    samples = list(log)
    one = make_estimator("isam2", estimating)
    update_each(one, samples)
    half = make_estimator("isam2", estimating)
    exported = 0
    while not half._front.robust.steps:  # the first step taken, then a few samples more
        update_each(half, [samples[exported]])
        exported += 1
    update_each(half, samples[exported : exported + 5])
    exported += 5
    state = half.export_state()
    # where the front end released the payload it held (the compliance known to within itself) and where the
    # step happened: each opens a window
    released = half._front.robust.payload_released_t_s
    np.testing.assert_array_equal(state["payload_steps"]["t_s"], [released, samples[40].t_s])
    before = half.estimate()
    assert abs(state["payload_steps"]["payload_kg"][-1] - 20.0) < 3.0 * _payload(before)[1]
    half._rebuild(half._first_snapshot(), half._replay)  # what a gtsam failure does
    rebuilt = half.estimate()
    m, sigma = _payload(before)
    assert abs(rebuilt.unannounced_payload_kg() - m) < 1e-3 * sigma
    np.testing.assert_allclose(rebuilt.error, before.error, rtol=0, atol=1e-6)
    resumed = make_estimator("isam2", estimating)
    resumed.import_state(state)
    update_each(resumed, samples[exported:])
    end, expected = resumed.estimate(), one.estimate()
    assert end.details["payload_steps"] == expected.details["payload_steps"] == 2
    # the run the walk had counts from the first sample before the checkpoint (its time kept in the state)
    assert end.details["payload_walk"] == expected.details["payload_walk"], end.details
    assert expected.details["payload_walk"]["over_s"] == pytest.approx(samples[-1].t_s - samples[0].t_s)
    assert abs(end.unannounced_payload_kg() - expected.unannounced_payload_kg()) < 1e-3 * _payload(expected)[1]
    np.testing.assert_allclose(end.error, expected.error, rtol=0, atol=1e-6)
    steps_t_s = state["payload_steps"]["t_s"]
    bad = {**state, "payload_steps": {"t_s": steps_t_s, "payload_kg": np.full(len(steps_t_s), np.nan)}}
    with pytest.raises(CalibError, match="payload_steps"):
        make_estimator("isam2", estimating).import_state(bad)
