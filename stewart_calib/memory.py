"""What a method that holds the whole log will need, said before it starts.

The online methods stream a log in bounded memory; a batch method whose memory grows with the
log (``lm``'s factor graph: every sample's factors and values; the registry's
:attr:`~stewart_calib.estimators.registry.MethodSpec.bytes_per_sample`) is refused before it
reads a row when the log it is given would need more memory than the machine has free, and
says what it will need when that is much.
"""

from __future__ import annotations

import os
from pathlib import Path

from .errors import CalibError, shown

#: what a run needs beside the samples (the interpreter, numpy, numba, gtsam) [bytes]
BASE_BYTES = 300 << 20
#: a need beyond this is said before the run starts [bytes]
SAID_BYTES = 1 << 30
#: the log's first bytes whose lines give the mean length of a row
SAMPLED_BYTES = 1 << 16


def estimated_rows(path: str | Path) -> int | None:
    """The data rows of the log at ``path`` from its size and the mean length of its first lines;
    None for what has no size (a pipe, standard input) or no lines."""
    try:
        if not Path(path).is_file():
            return None
        size = os.path.getsize(path)
        with open(path, "rb") as file:
            head = file.read(SAMPLED_BYTES)
    except OSError:
        return None
    lines = head.count(b"\n")
    if lines < 2:
        return max(lines - 1, 0) if len(head) == size else None
    header = head.index(b"\n") + 1
    row_bytes = (head.rindex(b"\n") + 1 - header) / (lines - 1)
    return round((size - header) / row_bytes)


def available_bytes() -> int | None:
    """Memory this process can still take: the kernel's ``MemAvailable``, within the cgroup's
    limit where one is set (a container); None where neither can be read."""
    available = None
    try:
        with open("/proc/meminfo", encoding="ascii") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    available = int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        used = int(Path("/sys/fs/cgroup/memory.current").read_text())
        if limit != "max":
            left = int(limit) - used
            available = left if available is None else min(available, left)
    except (OSError, ValueError):
        pass
    return available


def _size(n_bytes: float) -> str:
    for unit, scale in (("GB", 1e9), ("MB", 1e6)):
        if n_bytes >= scale:
            return f"{n_bytes / scale:.3g} {unit}"
    return f"{n_bytes / 1e3:.3g} kB"


def check_memory(method: str, bytes_per_sample: int | None, log: str | Path, option: str = "--log") -> str | None:
    """Refuse ``method`` on the log at ``log`` before it starts when the samples it holds
    (``bytes_per_sample`` each; None: it streams) would need more memory than is available.

    Returns:
        A line saying what it will need, when that is more than :data:`SAID_BYTES`; else None.
    Raises:
        CalibError: the need beyond the memory available, naming the log, the estimate and what
            streams instead.
    """
    rows = estimated_rows(log) if bytes_per_sample else None
    if not rows or not bytes_per_sample:
        return None
    need = BASE_BYTES + rows * bytes_per_sample
    available = available_bytes()
    what = (
        f"{method} holds every sample (~{_size(bytes_per_sample)} each): ~{_size(need)} for the ~{rows} rows of "
        f"{shown(log)}"
    )
    if available is not None and need > available:
        raise CalibError(
            f"{option} {shown(log)}: {what}, more than the {_size(available)} of memory available; expected a "
            "method that streams the log in bounded memory (ekf, isam2) or a shorter log"
        )
    if need > SAID_BYTES:
        return f"{what} ({_size(available) if available is not None else 'an unknown amount'} available)"
    return None
