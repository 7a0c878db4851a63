"""``stewart-calib reproduce [--out DIR] [--quick]``: the paper's experiments, simulated, in closed loop.

Runs ``configs/experiments/paper.toml`` (``--quick``: ``quick.toml``, a few seconds) before
calibration, with ``ls`` calibrated once at no load and frozen, and with ``paper-ekf``, ``ekf``
and ``isam2`` online through all load stages, using the estimator settings of
``configs/estimators/paper.toml``. Writes into DIR (default ``out``), each file atomically:

* ``tables.md`` — Tables 4, 5, 6 and the headline improvements, ours beside the paper's;
* ``results.json`` — every number, per-stage per-method details, run time, versions, seed;
* ``reproduce.rrd`` — the rerun recording (scene, parameters, pose errors, trajectories).

Progress bars (the run before calibration, then the methods' runs) go to stderr when it is a terminal.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from ..config import load_estimator_config
from ..errors import CalibError
from ..io import atomic_path, atomic_write_text
from ..reproduction import reproduce, results_dict, tables_markdown, write_recording
from ..resources import CONFIGS
from ..simulation import load_experiment
from . import run_command


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "reproduce",
        description="Simulate the paper's load stages in closed loop for ls (frozen at no load), paper-ekf, ekf "
        "and isam2 (online); write DIR/tables.md, DIR/results.json and DIR/reproduce.rrd.",
    )
    parser.add_argument("--out", default="out", metavar="DIR", help="output directory (default: out)")
    parser.add_argument("--quick", action="store_true", help="the small quick.toml experiment (a few seconds)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise CalibError(f"{out}: cannot create output directory ({err.strerror or err.__class__.__name__})") from None
    experiment = load_experiment(CONFIGS / "experiments" / ("quick.toml" if args.quick else "paper.toml"))
    config = load_estimator_config(CONFIGS / "estimators" / "paper.toml")
    reproduction = reproduce(experiment, config, progress=True)
    with atomic_path(out / "reproduce.rrd") as tmp:
        write_recording(tmp, reproduction)
    results = results_dict(reproduction, time.perf_counter() - start)
    atomic_write_text(out / "results.json", json.dumps(results, indent=1, ensure_ascii=False) + "\n")
    atomic_write_text(out / "tables.md", tables_markdown(results))
    print(f"reproduced '{experiment.name}' in {results['run_time_s']:.1f} s into {out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_command("reproduce", argv)
