"""Run a sweep's tasks on Dask distributed: an embedded local cluster, or a scheduler's workers.

The client keeps a bounded window of tasks in flight (a few per worker thread, so a study of
tens of thousands of tasks never sits in the scheduler at once), writes each task's part the
moment it finishes (:mod:`.store`) and refills the window. Dask does the rest: a task on a
worker that dies is handed to another worker by the scheduler (``distributed.scheduler.
allowed-failures`` times), and a scheduler address instead of the local cluster changes
nothing else. Task keys are ``sweep-<cell id>-<seed>``: a client that reconnects after being
killed attaches to a task still running under the same key instead of starting it again.
"""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import pyarrow as pa
from tqdm import tqdm

from ..errors import CalibError
from . import store
from .limits import MAX_CPU_HOURS, MAX_TASKS
from .spec import SweepSpec, cost_kind
from .task import run_task

#: How long to wait for a named scheduler before giving up [s].
CONNECT_TIMEOUT_S = 5

#: Tasks in flight per worker thread: enough to keep every worker busy between refills.
IN_FLIGHT_PER_THREAD = 4

#: Finished parts read for the cost of past rows (enough for a mean, few enough to be quick).
COST_PARTS = 64


@dataclass
class SweepPlan:
    """What a run will do, known before any work (:func:`plan_sweep`).

    Attributes:
        tasks: the spec's tasks (cells × seeds).
        done: those whose part exists already.
        cpu_seconds: estimated CPU time of the methods on the unfinished tasks [s]: the
            methods' CPU per sample for the task's instrument and drive (:func:`~.spec.cost_kind`;
            ``cpu_seconds`` of past rows, or
            of a pilot task run here) times the samples of every unfinished task.
        basis: where the per-sample costs come from, for the plan line.
        pilots: the pilot tasks' rows (each written as its part when the run goes ahead).
        damaged: ``"<part>: <why>"`` of the parts found damaged (cut short): their tasks run again.
    """

    tasks: int
    done: int
    cpu_seconds: float
    basis: str
    pilots: list[list[dict]] = field(default_factory=list)
    damaged: list[str] = field(default_factory=list)

    def describe(self, spec: SweepSpec, workers: int | None) -> str:
        """The plan line: cells, seeds, tasks, the estimated CPU and, for a known number of workers, wall time."""
        line = (
            f"{spec.name}: {spec.n_cells:,} cells × {len(spec.seeds):,} seeds = {self.tasks:,} tasks "
            f"({self.done:,} already done"
            + (f"; {len(self.damaged):,} damaged parts computed again, first {self.damaged[0]}" if self.damaged else "")
            + f"); the methods' CPU ≈ {_duration(self.cpu_seconds)} ({self.basis})"
        )
        if workers and self.cpu_seconds > 0:
            line += f", ≈ {_duration(self.cpu_seconds / workers)} on {workers} workers"
        return line


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 2 * 3600:
        return f"{seconds / 60:.0f} min"
    if seconds < 2 * 86400:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.1f} days"


