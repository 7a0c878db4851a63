"""``stewart-calib simulate --experiment E.toml --out DIR``: simulate an experiment, write its files.

Writes into DIR (created if needed), each file atomically:

* ``platform.toml`` — the nominal platform (spec §2), what estimators are given;
* ``log.csv`` — the measurement log (spec §3) with desired poses, stages and payload;
* ``truth.csv`` — the true drive parameters and true poses, row for row (spec §4).

The robot is driven by its nominal model (uncalibrated, as in the paper before calibration).
Same experiment file → identical files. A tqdm bar goes to stderr when it is a terminal.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import CalibError
from ..io import atomic_write_text, write_log, write_truth
from ..platform import platform_to_toml
from ..simulation.closed_loop import run_experiment
from ..simulation.experiment import load_experiment


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "simulate",
        help="simulate an experiment (true robot, load, tracker) and write platform, log and truth",
        description="Simulate the experiment of E.toml in closed loop with the nominal model; "
        "write DIR/platform.toml, DIR/log.csv and DIR/truth.csv.",
    )
    parser.add_argument("--experiment", required=True, metavar="E.toml")
    parser.add_argument("--out", required=True, metavar="DIR")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    experiment = load_experiment(args.experiment)
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise CalibError(f"{out}: cannot create output directory ({err.strerror or err.__class__.__name__})") from None
    result = run_experiment(experiment, progress=True)
    atomic_write_text(out / "platform.toml", platform_to_toml(experiment.platform))
    write_log(out / "log.csv", result.log)
    write_truth(out / "truth.csv", result.truth)
    print(f"simulated {len(result.log)} samples of '{experiment.name}' into {out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    from ..cli import main as cli_main

    return cli_main(["simulate", *(argv or [])])
