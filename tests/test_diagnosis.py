"""Mistakes in a log are refused with their cause, before any solver runs (issue 28).

:data:`MISTAKES` is the catalogue: the mistakes a new user made converting the shipped
hobby-hexapod example by hand (the issue's), and more of the same kind, each on a log of the
right robot with the mistake applied, and the one-line cause it must be refused with. The
correct logs (many geometries, frames, target offsets and sample counts) must pass untouched.
"""

from __future__ import annotations

import functools
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from stewart_calib import cli
from stewart_calib.errors import CalibError
from stewart_calib.io import write_log
from stewart_calib.model.platform import Instrument
from stewart_calib.samples import Log
from stewart_calib.simulation.instrument import InstrumentTruth
from stewart_calib.workflows.diagnosis import diagnose_log, required_samples

from . import instrument_data as idata
from . import synthetic as syn

#: the example's instrument truth (examples/hobby-mocap/make_raw.py): frame 40 mm and 30° off, body turned 90°
FRAME = np.array([40.0, -25.0, 15.0, 5.0, -3.0, 30.0])
TARGET = np.array([12.0, -8.0, 35.0, 0.0, 0.0, 90.0])


def _pose_case(n: int = 108, seed: int = 3):
    return idata.make_case(idata.hobby(), n, seed, InstrumentTruth(FRAME, TARGET))


def _points_case(n: int = 80, seed: int = 4):
    targets = np.array([[60.0, 0.0, 20.0], [-30.0, 50.0, 10.0]])
    instrument = Instrument("points", targets=targets, position_sigma_mm=0.05)
    return idata.make_case(idata.hobby(instrument), n, seed, InstrumentTruth(FRAME, np.zeros(6)), length_spread_mm=5.0)


def _tracker_log(n: int = 60, seed: int = 5):
    rng = np.random.default_rng(seed)
    platform = syn.nim_stewart()
    log, _ = syn.make_log(platform, syn.random_error(rng), syn.random_poses(platform, n, rng), rng, 0.002, 0.002)
    return platform, log


def _with(log: Log, strokes=None, readings=None) -> Log:
    return Log(
        log.t_s,
        log.strokes if strokes is None else strokes,
        log.readings if readings is None else readings,
    )


def _scaled(columns: slice, factor: float):
    def mistake(log: Log) -> Log:
        readings = log.readings.copy()
        readings[:, columns] *= factor
        return _with(log, readings=readings)

    return mistake


def _swapped(i: int, j: int):
    def mistake(log: Log) -> Log:
        strokes = log.strokes.copy()
        strokes[:, [i, j]] = strokes[:, [j, i]]
        return _with(log, strokes=strokes)

    return mistake


def _reversed(i: int, low: float, high: float):
    """An encoder counting the wrong way: its zero at the other end of the stroke range."""

    def mistake(log: Log) -> Log:
        strokes = log.strokes.copy()
        strokes[:, i] = low + high - strokes[:, i]
        return _with(log, strokes=strokes)

    return mistake


def _first(n: int):
    return lambda log: log.select(slice(0, n))


def _one_pose_repeated(log: Log) -> Log:
    return _with(log.select(np.zeros(len(log), dtype=int)))


def _strokes_in_metres(log: Log) -> Log:
    return _with(log, strokes=log.strokes / 1000.0)


def _unrelated_positions(log: Log) -> Log:
    readings = log.readings.copy()
    readings[:, :3] = np.random.default_rng(0).normal(0.0, 2000.0, (len(log), 3))
    return _with(log, readings=readings)


def _planar(rotate: tuple[int, ...]):
    """The log's robot and instrument at poses that translate and rotate only about the axes
    ``rotate`` (0 roll … 2 yaw)."""

    def mistake(log: Log) -> Log:
        platform = idata.hobby()
        rng = np.random.default_rng(8)
        ws = platform.workspace
        half = 0.6 * np.r_[[ws.translation_limit] * 3, [ws.rotation_limit] * 3]
        half[[3 + k for k in range(3) if k not in rotate]] = 0.0
        poses = ws.home + rng.uniform(-1.0, 1.0, (80, 6)) * half
        case = _pose_case()
        from stewart_calib.model import kinematics as kin

        R, t = kin.pose_to_rt(poses)
        true_drive = platform.drive.perturbed(case.true_params - platform.drive.as_vector())
        strokes = kin.inverse_kinematics(true_drive, R, t) / (1.0 + case.true_scale)
        readings = case.true_instrument.read(R, t, case.true_instrument.draw(80, rng))
        return Log(np.arange(80) * 0.1, strokes, readings)

    return mistake


