"""Where a sweep's rows live: one Parquet part per finished task, consolidated into results.parquet.

``DIR/parts/<cell id>-<seed>.parquet`` holds the rows of one task (one per method), written by
the client the moment the task finishes, atomically (temporary file, then rename): a part
either exists whole or not at all, so a sweep killed at any instant loses only the tasks in
flight, and the next run skips every task whose part exists whole. A part cut short all the same
(a rename that reached the disk before the data did, a crash of the machine, a copy stopped half
way) lacks Parquet's closing magic bytes: the next run counts it as damaged, says so and computes
its task again, replacing it. ``DIR/results.parquet`` is the
concatenation of the parts of the spec's tasks, sorted by (grid order, seed, method order), so
it is the same file whichever worker ran what and in which order.
"""

from __future__ import annotations

import os
from pathlib import Path

import pyarrow as pa
import pyarrow.dataset as pads
import pyarrow.parquet as pq

from ..errors import CalibError, shown
from ..io import atomic_path
from .spec import SweepSpec, cost_kind
from .task import METRICS

RESULTS = "results.parquet"
PARTS = "parts"


def schema(spec: SweepSpec) -> pa.Schema:
    """Columns of every row: keys, the settings (typed from the grid), scores, checkpoints, notes."""
    first = spec.cells[0].settings
    fields: list[pa.Field] = [
        pa.field("cell", pa.string()),
        pa.field("seed", pa.int64()),
        pa.field("method", pa.string()),
    ]
    kinds: dict[type, pa.DataType] = {bool: pa.bool_(), int: pa.int64(), float: pa.float64(), str: pa.string()}
    fields += [pa.field(name, kinds[type(value)]) for name, value in first.items()]
    fields += [pa.field(name, pa.float64()) for name in METRICS]
    fields += [pa.field("nees_dof", pa.int64())]
    fields += [pa.field("samples_rejected", pa.int64()), pa.field("glitches", pa.int64())]
    fields += [pa.field(f"rms_over_crb_at_{n}", pa.float64()) for n in spec.checkpoints]
    fields += [pa.field("failure", pa.string())]
    return pa.schema(fields)


def part_path(out: Path, cell_id: str, seed: int) -> Path:
    return out / PARTS / f"{cell_id}-{seed}.parquet"


def prepare(out: Path) -> None:
    """Create ``DIR/parts``; drop temporary files a killed run left behind (never a finished part)."""
    try:
        (out / PARTS).mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise CalibError(f"{out}: cannot create output directory ({err.strerror or err.__class__.__name__})") from None
    for leftover in (out / PARTS).glob(".*.tmp"):
        leftover.unlink(missing_ok=True)


#: a Parquet file opens and closes with these bytes; its footer's length comes just before the last
MAGIC = b"PAR1"


def _damage(path: Path) -> str | None:
    """Why ``path`` is no whole Parquet file (too short, no opening or closing magic bytes, a footer
    longer than the file), or None: a truncated part fails here, reading only its ends (cheap
    beside parsing it)."""
    try:
        with path.open("rb") as f:
            size = os.fstat(f.fileno()).st_size
            head = f.read(4)
            if size < 12:
                return f"{size} bytes, shorter than any Parquet file"
            f.seek(size - 8)
            tail = f.read(8)
    except OSError as err:
        return err.strerror or err.__class__.__name__
    if head != MAGIC or tail[4:] != MAGIC:
        return "cut short (no Parquet magic bytes at its end)" if head == MAGIC else "not a Parquet file"
    if int.from_bytes(tail[:4], "little") > size - 12:
        return "cut short (its footer is longer than the file)"
    return None


def part_states(spec: SweepSpec, out: Path) -> tuple[set[tuple[str, int]], list[str]]:
    """``(finished, damaged)``: (cell id, seed) of the spec's tasks whose part exists whole, and
    ``"<part path>: <why>"`` of those whose part exists damaged (their tasks are run again)."""
    present = {p.name for p in (out / PARTS).glob("*.parquet")}  # none when DIR does not exist yet
    done: set[tuple[str, int]] = set()
    damaged: list[str] = []
    for cell, seed in spec.tasks():
        path = part_path(out, cell.id, seed)
        if path.name in present:
            why = _damage(path)
            if why is None:
                done.add((cell.id, seed))
            else:
                damaged.append(f"{shown(path)}: {why}")
    return done, damaged


