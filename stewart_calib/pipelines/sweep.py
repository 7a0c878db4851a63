"""``stewart-calib sweep --spec S.toml --out DIR [--scheduler tcp://HOST:PORT] [--workers N]`` (spec §9).

Runs every cell × seed of the grid in S.toml (:mod:`stewart_calib.sweep.spec`) as independent
tasks on Dask distributed — an embedded local cluster of N worker processes (default: one per
core), or the workers of the scheduler at ``--scheduler`` — and writes into DIR:

* ``parts/`` — one Parquet file per finished task, written as it finishes;
* ``results.parquet`` — one row per (cell, method, seed): the settings, ``rms_mm``,
  ``rms_over_crb``, ``nees``, ``z2``, closed-loop errors, ``seconds`` (:mod:`stewart_calib.sweep.task`);
* ``summary.csv``, ``summary.md``, ``plots/`` — quantiles per cell and method, and plots.

Running the same command again skips the finished tasks (resume); so does a spec that only
adds seeds or grid values, or the full command after a ``--seeds N`` pilot. A tqdm bar goes to stderr
when it is a terminal.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from . import run_command

#: a local cluster's worker processes per core at most: they share this machine's cores and memory
#: (~200 MB each); a thousand on two cores never finish starting, and 10⁴⁰⁰ end in a traceback
WORKERS_PER_CORE = 4


def _workers(text: str) -> int:
    limit = WORKERS_PER_CORE * (os.cpu_count() or 1)
    try:
        value = int(text)
    except ValueError:
        value = 0
    if not 1 <= value <= limit:
        raise argparse.ArgumentTypeError(
            f"expected a whole number of worker processes from 1 to {limit} ({WORKERS_PER_CORE} per core), got {text!r}"
        )
    return value


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "sweep",
        description="Run every cell × seed of the sweep spec S.toml on Dask distributed (a local cluster, or "
        "--scheduler), writing DIR/results.parquet, DIR/summary.md and DIR/plots/; rerun to resume.",
    )
    parser.add_argument("--spec", required=True, metavar="S.toml", help="the grid (e.g. configs/sweeps/smoke.toml)")
    parser.add_argument("--out", required=True, metavar="DIR")
    parser.add_argument(
        "--scheduler", metavar="tcp://HOST:PORT", help="a running Dask scheduler (default: a local cluster)"
    )
    parser.add_argument(
        "--workers",
        type=_workers,
        metavar="N",
        help=f"worker processes of the local cluster (default: one per core; at most {WORKERS_PER_CORE} per core)",
    )
    parser.add_argument(
        "--seeds",
        type=int,
        metavar="N",
        help="a pilot: only the first N seeds of every cell (the full command resumes from it)",
    )
    parser.add_argument(
        "--yes",
        action="store_true",
        help="start a study over the limits of 100 000 tasks or 24 CPU-hours (refused otherwise; docs/sweeps.md)",
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # Dask, pyarrow and matplotlib load only for this command.
    from ..sweep import load_spec, run_sweep
    from ..sweep.limits import MAX_CPU_HOURS, MAX_TASKS
    from ..sweep.runner import default_workers, plan_sweep
    from ..sweep.store import RESULTS
    from ..sweep.summary import write_summary

    spec = load_spec(args.spec)
    if args.seeds is not None:
        spec = spec.pilot(args.seeds)
    out = Path(args.out)
    plan = plan_sweep(spec, out, None if args.yes else MAX_TASKS, None if args.yes else MAX_CPU_HOURS)
    workers = args.workers if args.workers is not None else (None if args.scheduler else default_workers())
    print(f"stewart-calib sweep: {plan.describe(spec, workers)}", flush=True)
    report = run_sweep(spec, out, scheduler=args.scheduler, workers=args.workers, progress=True, plan=plan)
    write_summary(spec, report.table, out)
    print(
        f"stewart-calib sweep: {report.ran} tasks run, {report.skipped} already done, {len(report.failed)} failed "
        f"of {report.tasks}; {report.table.num_rows} rows in {out / RESULTS} ({report.seconds:.0f} s)"
    )
    if report.failed:
        print(
            f"stewart-calib sweep: {len(report.failed)} tasks failed (first: {report.failed[0]}); run the command "
            "again to retry them",
            file=sys.stderr,
        )
        return 1
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_command("sweep", argv)