def _pose():
    case = _pose_case()
    return case.platform, case.log


def _points():
    case = _points_case()
    return case.platform, case.log


#: (name, (platform, correct log) maker, mistake, words its one-line refusal must hold)
MISTAKES = [
    # the issue's, on the hobby hexapod measured by motion capture (the shipped example's robot)
    ("mocap positions in metres", _pose, _scaled(slice(0, 3), 1e-3), "positions mx_mm…mz_mm look like metres"),
    ("mocap angles in radians", _pose, _scaled(slice(3, 6), np.pi / 180), "look like radians, not degrees"),
    ("two stroke columns swapped", _pose, _swapped(0, 1), "stroke columns q1_mm and q2_mm look swapped"),
    ("a log of 5 rows", _pose, _first(5), "too few samples: 5 distinct sample(s) for 48 unknowns"),
    (
        "tracker readings in metres",
        _tracker_log,
        _scaled(slice(0, 6), 1e-3),
        "tracker readings s1_mm…s6_mm look like metres",
    ),
    (
        "a leg's sign reversed",
        _pose,
        _reversed(2, 0.0, 90.0),
        "leg 3's stroke looks reversed (q3_mm counts the wrong way)",
    ),
    # ten more of the same kind
    ("strokes in metres", _pose, _strokes_in_metres, "strokes q1_mm…q6_mm look like metres"),
    ("mocap positions in centimetres", _pose, _scaled(slice(0, 3), 0.1), "look like centimetres"),
    ("mocap positions in inches", _pose, _scaled(slice(0, 3), 1 / 25.4), "look like inches"),
    ("mocap positions in micrometres", _pose, _scaled(slice(0, 3), 1e3), "look like micrometres"),
    (
        "laser-tracker points in metres",
        _points,
        _scaled(slice(0, 6), 1e-3),
        "target 1 positions p1x_mm…p1z_mm look like metres",
    ),
    ("tracker: stroke columns 4 and 6 swapped", _tracker_log, _swapped(3, 5), "q4_mm and q6_mm look swapped"),
    ("tracker: a leg's sign reversed", _tracker_log, _reversed(4, -420.0, 520.0), "leg 5's stroke looks reversed"),
    ("laser tracker: columns swapped", _points, _swapped(1, 4), "q2_mm and q5_mm look swapped"),
    ("one pose held for the whole log", _pose, _one_pose_repeated, "too few samples: 1 distinct sample(s)"),
    ("a laser-tracker log of 6 rows", _points, _first(6), "expected at least 8 distinct poses"),
    ("poses that only translate", _pose, _planar(()), "no rotation about roll or pitch or yaw"),
    ("poses that rotate only about yaw", _pose, _planar((2,)), "no rotation about roll or pitch"),
    ("positions from unrelated columns", _pose, _unrelated_positions, "positions mx_mm…mz_mm do not match the strokes"),
    ("tracker readings in micrometres", _tracker_log, _scaled(slice(0, 6), 1e3), "look like micrometres"),
]


@functools.cache
def _passing(make):
    """``make()``'s platform and correct log, which pass the diagnosis: checked once per maker, as
    its log is the same for every mistake (fixed seeds; a mistake copies what it changes; the pose
    log's diagnosis costs ~2.6 s CPU, 12 mistakes start from it)."""
    platform, log = make()
    diagnose_log(platform, log.strokes, log.readings, "log.csv")
    return platform, log


@pytest.mark.parametrize("name, make, mistake, cause", MISTAKES, ids=[m[0] for m in MISTAKES])
def test_a_mistake_is_refused_with_its_cause(name, make, mistake, cause):
    platform, log = _passing(make)
    wrong = mistake(log)
    with pytest.raises(CalibError) as refused:
        diagnose_log(platform, wrong.strokes, wrong.readings, "log.csv")
    message = str(refused.value)
    assert message.startswith("log.csv: ") and "\n" not in message
    assert cause in message, message


