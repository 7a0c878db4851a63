"""The elastic robot's files (spec §10): ``[elastic]`` in the platform file, ``load_kg`` as an input,
``simulate``'s platform with the masses and the compliance's truth."""

from __future__ import annotations

import tomllib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from stewart_calib.cli import main
from stewart_calib.errors import CalibError, SampleRejected
from stewart_calib.io import read_log, result_dict
from stewart_calib.io.logs import LogRowParser
from stewart_calib.io.platform_file import load_platform, parse_platform, platform_to_toml
from stewart_calib.model import kinematics as kin
from stewart_calib.model.platform import LegGeometry
from stewart_calib.model.statics import gravity_leg_forces
from stewart_calib.samples import LOAD_KG
from stewart_calib.simulation.experiment import load_experiment
from stewart_calib.simulation.load import settle
from tests.test_platform import _doc, _refusal, _to_toml

QUICK = Path(__file__).resolve().parents[1] / "configs" / "experiments" / "quick.toml"
ELASTIC = {"platform_mass_kg": 60.0, "platform_com_mm": [0.0, 0.0, -50.0]}


def _with_elastic(**keys) -> dict:
    doc = _doc()
    doc["elastic"] = {**ELASTIC, **keys}
    return doc


def test_elastic_reads_with_its_defaults_and_round_trips():
    platform = parse_platform(_with_elastic(), "p.toml")
    elastic = platform.elastic
    assert elastic.platform_mass_kg == 60.0
    np.testing.assert_array_equal(elastic.platform_com_mm, [0.0, 0.0, -50.0])
    np.testing.assert_array_equal(elastic.payload_com_mm, np.zeros(3))
    np.testing.assert_array_equal(elastic.compliance_mm_per_kN, np.zeros(6))
    # the default σ: the compliance at which a sixth of the platform's weight shortens a leg by 2 mm
    assert elastic.compliance_sigma_mm_per_kN == pytest.approx(2.0 / (60.0 * 9.80665 / 6 / 1000.0), rel=1e-12)
    assert elastic.true_compliance_mm_per_kN is None
    text = platform_to_toml(platform)
    again = parse_platform(tomllib.loads(text), "again.toml")
    assert platform_to_toml(again) == text
    assert parse_platform(_doc(), "rigid.toml").elastic is None


@pytest.mark.parametrize(
    ("keys", "expected"),
    [
        (
            {"platform_mass_kg": -1.0},
            "key 'elastic.platform_mass_kg': expected a mass in kg of at least 0.001 (a gram), got -1.0",
        ),
        (
            {"platform_mass_kg": 0.0},
            "key 'elastic.platform_mass_kg': expected a mass in kg of at least 0.001 (a gram), got 0.0",
        ),
        ({"platform_mass_kg": float("nan")}, "key 'elastic.platform_mass_kg': expected a finite number"),
        ({"platform_mass_kg": float("inf")}, "key 'elastic.platform_mass_kg': expected a finite number"),
        (
            {"platform_com_mm": [0.0, 0.0, -50000.0]},
            "key 'elastic.platform_com_mm': expected [x, y, z] in mm within 10",
        ),
        ({"payload_com_mm": [9000.0, 0.0, 0.0]}, "key 'elastic.payload_com_mm': expected [x, y, z] in mm within 10"),
        ({"compliance_sigma_mm_per_kN": -0.5}, "key 'elastic.compliance_sigma_mm_per_kN': expected a σ ≥ 0"),
        ({"compliance_mm_per_kN": [1.0] * 5}, "key 'elastic.compliance_mm_per_kN': expected a list of 6 numbers"),
        ({"payload_mass": 3.0}, "unknown key 'elastic.payload_mass'"),
    ],
)
def test_bad_elastic_tables_are_refused_in_one_line(tmp_path, keys, expected):
    assert expected in _refusal(tmp_path, _to_toml(_with_elastic(**keys)))


def test_a_missing_platform_mass_is_named(tmp_path):
    doc = _with_elastic()
    del doc["elastic"]["platform_mass_kg"]
    assert "key 'elastic.platform_mass_kg': expected the platform's mass in kg (missing)" in _refusal(
        tmp_path, _to_toml(doc)
    )


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "quick"
    assert main(["simulate", "--experiment", str(QUICK), "--out", str(out)]) == 0
    return out


def test_simulate_writes_the_masses_and_the_compliance_truth(simulated):
    load = load_experiment(QUICK).load
    elastic = load_platform(simulated / "platform.toml").elastic
    assert elastic.platform_mass_kg == load.platform_mass_kg
    np.testing.assert_array_equal(elastic.platform_com_mm, load.platform_com_mm)
    np.testing.assert_array_equal(elastic.payload_com_mm, load.payload_com_mm)
    np.testing.assert_array_equal(elastic.compliance_mm_per_kN, np.zeros(6))  # nominal: not yet calibrated
    series = 1e3 / load.leg_N_per_mm + 1e3 / load.base_joint_N_per_mm + 1e3 / load.platform_joint_N_per_mm
    np.testing.assert_allclose(elastic.true_compliance_mm_per_kN, series, rtol=5e-15)  # 15 digits


