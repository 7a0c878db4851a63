"""What every benchmark section shares: timing, the two geometries, synthetic streams, rows.

A section returns a :class:`Section`: a title, a methods paragraph (``note``), and :class:`Row` s,
each with the measured value, the target it is held against (or None), whether it is met and, for
a target it may miss, why; a section whose results do not fit one row a benchmark adds
:class:`Table` s of its own columns. Timing is always per call, reported as median and p99 over
many calls; comparisons are ratios of medians measured side by side in the same run.
"""

from __future__ import annotations

import ctypes
import os
import platform as host
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from stewart_calib.io.platform_file import load_platform
from stewart_calib.model.platform import Platform

ROOT = Path(__file__).resolve().parents[1]
NIM_STEWART_FILE = ROOT / "configs" / "platforms" / "nim-stewart.toml"


@dataclass
class Row:
    """One table row: ``value`` (a string as printed), the target, and whether it is met (None: no target)."""

    name: str
    value: str
    target: str = ""
    met: bool | None = None
    raw: dict = field(default_factory=dict)
    #: one sentence on why the target is not met, shown where it is not
    why: str = ""


@dataclass
class Table:
    """A table of its own columns below a section's rows (``cells``: one list of strings a line)."""

    title: str
    columns: list[str]
    cells: list[list[str]]
    note: str = ""


@dataclass
class Section:
    title: str
    note: str
    rows: list[Row]
    raw: dict = field(default_factory=dict)
    tables: list[Table] = field(default_factory=list)
    #: the file name of a plot beside the section's saved results, or ""
    plot: str = ""

    def to_dict(self) -> dict:
        return {
            "title": self.title,
            "note": self.note,
            "rows": [asdict(r) for r in self.rows],
            "raw": self.raw,
            "tables": [asdict(t) for t in self.tables],
            "plot": self.plot,
        }

    @classmethod
    def from_dict(cls, data: dict) -> Section:
        return cls(
            data["title"],
            data["note"],
            [Row(**row) for row in data["rows"]],
            data.get("raw", {}),
            [Table(**table) for table in data.get("tables", [])],
            data.get("plot", ""),
        )


def explain(section: Section, why: dict[str, str]) -> Section:
    """Give every row not met the sentence of ``why`` whose key its name starts with."""
    for row in section.rows:
        if row.met is False:
            row.why = next((text for start, text in why.items() if row.name.startswith(start)), row.why)
    return section


def per_call_us(calls) -> np.ndarray:
    """Wall time of each zero-argument call, in order [µs]."""
    times_ns = np.empty(len(calls))
    for k, call in enumerate(calls):
        start = time.perf_counter_ns()
        call()
        times_ns[k] = time.perf_counter_ns() - start
    return times_ns / 1e3


def stats_us(times_us: np.ndarray) -> dict:
    """Median and p99 of per-call times [µs]."""
    return {
        "median_us": float(np.median(times_us)),
        "p99_us": float(np.percentile(times_us, 99)),
        "calls": len(times_us),
    }


def fmt_time_us(value_us: float) -> str:
    """µs below 1 ms, ms above (three significant figures)."""
    return f"{value_us:.3g} µs" if value_us < 1e3 else f"{value_us / 1e3:.3g} ms"


def mark(met: bool | None) -> str:
    return {True: "met", False: "**not met**", None: "—"}[met]


def seeded_main(module: str, doc: str, run, default_seeds: int, argv: list[str] | None) -> int:
    """``python -m benchmarks.<module> [--seeds N] [--quick]``: prints :func:`markdown` of
    ``run(quick, seeds)``."""
    import argparse

    parser = argparse.ArgumentParser(prog=f"python -m benchmarks.{module}", description=doc.splitlines()[0])
    parser.add_argument("--seeds", type=int, help=f"seeds 0 … N−1 (default {default_seeds}; --quick: 1)")
    parser.add_argument(
        "--quick", action="store_true", help="tiny inputs, every row (smoke test; the numbers mean little)"
    )
    args = parser.parse_args(argv)
    print(markdown(run(args.quick, args.seeds)))
    return 0


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def markdown(section: Section) -> str:
    """A section's methods paragraph, its rows' table, a sentence for every target not met, and its
    own tables (no heading: :mod:`benchmarks.report` adds it, with the machine and date)."""
    lines = [section.note, ""]
    if section.rows:
        lines += ["| Benchmark | Measured | Target | Status |", "|---|---|---|---|"]
        lines += [
            f"| {_cell(row.name)} | {row.value} | {row.target or '—'} | {mark(row.met)} |" for row in section.rows
        ]
        lines.append("")
    missed: dict[str, list[str]] = {}  # the rows a sentence explains, in order
    for row in section.rows:
        if row.met is False and row.why:
            missed.setdefault(row.why, []).append(f"*{row.name}*")
    if missed:
        lines += ["Not met:", ""]
        lines += [f"- {', '.join(names)}: {why}" for why, names in missed.items()]
        lines.append("")
    for table in section.tables:
        lines += [f"#### {table.title}", ""]
        if table.note:
            lines += [table.note, ""]
        lines += ["| " + " | ".join(table.columns) + " |", "|" + "---|" * len(table.columns)]
        lines += ["| " + " | ".join(cells) + " |" for cells in table.cells]
        lines.append("")
    return "\n".join(lines).rstrip("\n")


