"""Do the predicted errors agree with each other and cover the truth? (motion and absolute apart)

On simulated rigid hobby hexapods (every parameter off by σ 0.5 mm, stroke scale 3 %; no weight, so the
truth file's drive is the robot's at every pose) seen
by a motion-capture pose and by three laser-tracker points, each seed is simulated, calibrated
(``calibrate --method ls``, default config) and assessed by ``identifiability --log`` on the same
log. The truth's mean error over the workspace poses of :func:`stewart_calib.analysis.accuracy.evaluation_poses`
is measured by closing the loop — the controller commands IK of the estimate, the true robot
executes it (``score``'s closed loop, the truth moved into the estimate's gauge) — absolute in {J}
and of the motion from the workspace's home. A row counts the seeds whose truth lies in the 90 %
band each command states, and the ratio of calibrate's expected mean to identifiability's.

``python -m benchmarks.prediction [--seeds N]`` prints a markdown table.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from stewart_calib import cli
from stewart_calib.analysis.accuracy import evaluation_poses
from stewart_calib.instruments import gauge
from stewart_calib.io import read_result, read_truth
from stewart_calib.io.platform_file import load_platform
from stewart_calib.model import kinematics as kin
from stewart_calib.model import rotations
from stewart_calib.model.drive import drive_model

EXPERIMENT = """
name = "prediction"
seed = {seed}
platform = "hobby-hexapod"
[robot]
errors = "random"
random_spread_mm = 0.5
stroke_scale_spread = 0.03
[load]
platform_mass_kg = 0.0
[poses]
calibration = 60
validation = 0
workspace_fraction = 0.8
[instrument]
{instrument}
frame_offset = [60.0, -30.0, 20.0, 10.0, -5.0, 120.0]
[[stages]]
name = "fit"
segments = ["calibration"]
"""

INSTRUMENTS = {
    "pose": 'kind = "pose"\nposition_sigma_mm = 0.2\norientation_sigma_deg = 0.05',
    "points": 'kind = "points"\nposition_sigma_mm = 0.05\n'
    "targets_mm = [[40.0, 0.0, 5.0], [-20.0, 35.0, 5.0], [-20.0, -35.0, 8.0]]",
}


def true_errors(platform, result: dict, truth) -> tuple[float, float]:
    """``(absolute, motion)`` mean position error [mm] over the workspace poses of the robot the
    truth holds when the controller commands IK of the result's drive (the truth in its gauge)."""
    true_params, _, _ = gauge.to_gauge(platform.drive, truth.params[-1])
    nominal = drive_model(replace(platform, elastic=None))  # the rigid drive of the truth, as score takes it
    fitted = {term.key: np.array(result[term.key]["estimate"]) for term in nominal.terms if term.key in result}
    commanded = nominal.calibrated(np.asarray(result["estimate"]) - platform.drive.as_vector(), fitted)
    true = nominal.true_drive(true_params - platform.drive.as_vector(), truth.drive_terms)
    poses = np.vstack([evaluation_poses(platform), platform.workspace.home])
    R_d, t_d = kin.pose_to_rt(poses)
    reached = true.forward_kinematics(true.inputs(commanded.inverse_kinematics(R_d, t_d)), guess=(R_d, t_d))
    absolute, _ = kin.pose_error(R_d[:-1], t_d[:-1], reached.R[:-1], reached.t[:-1])
    # the motion from home: (reached home)⁻¹ reached X against H⁻¹ X
    _, moved = rotations.compose(*rotations.inverse(reached.R[-1], reached.t[-1]), reached.R[:-1], reached.t[:-1])
    _, wanted = rotations.compose(*rotations.inverse(R_d[-1], t_d[-1]), R_d[:-1], t_d[:-1])
    return float(np.mean(absolute)), float(np.mean(np.linalg.norm(moved - wanted, axis=1)))


def _quiet(argv: list) -> int:
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        return cli.main([str(a) for a in argv])


def run_seed(kind: str, seed: int, work: Path) -> dict:
    (work / "e.toml").write_text(EXPERIMENT.format(seed=seed, instrument=INSTRUMENTS[kind]))
    assert _quiet(["simulate", "--experiment", work / "e.toml", "--out", work / "sim"]) == 0
    platform_path, log = work / "sim" / "platform.toml", work / "sim" / "log.csv"
    assert (
        _quiet(["calibrate", "--platform", platform_path, "--log", log, "--method", "ls", "--out", work / "r.json"])
        == 0
    )
    assert _quiet(["identifiability", "--platform", platform_path, "--log", log, "--json", work / "i.json"]) == 0
    platform, result = load_platform(platform_path), read_result(work / "r.json")
    absolute, motion = true_errors(platform, result, read_truth(work / "sim" / "truth.csv"))
    predictions = {
        "calibrate": result["predicted_closed_loop"],
        "identifiability": json.loads((work / "i.json").read_text())["predicted_closed_loop"],
    }
    row = {"absolute": absolute, "motion": motion}
    for command, predicted in predictions.items():
        low, high = predicted["position_band_mm"]
        m_low, m_high = predicted["motion_position_band_mm"]
        row[f"{command}_absolute_in_band"] = low <= absolute <= high
        row[f"{command}_motion_in_band"] = m_low <= motion <= m_high
        row[f"{command}_absolute_mm"] = predicted["position_mm"]
        row[f"{command}_motion_mm"] = predicted["motion_position_mm"]
    return row


def table(rows: dict[str, list[dict]]) -> list[str]:
    lines = [
        "| instrument | seeds | truth absolute / motion [mm] | calibrate: in 90 % band (abs / motion) | "
        "identifiability: in band (abs / motion) | calibrate ÷ identifiability (abs / motion) |",
        "|---|---|---|---|---|---|",
    ]
    for kind, runs in rows.items():
        n = len(runs)

        def share(key: str, runs=runs) -> str:
            return f"{sum(r[key] for r in runs)}/{len(runs)}"

        def median(key: str, runs=runs) -> float:
            return float(np.median([r[key] for r in runs]))

        ratio = [
            np.median([r[f"calibrate_{what}_mm"] / r[f"identifiability_{what}_mm"] for r in runs])
            for what in ("absolute", "motion")
        ]
        lines.append(
            f"| {kind} | {n} | {median('absolute'):.3g} / {median('motion'):.3g} | "
            f"{share('calibrate_absolute_in_band')} / {share('calibrate_motion_in_band')} | "
            f"{share('identifiability_absolute_in_band')} / {share('identifiability_motion_in_band')} | "
            f"{ratio[0]:.3g} / {ratio[1]:.3g} |"
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--instrument", choices=tuple(INSTRUMENTS), action="append")
    args = parser.parse_args(argv)
    rows: dict[str, list[dict]] = {}
    for kind in args.instrument or INSTRUMENTS:
        for seed in range(args.seeds):
            with tempfile.TemporaryDirectory() as directory:
                rows.setdefault(kind, []).append(run_seed(kind, seed, Path(directory)))
    print("\n".join(table(rows)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