@pytest.mark.parametrize(("value", "shown"), [("-2.0", "-2.0"), ("nan", "nan"), ("inf", "inf"), ("", "nan")])
def test_load_kg_is_an_input_with_elastic_refused_naming_the_row(simulated, tmp_path, value, shown):
    platform = load_platform(simulated / "platform.toml")
    lines = (simulated / "log.csv").read_text().splitlines()
    column = lines[0].split(",").index("load_kg")
    fields = lines[3].split(",")
    fields[column] = value
    lines[3] = ",".join(fields)
    path = tmp_path / "bad.csv"
    path.write_text("\n".join(lines) + "\n")
    expected = f"{path}: row 4: column 'load_kg': expected a finite payload ≥ 0 kg"
    with pytest.raises(CalibError, match=r"^[^\n]*$") as caught:
        read_log(path, platform)
    assert str(caught.value).startswith(expected) and str(caught.value).endswith(f"got {shown}")
    parser = LogRowParser(str(path), lines[0], platform)
    with pytest.raises(CalibError) as streamed:
        parser.parse(lines[3], 4)
    assert str(streamed.value) == str(caught.value)
    assert parser.parse_block([line.encode() for line in lines[1:5]]) is None
    # a rigid platform reads the payload for reports only: a blank or negative one is not its business
    rigid = load_platform("nim-stewart")
    assert len(read_log(path, rigid)) == len(lines) - 1


# ----------------------------------------------------------------------------- the elastic drive model


@pytest.fixture(scope="module")
def check(tmp_path_factory):
    """benchmarks.elastic's check, small: 40 poses a stage at 0 / 20 / 40 kg, 20 validation poses."""
    from benchmarks.elastic import check_run

    experiment, run, platform = check_run(tmp_path_factory.mktemp("check"), 40, validation=20)
    calibration = np.asarray(run.kinds) == "calibration"
    return experiment, run, platform, calibration


def test_the_drive_model_settles_where_compensation_sends_it(check):
    """IK under a payload (compensate) and the settled FK of those strokes are each other's inverse,
    and the truth's own compliance puts the simulated robot where the model says."""
    from stewart_calib.analysis.compensation import compensate
    from stewart_calib.model.drive import drive_model

    _, run, platform, _ = check
    truth = replace(platform.elastic, compliance_mm_per_kN=platform.elastic.true_compliance_mm_per_kN)
    true_platform = replace(platform, drive=LegGeometry.from_params(run.robot.base_params), elastic=truth)
    drive = drive_model(true_platform)
    poses = run.desired_poses[:20]
    for payload in (0.0, 40.0):
        strokes = compensate(drive, poses, inputs={LOAD_KG: payload})
        fk, inputs = drive.settled_kinematics(strokes, {LOAD_KG: np.full(len(poses), payload)})
        np.testing.assert_allclose(kin.rt_to_pose(fk.R, fk.t), poses, atol=1e-5)  # the fixed point: nm
        R, t = kin.pose_to_rt(poses)
        sol, _ = settle(run.robot.load, run.robot.base_params, strokes, np.full(len(poses), payload), (R, t))
        assert np.max(np.linalg.norm(sol.t - t, axis=-1)) < 1e-6  # the true robot lands there too [mm]
        assert np.all(inputs[:, 6:] > 0)  # every leg in compression


def test_the_compiled_tracker_residuals_are_those_of_validate_under_each_rows_payload(check):
    """calibrate's residual pass (:func:`~stewart_calib.workflows.validation.tracker_residuals`: one compiled pass,
    each sample settled by the simulator's settling kernel with the drive's joints rigid and its compliance
    the term on the forces) gives what validate's predictions (the drive's settled_kinematics, batch numpy)
    give, row by row at its own payload ``load_kg`` (0 / 20 / 40 kg), within what FK's tolerance and the
    settling's stop (:data:`~stewart_calib.model.drive.SETTLED_MM` of the extension) leave open — on the nominal
    model (compliance 0; alone, not settled: no leg gives) and a calibrated one whose soft legs (20 mm/kN)
    take several passes to settle."""
    from stewart_calib.model.drive import SETTLED_MM
    from stewart_calib.workflows.validation import nominal_model, tracker_residuals, validate
    from tests.test_kinematics import fk_tolerance_bound

    _, run, platform, _ = check
    log = run.log
    assert len(np.unique(log.inputs[LOAD_KG])) == 3
    error = np.random.default_rng(5).normal(0.0, 0.5, 42)
    result = {**nominal_model(platform), "error": error.tolist()}
    result["compliance"] = {"names": [f"c{i}" for i in range(1, 7)], "estimate": np.full(6, 20.0).tolist()}
    models = [(nominal_model(platform), "the nominal platform"), (result, "the result")]
    residuals = tracker_residuals(platform, log, models)
    assert residuals is not None
    for (model, source), got in zip(models, residuals, strict=True):
        predicted = validate(platform, model, log, False, source, errors=False)[0]
        drive = platform.drive.perturbed(np.array(model["error"]))
        fk = kin.forward_kinematics(drive, log.strokes)
        # the settling stops where an extension moves ≤ SETTLED_MM a pass, the batch where every sample's does
        bound = fk_tolerance_bound(platform.tracker, drive, fk.R, fk.t) * (1.0 + SETTLED_MM / kin.FK_TOLERANCE_MM)
        assert np.abs(got - (log.readings - predicted)).max() <= bound
        if model is models[0][0]:  # compliance 0: alone, its forces are not solved for (the rigid pass)
            assert np.abs(tracker_residuals(platform, log, models[:1])[0] - got).max() <= bound
    # the payload is each row's: the same log read as all unloaded predicts otherwise (c f: ~0.4 mm at 40 kg)
    unloaded = replace(log, inputs={LOAD_KG: np.zeros(len(log))})
    assert np.abs(tracker_residuals(platform, unloaded, models)[1] - residuals[1]).max() > 0.1


