"""``stewart-calib simulate --experiment E.toml --out DIR``: simulate an experiment, write its files.

Writes into DIR (created if needed), each file atomically:

* ``platform.toml`` — the nominal platform (spec §2), what estimators are given, with the
  experiment's masses and centres of mass and the truth of the legs' compliance as ``[elastic]``
  (spec §10; :func:`stewart_calib.simulation.load.elastic_of`);
* ``log.csv`` — the measurement log (spec §3) with desired poses, stages and payload;
* ``truth.csv`` — the true drive parameters and true poses, row for row (spec §4), and an elastic
  robot's unloaded drive (``unloaded_j1x …``, its compliance in ``platform.toml``);

``--controller nominal`` (default) drives the robot with IK of its nominal model (uncalibrated, as
in the paper before calibration); ``--controller frozen --result R.json`` drives it with IK of
the calibrated model ``nominal + error`` of a result JSON (spec §5), i.e. a compensated robot
whose model stays frozen while the load changes; an elastic result's (spec §10: its compliance and
every other identified term) under each stage's payload, its legs' give compensated. Same experiment
file (and result) → identical files. A tqdm bar goes to stderr when it is a terminal.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

from ..errors import CalibError, shown
from ..instruments import instrument_kind
from ..io import atomic_paths, log_text, output_directory, read_calibrated_drive, truth_text
from ..io.platform_file import platform_to_toml
from ..model import kinematics as kin
from ..model.drive import drive_model
from ..model.platform import Platform, vector_to_params
from ..simulation.closed_loop import FrozenController, NominalController, simulate_blocks
from ..simulation.experiment import load_experiment
from ..simulation.load import elastic_of
from . import run_command


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "simulate",
        description="Simulate the experiment of E.toml in closed loop with the nominal model, or "
        "with a calibrated model frozen from a result JSON; write DIR/platform.toml, DIR/log.csv "
        "and DIR/truth.csv.",
    )
    parser.add_argument("--experiment", required=True, metavar="E.toml")
    parser.add_argument("--out", required=True, metavar="DIR")
    parser.add_argument(
        "--controller",
        choices=("nominal", "frozen"),
        default="nominal",
        help="drive with IK of the nominal model (default) or of the model in --result, frozen",
    )
    parser.add_argument("--result", metavar="R.json", help="calibration result (spec §5) for --controller frozen")
    parser.set_defaults(func=run)


def controller_for(args: argparse.Namespace, platform: Platform):
    """The controller ``--controller`` asks for (``--result`` read and checked against ``platform``, the
    platform file simulate writes: with ``[elastic]``, a result's compliance is applied under each stage's
    payload)."""
    if args.controller == "nominal":
        if args.result is not None:
            raise CalibError("--result is only used with --controller frozen")
        return NominalController(platform)
    if args.result is None:
        raise CalibError("--controller frozen needs --result R.json (a calibration result)")
    drive = read_calibrated_drive(args.result, platform)
    return FrozenController(drive.legs, drive if drive.elastic is not None else None)


def written_platform(experiment) -> Platform:
    """The platform file simulate writes for ``experiment``: its nominal platform with the truth of the legs'
    compliance as ``[elastic]`` (a rotary drive is simulated rigid: none, spec §15)."""
    rotary = experiment.platform.drive.kind == "rotary"
    return replace(experiment.platform, elastic=None if rotary else elastic_of(experiment.load))


class _OutOfRange:
    """Samples whose strokes (or tracker readings) leave the platform's ranges: a log its own
    platform would refuse row by row, so the experiment is refused instead (no file written)."""

    def __init__(self, platform):
        self._ranges = [("strokes", "drive.stroke_range_mm", platform.stroke_range)]
        if not instrument_kind(platform).outside:  # a leg set's readings have a range
            self._ranges.append(("readings", "tracker.reading_range_mm", platform.reading_range))
        self.count, self._excess_mm, self._worst = 0, 0.0, ("", "", (0.0, 0.0), 0.0)

    def add(self, log) -> None:
        bad = np.zeros(len(log), dtype=bool)
        for column, key, bounds in self._ranges:
            if bounds is None or not len(log):
                continue
            values = np.asarray(getattr(log, column))
            excess = np.maximum(bounds[0] - values, values - bounds[1])  # > 0 outside [mm]
            bad |= (excess > 0).any(axis=1)
            k = np.unravel_index(np.argmax(excess), excess.shape)
            if excess[k] > self._excess_mm:
                self._excess_mm, self._worst = float(excess[k]), (column, key, bounds, float(values[k]))
        self.count += int(bad.sum())

    def refuse(self, source, total: int) -> None:
        if self.count:
            column, key, (low, high), value = self._worst
            raise CalibError(
                f"{shown(source)}: {self.count} of {total} samples need {column} outside the platform's {key} "
                f"[{low:g}, {high:g}] (up to {value:.4g} mm); expected poses within reach (a smaller workspace or "
                "trajectory)"
            )


def run(args: argparse.Namespace) -> int:
    experiment = load_experiment(args.experiment)
    platform = written_platform(experiment)
    controller = controller_for(args, platform)
    # the three files appear together or not at all, and a directory made for them goes again
    # on a failure (a full disk, a signal): no partial output
    with (
        output_directory(args.out) as out,
        atomic_paths([out / "log.csv", out / "truth.csv", out / "platform.toml"]) as (
            log_path,
            truth_path,
            platform_path,
        ),
    ):
        run = simulate_blocks(experiment, controller, progress=True)
        outside = _OutOfRange(experiment.platform)
        with open(log_path, "w", encoding="utf-8") as log_file, open(truth_path, "w", encoding="utf-8") as truth_file:
            # written a block at a time as the blocks are simulated: a run holds its schedule and noise, not its text
            squares = {"controller": np.zeros(4), "nominal": np.zeros(4)}
            counts = {"controller": np.zeros(4), "nominal": np.zeros(4)}
            for k, (log, truth) in enumerate(run.blocks):
                outside.add(log)
                log_file.write(log_text(log, experiment.platform, header=k == 0))
                truth_file.write(truth_text(truth, header=k == 0, platform=experiment.platform))
                errors = _pose_errors(experiment.platform, log, truth, args.controller != "nominal")
                for name, values in errors.items():
                    squares[name] += np.nansum(values**2, axis=0)
                    counts[name] += np.sum(np.isfinite(values), axis=0)
        outside.refuse(experiment.source, len(run.plan.t_s))
        platform_path.write_text(platform_to_toml(platform), encoding="utf-8")
    print(
        f"stewart-calib simulate: simulated {len(run.plan.t_s)} samples of '{shown(experiment.name)}' "
        f"({args.controller} controller) into {shown(out)}"
    )
    print(f"stewart-calib simulate: {_pose_error_line(squares, counts, args.controller)}")
    return 0


def _pose_errors(platform: Platform, log, truth, compare: bool) -> dict[str, np.ndarray]:
    """``(n, 4)`` true minus desired position ``x, y, z`` [mm] and rotation angle [deg] of a
    block: the controller's (the simulated robot's true poses) and, with ``compare``, what the
    nominal controller would have reached there: IK of the nominal model, executed by the true
    robot of each sample (its parameters and stroke scale from the truth; the settling of the
    closed loop left out)."""
    R_d, t_d = kin.pose_to_rt(log.desired_poses)
    R_true, t_true = kin.pose_to_rt(truth.true_poses)
    out = {"controller": np.column_stack([t_true - t_d, kin.pose_error(R_d, t_d, R_true, t_true)[1]])}
    if compare:
        # rigid, as the truth's per-sample parameters already carry the sag (spec §4)
        nominal = drive_model(replace(platform, elastic=None))
        logged = nominal.inverse_kinematics(R_d, t_d)
        if platform.drive.kind == "rotary":  # rigid: one true drive for every sample
            true = nominal.true_drive(truth.params[0] - nominal.legs.as_vector(), truth.drive_terms)
            reached = true.forward_kinematics(logged, guess=(R_d, t_d), strict=False)
        else:
            extensions = nominal.true_drive(np.zeros(nominal.n_params), truth.drive_terms).extensions(logged)
            legs = vector_to_params(truth.params)
            reached = kin.forward_kinematics_per_pose(
                legs[:, :, :3], legs[:, :, 3:6], legs[:, :, 6], extensions, (R_d, t_d), strict=False
            )
        ok = reached.converged
        error = np.full((len(R_d), 4), np.nan)
        error[ok] = np.column_stack(
            [reached.t[ok] - t_d[ok], kin.pose_error(R_d[ok], t_d[ok], reached.R[ok], reached.t[ok])[1]]
        )
        out["nominal"] = error  # NaN where the true robot cannot reach the nominal strokes
    return out


def _pose_error_line(squares: dict[str, np.ndarray], counts: dict[str, np.ndarray], controller: str) -> str:
    """The true pose's error from the desired one, RMS per axis and of the rotation: with the
    nominal model → with the controller's (``frozen``), or the nominal controller's alone."""
    rms = {name: np.sqrt(values / np.maximum(counts[name], 1)) for name, values in squares.items()}

    names, units = ("x", "y", "z", "rotation"), ("mm", "mm", "mm", "°")
    if controller == "nominal":
        parts = [f"{names[k]} {rms['controller'][k]:.4g} {units[k]}" for k in range(4)]
        return f"pose error RMS (true − desired), nominal controller: {', '.join(parts)}".replace(" °", "°")
    pairs = [f"{names[k]} {rms['nominal'][k]:.4g} → {rms['controller'][k]:.4g} {units[k]}" for k in range(4)]
    pairs = [pair.replace(" °", "°") for pair in pairs]
    return f"pose error RMS (true − desired), nominal → {controller} controller: {', '.join(pairs)}"


def main(argv: list[str] | None = None) -> int:
    return run_command("simulate", argv)
