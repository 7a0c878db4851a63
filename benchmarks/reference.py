"""The prismatic robot's per-sample cost of ``calibrate`` beside the reference code's, measured side by side.

The reference is the package before the leg-model reshape: the last commit of this checkout's
first-parent history made before :data:`REFERENCE_BEFORE` (``git rev-list --first-parent
--before``), unpacked by ``git archive`` into a temporary directory and run from there
(``PYTHONPATH`` and the working directory at its root, so it imports its own package; numba's cache
a directory of its own for each tree). Both trees run ``python -m stewart_calib calibrate`` on the
same files, one command after the other, the two trees' order swapped every repeat, so that a
shared machine's drift falls on both alike; each reports the median over the repeats and the
ratio of the medians.

Per-sample cost is marginal, as in :mod:`benchmarks.scale`: ``(t(N) − t(N₀)) / (N − N₀)`` of the
same command on the first ``N₀`` and ``N`` samples of one 10 Hz Lissajous log, so start-up is not
spread over the samples; CPU (user + system, all threads) is the figure a target is held on, wall
time is shown beside it. Both trees run their JIT kernels from their warm caches
(``STEWART_CALIB_AOT=0``: an ahead-of-time module exists only where an installation built one, and
would compare compilers rather than code) with one BLAS thread. The results of the two trees at
``N`` are compared too: the largest difference of their estimates and standard deviations.

``python -m benchmarks.reference [--quick] [--reference REV]`` prints the section.
"""

from __future__ import annotations

import argparse
import io
import json
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.common import ROOT, Row, Section, Table, markdown, nim_stewart, synthetic_stream
from benchmarks.scale import CLI_CAP_S, RATE_HZ, _run_cli
from stewart_calib.io import write_log

#: the reference: the newest first-parent commit made before this moment, the code before the leg-model reshape
REFERENCE_BEFORE = "2026-12-01 22:10 UTC"
#: what the reference tree needs to run the CLI: the package and its shipped files
REFERENCE_PATHS = ("stewart_calib", "configs", "pyproject.toml")
#: method → (N₀, N) samples of the marginal cost; ``--quick``: :data:`QUICK_SIZES` for every method
SIZES = {"ekf": (1_000, 100_000), "ls": (1_000, 10_000), "isam2": (1_000, 10_000)}
QUICK_SIZES = (100, 600)
#: repeats of every (tree, size) command, the two trees' order swapped each time
REPEATS = 7
QUICK_REPEATS = 2
#: ``calibrate ekf``'s per-sample CPU against the reference's, at most
EKF_TARGET_RATIO = 1.10
#: one BLAS thread, JIT kernels from each tree's own warm cache
ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "STEWART_CALIB_AOT": "0"}