def plan_sweep(
    spec: SweepSpec,
    out: str | Path,
    max_tasks: int | None = MAX_TASKS,
    max_cpu_hours: float | None = MAX_CPU_HOURS,
) -> SweepPlan:
    """Count the tasks and estimate their CPU before any work; refuse a study over the limits.

    The count comes from the grid's axes, before a cell is built. The cost per sample of each
    instrument comes from the finished parts in ``out`` (their methods' ``cpu_seconds``), or
    else from one pilot task run in this process (the first unfinished task of that instrument;
    its rows are kept, see :attr:`SweepPlan.pilots`). A limit of None switches that check off
    (``--yes``).

    Raises:
        CalibError: one line naming the spec, the number of tasks or the CPU hours, and the limit.
    """
    out = Path(out)
    if max_tasks is not None and spec.n_tasks > max_tasks:
        raise CalibError(
            f"{spec.source}: {spec.n_tasks:,} tasks ({spec.n_cells:,} cells × {len(spec.seeds):,} seeds) is more "
            f"than the limit of {max_tasks:,}; shrink the grid, run a pilot with --seeds N, or pass --yes"
        )
    done, damaged = store.part_states(spec, out)
    todo = [(cell, seed) for cell, seed in spec.tasks() if (cell.id, seed) not in done]
    # an instrument sets a task's cost more than any other setting (motion capture and laser
    # trackers run the methods' general paths), and a rotary drive (numpy paths, no compiled
    # kernels): one cost per sample for each of their pairs
    past = store.past_cost(out, COST_PARTS)
    per_sample = {kind: cost for kind, (cost, _) in past.items()}
    said = [f"{count} finished {kind} tasks" for kind, (_, count) in past.items()]
    pilots = []
    for kind in dict.fromkeys(cost_kind(cell.settings) for cell, _ in todo):
        if kind in per_sample:
            continue
        cell, seed = next(task for task in todo if cost_kind(task[0].settings) == kind)
        rows = run_task(cell, seed, spec.methods, spec.checkpoints, spec.refit_at_checkpoints)
        cpu = sum(row["cpu_seconds"] for row in rows if row["cpu_seconds"] == row["cpu_seconds"])
        per_sample[kind] = cpu / cell.settings["samples"]
        pilots.append(rows)
        said.append(f"a {kind} pilot task: {cpu:.2g} CPU-s for {cell.settings['samples']} samples")
    basis = "; ".join(said) or "nothing left to run"
    cpu_seconds = sum(per_sample[cost_kind(cell.settings)] * cell.settings["samples"] for cell, _ in todo)
    if max_cpu_hours is not None and cpu_seconds > max_cpu_hours * 3600:
        raise CalibError(
            f"{spec.source}: {len(todo):,} tasks would take ≈ {cpu_seconds / 3600:,.0f} CPU-hours ({basis}), more "
            f"than the limit of {max_cpu_hours:g} CPU-hours; shrink the grid, run a pilot with --seeds N, or pass "
            f"--yes (docs/sweeps.md: on a cluster)"
        )
    return SweepPlan(len(spec.seeds) * spec.n_cells, len(done), cpu_seconds, basis, pilots, damaged)


@dataclass
class SweepReport:
    """What a run did: tasks in the spec, already finished before, run now, failed; the
    consolidated results (``table``, as in results.parquet); wall time [s]."""

    tasks: int
    skipped: int
    ran: int
    failed: list[str]
    table: pa.Table
    seconds: float