def test_neglected_force_derivatives_are_small_against_the_rows_they_would_join(check):
    """The factors and the EKF take the leg forces at the pose and geometry they evaluate, but leave
    ``c ∂f/∂ξ / 1000`` and ``c ∂f/∂M / 1000`` out of the Jacobians. Here (1 mm/kN, 60 + 40 kg) they
    are ~1.2e-3 of ``∂r/∂ξ`` and ``∂r/∂M`` (the relative error of a Newton step that leaves them
    out); a hobby robot's 150 mm/kN at 2 kg gives the same order (c·f is what matters: 0.2 mm
    here, 0.5 mm there, against legs of 200–700 mm)."""
    from stewart_calib.model.statics import leg_force_jacobians

    _, run, platform, _ = check
    drive, elastic = platform.drive, platform.elastic
    R, t = kin.pose_to_rt(run.desired_poses[:30])
    masses = np.stack([np.full(30, elastic.platform_mass_kg), np.full(30, 40.0)], axis=-1)
    coms = np.stack([elastic.platform_com_mm, elastic.payload_com_mm])
    forces = gravity_leg_forces(drive, R, t, masses, coms)
    df_dxi, df_dM = leg_force_jacobians(drive, R, t, forces, masses, coms)
    c = elastic.true_compliance_mm_per_kN[:, None] / 1000.0
    J_pose, J_M = kin.leg_residual_jacobians(drive, R, t)
    pose_ratio = np.abs(c * df_dxi).max() / np.abs(J_pose).max()
    params_ratio = np.abs(c * df_dM).max() / np.abs(J_M).max()
    assert pose_ratio < 3e-3 and params_ratio < 3e-3, (pose_ratio, params_ratio)


@pytest.mark.parametrize("method", ["ls", "lm", "ekf", "isam2"])
def test_every_method_identifies_the_compliance_and_compensates_any_payload(check, method):
    from benchmarks.elastic import _subset, closed_loop_um
    from stewart_calib.workflows.calibration import run_calibration

    _, run, platform, calibration = check
    validation = run.desired_poses[np.asarray(run.kinds) == "validation"][:20]
    estimate = run_calibration(platform, _subset(run.log, calibration), method).estimate
    compliance = estimate.block_values("compliance")
    np.testing.assert_allclose(compliance, platform.elastic.true_compliance_mm_per_kN, rtol=0.05)
    for payload in (0.0, 40.0):
        assert closed_loop_um(run, platform, estimate, validation, payload) < 5.0  # rigid: ~60-100 µm
    result = result_dict(estimate, platform)
    assert result["compliance"]["names"] == [f"c{i}" for i in range(1, 7)]
    assert np.all(np.asarray(result["compliance"]["stddev"]) > 0)


def test_the_command_line_under_load(check, tmp_path, capsys):
    """calibrate writes the compliance block (its covariance last, spec §10) and --platform-out its
    estimate; validate predicts every row at its own payload; compensate --payload-kg gives the
    strokes of that load; paper-ekf holds the compliance at its nominal."""
    import json

    from stewart_calib.io import log_text

    _, run, platform, _ = check
    (tmp_path / "platform.toml").write_text(platform_to_toml(platform))
    (tmp_path / "log.csv").write_text(log_text(run.log, platform))
    files = {name: str(tmp_path / name) for name in ("platform.toml", "log.csv", "r.json", "c.toml", "V.csv")}
    argv = ["calibrate", "--platform", files["platform.toml"], "--log", files["log.csv"], "--method", "ekf"]
    report = tmp_path / "report"
    assert main([*argv, "--out", files["r.json"], "--platform-out", files["c.toml"], "--report", str(report)]) == 0
    assert "Leg compliance c ± σ" in (report / "index.html").read_text()
    rrd = tmp_path / "run.rrd"
    assert main([*argv, "--out", str(tmp_path / "r2.json"), "--rerun", str(rrd)]) == 0
    from tests.readback import read_scalars

    _, forces = read_scalars(rrd, "forces/leg1/ekf")
    assert len(forces) == len(run.log) and np.all(forces > 0)  # compression at every sample [N]
    _, c1 = read_scalars(rrd, "compliance/leg1/ekf")
    second = json.loads((tmp_path / "r2.json").read_text())
    assert c1[-1] == pytest.approx(second["compliance"]["estimate"][0], rel=1e-6)
    result = json.loads(Path(files["r.json"]).read_text())
    covariance = np.array(result["covariance"])
    np.testing.assert_allclose(np.sqrt(np.diag(covariance))[-6:], result["compliance"]["stddev"], rtol=1e-12)
    written = load_platform(files["c.toml"]).elastic.compliance_mm_per_kN
    np.testing.assert_array_equal(written, result["compliance"]["estimate"])
    validate = ["validate", "--platform", files["platform.toml"], "--result", files["r.json"], "--log"]
    assert main([*validate, files["log.csv"], "--out", files["V.csv"]]) == 0
    assert "position RMS 0.00" in capsys.readouterr().out  # µm: every row at its payload
    poses = tmp_path / "poses.csv"
    poses.write_text("x_mm,y_mm,z_mm,roll_deg,pitch_deg,yaw_deg\n0,0,760,0,0,0\n")
    strokes = {}
    for payload in ("0", "40"):
        out = tmp_path / f"q{payload}.csv"
        compensate = ["compensate", "--platform", files["platform.toml"], "--result", files["r.json"]]
        assert main([*compensate, "--poses", str(poses), "--out", str(out), "--payload-kg", payload]) == 0
        strokes[payload] = np.genfromtxt(out, delimiter=",", names=True)
    assert 0.02 < strokes["40"]["q1_mm"] - strokes["0"]["q1_mm"] < 0.2  # 40 kg: ~65 N more a leg, 1 mm/kN
    for bad in ("-1", "nan"):
        assert main([*compensate, "--poses", str(poses), "--out", str(out), "--payload-kg", bad]) != 0
        assert "--payload-kg: expected a finite payload ≥ 0 kg" in capsys.readouterr().err
    # paper-ekf is the paper's model: δM alone, the compliance held at [elastic]'s nominal
    assert main([*argv[:-1], "paper-ekf", "--out", str(tmp_path / "p.json")]) == 0
    assert "compliance" not in json.loads((tmp_path / "p.json").read_text())