def rss_mib() -> float:
    """Resident set size of this process [MiB] (Linux ``/proc/self/statm``; includes C++ heaps)."""
    with open("/proc/self/statm") as f:
        resident_pages = int(f.read().split()[1])
    return resident_pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def machine() -> dict:
    """Machine, load and versions, for the report header."""
    import filterpy
    import gtsam
    import numba
    import scipy

    import stewart_calib

    with open("/proc/cpuinfo") as f:
        cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), host.processor())
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "blas_kernels": blas_kernels(),
        "load_average_1_5_15": [round(x, 2) for x in os.getloadavg()],
        "python": host.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "numba": numba.__version__,
        "gtsam": getattr(gtsam, "__version__", "4.3.0"),
        "filterpy": filterpy.__version__,
        "stewart_calib": getattr(stewart_calib, "__version__", "0.1.0"),
    }


#: the function naming the kernels OpenBLAS chose at load: scipy-openblas 64-bit and 32-bit (numpy's), plain OpenBLAS
OPENBLAS_CORENAME = ("scipy_openblas_get_corename64_", "scipy_openblas_get_corename", "openblas_get_corename")


def blas_kernels() -> str | None:
    """The kernels the OpenBLAS numpy loaded chose for this CPU (``"OpenBLAS SkylakeX"``), None for another BLAS.
    Kernels round differently, and plan's exchanges then pick other, equally good poses: benchmarks.plan_poses's
    hobby with a laser tracker, seed 0, the same code, leaves 46 µm with Haswell's kernels (an AMD EPYC's) and 128 µm
    with SkylakeX's (predicted 156 and 153 µm)."""
    with open("/proc/self/maps") as f:
        libraries = sorted({line.split()[-1] for line in f if "openblas" in line.lower() and ".so" in line})
    for library in libraries:
        loaded = ctypes.CDLL(library)
        for symbol in OPENBLAS_CORENAME:
            if hasattr(loaded, symbol):
                corename = getattr(loaded, symbol)
                corename.restype = ctypes.c_char_p
                return f"OpenBLAS {corename().decode()}"
    return None


def nim_stewart() -> Platform:
    return load_platform(NIM_STEWART_FILE)


#: compact-600/250's drive rings: base radius, platform radius [mm], base and platform pair half
#: angles [deg] (:func:`stewart_calib.sweep.spec.ring_platform`).
COMPACT_RINGS = (600.0, 250.0, 20.0, 40.0)


def compact_variant() -> Platform:
    """nim-stewart with a second drive geometry: base radius 600 mm (pairs at 120k ± 20°),
    platform radius 250 mm (pairs at 120k ± 40°), same joint heights and tracker.

    A smaller, less splayed drive than nim-stewart's 750/300 mm with ±10°/±50° pairs: its legs
    are more parallel, so the identification is worse conditioned — the interesting contrast.
    Initial lengths are the leg lengths at home (every stroke 0 at home).
    """
    from stewart_calib.sweep.spec import ring_platform

    return ring_platform(nim_stewart(), *COMPACT_RINGS, name="compact-600/250")


GEOMETRIES = {"nim-stewart": nim_stewart, "compact-600/250": compact_variant}


def synthetic_stream(platform: Platform, n: int, rng: np.random.Generator, rate_hz: float, smooth: bool, noise=None):
    """An exact synthetic log (``tests/synthetic.py``) of ``n`` samples at ``rate_hz`` and its true δM.

    ``smooth``: the 1 kHz-style Lissajous path of ``benchmarks/fk_speed.py`` (warm-started FK
    sees 1–2 Newton iterations, as online); otherwise random workspace poses (rich data for
    identification). The true δM is drawn with σ = 1 mm; reading and stroke noise are those of
    ``noise`` (an estimator ``NoiseConfig``), so the estimators' noise model is exact.
    Returns ``(log, true_error (42,))``.
    """
    from benchmarks.fk_speed import trajectory
    from stewart_calib.config import NoiseConfig
    from tests.synthetic import make_log, random_error, random_poses

    noise = noise or NoiseConfig()
    true_error = random_error(rng)
    poses = trajectory(platform.workspace.home, n, rate_hz) if smooth else random_poses(platform, n, rng, fraction=0.8)
    log, _ = make_log(platform, true_error, poses, rng, noise.reading_sigma_mm, noise.stroke_sigma_mm, 1.0 / rate_hz)
    return log, true_error