@pytest.mark.parametrize("seed", range(6))
def test_correct_logs_pass(seed):
    """Frames anywhere, bodies turned any way, 15 mm leg errors, few or many samples: no refusal."""
    rng = np.random.default_rng(100 + seed)
    frame = np.r_[rng.uniform(-500, 500, 3), rng.uniform(-180, 180, 3)]
    target = np.r_[rng.uniform(-50, 50, 3), rng.uniform(-180, 180, 3)]
    n = int(rng.integers(12, 150))
    for case in (
        idata.make_case(
            idata.hobby(), n, seed, InstrumentTruth(frame, target), length_spread_mm=15.0, scale_spread=0.03
        ),
        idata.make_case(
            idata.hobby(Instrument("points", targets=np.array([[50.0, 10.0, 30.0]]), position_sigma_mm=0.05)),
            n + 20,
            seed,
            InstrumentTruth(frame, np.zeros(6), target_spread_mm=5.0),
            length_spread_mm=15.0,
        ),
    ):
        diagnose_log(case.platform, case.log.strokes, case.log.readings, "log.csv")
    platform, log = _tracker_log(n, seed)
    diagnose_log(platform, log.strokes, log.readings, "log.csv")


def test_required_samples_count_the_unknowns():
    assert required_samples(syn.nim_stewart())[:2] == (7, 42)
    assert required_samples(idata.hobby())[:2] == (8, 48)  # 42 + 6 + 12 − 12 over 6 a pose
    two = replace(idata.hobby(), instrument=Instrument("points", targets=np.zeros((2, 3))))
    assert required_samples(two)[:2] == (8, 48)  # 42 + 6 + 12 − 12 over 6 a sample