def test_ekf_blocks_and_checkpoints_take_the_same_forces_as_one_sample_at_a_time(check):
    """The compiled block path prepares a block's inputs ahead, update() one sample at a time: both
    take the forces at the start-up's geometry, so they agree to FK's tolerance (the block path starts
    each pose's Newton at the pose its forces were taken at, update() at the sample before's: poses
    within 1e-9 mm of leg length, δM 3e-8 mm apart, 1e-5 of its smallest σ); a checkpoint keeps it."""
    from stewart_calib.estimators import make_estimator
    from stewart_calib.estimators.base import update_block, update_each

    _, run, platform, _ = check
    samples = list(run.log)
    one, block = make_estimator("ekf", platform), make_estimator("ekf", platform)
    update_each(one, samples)
    update_block(block, run.log)
    assert block._compiled  # the compiled recursion runs on the drive's blocks too
    np.testing.assert_allclose(block.estimate().error, one.estimate().error, rtol=0, atol=1e-6)  # σ ≥ 2e-3 mm
    np.testing.assert_allclose(  # σ ≥ 5e-3 mm/kN
        block.estimate().block_values("compliance"), one.estimate().block_values("compliance"), rtol=0, atol=1e-6
    )
    half, resumed = make_estimator("ekf", platform), make_estimator("ekf", platform)
    update_each(half, samples[:200])
    resumed.import_state(half.export_state())
    update_each(resumed, samples[200:])
    np.testing.assert_array_equal(resumed.estimate().error, one.estimate().error)
    # buffered rows of another layout (a checkpoint of another version of the model) are refused, not misread
    state = half.export_state()
    state["robust"]["buffer_prepared"] = state["robust"]["buffer_prepared"][:, :-1]
    with pytest.raises(CalibError, match=r"buffered samples of \d+ columns, expected \d+"):
        make_estimator("ekf", platform).import_state(state)


def test_an_isam2_checkpoint_keeps_each_samples_payload(check):
    """isam2 replays its buffered samples on resume: with their payloads, the forces they carry are
    the ones the uninterrupted run took (a checkpoint without them resumed at 0 kg)."""
    from stewart_calib.estimators import make_estimator
    from stewart_calib.estimators.base import update_each

    _, run, platform, _ = check
    loaded = [sample for sample in run.log if sample.inputs[LOAD_KG]]
    samples = loaded[:80]
    one, half = make_estimator("isam2", platform), make_estimator("isam2", platform)
    update_each(one, samples)
    update_each(half, samples[:40])
    state = half.export_state()
    assert np.all(state["replay"]["load_kg"] > 0)
    resumed = make_estimator("isam2", platform)
    resumed.import_state(state)
    update_each(resumed, samples[40:])
    np.testing.assert_allclose(resumed.estimate().error, one.estimate().error, rtol=0, atol=1e-9)
    older = {**state, "replay": {k: v for k, v in state["replay"].items() if k != "load_kg"}}
    make_estimator("isam2", platform).import_state(older)  # a checkpoint of before: loads, at 0 kg


# ----------------------------------------------------------------------------- the unannounced payload


def _payload_platform(platform, sigma_kg: float = 50.0):
    return replace(platform, elastic=replace(platform.elastic, payload_sigma_kg=sigma_kg))


def test_payload_sigma_reads_round_trips_and_refuses_a_negative_one(tmp_path):
    platform = parse_platform(_with_elastic(payload_sigma_kg=30.0), "p.toml")
    assert platform.elastic.payload_sigma_kg == 30.0
    assert parse_platform(tomllib.loads(platform_to_toml(platform)), "a.toml").elastic.payload_sigma_kg == 30.0
    assert parse_platform(_with_elastic(), "p.toml").elastic.payload_sigma_kg == 0.0
    assert "key 'elastic.payload_sigma_kg': expected a σ ≥ 0" in _refusal(
        tmp_path, _to_toml(_with_elastic(payload_sigma_kg=-1.0))
    )


def test_a_payload_adds_its_mass_times_the_forces_per_kg(check):
    """The leg forces are linear in the masses: those under a payload m are the platform's alone plus
    m times :meth:`DriveModel.payload_leg_forces` (closed form of the statics, to rounding)."""
    from stewart_calib.model.drive import drive_model

    _, run, platform, _ = check
    drive = drive_model(platform)
    R, t = kin.pose_to_rt(run.desired_poses[:25])
    per_kg = drive.payload_leg_forces(R, t)
    for mass in (7.5, 40.0):
        np.testing.assert_allclose(
            drive.leg_forces(R, t, {LOAD_KG: mass}), drive.leg_forces(R, t) + mass * per_kg, rtol=1e-12, atol=1e-9
        )
        inputs = drive.inputs(run.log.strokes[:25], None, R, t)
        np.testing.assert_allclose(
            drive.loaded_inputs(inputs, per_kg, mass)[:, 6:], drive.leg_forces(R, t, {LOAD_KG: mass})
        )


def test_the_ekf_payload_column_is_the_numerical_derivative(check):
    """``∂r/∂m = c_i f_{m,i} / 1000`` against central differences of the observation, at a state with
    the compliance and the payload away from zero (the residual is bilinear in c and m)."""
    from stewart_calib.estimators import make_estimator
    from stewart_calib.estimators.measurement import check_sample

    _, run, platform, _ = check
    ekf = make_estimator("ekf", _payload_platform(platform))
    layout = ekf.layout
    x = np.zeros(layout.size)
    x[layout.slice("compliance")] = platform.elastic.true_compliance_mm_per_kN
    x[layout.slice("payload")] = 25.0
    column = layout.slice("payload").start
    for k in (0, 50, 100):
        sample = replace(run.log[k], inputs={})
        strokes, z = check_sample(ekf.platform, ekf.model, sample)
        prepared = ekf._prepared(strokes, z, sample)
        _, H, _ = ekf._observe(prepared, x)
        step = 1.0
        shifted = [ekf._observe(prepared, x + sign * step * np.eye(layout.size)[column])[0] for sign in (1, -1)]
        numeric = -(shifted[0] - shifted[1]) / (2 * step)  # ν = −r
        np.testing.assert_allclose(H[:, column], numeric, rtol=1e-7, atol=1e-12)
        assert np.abs(H[:, column]).max() > 1e-4  # mm per kg: the column is there to be checked


