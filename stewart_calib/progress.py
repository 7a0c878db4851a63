"""Progress of long work on stderr: a bar with the rate on a terminal, nothing when piped.

One helper for every command (``calibrate``, ``validate``, ``reproduce``, ``simulate``), so
they look alike and all stay silent in scripts, logs and CI, where stderr is not a terminal.
"""

from __future__ import annotations

import sys
from typing import Iterable


def progress_bar(iterable: Iterable | None = None, *, total: int | None = None, desc: str, unit: str = "sample",
                 show: bool = True):
    """A tqdm bar on stderr (count, rate per second, time left), or a silent one.

    Args:
        iterable: what to wrap, or None to tick by hand (``bar.update(n)``).
        total: the count when ``iterable`` has no length (or there is none).
        desc: what is being done, e.g. ``"calibrate ekf"``.
        unit: what is counted (the rate reads "… unit/s").
        show: False keeps it silent whatever stderr is (e.g. short runs).
    Returns:
        A ``tqdm`` object (a context manager; iterate it, or call ``update``/``close``). It
        is disabled — no output at all — unless ``show`` and stderr is a terminal.
    """
    from tqdm import tqdm  # ~40 ms of imports a short run does not need

    return tqdm(iterable, total=total, desc=desc, unit=unit, unit_scale=True, file=sys.stderr, leave=False,
                dynamic_ncols=True, mininterval=0.2, disable=not (show and sys.stderr.isatty()))