def test_calibrate_refuses_before_the_solver_in_one_line(tmp_path, capsys):
    """Through the command line: exit 2, one line, nothing written."""
    platform, log = _pose()
    path, out = tmp_path / "log.csv", tmp_path / "r.json"
    write_log(path, _scaled(slice(0, 3), 1e-3)(log), platform)
    code = cli.main(
        ["calibrate", "--platform", "hobby-hexapod", "--log", str(path), "--method", "ls", "--out", str(out)]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and not out.exists()
    assert err[0].startswith(f"stewart-calib calibrate: error: {path}: the positions mx_mm…mz_mm look like metres")


def test_a_fit_that_does_not_converge_names_what_it_fitted_and_why():
    """Past the diagnosis (the API, or a mistake it does not know), ls still names the cause."""
    from stewart_calib.workflows.calibration import run_calibration

    platform, log = _pose()
    with pytest.raises(CalibError) as refused:
        run_calibration(platform, _scaled(slice(0, 3), 1e-3)(log), "ls")
    message = str(refused.value)
    assert "did not converge in 200 evaluations fitting 30 drive directions" in message, message
    assert "6 stroke scales, the 12 instrument unknowns to 108 samples" in message
    assert "most likely the readings move the platform by another amount than the strokes say" in message


def test_validate_diagnoses_the_held_out_log_and_names_a_moved_frame(tmp_path, capsys):
    """A held-out log's mistakes are named as calibrate's; a frame that moved since the calibration
    is named with the errors through the result's frame and through a frame fitted again."""
    fit = _pose_case()
    moved = idata.make_case(idata.hobby(), 60, 3, InstrumentTruth(FRAME + [8.0, -5.0, 3.0, 1.0, 0.5, -2.0], TARGET))
    paths = {name: tmp_path / f"{name}.csv" for name in ("fit", "moved", "radians")}
    write_log(paths["fit"], fit.log, fit.platform)
    write_log(paths["moved"], moved.log, fit.platform)
    write_log(paths["radians"], _scaled(slice(3, 6), np.pi / 180)(moved.log), fit.platform)
    result = tmp_path / "r.json"
    common = ["--platform", "hobby-hexapod", "--out"]
    assert cli.main(["calibrate", *common, str(result), "--log", str(paths["fit"]), "--method", "ls"]) == 0
    capsys.readouterr()
    validate = ["validate", *common, str(tmp_path / "V.csv"), "--result", str(result), "--log"]
    assert cli.main([*validate, str(paths["radians"])]) == 2
    assert "look like radians, not degrees" in capsys.readouterr().err
    assert cli.main([*validate, str(paths["moved"])]) == 0
    hint = [line for line in capsys.readouterr().err.splitlines() if "looks moved" in line]
    assert len(hint) == 1 and "the instrument frame looks moved since the calibration" in hint[0], hint
    assert hint[0].endswith("add --register-instrument")
    assert cli.main([*validate, str(paths["fit"])]) == 0
    assert "looks moved" not in capsys.readouterr().err  # the calibration's own session: nothing moved


def _calibrated_then_moved(tmp_path, capsys) -> tuple[dict, Path, list[str]]:
    """A hobby session calibrated by ls (``fit.csv``) and another day's log with the cameras moved
    (``moved.csv``): the logs' paths, the result's, and the ``--platform … --out`` arguments."""
    fit = _pose_case()
    moved = idata.make_case(idata.hobby(), 60, 3, InstrumentTruth(FRAME + [8.0, -5.0, 3.0, 1.0, 0.5, -2.0], TARGET))
    paths = {name: tmp_path / f"{name}.csv" for name in ("fit", "moved")}
    write_log(paths["fit"], fit.log, fit.platform)
    write_log(paths["moved"], moved.log, fit.platform)
    result = tmp_path / "r.json"
    common = ["--platform", "hobby-hexapod", "--out"]
    assert cli.main(["calibrate", *common, str(result), "--log", str(paths["fit"]), "--method", "ls"]) == 0
    capsys.readouterr()
    return paths, result, common


def test_validate_verdict_through_a_moved_frame_blames_the_frame_not_the_robot(tmp_path, capsys):
    """Where validate names a moved frame ("not the robot"), its verdict does not hold the errors through
    that frame against the tolerance (calling the motion over and asking for more poses): it says the
    frame moved and what to add."""
    paths, result, common = _calibrated_then_moved(tmp_path, capsys)
    validate = ["validate", *common, str(tmp_path / "V.csv"), "--result", str(result), "--log", str(paths["moved"])]
    for report in ([], ["--report", str(tmp_path / "report")]):  # the report reads the log whole: named there too
        assert cli.main([*validate, "--tolerance-mm", "1", *report]) == 0  # the prediction's motion: 0.2–0.65 mm
        captured = capsys.readouterr()
        assert "the instrument frame looks moved since the calibration" in captured.err, (report, captured.err)
        verdict = [line for line in captured.out.splitlines() if "verdict:" in line]
        assert len(verdict) == 1, captured.out
        assert "above the predicted registered error" not in verdict[0], verdict[0]
        assert "motion within" in verdict[0] and "more poses" not in verdict[0], verdict[0]
        assert "looks moved" in verdict[0] and "--register-instrument" in verdict[0], verdict[0]


def test_validate_without_register_names_each_sides_frame_and_compares_no_moved_one(tmp_path, capsys):
    """Without --register-instrument the nominal model's frame and target are fitted to the held-out log
    (12 unknowns) while the calibrated model reads it through the calibration's: on the README's hobby
    log, moved cameras and all, the line read "nominal → calibrated model: x 3.671 → 7.743 mm" —
    "calibration made it 2× worse". Where the moved-frame hint fires, the nominal model's figures stand
    alone, the calibrated model's not set beside them; on the calibration's own session (nothing moved)
    the comparison stands with each side's frame named."""
    paths, result, common = _calibrated_then_moved(tmp_path, capsys)
    validate = ["validate", *common, str(tmp_path / "V.csv"), "--result", str(result), "--log"]
    assert cli.main([*validate, str(paths["moved"])]) == 0
    (line,) = [line for line in capsys.readouterr().err.splitlines() if "pose error RMS" in line]
    assert "→" not in line and "calibrated model's, which through the calibration's instrument frame" in line, line
    assert line.startswith(
        "stewart-calib validate: pose error RMS, nominal model, its instrument frame and target(s) fitted to this "
        "log: x "
    ), line
    assert line.endswith("(add --register-instrument to compare the two alike)"), line
    assert cli.main([*validate, str(paths["fit"])]) == 0
    (line,) = [line for line in capsys.readouterr().err.splitlines() if "pose error RMS" in line]
    assert line.startswith(
        "stewart-calib validate: pose error RMS, nominal → calibrated model (nominal: instrument frame and target(s) "
        "fitted to this log; calibrated: through the calibration's): x "
    ), line
    assert cli.main([*validate, str(paths["moved"]), "--register-instrument"]) == 0  # alike: as before
    (line,) = [line for line in capsys.readouterr().err.splitlines() if "pose error RMS" in line]
    assert line.startswith("stewart-calib validate: pose error RMS, nominal → calibrated model: x "), line