def test_a_payload_step_is_its_samples_payload_in_closed_form():
    """A linear toy of the step rule: six residuals on δM (known to 1 µm) and a payload column h.
    The sample where m steps by 20 kg is gated at the state before it and begins a candidate step; the
    samples of the window after it, gated too, confirm it, and m lands on their least squares
    ``(hᵀR⁻¹h)⁻¹ hᵀR⁻¹ ν̄`` (the prior's σ_m is 50 kg, the data's 0.02); a misfit the payload does not
    explain is refused, not taken for a step."""
    from stewart_calib.config import RobustConfig
    from stewart_calib.estimators.robust import RobustFilter
    from stewart_calib.model.drive import PAYLOAD
    from stewart_calib.model.unknowns import UnknownBlock, UnknownLayout

    rng = np.random.default_rng(5)
    layout = UnknownLayout((UnknownBlock(PAYLOAD, ("payload_kg",), np.zeros(1), np.array([50.0])),), n_params=42)
    A = rng.normal(size=(6, 42))
    h = np.array([1.0, 2.0, 0.5, 1.5, 1.0, 0.8]) * 1e-3  # mm per kg
    sigma = 1e-4  # mm: the payload is known from one sample to σ / ‖h‖ ≈ 0.03 kg
    H = np.column_stack([A, h])

    def observe(prepared, x):
        return prepared - H @ x, H, sigma**2 * np.eye(6)

    robust = RobustConfig(startup_samples=0, adapt_noise=False, lockout_window_samples=3, lockout_gated_samples=2)
    f = RobustFilter("toy", 1e-3, 0.0, 0.9999, observe, robust, 6, layout=layout, step=(42, 50.0**2))
    f.filter.P[42, 42] = 1e-4  # m known at 0 before the step
    truth = np.zeros(43)
    truth[:42] = rng.normal(0.0, 1e-3, 42)
    f.filter.x[:42] = truth[:42]
    for k in range(5):
        f.update(float(k), H @ truth + rng.normal(0.0, sigma, 6))
    assert f.steps == 0
    truth[42] = 20.0
    after = robust.lockout_window_samples + 1  # the step's sample and the window that confirms it
    innovation = np.zeros(6)
    for k in range(5, 5 + after):
        z = H @ truth + rng.normal(0.0, sigma, 6)
        innovation += (z - H @ f.filter.x) / after
        if k < 4 + after:
            with pytest.raises(SampleRejected):  # gated at m = 0 (NIS ~10⁷), taken by the candidate step
                f.update(float(k), z)
            assert f.steps == 0
        else:
            f.update(float(k), z)  # the candidate has led over its window: the step is taken
    assert f.steps == 1 and f.filter.samples_used == 5 + after
    least_squares = (h @ innovation) / (h @ h)  # R ∝ I; δM's 1 µm prior moves it by 1e-3 of σ_m
    assert abs(f.filter.x[42] - least_squares) < 0.05 * sigma / np.linalg.norm(h) + 1e-3 * abs(least_squares)
    assert abs(f.filter.x[42] - 20.0) < 4 * np.sqrt(f.filter.P[42, 42])
    # a residual beyond the gate in directions the payload does not explain: refused, no step
    orthogonal = rng.normal(size=6)
    orthogonal -= h * (h @ orthogonal) / (h @ h)
    glitch = H @ truth + 6.0 * sigma * orthogonal / np.linalg.norm(orthogonal) * np.sqrt(6)
    with pytest.raises(SampleRejected):
        f.update(10.0, glitch)
    assert f.steps == 1


def test_the_start_up_solves_a_payload_with_the_rest():
    """The start-up batch with an unannounced payload in the state, on a linear toy: once decided it is
    the exact posterior of its samples and the prior, the payload's variance included. Its last solve
    runs as the filter has started, where later batches hold the payload as the filter knows it; held
    so there too, the payload's prior was the consensus pass's posterior — the same samples counted
    twice, and its correlations cut (table 3's robot in the loop: σ_m 0.012 kg where the batch's own
    Hessian gives 0.21, the payload 0.29 kg off and never freed)."""
    from stewart_calib.config import RobustConfig
    from stewart_calib.estimators.robust import RobustFilter
    from stewart_calib.model.drive import PAYLOAD
    from stewart_calib.model.unknowns import UnknownBlock, UnknownLayout

    rng = np.random.default_rng(3)
    layout = UnknownLayout((UnknownBlock(PAYLOAD, ("payload_kg",), np.zeros(1), np.array([50.0])),), n_params=42)
    sigma, count = 1e-3, 12
    H_all = [np.column_stack([rng.normal(size=(6, 42)), rng.normal(size=6) * 2e-3]) for _ in range(count)]

    def observe(prepared, x):
        k = int(prepared[0])
        return prepared[1:] - H_all[k] @ x, H_all[k], sigma**2 * np.eye(6)

    robust = RobustConfig(startup_samples=count, adapt_noise=False)
    f = RobustFilter("toy", 1.0, 0.0, 0.9999, observe, robust, 6, layout=layout, step=(42, 50.0**2))
    P0 = f.filter.P.copy()
    truth = np.r_[rng.normal(0.0, 1.0, 42), 3.0]
    for k in range(count):
        f.update(0.1 * k, np.r_[k, H_all[k] @ truth + rng.normal(0.0, sigma, 6)])
    assert f.started and not f.startup_outliers.any()
    information = np.linalg.inv(P0) + sum(H.T @ H for H in H_all) / sigma**2
    np.testing.assert_allclose(f.filter.P, np.linalg.inv(information), rtol=1e-6, atol=1e-12)