def reference_commit(before: str = REFERENCE_BEFORE, root: Path = ROOT) -> str:
    """The newest commit of ``root``'s first-parent history made before ``before``; ValueError where none is."""
    try:
        out = subprocess.run(
            ["git", "-C", str(root), "rev-list", "-1", "--first-parent", f"--before={before}", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError) as error:
        raise ValueError(f"{root}: not a git checkout with history (git rev-list failed: {error})") from error
    if not out:
        raise ValueError(f"{root}: no commit before {before} (a shallow clone?)")
    return out


def unpack(commit: str, directory: Path, root: Path = ROOT) -> Path:
    """``git archive`` of ``commit``'s :data:`REFERENCE_PATHS` unpacked into ``directory``; its root."""
    tar = subprocess.run(
        ["git", "-C", str(root), "archive", "--format=tar", commit, *REFERENCE_PATHS], capture_output=True, check=True
    ).stdout
    directory.mkdir(parents=True, exist_ok=True)
    with tarfile.open(fileobj=io.BytesIO(tar)) as archive:
        archive.extractall(directory, filter="tar")  # the package's configs link stays a link inside the tree
    return directory


def _argv(method: str, log: Path, out: Path) -> list[str]:
    return ["calibrate", "--platform", "nim-stewart", "--log", str(log), "--method", method, "--out", str(out)]


def _run(tree: Path, cache: Path, method: str, log: Path, out: Path) -> dict:
    run = _run_cli(
        _argv(method, log, out),
        CLI_CAP_S,
        out.with_suffix(".stdout"),
        env={**ENV, "NUMBA_CACHE_DIR": str(cache)},
        root=tree,
    )
    if run["capped"] or run.get("exit"):
        error = out.with_suffix(".err").read_text(encoding="utf-8", errors="replace").strip().splitlines()
        raise RuntimeError(f"calibrate --method {method} in {tree} failed: {error[-1] if error else run}")
    return run


def _result_difference(a: Path, b: Path) -> dict:
    """The largest |difference| of two results' ``estimate`` and ``stddev`` [mm, rad as written]."""
    first, second = (json.loads(p.read_text(encoding="utf-8")) for p in (a, b))
    difference = {}
    for key in ("estimate", "stddev"):
        x, y = (np.asarray(r.get(key) if r.get(key) is not None else [], dtype=float) for r in (first, second))
        difference[key] = float(np.max(np.abs(x - y))) if x.shape == y.shape and x.size else float("nan")
    return difference


def run(quick: bool, seed: int = 2024, reference: str | None = None) -> Section:
    """The section: every method of :data:`SIZES` on both trees, interleaved, :data:`REPEATS` times."""
    commit = reference or reference_commit()
    repeats = QUICK_REPEATS if quick else REPEATS
    sizes = {method: QUICK_SIZES if quick else n for method, n in SIZES.items()}
    with tempfile.TemporaryDirectory(prefix="stewart-calib-reference-") as tmp:
        work = Path(tmp)
        trees = {
            "current": (ROOT, work / "cache-current"),
            "reference": (unpack(commit, work / "reference"), work / "cache-reference"),
        }
        log, _ = synthetic_stream(
            nim_stewart(), max(n for pair in sizes.values() for n in pair), np.random.default_rng(seed), RATE_HZ, True
        )
        logs = {n: work / f"log-{n}.csv" for pair in sizes.values() for n in pair}
        for n, path in logs.items():
            write_log(path, log.select(slice(0, n)))
        out = work / "out"
        out.mkdir()
        for name, (tree, cache) in trees.items():  # unmeasured: each tree's numba cache filled by a first run
            for method, (n0, _) in sizes.items():
                _run(tree, cache, method, logs[n0], out / f"warm-{name}-{method}.json")
        runs: dict[str, dict[str, list[dict]]] = {m: {name: [] for name in trees} for m in sizes}
        differences = {}
        for repeat in range(repeats):
            order = list(trees) if repeat % 2 == 0 else list(trees)[::-1]
            for method, (n0, n) in sizes.items():
                for name in order:
                    tree, cache = trees[name]
                    small = _run(tree, cache, method, logs[n0], out / f"{name}-{method}-{n0}.json")
                    large = _run(tree, cache, method, logs[n], out / f"{name}-{method}-{n}.json")
                    runs[method][name].append(
                        {
                            "wall_us_per_sample": (large["wall_s"] - small["wall_s"]) / (n - n0) * 1e6,
                            "cpu_us_per_sample": (large["cpu_s"] - small["cpu_s"]) / (n - n0) * 1e6,
                            "small": small,
                            "large": large,
                        }
                    )
                    print(
                        f"  {method} {name} repeat {repeat + 1}: CPU {runs[method][name][-1]['cpu_us_per_sample']:.1f} "
                        "µs/sample",
                        file=sys.stderr,
                    )
                differences[method] = _result_difference(
                    out / f"current-{method}-{n}.json", out / f"reference-{method}-{n}.json"
                )
    return _section(commit, sizes, repeats, runs, differences)


def _median(runs: list[dict], key: str) -> float:
    return float(np.median([r[key] for r in runs]))


def _section(commit: str, sizes: dict, repeats: int, runs: dict, differences: dict) -> Section:
    rows, cells = [], []
    for method, (n0, n) in sizes.items():
        by_tree = runs[method]
        cpu = {name: _median(r, "cpu_us_per_sample") for name, r in by_tree.items()}
        wall = {name: _median(r, "wall_us_per_sample") for name, r in by_tree.items()}
        ratio_cpu, ratio_wall = cpu["current"] / cpu["reference"], wall["current"] / wall["reference"]
        difference = differences[method]
        agree = (
            "results identical"
            if difference["estimate"] == 0.0 and difference["stddev"] == 0.0
            else f"results differ by ≤ {difference['estimate']:.1e} (estimate), {difference['stddev']:.1e} (σ)"
        )
        cells.append(
            [
                f"calibrate {method}",
                f"{n0:,} → {n:,}",
                f"{cpu['reference']:.3g} µs",
                f"{cpu['current']:.3g} µs",
                f"**{ratio_cpu:.2f}**",
                f"{wall['reference']:.3g} µs",
                f"{wall['current']:.3g} µs",
                f"{ratio_wall:.2f}",
            ]
        )
        target = f"≤ {EKF_TARGET_RATIO:.2f}× the reference (CPU)" if method == "ekf" else ""
        rows.append(
            Row(
                f"calibrate {method} per sample, against the reference code",
                f"{ratio_cpu:.2f}× the reference's CPU per sample ({ratio_wall:.2f}× its wall time); {agree}",
                target,
                ratio_cpu <= EKF_TARGET_RATIO if method == "ekf" else None,
                {"sizes": [n0, n], "median_cpu_us": cpu, "median_wall_us": wall, "runs": by_tree, **difference},
                why=EKF_WHY if method == "ekf" else "",
            )
        )
    note = (
        "The prismatic robot (nim-stewart and its in-situ tracker, the default configuration) beside the reference "
        "code: the package before the leg-model reshape (the last commit made before "
        f"{REFERENCE_BEFORE}), unpacked into a directory of its own and importing its own package. "
        "Both run `python -m stewart_calib calibrate` on the same 10 Hz Lissajous log, one after the other, their "
        f"order swapped every repeat; median over {repeats} repeats. Per sample: marginal, (t(N) − t(N₀)) / (N − N₀) "
        "of the same command; CPU is user + system time, wall beside it. Both trees run their JIT kernels from warm "
        "caches of their own (no ahead-of-time module), one BLAS thread. Target: `calibrate ekf` within 10 % of the "
        "reference's CPU per sample; `ls` and `isam2` reported as they are."
    )
    table = Table(
        "Per sample, side by side",
        [
            "command",
            "samples N₀ → N",
            "reference CPU",
            "current CPU",
            "current / reference (CPU)",
            "reference wall",
            "current wall",
            "current / reference (wall)",
        ],
        cells,
    )
    return Section("Prismatic speed beside the reference code", note, rows, raw={"reference": commit}, tables=[table])


#: why ekf's per-sample cost is above the reference's
EKF_WHY = (
    "ekf measures the parameters' walk from every pair of its last 16 noise windows, so that a stationary "
    "misfit (an unmodelled tracker geometry) is not read as a walk: a window's test solves a 15 × 15 "
    "eigenproblem along each of its 42 directions besides the 42 × 42 one that successive pairs alone needed, "
    "about 0.6 ms a window more, 2.5 µs a sample on this log."
)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.reference", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="tiny logs, two repeats (a smoke test)")
    parser.add_argument(
        "--reference", metavar="REV", help=f"the reference commit (default: the last before {REFERENCE_BEFORE})"
    )
    parser.add_argument("--seed", type=int, default=2024, help="seed of the synthetic log")
    args = parser.parse_args(argv)
    print(markdown(run(args.quick, args.seed, args.reference)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
