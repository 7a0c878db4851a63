"""Scale: per-update cost and memory of ``isam2`` and the EKFs from 10² to 10⁵ samples.

Each estimator runs in its own fresh (spawned) process (in-process under ``--quick``) on the same 10 Hz stream (the FK
benchmark's Lissajous path, default noise and random walk), so its resident memory can be
read without the other estimators' allocations — RSS, because GTSAM's C++ heap is invisible
to Python's tracemalloc. Every update is timed; at each checkpoint n the median and p99 are
over the last ``max(50, n/10)`` updates up to n. Runs are capped by wall time; a checkpoint
not reached within the cap is reported as such.

The growth curve of **full-history iSAM2** is the same estimator with its fixed-lag smoother
swapped for a plain ``gtsam.ISAM2`` with the same parameters: the same factors, no
marginalisation.
"""

from __future__ import annotations

import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from benchmarks.common import Row, Section, fmt_time_us, nim_stewart, rss_mib, stats_us, synthetic_stream
from stewart_calib.estimators import make_estimator
from stewart_calib.samples import Log

ISAM2_MEDIAN_TARGET_US = 1000.0
ISAM2_P99_TARGET_US = 5000.0
ISAM2_FLAT_TARGET = 1.3
RATE_HZ = 10.0


class _FullHistory:
    """The calls ``ISAM2Estimator`` makes of its smoother, on a plain ``gtsam.ISAM2`` (no marginalisation)."""

    def __init__(self, params):
        import gtsam

        self.isam = gtsam.ISAM2(params)

    def update(self, factors, values, timestamps):
        self.isam.update(factors, values)

    def calculateEstimateVector(self, key):
        return self.isam.calculateEstimateVector(key)

    def marginalCovariance(self, key):
        return self.isam.marginalCovariance(key)


def _estimator(method: str):
    platform = nim_stewart()
    if method == "isam2 full history":
        est = make_estimator("isam2", platform)
        est._smoother = _FullHistory(est._smoother.getISAM2().params())
        return est
    return make_estimator(method, platform)