def test_a_payload_step_is_the_map_of_its_sample_where_the_pattern_is_bilinear():
    """The payload's pattern is bilinear (``c_i f_{m,i} m``): a toy whose first unknown plays the
    compliance, ``h(x) = A x + (1 + x_0) m f_m``. At the step's sample (m 0 → 20 kg) a candidate step
    begins with the update iterated, and once the window after it confirms it the filter is the MAP
    of those samples and the state before them (prior, plus σ_m² on m), mean and Laplace
    covariance, found here by Gauss–Newton to round-off. Linearised at m = 0 instead, the
    compliance's column lacks ``m f_m`` and the covariance misses the line that ties m to it (the
    correlation more than 0.3 off the MAP's)."""
    from stewart_calib.config import RobustConfig
    from stewart_calib.estimators.robust import RELINEARISE_TOLERANCE, RobustFilter
    from stewart_calib.model.drive import PAYLOAD
    from stewart_calib.model.unknowns import UnknownBlock, UnknownLayout

    rng = np.random.default_rng(11)
    layout = UnknownLayout((UnknownBlock(PAYLOAD, ("payload_kg",), np.zeros(1), np.array([50.0])),), n_params=42)
    A = rng.normal(size=(6, 42))
    A[:, 0] *= 1e-3  # the compliance seen little before the payload comes (the platform's weight alone)
    f_m = np.array([1.0, 2.0, 0.5, 1.5, 1.0, 0.8]) * 1e-3  # mm per kg at x_0 = 0
    sigma, variance = 1e-4, 50.0**2

    def h(x):
        return A @ x[:42] + (1.0 + x[0]) * x[42] * f_m

    def jacobian(x):
        J = np.column_stack([A, (1.0 + x[0]) * f_m])
        J[:, 0] += x[42] * f_m
        return J

    def observe(prepared, x):
        return prepared - h(x), jacobian(x), sigma**2 * np.eye(6)

    robust = RobustConfig(startup_samples=0, adapt_noise=False, lockout_window_samples=3, lockout_gated_samples=2)
    f = RobustFilter("toy", 1e-3, 0.0, 0.9999, observe, robust, 6, layout=layout, step=(42, variance))
    f.filter.P[42, 42] = 1e-4  # m known at 0 before the step
    truth = np.zeros(43)
    truth[:42] = rng.normal(0.0, 1e-3, 42)
    truth[0] = 0.05  # the compliance 5 % off its nominal: its column moves with m
    f.filter.x[:42] = truth[:42] + rng.normal(0.0, 1e-4, 42)
    f.filter.P[:42, :42] = np.diag(np.full(42, 1e-4**2))
    f.filter.P[0, 0] = 0.05**2  # the compliance known to 5 % only
    for k in range(5):
        f.update(float(k), h(truth) + rng.normal(0.0, sigma, 6))
    truth[42] = 20.0
    zs = [h(truth) + rng.normal(0.0, sigma, 6) for _ in range(robust.lockout_window_samples + 1)]
    x_prior, P_prior = f.filter.x.copy(), f.filter.P.copy()
    P_prior[42, 42] += variance
    for k, z in enumerate(zs[:-1]):
        with pytest.raises(SampleRejected):  # gated at m = 0, taken by the candidate step begun at the first
            f.update(5.0 + k, z)
    f.update(5.0 + len(zs) - 1, zs[-1])  # the candidate has led over its window: the step is taken
    assert f.steps == 1
    # the MAP of the two samples and that prior, by Gauss–Newton from the prior
    information_prior = np.linalg.inv(P_prior)
    x = x_prior.copy()
    for _ in range(50):
        J = jacobian(x)
        information = information_prior + len(zs) * J.T @ J / sigma**2
        gradient = information_prior @ (x - x_prior) - J.T @ sum(z - h(x) for z in zs) / sigma**2
        move = np.linalg.solve(information, gradient)
        x -= move
        if np.linalg.norm(move) < 1e-14:
            break
    J = jacobian(x)
    P_map = np.linalg.inv(information_prior + len(zs) * J.T @ J / sigma**2)
    miss = f.filter.x - x
    assert miss @ np.linalg.solve(P_map, miss) < RELINEARISE_TOLERANCE**2, miss
    correlation = lambda P: P[0, 42] / np.sqrt(P[0, 0] * P[42, 42])  # noqa: E731
    # linearised within 0.1σ of the MAP, the bilinear columns are off by 0.1 σ_m / m of themselves
    # (0.5 % here; measured 6e-4 on the σ, 4e-7 on the correlation)
    relative = RELINEARISE_TOLERANCE * np.sqrt(P_map[42, 42]) / x[42]
    np.testing.assert_allclose(correlation(f.filter.P), correlation(P_map), atol=relative)
    np.testing.assert_allclose(np.sqrt(np.diag(f.filter.P)), np.sqrt(np.diag(P_map)), rtol=relative)
    # the toy is one where the linearisation point matters: one update linearised before the step
    H = jacobian(x_prior)
    H = np.vstack([H] * len(zs))
    P_once = P_prior - P_prior @ H.T @ np.linalg.solve(H @ P_prior @ H.T + sigma**2 * np.eye(len(H)), H @ P_prior)
    assert abs(correlation(P_once) - correlation(P_map)) > 0.3