def default_workers() -> int:
    """Worker processes of the local cluster: the cores this process may use."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def connect(scheduler: str | None, workers: int | None):
    """A Dask client: to ``scheduler``, or to a new local cluster of ``workers`` processes.

    Raises:
        CalibError: the scheduler is not reachable within :data:`CONNECT_TIMEOUT_S` (one line
            with the address), or ``workers`` is given with a scheduler.
    """
    from distributed import Client, LocalCluster

    if scheduler is not None:
        if workers is not None:
            raise CalibError(
                "--workers sizes the local cluster only: the scheduler's workers are started on the cluster"
            )
        _probe(scheduler)
        try:
            return Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s", set_as_default=False)
        except (OSError, TimeoutError) as err:
            raise _unreachable(scheduler, err) from None
    n = default_workers() if workers is None else workers
    if n < 1:
        raise CalibError(f"--workers: expected at least 1 worker, got {n}")
    # One thread per process: the estimators are single-threaded numpy/numba/GTSAM, and
    # processes keep tasks apart (GIL, GTSAM's own state). Scheduler, workers and the dashboard
    # listen on the loopback only: they take no authentication, so on all interfaces anyone on
    # the network could watch and drive them (a study on other hosts uses --scheduler).
    cluster = LocalCluster(
        n_workers=n,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address="127.0.0.1:0",
        silence_logs=logging.ERROR,
    )
    return Client(cluster, set_as_default=False)


def _probe(scheduler: str) -> None:
    """Ask the address who it is before building a client: a malformed address, nothing
    listening, or something that is not a Dask scheduler is one line at once (a failed
    ``Client`` would retry until its timeout and then spend another ten seconds closing).

    Raises:
        CalibError: one line with the address.
    """
    from distributed.comm import connect as dask_connect
    from distributed.comm.addressing import parse_address, parse_host_port

    try:
        protocol, location = parse_address(scheduler, strict=True)
        host, port = parse_host_port(location)
    except ValueError as err:
        raise CalibError(f"--scheduler {scheduler!r}: expected tcp://HOST:PORT ({err})") from None
    if protocol == "tcp":  # Dask retries a refused connection until its timeout; the socket knows at once
        try:
            socket.create_connection((host, port), timeout=CONNECT_TIMEOUT_S).close()
        except OSError as err:
            raise _unreachable(scheduler, err) from None

    async def identity() -> dict:
        comm = await dask_connect(scheduler, timeout=CONNECT_TIMEOUT_S)
        try:
            await comm.write({"op": "identity"})
            return await comm.read()
        finally:
            await comm.close()

    try:
        reply = asyncio.run(asyncio.wait_for(identity(), CONNECT_TIMEOUT_S))
    except Exception as err:  # timed out, or not speaking Dask's protocol
        raise CalibError(
            f"{scheduler} does not answer as a Dask scheduler within {CONNECT_TIMEOUT_S} s ({_reason(err)})"
        ) from None
    if not isinstance(reply, dict) or reply.get("type") != "Scheduler":
        raise CalibError(f"{scheduler} is not a Dask scheduler (it answered {str(reply)[:60]!r})")


def _reason(err: BaseException) -> str:
    return str(err).splitlines()[0][:120] if str(err) else err.__class__.__name__


def _unreachable(scheduler: str, err: BaseException) -> CalibError:
    return CalibError(f"cannot reach the Dask scheduler at {scheduler} within {CONNECT_TIMEOUT_S} s ({_reason(err)})")


def run_sweep(
    spec: SweepSpec,
    out: str | Path,
    scheduler: str | None = None,
    workers: int | None = None,
    progress: bool = True,
    plan: SweepPlan | None = None,
) -> SweepReport:
    """Run every unfinished task of ``spec``, writing parts as they finish, then results.parquet.

    Tasks that raise are reported (``failed``: the cell's settings, the seed and the error)
    and left unfinished, so the next run retries them; the others still land. A ``plan``'s
    pilot tasks are written first and not run again.
    """
    out = Path(out)
    start = time.perf_counter()
    table_schema = store.schema(spec)
    tasks = spec.tasks()
    done = store.finished(spec, out)
    pilots = plan.pilots if plan is not None else []
    piloted = {(rows[0]["cell"], rows[0]["seed"]) for rows in pilots}
    todo = deque((cell, seed) for cell, seed in tasks if (cell.id, seed) not in done | piloted)
    failed: list[str] = []
    ran = 0
    if todo:
        client = connect(scheduler, workers)  # before DIR exists: an unreachable scheduler leaves nothing behind
        try:
            store.prepare(out)
            ran += _write_pilots(out, pilots, table_schema)
            ran += _drain(client, spec, out, todo, table_schema, failed, len(tasks), len(done) + ran, progress)
        except KeyboardInterrupt:
            store.consolidate(spec, out, table_schema)  # what finished is in results.parquet too
            raise
        finally:
            _close(client)
    else:
        store.prepare(out)
        ran += _write_pilots(out, pilots, table_schema)
    table = store.consolidate(spec, out, table_schema)
    return SweepReport(len(tasks), len(done), ran, failed, table, time.perf_counter() - start)


def _write_pilots(out: Path, pilots: list[list[dict]], table_schema) -> int:
    for rows in pilots:
        store.write_part(out, rows, table_schema)
    return len(pilots)


def _drain(
    client, spec: SweepSpec, out: Path, todo: deque, table_schema, failed: list, total: int, done: int, progress: bool
) -> int:
    """Submit, collect and write until nothing is left; the number of tasks that finished."""
    from distributed import as_completed

    window = max(2, IN_FLIGHT_PER_THREAD * max(1, sum(client.nthreads().values())))
    pending = as_completed(loop=client.loop)
    names = {}

    def submit_next() -> None:
        cell, seed = todo.popleft()
        future = client.submit(
            run_task,
            cell,
            seed,
            spec.methods,
            spec.checkpoints,
            spec.refit_at_checkpoints,
            key=f"sweep-{cell.id}-{seed}",
        )
        names[future.key] = f"{', '.join(f'{k}={v}' for k, v in cell.settings.items())}, seed {seed}"
        pending.add(future)

    for _ in range(min(window, len(todo))):
        submit_next()
    ran = 0
    # disable=None: tqdm hides the bar when stderr is not a terminal.
    with tqdm(
        total=total, initial=done, unit="task", desc=f"sweep {spec.name}", disable=None if progress else True
    ) as bar:
        for future in pending:
            if future.status == "finished":
                store.write_part(out, future.result(), table_schema)
                ran += 1
            else:
                error = future.exception()
                failed.append(
                    f"{names[future.key]}: {error.__class__.__name__}: "
                    f"{str(error).splitlines()[0] if str(error) else ''}"
                )
                bar.write(f"task failed ({failed[-1]})")
            del names[future.key]
            future.release()
            bar.update()
            if todo:
                submit_next()
    return ran


def _close(client) -> None:
    """Close the client, and the local cluster it started (a named scheduler stays up)."""
    cluster = client.cluster
    client.close()
    if cluster is not None:
        cluster.close()
