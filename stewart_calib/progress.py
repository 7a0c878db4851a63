"""Progress of long work on stderr: a bar with the rate on a terminal, nothing when piped.

One helper for every command (``calibrate``, ``validate``, ``reproduce``, ``simulate``), so
they look alike and all stay silent in scripts, logs and CI, where stderr is not a terminal.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable


def progress_bar(
    iterable: Iterable | None = None, *, total: int | None = None, desc: str, unit: str = "sample", show: bool = True
):
    """A tqdm bar on stderr (count, rate per second, time left), or a silent one.

    Args:
        iterable: what to wrap, or None to tick by hand (``bar.update(n)``).
        total: the count when ``iterable`` has no length (or there is none).
        desc: what is being done, e.g. ``"calibrate ekf"``.
        unit: what is counted (the rate reads "… unit/s").
        show: False keeps it silent whatever stderr is (e.g. short runs).
    Returns:
        A ``tqdm`` object (a context manager; iterate it, or call ``update``/``close``) when
        ``show`` and stderr is a terminal; otherwise a silent stand-in with the same calls.
    """
    if not (show and sys.stderr.isatty()):
        return _Silent(iterable)
    from tqdm import tqdm  # tens of ms of imports that a piped or short run does not need

    return tqdm(
        iterable,
        total=total,
        desc=desc,
        unit=unit,
        unit_scale=True,
        file=sys.stderr,
        leave=False,
        dynamic_ncols=True,
        mininterval=0.2,
    )


#: logs at least this long get a bar (a shorter run is over before a bar would tell anything).
MIN_LOG_ROWS = 1000


def log_progress_bar(path: str, desc: str):
    """A bar over the rows of the log file at ``path`` (ticked by hand, per block read), shown on
    a terminal for a log of at least :data:`MIN_LOG_ROWS` rows; the rows are counted (one pass
    over the bytes) only when it can be shown."""
    show = sys.stderr.isatty()
    total = count_rows(path) if show else None
    return progress_bar(total=total, desc=desc, show=show and (total or 0) >= MIN_LOG_ROWS)


def count_rows(path: str) -> int:
    """Lines after the header (a bar's total; a blank line is counted too): one pass over the bytes."""
    lines = 0
    with open(path, "rb") as file:
        for chunk in iter(lambda: file.read(1 << 22), b""):
            lines += chunk.count(b"\n")
    return max(lines - 1, 0)


class _Silent:
    """What :func:`progress_bar` gives when nothing is to be shown: the same calls, no output."""

    def __init__(self, iterable):
        self._iterable = iterable

    def __iter__(self):
        return iter(self._iterable)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        return None

    def update(self, n: int = 1) -> None:
        return None

    def close(self) -> None:
        return None