def test_ekf_finds_an_unannounced_payload_and_its_steps(check):
    """The check's 0 / 20 / 40 kg stages logged without ``load_kg``: with ``[elastic]
    payload_sigma_kg`` ekf takes each step as one (two), ends at 40 kg within 3σ of its own σ, keeps
    each c_i within 5 % and compensates at 40 kg as with the payload known (rigid-like without it);
    a checkpoint keeps the payload and its steps."""
    from benchmarks.elastic import _subset, closed_loop_um
    from stewart_calib.estimators import make_estimator
    from stewart_calib.estimators.base import update_each
    from stewart_calib.workflows.calibration import run_calibration

    _, run, platform, calibration = check
    log = replace(_subset(run.log, calibration), inputs={})
    estimating = _payload_platform(platform)
    estimate = run_calibration(estimating, log, "ekf").estimate
    column = estimate.layout.slice("payload").start
    payload, sigma = estimate.block_values("payload")[0], np.sqrt(estimate.full_covariance[column, column])
    assert estimate.details["payload_steps"] == 2
    assert abs(payload - 40.0) < 3 * sigma and sigma < 2.0, (payload, sigma)
    np.testing.assert_allclose(
        estimate.block_values("compliance"), platform.elastic.true_compliance_mm_per_kN, rtol=0.05
    )
    validation = run.desired_poses[np.asarray(run.kinds) == "validation"][:20]
    # the closed loop commands under the payload found: logged 0 plus the estimate's
    # ignoring it: ~200 µm
    assert closed_loop_um(run, platform, estimate, validation, 40.0) < 5.5
    result = result_dict(estimate, estimating)
    assert result["payload"]["names"] == ["payload_kg"] and result["payload_steps"] == 2
    samples = list(log)
    one, resumed = make_estimator("ekf", estimating), make_estimator("ekf", estimating)
    update_each(one, samples)
    half = make_estimator("ekf", estimating)
    update_each(half, samples[:60])
    resumed.import_state(half.export_state())
    update_each(resumed, samples[60:])
    np.testing.assert_array_equal(resumed.estimate().block_values("payload"), one.estimate().block_values("payload"))
    assert resumed.robust.steps == one.robust.steps == 2
    # a controller asking the library for strokes gets them under the payload found, as the loop above
    from stewart_calib.analysis.compensation import compensate
    from stewart_calib.model.drive import drive_model
    from stewart_calib.workflows.online import OnlineCalibrator

    online = OnlineCalibrator(estimating, "ekf")
    for sample in samples:
        try:
            online.update(sample)
        except SampleRejected:  # a step's first samples, refused until the samples after them confirm it
            pass
    found = online.estimate()
    strokes = online.compensated_strokes_rad(validation[:5], {LOAD_KG: 0.0})
    expected = compensate(
        drive_model(estimating).calibrated_by(found), validation[:5], inputs={LOAD_KG: found.block_values("payload")[0]}
    )
    np.testing.assert_allclose(strokes, expected, rtol=0, atol=1e-9)
    ignored = compensate(drive_model(estimating).calibrated_by(found), validation[:5], inputs={LOAD_KG: 0.0})
    assert np.abs(strokes - ignored).max() > 0.05  # ~40 kg: tens of µm a leg at 2.3 mm/kN


# ----------------------------------------------------------------------------- identifiability of c


def _tracker_report(platform, log, noise):
    from stewart_calib.analysis.identifiability import identifiability_report, tracker_samples
    from stewart_calib.model.drive import drive_model

    poses, strokes, channels = tracker_samples(platform, log)
    report = identifiability_report(platform, poses, noise, False, drive_model(platform, noise), strokes, channels)
    return report, poses, strokes, channels


def test_the_tracker_bound_covers_the_compliance_as_the_stacked_drive_jacobian(check):
    """The report's Cramér–Rao σ of δM and c1…c6 are those of the drive model's own ∂r/∂x_drive
    (drive.jacobians at the tracker's poses and the samples' forces) whitened by the residual's
    covariance and stacked densely; the blocks' scaling changes the SVD's units, not the bound."""
    from benchmarks.elastic import _subset
    from stewart_calib.analysis.identifiability import residual_covariance
    from stewart_calib.config import load_estimator_config
    from stewart_calib.model.drive import drive_model

    _, run, platform, calibration = check
    noise = load_estimator_config().noise
    report, poses, strokes, channels = _tracker_report(platform, _subset(run.log, calibration), noise)
    assert report.names[42:] == tuple(f"c{i}" for i in range(1, 7)) and report.rank == 48
    drive = drive_model(platform, noise)
    R, t = kin.pose_to_rt(poses)
    _, J = drive.jacobians(None, R, t, drive.inputs(strokes, channels, R, t))
    A = np.linalg.solve(np.linalg.cholesky(residual_covariance(platform, R, t, noise)), J).reshape(-1, 48)
    stddev = np.sqrt(np.diag(np.linalg.inv(A.T @ A)))
    np.testing.assert_allclose(report.predicted_stddev_mm, stddev[:42], rtol=1e-6)
    np.testing.assert_allclose(report.block_stddev["compliance"][1], stddev[42:], rtol=1e-6)
    assert report.to_dict()["blocks"]["compliance"]["names"] == [f"c{i}" for i in range(1, 7)]
    assert "compliance [mm/kN]: c1" in report.format_text()
    rigid = _tracker_report(replace(platform, elastic=None), _subset(run.log, calibration), noise)[0]
    assert rigid.names == rigid.names[:42] and "blocks" not in rigid.to_dict()  # without [elastic]: the 42


