"""Predicted errors against the truth: ``calibrate``, ``identifiability``, ``plan`` and ``validate``.

Three instruments, each on a robot rigid and elastic: **tracker** — nim-stewart with its in-situ
tracker (readings 2 µm, strokes 1 µm: the default config's noise; its geometry exact); **pose** — the
hobby hexapod with motion capture (0.2 mm / 0.05°); **points** — the hobby hexapod with a laser tracker
on three reflectors (50 µm); the outside instruments' frame 60 mm / 10° off its nominal, the stroke scale
off by σ 3 %. Every drive parameter off by σ 0.5 mm. **Elastic**: the platform weighs 15 kg (nim-stewart,
2.33 mm/kN a leg) or 2 kg (hobby, 100 mm/kN), ``[elastic]`` in the platform file ``simulate`` writes
(compliance identified from nominal 0), and the calibration poses are measured twice, without and with
a payload (40 kg, 2 kg) in ``load_kg``. Per seed, through the CLI (``stewart_calib.cli.main``, default
config): ``simulate`` 60 random calibration poses (80 % of the workspace box) and 30 held-out ones (0 kg);
``calibrate --method ls``, ``calibrate --method ekf`` (the online method, its prediction that of its
estimate given the log through an outside instrument) and ``identifiability --log`` on the calibration
poses; ``validate`` of the
result on the held-out poses (``--tolerance-mm``: the result's expected mean of what validate measures);
``plan --n 60 --seed S`` on the same platform file, then the same robot ``simulate``d at the planned poses
(``[poses] calibration_file``, 0 kg: a pose list carries no payload) and calibrated (``--skip-bad-rows``:
where the true robot's tracker reads beyond its range at a planned pose, the simulated tracker reads
nothing).

**The truth**: the result's drive (its IK, under the platform's weight) commands the workspace poses of
``analysis.accuracy.evaluation_poses`` and home; the true robot (its parameters moved into the estimate's
gauge where the instrument is outside, the true stroke scale and compliance) settles at the strokes. Its
mean position error absolute in {J} and of the motion from home, against each command's 90 % band of
the same, and through an outside instrument its **registered** error (its noise-free readings of the
poses reached, the instrument's frame and target(s) fitted to them by its own least squares, the
readings' error left) against calibrate's registered band; ``validate``'s measured RMS beyond the
instrument's noise (through an outside instrument with ``--register-instrument``) with the 90 % interval
it states from the noise's spread over its rows: the truth's at its own held-out poses (RMS of the
registered error through an outside instrument, absolute with the tracker) in it, and it meeting the
result's band of the same;
its verdict is wrong where it says "within" of a truth over the tolerance or "over" of one within
(absolute place and motion). Ratios: medians over the seeds of one command's expected mean error over
another's for the same poses (calibrate ÷ identifiability on the log, calibrate on the planned poses ÷
plan). Targets: a band's row needs the hits of 20 seeds an honest 90 % band falls below 4 % of the time
(16 of 20; "90 % of seeds" is the binomial's mean, missed by an honest band in 32 % of rows); every band pooled
holds 90 % within two standard errors, and its misses above and below within two standard deviations of
an even split (a band too small or too large on one side; the deviation's variance taken seed by seed, as
a seed's bands share its truth).

``python -m benchmarks.prediction [--seeds N] [--quick]`` prints the table; ``python -m benchmarks --only
prediction`` saves it as the section of BENCHMARKS.md.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import re
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmarks.common import Row, Section, Table, seeded_main
from stewart_calib import cli
from stewart_calib.analysis.accuracy import evaluation_poses
from stewart_calib.instruments import gauge, instrument_kind, outside_model, registration
from stewart_calib.io import read_log
from stewart_calib.io.platform_file import load_platform
from stewart_calib.model import kinematics as kin
from stewart_calib.model.drive import COMPLIANCE, STROKE_SCALE, drive_model
from stewart_calib.model.rotations import motion_error
from stewart_calib.pipelines.handover import calibrated_model
from stewart_calib.pipelines.score import closed_loop_poses
from stewart_calib.simulation.closed_loop import simulate_blocks
from stewart_calib.simulation.experiment import load_experiment

SEEDS, QUICK_SEEDS = 20, 2
CALIBRATION_POSES, HELD_OUT_POSES = 60, 30
QUICK_POSES = 30
IN_BAND_TARGET = 0.9
#: a row of one band over the seeds fails an honest 90 % band at most this often (:func:`seeds_needed`)
ROW_FALSE_FAIL = 0.1
#: the ratio of two commands' predictions for the same poses counts as agreeing within this factor
RATIO_TARGET = 1.25
#: validate's tolerance: this many times the result's expected mean of what validate measures
TOLERANCE_FACTOR = 1.0


@dataclass(frozen=True)
class Setup:
    """An instrument's robot: platform, the experiment's ``[instrument]`` (empty: the in-situ tracker),
    the stroke scale's spread, the elastic robot's ``[load]`` and the payload of its second pass."""

    platform: str
    instrument: str
    stroke_scale_spread: float
    load: str
    payload_kg: float


HOBBY_LOAD = (
    "platform_mass_kg = 2.0\nplatform_com_mm = [0.0, 0.0, -10.0]\npayload_com_mm = [10.0, 5.0, 20.0]\n"
    "leg_N_per_mm = 10.0\nbase_joint_N_per_mm = 1e6\nplatform_joint_N_per_mm = 1e6"
)
FRAME_OFFSET = "frame_offset = [60.0, -30.0, 20.0, 10.0, -5.0, 120.0]"
SETUPS = {
    "tracker": Setup("nim-stewart", "", 0.0, "platform_mass_kg = 15.0", 40.0),
    "pose": Setup(
        "hobby-hexapod",
        f'[instrument]\nkind = "pose"\nposition_sigma_mm = 0.2\norientation_sigma_deg = 0.05\n{FRAME_OFFSET}',
        0.03,
        HOBBY_LOAD,
        2.0,
    ),
    "points": Setup(
        "hobby-hexapod",
        '[instrument]\nkind = "points"\nposition_sigma_mm = 0.05\n'
        f"targets_mm = [[40.0, 0.0, 5.0], [-20.0, 35.0, 5.0], [-20.0, -35.0, 8.0]]\n{FRAME_OFFSET}",
        0.03,
        HOBBY_LOAD,
        2.0,
    ),
}
MODELS = ("rigid", "elastic")

EXPERIMENT = """name = "prediction"
seed = {seed}
platform = "{platform}"
sample_period_s = 0.1
[robot]
errors = "random"
random_spread_mm = 0.5
stroke_scale_spread = {scale}
encoder_noise_mm = 0.001
[load]
{load}
[tracker]
noise_mm = 0.002
quantum_mm = 0.0
geometry_residual_mm = 0.0
[poses]
{poses}
workspace_fraction = 0.8
{instrument}
{stages}"""


def _stage(name: str, load_kg: float, segment: str) -> str:
    return f'[[stages]]\nname = "{name}"\nload_kg = {load_kg!r}\nsegments = ["{segment}"]\n'


def experiment_text(setup: Setup, elastic: bool, seed: int, poses: int, planned: bool) -> str:
    """The experiment of one seed: random calibration poses (twice, without and with the payload, on
    the elastic robot) and held-out ones, or ``planned``: the poses of ``plan.csv``, without a payload."""
    if planned:
        pose_lines, stages = 'calibration_file = "plan.csv"\nvalidation = 0', _stage("fit", 0.0, "calibration")
    else:
        pose_lines = f"calibration = {poses}\nvalidation = {HELD_OUT_POSES}"
        stages = _stage("fit", 0.0, "calibration")
        if elastic:
            stages += _stage("fit-loaded", setup.payload_kg, "calibration")
        stages += _stage("held-out", 0.0, "validation")
    return EXPERIMENT.format(
        seed=seed,
        platform=setup.platform,
        scale=setup.stroke_scale_spread,
        load=setup.load if elastic else "platform_mass_kg = 0.0",
        poses=pose_lines,
        instrument=setup.instrument,
        stages=stages,
    )


def _run(argv: list) -> str:
    """A command's standard output (its standard error dropped); an exit status other than 0 raises."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = cli.main([str(a) for a in argv])
    if status != 0:
        raise RuntimeError(f"{argv[0]} exited with {status}: {err.getvalue()}")
    return out.getvalue()