def finished(spec: SweepSpec, out: Path) -> set[tuple[str, int]]:
    """(cell id, seed) of the spec's tasks whose part exists whole (:func:`part_states`)."""
    return part_states(spec, out)[0]


def past_cost(out: Path, limit: int) -> dict[str, tuple[float, int]]:
    """Per instrument and drive (:func:`~.spec.cost_kind`), the methods' CPU time per sample over up to
    ``limit`` finished parts in ``out`` [s] and how many parts gave it (none where there are none, or
    none readable; a part without a ``drive`` column is a prismatic one's)."""
    totals: dict[str, list[float]] = {}
    for path in sorted((out / PARTS).glob("*.parquet"))[:limit]:
        try:
            drive_column = ["drive"] if "drive" in pq.read_schema(path).names else []
            table = pq.read_table(path, columns=["cpu_seconds", "samples", "instrument", *drive_column])
        except (OSError, ValueError, KeyError, pa.ArrowException):  # a part the run will recompute or refuse
            continue
        if not table.num_rows:
            continue
        values = [v for v in table["cpu_seconds"].to_pylist() if v is not None and v == v]
        drive = table["drive"][0].as_py() if drive_column else "prismatic"
        kind = cost_kind({"instrument": table["instrument"][0].as_py(), "drive": drive})
        total = totals.setdefault(kind, [0.0, 0.0, 0])
        total[0] += sum(values)
        total[1] += table["samples"][0].as_py()
        total[2] += 1
    return {kind: (cpu / samples, int(parts)) for kind, (cpu, samples, parts) in totals.items() if samples > 0}


def _atomic_write(table: pa.Table, path: Path) -> None:
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp)


def write_part(out: Path, rows: list[dict], table_schema: pa.Schema) -> None:
    """The rows of one finished task, as its part file."""
    _atomic_write(pa.Table.from_pylist(rows, schema=table_schema), part_path(out, rows[0]["cell"], rows[0]["seed"]))


def _unreadable(paths: list[str], table_schema: pa.Schema) -> str | None:
    """The refusal naming the first of ``paths`` that does not read as a part, or None."""
    for path in paths:
        try:
            pq.read_table(path, schema=table_schema)
        except (OSError, pa.ArrowException) as err:
            detail = " ".join(str(err).split())
            return f"{shown(path)}: a damaged sweep part ({detail}); remove it and run the sweep again to recompute it"
    return None


def consolidate(spec: SweepSpec, out: Path, table_schema: pa.Schema) -> pa.Table:
    """Write ``DIR/results.parquet`` from the parts of the spec's finished tasks; returns the table."""
    done = finished(spec, out)
    paths = [str(part_path(out, cell.id, seed)) for cell, seed in spec.tasks() if (cell.id, seed) in done]
    try:
        table = (
            pads.dataset(paths, schema=table_schema, format="parquet").to_table()
            if paths
            else table_schema.empty_table()
        )
    except (OSError, pa.ArrowException) as err:  # damaged inside, its ends whole: name the part
        raise CalibError(_unreadable(paths, table_schema) or f"{out / PARTS}: cannot read the parts ({err})") from None
    order = {cell.id: cell.index for cell in spec.cells}
    method_order = {m: k for k, m in enumerate(spec.methods)}
    columns: list[list] = [table[name].to_pylist() for name in ("cell", "seed", "method")]
    cells, seeds, methods = columns
    keys = sorted(range(table.num_rows), key=lambda r: (order[cells[r]], seeds[r], method_order[methods[r]]))
    table = table.take(pa.array(keys, type=pa.int64()))
    _atomic_write(table, out / RESULTS)
    return table