def _run_stream(method: str, arrays: tuple, checkpoints: list[int], cap_s: float) -> dict:
    """In a fresh process: time every update, read RSS at each checkpoint, stop at the cap."""
    samples = list(Log(*arrays))
    est = _estimator(method)
    est.update(samples[0])  # first call loads numba caches / builds the graph
    baseline_mib = rss_mib()
    times_us = np.empty(len(samples))
    times_us[0] = np.nan
    rss = {}
    start = time.perf_counter()
    n = 1
    for n, sample in enumerate(samples[1:], start=2):
        t0 = time.perf_counter_ns()
        est.update(sample)
        times_us[n - 1] = (time.perf_counter_ns() - t0) / 1e3
        if n in checkpoints:
            rss[n] = rss_mib() - baseline_mib
        if time.perf_counter() - start > cap_s:
            break
    reached = {}
    for c in checkpoints:
        if c <= n:
            window = times_us[max(1, c - max(50, c // 10)) : c]
            reached[c] = {**stats_us(window), "rss_growth_mib": rss[c]}
    return {"method": method, "samples_done": n, "seconds": time.perf_counter() - start, "capped": n < len(samples), "checkpoints": reached}


def _plot(results: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_time, ax_mem) = plt.subplots(1, 2, figsize=(11, 4))
    for r in results:
        cps = sorted(r["checkpoints"])
        ax_time.plot(cps, [r["checkpoints"][c]["median_us"] for c in cps], "o-", label=r["method"])
        ax_mem.plot(cps, [r["checkpoints"][c]["rss_growth_mib"] for c in cps], "o-", label=r["method"])
    ax_time.set(xscale="log", yscale="log", xlabel="samples", ylabel="median update [µs]", title="Per-update cost")
    ax_mem.set(xscale="log", xlabel="samples", ylabel="RSS growth [MiB]", title="Memory")
    for ax in (ax_time, ax_mem):
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(quick: bool, seed: int, png_path: Path) -> tuple[Section, list[Row]]:
    """The scale section (its plot written to ``png_path``), and the ``isam2`` rows of the speed table."""
    max_samples = 300 if quick else 100_000
    checkpoints = [c for c in (100, 1_000, 10_000, 100_000) if c <= max_samples]
    full_history_samples = 200 if quick else 3_000
    full_checkpoints = [c for c in (100, 300, 1_000, 2_000, 3_000) if c <= full_history_samples]
    cap_s = {"ekf": 5.0, "paper-ekf": 5.0, "isam2": 5.0, "isam2 full history": 5.0} if quick else {
        "ekf": 120.0, "paper-ekf": 120.0, "isam2": 300.0, "isam2 full history": 120.0}
    log, _ = synthetic_stream(nim_stewart(), max_samples, np.random.default_rng(seed), RATE_HZ, smooth=True)
    arrays = (log.t_s, log.strokes, log.readings)
    results = []
    spawn = multiprocessing.get_context("spawn")
    for method, n, cps in (
        ("ekf", max_samples, checkpoints),
        ("paper-ekf", max_samples, checkpoints),
        ("isam2", max_samples, checkpoints),
        ("isam2 full history", full_history_samples, full_checkpoints),
    ):
        job = (method, tuple(a[:n] for a in arrays), cps, cap_s[method])
        if quick:  # a fresh interpreter costs seconds; the smoke test does not read the memory
            results.append(_run_stream(*job))
            continue
        with ProcessPoolExecutor(max_workers=1, mp_context=spawn) as pool:
            results.append(pool.submit(_run_stream, *job).result())
    _plot(results, png_path)

    rows = []
    for r in results:
        for c in full_checkpoints if r["method"] == "isam2 full history" else checkpoints:
            point = r["checkpoints"].get(c)
            value = (
                f"median {fmt_time_us(point['median_us'])}, p99 {fmt_time_us(point['p99_us'])}, RSS +{point['rss_growth_mib']:.1f} MiB"
                if point
                else f"not reached: capped at {cap_s[r['method']]:.0f} s after {r['samples_done']:,} samples"
            )
            rows.append(Row(f"{r['method']} at {c:,} samples", value, raw=point or {}))

    isam2 = next(r for r in results if r["method"] == "isam2")
    cps = isam2["checkpoints"]
    first, largest = min(cps), max(cps)
    flat_at = 10_000 if 10_000 in cps else largest
    flat_ratio = cps[flat_at]["median_us"] / cps[first]["median_us"]
    overall = cps[largest]
    full = next(r for r in results if r["method"] == "isam2 full history")["checkpoints"]
    full_last = max(full)
    speed_rows = [
        Row(
            f"isam2 update per sample (at {largest:,} samples)",
            f"median {fmt_time_us(overall['median_us'])}, p99 {fmt_time_us(overall['p99_us'])}",
            f"≤ {fmt_time_us(ISAM2_MEDIAN_TARGET_US)} median, ≤ {fmt_time_us(ISAM2_P99_TARGET_US)} p99",
            overall["median_us"] <= ISAM2_MEDIAN_TARGET_US and overall["p99_us"] <= ISAM2_P99_TARGET_US,
            overall,
        ),
        Row(
            f"isam2 flat: median at {flat_at:,} / at {first:,} samples",
            f"{flat_ratio:.2f} ({fmt_time_us(cps[flat_at]['median_us'])} / {fmt_time_us(cps[first]['median_us'])}); "
            f"full-history iSAM2: {fmt_time_us(full[min(full)]['median_us'])} at {min(full):,} → "
            f"{fmt_time_us(full[full_last]['median_us'])} at {full_last:,} samples",
            f"≤ {ISAM2_FLAT_TARGET} (at 10 000 / at 100)",
            flat_ratio <= ISAM2_FLAT_TARGET if flat_at == 10_000 else None,
            {"ratio": flat_ratio, "at": flat_at, "reference": first},
        ),
    ]
    note = (
        f"One {RATE_HZ:g} Hz stream (Lissajous path, default noise and random walk), each estimator in a fresh "
        f"process{' (in-process under --quick: RSS meaningless)' if quick else ''}; median / p99 over the last max(50, n/10) updates before n; RSS growth since the first update. "
        f"Wall-time caps per estimator [s]: {', '.join(f'{k} {v:g}' for k, v in cap_s.items())}."
    )
    return Section("Scale", note, rows, raw={"results": results, "caps_s": cap_s}), speed_rows
