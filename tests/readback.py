"""Read an ``.rrd`` written by :mod:`stewart_calib.viz.recording` back, for the tests.

Entity paths are returned and accepted as rerun stores them, with a leading ``/``
(``/params/leg3/d_y/isam2``); a path given without it is normalised.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
from rerun.chunk import RrdReader

from stewart_calib.viz.recording import SAMPLE_TIMELINE


def _entity(path: str) -> str:
    return "/" + path.lstrip("/")


def _chunks(rrd_path: str | Path):
    return RrdReader(Path(rrd_path)).stream().to_chunks()


def read_entity_rows(rrd_path: str | Path, static: bool = False) -> dict[str, int]:
    """Rows per entity path: of the time-indexed chunks, or of the static ones if ``static``.

    For a time series this is the number of samples logged, whatever the chunking.
    """
    rows: dict[str, int] = defaultdict(int)
    for chunk in _chunks(rrd_path):
        if chunk.is_static == static:
            rows[chunk.entity_path] += chunk.num_rows
    return dict(rows)


def read_scalars(
    rrd_path: str | Path, entity_path: str, timeline: str = SAMPLE_TIMELINE
) -> tuple[np.ndarray, np.ndarray]:
    """``(index, values)`` of a scalar series, sorted by ``timeline``.

    The index is the timeline's raw value: a sample number for ``sample``, a ``timedelta64[ns]``
    for ``time``.
    """
    entity_path = _entity(entity_path)
    batches = [
        chunk.to_record_batch()
        for chunk in _chunks(rrd_path)
        if chunk.entity_path == entity_path and not chunk.is_static
    ]
    if not batches:
        raise KeyError(f"no time series at {entity_path}")
    index = np.concatenate([batch.column(timeline).to_numpy() for batch in batches])
    values = np.concatenate([batch.column("Scalars:scalars").flatten().to_numpy() for batch in batches])
    order = np.argsort(index, kind="stable")
    return index[order], values[order]


def read_static(rrd_path: str | Path, entity_path: str) -> dict[str, list]:
    """Static components at ``entity_path``: column name (``Archetype:field`` or an AnyValues
    name) → the list of instances of its last row."""
    entity_path = _entity(entity_path)
    columns: dict[str, list] = {}
    for chunk in _chunks(rrd_path):
        if chunk.entity_path == entity_path and chunk.is_static:
            batch = chunk.to_record_batch()
            for name in batch.schema.names:
                if name != "rerun.controls.RowId":
                    columns[name] = batch.column(name)[-1].as_py()
    return columns


def read_blueprint_names(rrd_path: str | Path) -> set[str]:
    """Display names of the views and containers (tabs) of every blueprint in the file."""
    reader = RrdReader(Path(rrd_path))
    names: set[str] = set()
    for store in reader.blueprints():
        for chunk in reader.stream(store=store).to_chunks():
            batch = chunk.to_record_batch()
            for column in ("ViewBlueprint:display_name", "ContainerBlueprint:display_name"):
                if column in batch.schema.names:
                    names.update(name for row in batch.column(column).to_pylist() if row for name in row)
    return names