def test_the_tracker_bound_of_c_is_the_batch_fits_covariance(check):
    """``lm`` solves the same leg-length problem in batch: with its noise as configured (no scale from
    the data, no random walk) its covariance of c is the bound, to its priors' share (5 mm on δM,
    20 mm/kN on c: under 1 %)."""
    import dataclasses

    from benchmarks.elastic import _subset
    from stewart_calib.config import load_estimator_config
    from stewart_calib.workflows.calibration import run_calibration

    _, run, platform, calibration = check
    config = load_estimator_config()
    config = dataclasses.replace(
        config,
        noise=dataclasses.replace(config.noise, random_walk_mm_per_sqrt_s=0.0),
        robust=dataclasses.replace(config.robust, adapt_noise=False),
    )
    log = _subset(run.log, calibration)
    report = _tracker_report(platform, log, config.noise)[0]
    estimate = run_calibration(platform, log, "lm", config).estimate
    columns = estimate.layout.slice("compliance")
    fitted = np.sqrt(np.diag(estimate.full_covariance)[columns])
    np.testing.assert_allclose(fitted, report.block_stddev["compliance"][1], rtol=0.02)


@pytest.mark.parametrize("kind", ["pose", "points"])
def test_the_ekf_payload_column_with_an_outside_instrument_is_the_numerical_derivative(kind):
    """The same column where the instrument fixes the pose (a pose instrument: the drive's residuals
    there) and where it does not (two targets seen: the instrument's residual at the drive's forward
    kinematics, ``∂ξ/∂m = −J_g⁻¹ ∂g/∂m``), on the hobby hexapod with soft legs (150 mm/kN)."""
    from stewart_calib.estimators import make_estimator
    from stewart_calib.estimators.measurement import check_sample
    from stewart_calib.model.platform import Elastic
    from tests.instrument_data import hobby, make_case
    from tests.test_instrument_ls import POINTS, POINTS_TRUTH, POSE_TRUTH

    platform, truth = (hobby(), POSE_TRUTH) if kind == "pose" else (hobby(POINTS), POINTS_TRUTH)
    soft = Elastic(2.0, np.array([5.0, -3.0, 20.0]), np.array([0.0, 0.0, 30.0]), np.full(6, 150.0))
    platform = replace(platform, elastic=replace(soft, payload_sigma_kg=2.0))
    case = make_case(platform, 8, 24, truth)
    ekf = make_estimator("ekf", platform)
    layout = ekf.layout
    x = np.zeros(layout.size)
    x[layout.slice("payload")] = 0.5
    column = layout.slice("payload").start
    checked = 0
    for sample in case.log:
        readings = np.array(sample.readings, dtype=float).reshape(-1, 3)
        if kind == "points":  # two of the targets seen: no pose from the instrument alone
            seen = np.flatnonzero(np.isfinite(readings).all(axis=1))
            if len(seen) < 2:
                continue
            readings[seen[2:]] = np.nan
        sample = replace(sample, readings=readings.reshape(-1))
        checked += 1
        strokes, z = check_sample(ekf.platform, ekf.model, sample)
        prepared = ekf._prepared(strokes, z, sample)
        _, H, _ = ekf._observe(prepared, x)
        step = 0.05
        shifted = [ekf._observe(prepared, x + sign * step * np.eye(layout.size)[column])[0] for sign in (1, -1)]
        numeric = -(shifted[0] - shifted[1]) / (2 * step)
        np.testing.assert_allclose(H[:, column], numeric, rtol=1e-5, atol=1e-9)
        assert np.abs(H[:, column]).max() > 1e-3
    assert checked >= 4


def test_the_settled_pose_jacobian_matches_numerical_differences():
    """∂ξ/∂x_drive of settled_kinematics' poses, the forces' own change with the pose and the joints
    included (what the batch fit steps with), against central differences through the body tangent
    ``ξ = [ω, v]``; a hobby robot's soft legs (150 mm/kN, 2 kg, 5 kg payload) make that change show."""
    from benchmarks.hobby import SOFT_LEGS, simulate
    from stewart_calib.config import NoiseConfig
    from stewart_calib.model import rotations
    from stewart_calib.model.drive import drive_model

    platform = simulate(0, n_fit=4, n_held_out=1, build=SOFT_LEGS).elastic
    platform = replace(platform, elastic=replace(platform.elastic, compliance_mm_per_kN=np.full(6, 150.0)))
    drive = drive_model(platform, NoiseConfig(stroke_scale_sigma=0.05))
    data = simulate(0, n_fit=4, n_held_out=1, build=SOFT_LEGS)
    strokes, payload = data.fit.strokes, np.full(4, 5.0)
    x = np.random.default_rng(3).normal(0.0, 0.3, drive.size)
    fk, inputs = drive.settled_kinematics(strokes, {LOAD_KG: payload}, x)
    analytic = drive.settled_pose_jacobian(x, fk.R, fk.t, inputs, {LOAD_KG: payload})
    numeric = np.zeros_like(analytic)
    step = 1e-4
    for j in range(drive.size):
        dx = np.zeros(drive.size)
        dx[j] = step
        plus, _ = drive.settled_kinematics(strokes, {LOAD_KG: payload}, x + dx, (fk.R, fk.t))
        minus, _ = drive.settled_kinematics(strokes, {LOAD_KG: payload}, x - dx, (fk.R, fk.t))
        omega = rotations.so3_log(np.swapaxes(minus.R, -1, -2) @ plus.R)
        v = np.einsum("...ji,...j->...i", fk.R, plus.t - minus.t)
        numeric[..., j] = np.concatenate([omega, v], axis=-1) / (2 * step)
    np.testing.assert_allclose(analytic, numeric, atol=1e-5 * np.abs(numeric).max())  # settled to SETTLED_MM
    # and the forces' part is what the difference sees: without it the Jacobian is off by more
    rigid_part = drive.pose_jacobian(x, fk.R, fk.t, inputs)
    assert np.abs(rigid_part - numeric).max() > 100 * np.abs(analytic - numeric).max()