def split_log(log: Path, parts: dict[str, tuple[str, ...]]) -> None:
    """Write the rows of ``log`` whose ``stage`` is one of ``parts[name]`` to ``log``'s directory ``name``."""
    with open(log, newline="", encoding="utf-8") as handle:
        rows = list(csv.reader(handle))
    stage = rows[0].index("stage")
    for name, stages in parts.items():
        with open(log.parent / name, "w", newline="", encoding="utf-8") as handle:
            csv.writer(handle).writerows([rows[0], *(row for row in rows[1:] if row[stage] in stages)])


def true_drive(platform, experiment: Path):
    """The simulated robot as a drive model: its unloaded parameters (moved into the estimate's gauge
    where the instrument is outside), true stroke scale and, elastic, true compliance."""
    robot = simulate_blocks(load_experiment(experiment)).robot  # drawn, nothing simulated yet
    params = robot.base_params
    if instrument_kind(platform).outside:
        params, _, _ = gauge.to_gauge(platform.drive, params)
    terms = {STROKE_SCALE: robot.stroke_scale}
    if platform.elastic is not None:
        terms[COMPLIANCE] = platform.elastic.true_compliance_mm_per_kN
    return drive_model(platform).true_drive(params - platform.drive.as_vector(), terms)


def closed_loop(commanded, true, poses: np.ndarray, home: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pose ``(absolute, motion from home)`` position error [mm] of the ``true`` robot settled at the
    strokes IK of ``commanded`` gives (both under the platform's weight, no payload: score's closed loop)."""
    R, t = kin.pose_to_rt(np.vstack([poses, home]))
    reached_R, reached_t = closed_loop_poses(commanded, true, np.vstack([poses, home]))
    absolute, _ = kin.pose_error(R[:-1], t[:-1], reached_R[:-1], reached_t[:-1])
    motion, _ = motion_error(
        (R[-1], t[-1]), (R[:-1], t[:-1]), (reached_R[-1], reached_t[-1]), (reached_R[:-1], reached_t[:-1])
    )
    return absolute, motion


def registered_error(platform, commanded, true, poses: np.ndarray) -> np.ndarray:
    """Per pose the position error [mm] the platform's outside instrument sees of the ``true`` robot
    settled at the strokes IK of ``commanded`` gives, after the best registration: its noise-free
    readings of the poses reached, its frame and target(s) fitted to them at the desired poses (plain
    least squares, the instrument's own fit), the readings' error left."""
    model = outside_model(platform)
    R, t = kin.pose_to_rt(poses)
    reached, _ = true.settled_kinematics(commanded.inverse_kinematics(R, t), None, guess=(R, t))
    readings = model.predicted_readings(model.nominal_unknowns(), reached.R, reached.t)
    seen = model.seen_channels(reached.R, reached.t)
    readings = np.where(seen, readings, np.nan)
    fitted = registration.refine(model, model.nominal_unknowns(), readings, R, t, frame_only=False)
    return model.prediction_errors(fitted, R, t, readings)[1]


NUMBER = r"([0-9.e+-]+)"
PLAN_LINE = re.compile(
    rf"absolute place in \{{J\}} {NUMBER} mm .*?\(90 ?%: {NUMBER}–{NUMBER} mm\), motion from home {NUMBER} mm "
    rf".*?\(90 ?%: {NUMBER}–{NUMBER} mm\)"
)
VALIDATE_LINE = re.compile(
    r"verdict: .*validate measured the (error as the instrument sees it after registration \(its frame and target\(s\) "
    r"fitted again to this log\)|absolute place in "
    rf"\{{J\}}): position RMS {NUMBER} mm.*? noise alone leaves {NUMBER} mm.*?; beyond it {NUMBER} mm "
    rf"\(90 ?%: {NUMBER}–{NUMBER} mm\).*?; against [0-9.e+-]+ mm: "
    r"motion (within|over|not sure), absolute place (within|over|not sure)"
)


def _column(path: Path, name: str) -> int:
    with open(path, encoding="utf-8") as handle:
        return handle.readline().rstrip("\n").split(",").index(name)


def plan_prediction(stdout: str) -> dict:
    """``plan``'s printed prediction as the result's field (expected means and 90 % bands)."""
    found = PLAN_LINE.search(stdout)
    if found is None:
        raise RuntimeError(f"plan printed no prediction: {stdout!r}")
    a, a_low, a_high, m, m_low, m_high = (float(v) for v in found.groups())
    return {
        "position_mm": a,
        "position_band_mm": [a_low, a_high],
        "motion_position_mm": m,
        "motion_position_band_mm": [m_low, m_high],
    }


def in_band(predicted: dict, absolute: float, motion: float) -> dict:
    low, high = predicted["position_band_mm"]
    m_low, m_high = predicted["motion_position_band_mm"]
    return {
        "absolute_in_band": bool(low <= absolute <= high),
        "motion_in_band": bool(m_low <= motion <= m_high),
        "absolute_mm": predicted["position_mm"],
        "motion_mm": predicted["motion_position_mm"],
        "absolute_band_mm": [low, high],
        "motion_band_mm": [m_low, m_high],
    }


def run_seed(name: str, elastic: bool, seed: int, work: Path, poses: int) -> dict:
    """One seed of an instrument's robot: every command's prediction beside the truth."""
    setup = SETUPS[name]
    (work / "e.toml").write_text(experiment_text(setup, elastic, seed, poses, planned=False))
    _run(["simulate", "--experiment", work / "e.toml", "--out", work / "sim"])
    sim = work / "sim"
    stages = ("fit", "fit-loaded")
    split_log(sim / "log.csv", {"fit.csv": stages, "held-out.csv": ("held-out",)})
    platform_path = sim / "platform.toml"
    platform = load_platform(platform_path)
    true = true_drive(platform, work / "e.toml")
    home = platform.workspace.home
    workspace = evaluation_poses(platform)
    started = time.process_time()
    _run(
        ["calibrate", "--platform", platform_path, "--log", sim / "fit.csv", "--method", "ls", "--out", work / "r.json"]
    )
    calibrate_s = time.process_time() - started
    _run(["identifiability", "--platform", platform_path, "--log", sim / "fit.csv", "--json", work / "i.json"])
    result = json.loads((work / "r.json").read_text())
    commanded = calibrated_model(platform, str(work / "r.json"))
    absolute, motion = (float(np.mean(v)) for v in closed_loop(commanded, true, workspace, home))
    out = {"seed": seed, "absolute_mm": absolute, "motion_mm": motion, "calibrate_cpu_s": calibrate_s}
    out["calibrate"] = in_band(result["predicted_closed_loop"], absolute, motion)
    argv = ["calibrate", "--platform", platform_path, "--log", sim / "fit.csv", "--method", "ekf"]
    _run([*argv, "--out", work / "re.json"])
    online = json.loads((work / "re.json").read_text())["predicted_closed_loop"]
    e_absolute, e_motion = (
        float(np.mean(v)) for v in closed_loop(calibrated_model(platform, str(work / "re.json")), true, workspace, home)
    )
    out["ekf"] = in_band(online, e_absolute, e_motion)
    out["ekf"].update({"truth_absolute_mm": e_absolute, "truth_motion_mm": e_motion})
    outside = instrument_kind(platform).outside
    if outside:  # the truth as the instrument sees it after registration, over the workspace poses
        out["registered_mm"] = float(np.mean(registered_error(platform, commanded, true, workspace)))
        low, high = result["predicted_closed_loop"]["registered_position_band_mm"]
        out["calibrate"]["registered_mm"] = result["predicted_closed_loop"]["registered_position_mm"]
        out["calibrate"]["registered_in_band"] = bool(low <= out["registered_mm"] <= high)
        out["calibrate"]["registered_band_mm"] = [low, high]
    identified = json.loads((work / "i.json").read_text())["predicted_closed_loop"]
    out["identifiability"] = in_band(identified, absolute, motion)

    # validate on the held-out poses (the frame fitted again through an outside instrument), against a
    # tolerance from the result's own prediction of what it measures
    predicted = result["predicted_closed_loop"]
    measures = "registered_position_mm" if outside else "position_mm"
    tolerance = TOLERANCE_FACTOR * predicted[measures]
    printed = _run(
        [
            "validate",
            "--platform",
            platform_path,
            "--result",
            work / "r.json",
            "--log",
            sim / "held-out.csv",
            "--out",
            work / "v.csv",
            "--tolerance-mm",
            f"{tolerance:.6g}",
            *(["--register-instrument"] if outside else []),
        ]
    )
    found = VALIDATE_LINE.search(printed)
    if found is None:
        raise RuntimeError(f"validate printed no verdict: {printed!r}")
    what, _, noise, seen, seen_low, seen_high, motion_word, absolute_word = found.groups()
    rms = float(
        np.sqrt(
            np.nanmean(
                np.loadtxt(
                    work / "v.csv", delimiter=",", skiprows=1, usecols=_column(work / "v.csv", "position_error_mm")
                )
                ** 2
            )
        )
    )
    held_out = read_log(sim / "held-out.csv", platform).desired_poses
    held_absolute, _ = closed_loop(commanded, true, held_out, home)
    truth_here = registered_error(platform, commanded, true, held_out) if outside else held_absolute
    key = "registered_position_band_mm" if outside else "position_band_mm"
    truth_rms = float(np.sqrt(np.mean(truth_here**2)))
    interval = float(seen_low), float(seen_high)
    out["validate"] = {
        "measures": what,
        "rms_mm": float(rms),
        "noise_mm": float(noise),
        "seen_mm": float(seen),
        "seen_interval_mm": interval,
        "truth_rms_mm": truth_rms,
        "truth_in_interval": bool(interval[0] <= truth_rms <= interval[1]),
        "seen_in_band": bool(interval[0] <= predicted[key][1] and interval[1] >= predicted[key][0]),
        "tolerance_mm": tolerance,
        "words": [motion_word, absolute_word],
        "wrong": [
            (word == "within" and truth > tolerance) or (word == "over" and truth <= tolerance)
            for word, truth in ((motion_word, motion), (absolute_word, absolute))
        ],
    }

    # plan, then the same robot measured at the planned poses and calibrated
    planned = _run(["plan", "--platform", platform_path, "--n", poses, "--out", work / "plan.csv", "--seed", seed])
    (work / "p.toml").write_text(experiment_text(setup, elastic, seed, poses, planned=True))
    _run(["simulate", "--experiment", work / "p.toml", "--out", work / "planned"])
    # a true robot off its nominal may still read beyond the tracker's range at a planned pose (plan's
    # margin covers a robot built within the prior; the simulated tracker then reads nothing), rows a user skips
    _run(
        [
            "calibrate",
            "--platform",
            platform_path,
            "--log",
            work / "planned" / "log.csv",
            "--method",
            "ls",
            "--out",
            work / "rp.json",
            "--skip-bad-rows",
        ]
    )
    result_planned = json.loads((work / "rp.json").read_text())
    out["planned_rows_skipped"] = int(result_planned.get("samples_skipped", 0))
    commanded = calibrated_model(platform, str(work / "rp.json"))
    p_absolute, p_motion = (float(np.mean(v)) for v in closed_loop(commanded, true, workspace, home))
    out["plan"] = in_band(plan_prediction(planned), p_absolute, p_motion)
    out["planned"] = in_band(result_planned["predicted_closed_loop"], p_absolute, p_motion)
    out["planned"].update({"truth_absolute_mm": p_absolute, "truth_motion_mm": p_motion})
    return out


def _below(n: int, k: int, p: float = IN_BAND_TARGET) -> float:
    """``P(X < k)`` for ``X ~ Binomial(n, p)``: an honest band's chance of fewer than ``k`` hits in ``n``."""
    return sum(math.comb(n, j) * p**j * (1.0 - p) ** (n - j) for j in range(k))


def seeds_needed(n: int) -> int:
    """The hits of ``n`` seeds a band row needs: the most ``k`` with ``P(X < k) ≤`` :data:`ROW_FALSE_FAIL`
    for the hits ``X ~ Binomial(n, 0.9)`` of an honest 90 % band. "≥ 90 % of seeds" itself is the
    binomial's mean, which an honest band misses in more than a quarter of rows of 10 seeds (26 %: each
    row a coin with a quarter's bias); 8 of 10 it misses in 7 % (at 20 seeds 16 of them, 4 %; at 30, 25, 7 %). A band
    too narrow on one side shows in the pooled rows (:func:`pooled_row`, :func:`sides_row`), whose
    hundreds of bands hold the share to 90 % within two standard errors and the misses to both sides."""
    k = 0
    while k < n and _below(n, k + 1) <= ROW_FALSE_FAIL:
        k += 1
    return k


def _target(n: int, each: bool = False) -> str:
    need = seeds_needed(n)
    return (
        f"≥ {need}/{n} seeds{' each' if each else ''} (an honest 90 % band falls below {need} of {n} with "
        f"probability {_below(n, need):.2f})"
    )


def _share(runs: list[dict], command: str, what: str) -> int:
    return sum(r[command][f"{what}_in_band"] for r in runs)


def _ratio(runs: list[dict], top: str, bottom: str, what: str) -> float:
    return float(np.median([r[top][f"{what}_mm"] / r[bottom][f"{what}_mm"] for r in runs]))


def rows_of(label: str, runs: list[dict]) -> list[Row]:
    """The rows of one instrument's robot (see the module docstring), each not met with its why."""
    rows = _rows(label, runs)
    why = _why(label, runs)
    for row in rows:
        if row.met is False:
            row.why = next((text for part, text in why.items() if part in row.name), "") or _outside_band(row, runs)
    return rows


#: the truth of each command's band: its keys in a run (absolute, motion)
TRUTHS = {
    "calibrate": ("absolute_mm", "motion_mm"),
    "identifiability": ("absolute_mm", "motion_mm"),
    "plan": ("planned.truth_absolute_mm", "planned.truth_motion_mm"),
    "ekf": ("ekf.truth_absolute_mm", "ekf.truth_motion_mm"),
}


def _outside_band(row: Row, runs: list[dict]) -> str:
    """A band row's why where no cause is known: :func:`_outside_band_text` of its command."""
    command = next((c for c in TRUTHS if f"{c}'s 90 % band" in row.name), None)
    return "" if command is None else _outside_band_text(runs, command)


def _outside_band_text(runs: list[dict], command: str) -> str:
    """How often the truth fell above and below ``command``'s band (against its expected mean), and how
    likely that many misses are for an honest band."""
    parts = []
    for what, key in zip(("absolute", "motion"), TRUTHS[command], strict=True):
        missed = [r for r in runs if not r[command][f"{what}_in_band"]]
        above = sum(_dig(r, tuple(key.split("."))) > r[command][f"{what}_mm"] for r in missed)
        parts.append(f"{what} {len(missed)} outside ({above} above, {len(missed) - above} below)")
    n = len(runs)
    need = seeds_needed(n)
    chance = _below(n, need)
    return (
        f"{'; '.join(parts)} of {n} seeds; an honest 90 % band misses more than {n - need} of {n} with "
        f"probability {chance:.2f} for each of the two."
    )


def _why(label: str, runs: list[dict]) -> dict[str, str]:
    """Why a row of ``label`` may miss its target, by a part of its name, with this run's numbers."""
    if label.startswith("tracker"):
        planned = _ratio(runs, "planned", "plan", "absolute"), _ratio(runs, "planned", "plan", "motion")
        skipped = sum(r["planned_rows_skipped"] for r in runs)
        ls = (
            "calibrate --method ls with the in-situ tracker whitens each pose's rows by the readings' and strokes' "
            "noise (generalised least squares, the leg-length maximum likelihood to first order, whose Cramér–Rao "
            f"bound plan and identifiability state): on plan's poses its own covariance predicts {planned[0]:.2g}× / "
            f"{planned[1]:.2g}× the bound's error (absolute / motion), the bound's own to the data's noise scale s "
            "(its spread over 6·60 − 42 residual degrees of freedom: ±4 %)"
        )
        over = {
            command: [
                float(np.median([r[key] / r[command][f"{key}"] for r in runs])) for key in ("absolute_mm", "motion_mm")
            ]
            for command in ("calibrate", "identifiability")
        }
        return {
            **_validate_why(runs),
            "calibrate's 90 % band": (
                f"the truth is {over['calibrate'][0]:.2f}× / {over['calibrate'][1]:.2f}× calibrate's expected error "
                "(median, absolute / motion); ls's covariance with the tracker is that of its fit whitened by the "
                "readings' and strokes' noise through forward kinematics, exact to first order (tests/test_ls.py "
                "draws it; measured aside over seeds 0–39, the estimate's error against it χ² 42.6 ± 1.5 on average "
                "against its 42 degrees of freedom, the truth in calibrate's band in 36 / 34 of 40 seeds, 2 / 3 above "
                "and 2 / 3 below, absolute / motion), so a band missed in more than one seed in ten is the band's "
                f"own spread over {len(runs)} seeds or the prediction's mean over the workspace against the truth's. "
            )
            + _outside_band_text(runs, "calibrate"),
            "identifiability's 90 % band": (
                f"the truth is {over['identifiability'][0]:.2f}× / {over['identifiability'][1]:.2f}× "
                "identifiability's expected error (median, absolute / motion), its misses above the band: "
                f"identifiability states the Cramér–Rao bound of the leg-length form, the truth is that of {ls}."
            ),
            "÷ plan": ls + ".",
            "plan's 90 % band": (
                f"the truth is that of {ls}; plan keeps the tracker's readings inside their range by twice the "
                f"spread a robot built within the prior puts on them, and {skipped} planned pose(s) over the seeds "
                "read beyond it on the true robot and were skipped."
            ),
        }
    identified = _ratio(runs, "identifiability", "calibrate", "absolute")
    why = (
        {}
        if "elastic" not in label
        else {
            "identifiability's 90 % band": (
                f"identifiability's expected absolute error is {identified:.2f}× calibrate's on the same log (median); "
                "its bound is taken at the log's own ls fit, the settled pose Jacobian at the fitted compliance, "
                "the same point as calibrate's covariance; its misses are the band's spread over the seeds. "
            )
            + _outside_band_text(runs, "identifiability")
        }
    )
    registered = [r["registered_mm"] / r["calibrate"]["registered_mm"] for r in runs]
    missed = [v for r, v in zip(runs, registered, strict=True) if not r["calibrate"]["registered_in_band"]]
    outside = sum(v > 1 for v in missed), sum(v <= 1 for v in missed)
    return {
        **why,
        "calibrate's registered 90 % band": (
            f"the truth's registered error is {np.median(registered):.2f}× calibrate's prediction of it (median; "
            f"{sum(v > 1 for v in registered)} of {len(runs)} above); of the seeds outside the band {outside[0]} "
            f"above, {outside[1]} below; an honest band leaves {max(outside)} or more of {len(runs)} on one side "
            f"with probability {1.0 - _below(len(runs), max(outside), 0.05):.3f}."
            + (
                " Measured aside over seeds 0–39 (the same simulation, ls alone): the estimate's error against its "
                "covariance over the free drive directions χ² 42.9 ± 1.5 on average against its 42 degrees of "
                "freedom, its mean square in the registered error's directions 1.04 ± 0.06× the covariance's, and "
                "the truth in calibrate's registered band in 33 of 40 seeds (4 above, 3 below); seeds 0–9 alone "
                "χ² 48.7 and 1.34×: ls's covariance is honest there, these ten seeds drew large errors."
                if label == "pose, elastic"
                else ""
            )
        ),
        **_validate_why(runs),
    }


def _validate_why(runs: list[dict]) -> dict[str, str]:
    """Why validate's rows may miss: where the truth fell against its interval, and what the interval is of."""
    noise = float(np.median([r["validate"]["noise_mm"] / r["validate"]["rms_mm"] for r in runs]))
    missed = [r["validate"] for r in runs if not r["validate"]["truth_in_interval"]]
    above = sum(v["truth_rms_mm"] > v["seen_interval_mm"][1] for v in missed)
    outside = runs[0]["validate"]["measures"].startswith("error")
    sees = (
        "through the frame fitted again on the held-out log and the target(s) the calibration fitted, the truth's "
        "registered error with the best frame and target(s) fitted at the held-out poses: the two differ by where "
        "the target(s) were fitted"
        if outside
        else "the absolute place in {J}, the truth's at the same poses"
    )
    return {
        "validate's stated 90 % interval": (
            f"the truth above the interval in {above}, below in {len(missed) - above} of {len(runs)} seeds; "
            f"validate sees {sees}; the noise is {noise:.0%} of its RMS (median)."
        ),
        "meets the result's 90 % band": (
            "the result's band is of a mean over the workspace, validate's interval of an RMS over its 30 poses; "
            f"validate sees {sees}."
        ),
    }


def _rows(label: str, runs: list[dict]) -> list[Row]:
    n = len(runs)
    need = seeds_needed(n)
    rows = []
    for command, truth in (
        ("calibrate", "the truth"),
        ("identifiability", "the truth"),
        ("plan", "the truth at its poses"),
        ("ekf", "the truth of calibrate --method ekf"),
    ):
        a, m = _share(runs, command, "absolute"), _share(runs, command, "motion")
        rows.append(
            Row(
                f"{label}: {truth} in {command}'s 90 % band (absolute / motion)",
                f"{a}/{n} / {m}/{n}",
                _target(n, each=True),
                bool(a >= need and m >= need),
            )
        )
    if "registered_in_band" in runs[0]["calibrate"]:
        registered = sum(r["calibrate"]["registered_in_band"] for r in runs)
        rows.append(
            Row(
                f"{label}: the truth's registered error in calibrate's registered 90 % band",
                f"{registered}/{n}",
                _target(n),
                bool(registered >= need),
            )
        )
    seen = [r["validate"]["seen_mm"] / r["validate"]["truth_rms_mm"] for r in runs]
    covered = sum(r["validate"]["truth_in_interval"] for r in runs)
    what = "absolute place in {J}" if runs[0]["validate"]["measures"].startswith("absolute") else "registered error"
    rows.append(
        Row(
            f"{label}: the truth's RMS at its poses in validate's stated 90 % interval of the {what} (noise out)",
            f"{covered}/{n} (validate's own ÷ the truth's, median {np.median(seen):.3g}×)",
            _target(n),
            bool(covered >= need),
        )
    )
    banded = sum(r["validate"]["seen_in_band"] for r in runs)
    rows.append(
        Row(
            f"{label}: validate's 90 % interval of the {what} meets the result's 90 % band",
            f"{banded}/{n}",
            _target(n),
            bool(banded >= need),
        )
    )
    wrong = sum(any(r["validate"]["wrong"]) for r in runs)
    rows.append(
        Row(
            f"{label}: validate's verdict at {TOLERANCE_FACTOR:g}× the predicted error (wrong: motion or absolute)",
            f"wrong in {wrong}/{n}",
            f"≤ {1 - IN_BAND_TARGET:.0%} of seeds",
            bool(wrong <= n - math.ceil(IN_BAND_TARGET * n)),
        )
    )
    ratios = {
        key: (_ratio(runs, top, bottom, "absolute"), _ratio(runs, top, bottom, "motion"))
        for key, top, bottom in (("identifiability", "calibrate", "identifiability"), ("plan", "planned", "plan"))
    }
    for key, (a, m) in ratios.items():
        rows.append(
            Row(
                f"{label}: calibrate ÷ {key} for the same poses (absolute / motion, median)",
                f"{a:.3g} / {m:.3g}",
                f"within {RATIO_TARGET:g}× of 1",
                bool(all(1 / RATIO_TARGET <= v <= RATIO_TARGET for v in (a, m))),
            )
        )
    return rows


def section(quick: bool = False, seeds: int | None = None) -> Section:
    seeds = seeds or (QUICK_SEEDS if quick else SEEDS)
    poses = QUICK_POSES if quick else CALIBRATION_POSES
    runs: dict[str, list[dict]] = {}
    for name in SETUPS:
        for model in MODELS:
            label = f"{name}, {model}"
            for seed in range(seeds):
                with tempfile.TemporaryDirectory() as directory:
                    runs.setdefault(label, []).append(run_seed(name, model == "elastic", seed, Path(directory), poses))
    return section_of(runs, seeds)


def _coverages(run: dict) -> list[bool]:
    """Each stated 90 % band of one seed against its truth: calibrate's, identifiability's, plan's and ekf's
    (absolute and motion), calibrate's registered one, validate's interval."""
    covered = [run[command][f"{what}_in_band"] for command in TRUTHS for what in ("absolute", "motion")]
    if "registered_in_band" in run["calibrate"]:
        covered.append(run["calibrate"]["registered_in_band"])
    return [*covered, run["validate"]["truth_in_interval"]]


def pooled_row(runs: dict[str, list[dict]]) -> Row:
    """Every band of every instrument's robot and seed, pooled: a row per instrument misses ≥ 90 % by
    chance alone in a quarter of runs of 10 seeds, the pool of several hundred rarely. Its target is
    what honest 90 % bands keep: a share no lower than 90 % less two standard errors of a share of that
    many (an honest pool falls below it 2 % of the time; the bands of one seed share its truth and are
    not independent, which would widen the error — taken as independent, the target is the stricter)."""
    covered = [c for group in runs.values() for run in group for c in _coverages(run)]
    share = sum(covered) / len(covered)
    lowest = IN_BAND_TARGET - 2.0 * math.sqrt(IN_BAND_TARGET * (1.0 - IN_BAND_TARGET) / len(covered))
    row = Row(
        "every stated 90 % band against its truth, pooled over the instruments, robots and seeds",
        f"{sum(covered)}/{len(covered)} ({share:.1%})",
        f"≥ {lowest:.1%} ({IN_BAND_TARGET:.0%} less two standard errors of a share of {len(covered)})",
        bool(share >= lowest),
    )
    if not row.met:
        missed = {label: sum(not c for run in group for c in _coverages(run)) for label, group in runs.items()}
        row.why = "misses by instrument and robot: " + ", ".join(f"{label} {k}" for label, k in missed.items()) + "."
    return row


def _sides(run: dict) -> list[int]:
    """Where each band of :func:`_coverages` left its truth: +1 above, −1 below, 0 within (above or below
    the band's expected mean where the band itself is not in the run)."""
    sides = []
    for command, keys in TRUTHS.items():
        for what, key in zip(("absolute", "motion"), keys, strict=True):
            if not run[command][f"{what}_in_band"]:
                sides.append(1 if _dig(run, tuple(key.split("."))) > run[command][f"{what}_mm"] else -1)
            else:
                sides.append(0)
    if "registered_in_band" in run["calibrate"]:
        inside = run["calibrate"]["registered_in_band"]
        sides.append(0 if inside else (1 if run["registered_mm"] > run["calibrate"]["registered_mm"] else -1))
    validate = run["validate"]
    inside = validate["truth_in_interval"]
    sides.append(0 if inside else (1 if validate["truth_rms_mm"] > validate["seen_interval_mm"][1] else -1))
    return sides


def sides_row(runs: dict[str, list[dict]]) -> Row:
    """The pooled misses by side: an honest band leaves 5 % of its truths above it and 5 % below, so the
    misses above less those below have mean 0; one side's prediction too small or too large (an omitted
    noise term, a spread too narrow) tips them. The bands of one seed of one robot are not independent:
    they share its truth, and calibrate's and identifiability's are one prediction, so where one misses
    the others mostly miss on the same side. The difference's variance is therefore taken seed by seed
    (each seed's misses above less below, ``d_s``: ``Σ d_s²``, the cluster-robust variance; ``m``, the
    number of misses, where every miss is independent). Target: ``|above − below| ≤ 2 √(Σ d_s²)`` (an
    honest pool beyond it 5 % of the time)."""
    per_seed = [_sides(run) for group in runs.values() for run in group]
    sides = [side for seed in per_seed for side in seed]
    above, below = sides.count(1), sides.count(-1)
    limit = 2.0 * math.sqrt(sum(sum(seed) ** 2 for seed in per_seed))
    row = Row(
        "the pooled misses of every stated 90 % band: truth above against below",
        f"{above} above, {below} below",
        f"|above − below| ≤ {limit:.3g} (two standard deviations of the difference, its variance summed over the "
        f"{len(per_seed)} seeds of the robots: {2.0 * math.sqrt(above + below):.3g} were the {above + below} misses "
        "independent)",
        bool(abs(above - below) <= limit),
    )
    if not row.met:
        by = {
            label: (
                sum(s == 1 for run in group for s in _sides(run)),
                sum(s == -1 for run in group for s in _sides(run)),
            )
            for label, group in runs.items()
        }
        # calibrate's and identifiability's bands are one prediction (their ratio within a few per cent) of
        # one truth: where one misses the other mostly does too, on the same side
        paired = [
            side
            for group in runs.values()
            for run in group
            for side, twin in zip(_sides(run)[0:2], _sides(run)[2:4], strict=True)
            if side == twin != 0
        ]
        up, down = above - paired.count(1), below - paired.count(-1)
        row.why = (
            "above / below by instrument and robot: "
            + ", ".join(f"{k} {a}/{b}" for k, (a, b) in by.items())
            + f"; {len(paired)} of the misses are calibrate's and identifiability's bands of one seed missing on "
            f"the same side together (one prediction, within a few per cent, of one truth): counted once, "
            f"{up} above, {down} below against |above − below| ≤ {2.0 * math.sqrt(up + down):.3g}."
        )
    return row


def _family_text(runs: dict[str, list[dict]], seeds: int) -> str:
    """How likely honest bands leave some one of the section's band rows below its need: each of its
    ``B`` bands a seed (:func:`_coverages`, over the instruments and robots) falls below :func:`seeds_needed`
    with probability ``p``, so some one of them with ``1 − (1 − p)^B`` (taken as independent; the bands of
    one seed share its truth, which lowers it)."""
    bands = sum(len(_coverages(group[0])) for group in runs.values())
    chance = _below(seeds, seeds_needed(seeds))
    return (
        f"The section judges {bands} bands so, {seeds} seeds each: honest bands leave some one of them below its "
        f"need with probability {1.0 - (1.0 - chance) ** bands:.2f}; the pooled rows below are the test of the "
        "bands together."
    )


def section_of(runs: dict[str, list[dict]], seeds: int) -> Section:
    """The section of measured ``runs`` (by instrument and robot, one a seed): rows, whys and the table."""
    rows = [row for label, group in runs.items() for row in rows_of(label, group)]
    family = _family_text(runs, seeds)
    for row in rows:
        if row.met is False and "90 %" in row.name:
            row.why = f"{row.why} {family}".strip()
    rows.append(pooled_row(runs))
    rows.append(sides_row(runs))
    cells = []
    for label, group in runs.items():
        median = lambda *keys, group=group: float(np.median([_dig(r, keys) for r in group]))  # noqa: E731
        cells.append(
            [
                label,
                f"{median('absolute_mm'):.3g} / {median('motion_mm'):.3g}",
                f"{median('calibrate', 'absolute_mm'):.3g} / {median('calibrate', 'motion_mm'):.3g}",
                f"{median('identifiability', 'absolute_mm'):.3g} / {median('identifiability', 'motion_mm'):.3g}",
                f"{median('planned', 'truth_absolute_mm'):.3g} / {median('planned', 'truth_motion_mm'):.3g}",
                f"{median('plan', 'absolute_mm'):.3g} / {median('plan', 'motion_mm'):.3g}",
                f"{median('ekf', 'truth_absolute_mm'):.3g} / {median('ekf', 'truth_motion_mm'):.3g}",
                f"{median('ekf', 'absolute_mm'):.3g} / {median('ekf', 'motion_mm'):.3g}",
                f"{median('validate', 'rms_mm'):.3g} ({median('validate', 'noise_mm'):.3g}) / "
                f"{median('validate', 'truth_rms_mm'):.3g}",
            ]
        )
    table = Table(
        f"Medians over {seeds} seed(s) [mm]",
        [
            "instrument, robot",
            "truth: absolute / motion",
            "calibrate predicts",
            "identifiability predicts",
            "truth at plan's poses",
            "plan predicts",
            "truth of ekf's result",
            "ekf predicts",
            "validate's RMS (noise) / truth's RMS at its poses",
        ],
        cells,
    )
    note = __doc__.split("\n\n", 1)[1].rsplit("\n\n", 1)[0].replace("\n\n", " ").replace("\n", " ")
    return Section("Predicted errors against the truth", note, rows, {"runs": runs, "seeds": seeds}, [table])


def _dig(record: dict, keys: tuple[str, ...]) -> float:
    for key in keys:
        record = record[key]
    return float(record)  # type: ignore[arg-type]


def main(argv: list[str] | None = None) -> int:
    return seeded_main("prediction", __doc__, section, SEEDS, argv)


if __name__ == "__main__":
    raise SystemExit(main())
