"""``stewart-calib reproduce [--out DIR] [--quick]``: the paper's experiments, simulated, in closed loop.

Runs ``configs/experiments/paper.toml`` (``--quick``: ``quick.toml``, a few seconds) before
calibration, with ``ls`` calibrated once at no load and frozen, and with ``paper-ekf``, ``ekf``
and ``isam2`` online through all load stages, using the estimator settings of
``configs/estimators/paper.toml``; then ``ekf`` and ``isam2`` again with each part of the model of
:data:`PARTS` added in turn (the tracker's own geometry identified: ``paper-tracker.toml``; then
the legs' compliance under the platform's weight and the payload: ``paper-elastic.toml`` on the
platform with ``[elastic]``). Writes into DIR
(default ``out``), each file atomically:

* ``tables.md`` — Tables 4, 5, 6 and the headline improvements, ours beside the paper's;
* ``results.json`` — every number, per-stage per-method details, run time, versions, seed;
* ``reproduce.rrd`` — the rerun recording (scene, parameters, pose errors, trajectories);
* ``fig5_<run>.png`` … ``fig9_polar.png`` — the paper's Figs. 5–9 (:mod:`stewart_calib.reproduction.figures`);
* ``index.html`` — tables.md and the figures on one static page (no server, no network).

The methods' runs share ``--jobs`` worker processes (default: the CPUs this process may use, at
most :data:`MAX_JOBS`; ``--quick``: one). Progress bars (the run before calibration, the methods'
runs, the figures) go to stderr when it is a terminal.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

from ..config import load_estimator_config
from ..errors import CalibError, shown, without_noise
from ..io import atomic_path, atomic_write_text
from ..model.platform import Platform
from ..progress import progress_bar
from ..reproduction import Part, index_html, reproduce, results_dict, tables_markdown, write_figures, write_recording
from ..reproduction.figures import RunFigures, draw_in, figures
from ..reproduction.runs import WorkerPool
from ..resources import CONFIGS
from ..simulation import load_experiment
from ..simulation.experiment import Experiment
from ..simulation.load import elastic_of
from . import run_command

#: the estimator settings of ls, paper-ekf and the online methods' rigid runs
CONFIG = "paper.toml"


def elastic_platform(experiment: Experiment) -> Platform:
    """The experiment's platform with the ``[elastic]`` table (spec §10) its builder can write: the
    platform's mass and the centres of mass of the load model, the nominal compliance 0 at its
    default prior σ. The simulator's true compliance is left out: no estimator is given it."""
    elastic = elastic_of(experiment.load)
    if elastic is None:
        raise CalibError(f"{experiment.name}: the elastic part needs [load] platform_mass_kg > 0")
    return replace(experiment.platform, elastic=replace(elastic, true_compliance_mm_per_kN=None))


#: the parts of the model added one by one to ekf and isam2: (name, what it adds, settings, the
#: estimator's platform or None for the experiment's)
PARTS: tuple[tuple[str, str, str, Callable[[Experiment], Platform] | None], ...] = (
    ("tracker", "the tracker's own geometry identified", "paper-tracker.toml", None),
    ("elastic", "the legs' compliance under weight and payload identified", "paper-elastic.toml", elastic_platform),
)


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "reproduce",
        description="Simulate the paper's load stages in closed loop for ls (frozen at no load), paper-ekf, ekf "
        "and isam2 (online); write DIR/tables.md, DIR/results.json and DIR/reproduce.rrd.",
    )
    parser.add_argument("--out", default="out", metavar="DIR", help="output directory (default: out)")
    parser.add_argument("--quick", action="store_true", help="the small quick.toml experiment (a few seconds)")
    parser.add_argument(
        "--jobs",
        type=int,
        default=None,
        metavar="N",
        help="processes for the methods' runs (default: the CPUs this process may use, at most "
        f"{MAX_JOBS}; --quick: 1)",
    )
    parser.set_defaults(func=run)


#: more processes than this gain nothing: the longest run (isam2 with every part) is about a third
#: of the methods' total, so from 3 processes on it alone sets the wall time.
MAX_JOBS = 3


def _jobs(args: argparse.Namespace) -> int:
    if args.jobs is not None:
        if args.jobs < 1:
            raise CalibError(f"--jobs: expected a positive number of processes, got {args.jobs}")
        return args.jobs
    if args.quick:  # a few seconds of runs: starting processes would cost more than it saves
        return 1
    return max(
        1, min(MAX_JOBS, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)
    )


def run(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    workers = _jobs(args)
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise CalibError(f"{out}: cannot create output directory ({err.strerror or err.__class__.__name__})") from None
    experiment = load_experiment(CONFIGS / "experiments" / ("quick.toml" if args.quick else "paper.toml"))
    config = load_estimator_config(CONFIGS / "estimators" / CONFIG)
    parts = tuple(
        Part(
            name,
            description,
            load_estimator_config(CONFIGS / "estimators" / file),
            f"configs/estimators/{file}",
            platform,
        )
        for name, description, file, platform in PARTS
    )
    draw = RunFigures.of(experiment.platform.prismatic_drive("the paper's figures"), parts)
    with WorkerPool(workers) if workers > 1 else contextlib.nullcontext() as pool:
        reproduction = reproduce(experiment, config, progress=True, parts=parts, workers=pool or 1, draw=draw)
        drawing = {} if pool is None else draw_in(pool, reproduction)
        with atomic_path(out / "reproduce.rrd") as tmp:
            write_recording(tmp, reproduction)
        reproduction.drawn.update({name: future.result() for name, future in drawing.items()})
    with progress_bar(total=len(figures(reproduction)), desc="reproduce: figures", unit="figure") as bar:
        written = write_figures(out, reproduction, bar)
    results = results_dict(reproduction, time.perf_counter() - start, f"configs/estimators/{CONFIG}")
    atomic_write_text(out / "results.json", json.dumps(without_noise(results), indent=1, ensure_ascii=False) + "\n")
    tables = tables_markdown(results)
    atomic_write_text(out / "tables.md", tables)
    atomic_write_text(out / "index.html", index_html(tables, written, "reproduce.rrd"))
    print(
        f"stewart-calib reproduce: reproduced '{shown(experiment.name)}' in {results['run_time_s']:.1f} s into "
        f"{shown(out)}"
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_command("reproduce", argv)
