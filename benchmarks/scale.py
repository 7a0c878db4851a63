"""Scale: per-update cost and memory of ``isam2`` and the EKFs from 10² to 10⁵ samples.

Each estimator runs in its own fresh (spawned) process (in-process under ``--quick``) on the same 10 Hz stream (the FK
benchmark's Lissajous path, default noise and random walk), so its resident memory can be
read without the other estimators' allocations — RSS, because GTSAM's C++ heap is invisible
to Python's tracemalloc. Every update is timed; at each checkpoint n the median and p99 are
over the last ``max(50, n/10)`` updates up to n. Runs are capped by wall time (past the first
checkpoint); a checkpoint not reached within the cap is reported as such.

The growth curve of **full-history iSAM2** is the same estimator with its fixed-lag smoother
swapped for a plain ``gtsam.ISAM2`` with the same parameters: the same factors, no
marginalisation.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmarks.common import ROOT, Row, Section, explain, fmt_time_us, nim_stewart, rss_mib, stats_us, synthetic_stream
from stewart_calib.errors import SampleRejected
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
    refused = 0
    for n, sample in enumerate(samples[1:], start=2):
        t0 = time.perf_counter_ns()
        try:
            est.update(sample)
        except SampleRejected:  # the gate's 1e-4 of clean samples: ~10 at 10⁵, timed as any other update
            refused += 1
        times_us[n - 1] = (time.perf_counter_ns() - t0) / 1e3
        if n in checkpoints:
            rss[n] = rss_mib() - baseline_mib
        if n >= checkpoints[0] and time.perf_counter() - start > cap_s:  # the first checkpoint is always reached
            break
    reached = {}
    for c in checkpoints:
        if c <= n:
            window = times_us[max(1, c - max(50, c // 10)) : c]
            reached[c] = {**stats_us(window), "rss_growth_mib": rss[c]}
    return {
        "method": method,
        "samples_done": n,
        "samples_refused": refused,
        "seconds": time.perf_counter() - start,
        "capped": n < len(samples),
        "checkpoints": reached,
    }


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
    cap_s = (
        {"ekf": 5.0, "paper-ekf": 5.0, "isam2": 5.0, "isam2 full history": 5.0}
        if quick
        else {"ekf": 120.0, "paper-ekf": 120.0, "isam2": 300.0, "isam2 full history": 120.0}
    )
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
                f"median {fmt_time_us(point['median_us'])}, p99 {fmt_time_us(point['p99_us'])}, RSS "
                f"+{point['rss_growth_mib']:.1f} MiB ({r['samples_refused']} of {r['samples_done']:,} samples refused)"
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
        f"process{' (in-process under --quick: RSS meaningless)' if quick else ''}; median / p99 over the last "
        "max(50, n/10) updates before n; RSS growth since the first update. Wall-time caps per estimator [s]: "
        f"{', '.join(f'{k} {v:g}' for k, v in cap_s.items())}. No outside peer: the estimators against each "
        "other and isam2's fixed lag against full-history iSAM2. Targets: isam2's update per sample at 10⁵ samples "
        "and its flatness, as its rows state."
    )
    return Section("Scale", note, rows, raw={"results": results, "caps_s": cap_s}), speed_rows


# ----------------------------------------------------------------------------- through the CLI
#
# Every command as a user runs it: a fresh ``python -m stewart_calib …`` process on files,
# timed by the wall clock and measured by the kernel's peak resident set (GNU time's
# ``ru_maxrss``, which counts C++ and BLAS heaps and every import). Per-sample cost is the
# marginal one, ``(wall(N) − wall(start)) / (N − n_start)`` against the same command on
# :data:`CLI_START_SAMPLES` samples, so the interpreter's start-up and imports (reported
# separately, with ``-X importtime``) do not hide or fake linearity.

CLI_SIZES = (1_000, 10_000, 100_000, 1_000_000)
CLI_START_SAMPLES = 100
#: a run longer than this is stopped and reported as over the cap (larger sizes are skipped).
CLI_CAP_S = 900.0
#: modules a start-up must not import: recording, reproduction, statistics, graph methods.
HEAVY_MODULES = ("rerun", "gtsam", "scipy.stats", "stewart_calib.reproduction")

CLI_TARGETS = {  # (command, size): (target text, value in µs/sample or MiB, key)
    ("calibrate ekf", 100_000): 20.0,
    ("calibrate ekf [elastic]", 100_000): 25.0,
    ("calibrate isam2", 100_000): 1000.0,
    ("track ekf", 100_000): 40.0,
    ("identifiability", 100_000): 20.0,
    ("import", 1_000_000): 10.0,  # 10⁶ rows in ≤ 10 s
}
CLI_RSS_TARGET_MIB = {("calibrate ekf", 1_000_000): 500.0, ("import", 1_000_000): 300.0}
IMPORT_TARGET_S = 1.0
QUICK_CASES = ("calibrate ekf",)


@dataclass(frozen=True)
class CliCase:
    """One command: its argument list for a size (file names from :class:`CliInputs`), the sizes it runs at.

    ``unit``: what the size counts (samples, or ``plan``'s poses). ``fixed``: a command without
    a size (``reproduce --quick``), run once and reported by its time and peak RSS alone.
    """

    name: str
    argv: Callable[[CliInputs, int], list[str]]
    sizes: tuple[int, ...]
    unit: str = "sample"
    fixed: bool = False


@dataclass(frozen=True)
class CliInputs:
    """The files the commands read, written once per size into ``root``."""

    root: Path

    @property
    def platform(self) -> str:
        return str(self.root / "platform.toml")

    @property
    def elastic_platform(self) -> str:
        """The platform with ``[elastic]`` (spec §10): a 60 kg platform, the log's payload 0."""
        return str(self.root / "platform-elastic.toml")

    def log(self, n: int) -> str:
        return str(self.root / f"log-{n}.csv")

    def poses(self, n: int) -> str:
        return str(self.root / f"poses-{n}.csv")

    def experiment(self, n: int) -> str:
        return str(self.root / f"experiment-{n}.toml")

    def motive(self, n: int) -> str:
        return str(self.root / f"motive-{n}.csv")

    def counts(self, n: int) -> str:
        return str(self.root / f"counts-{n}.csv")

    @property
    def import_mapping(self) -> str:
        return str(self.root / "controller.toml")

    def out(self, name: str) -> str:
        return str(self.root / "out" / name)

    def write(self, sizes: list[int], seed: int, exports: bool = True) -> None:
        """Platform, and per size a 10 Hz log (the Lissajous stream), a pose list and an experiment;
        with ``exports`` also ``import``'s Motive export and count log."""
        from stewart_calib.io import atomic_write_text, write_log, write_pose_list
        from stewart_calib.io.platform_file import platform_to_toml
        from stewart_calib.model.platform import Elastic

        platform = nim_stewart()
        (self.root / "out").mkdir(parents=True, exist_ok=True)
        atomic_write_text(self.platform, platform_to_toml(platform))
        elastic = Elastic(60.0, np.array([0.0, 0.0, -50.0]), np.array([50.0, 0.0, 100.0]))
        atomic_write_text(self.elastic_platform, platform_to_toml(dataclasses.replace(platform, elastic=elastic)))
        log, _ = synthetic_stream(platform, max(sizes), np.random.default_rng(seed), RATE_HZ, smooth=True)
        if exports:
            self._write_exports(log, sizes)
        for n in sizes:
            write_log(self.log(n), log.select(slice(0, n)))
            write_pose_list(self.poses(n), log.desired_poses[:n])
            # one stage of static calibration poses, 10 samples held at each: n samples in all
            atomic_write_text(
                self.experiment(n),
                f'name = "scale-{n}"\nseed = {seed}\nplatform = "nim-stewart"\nsample_period_s = 0.1\n\n'
                f"[poses]\ncalibration = {max(1, n // 10)}\nvalidation = 0\nsamples_per_pose = 10\n\n"
                '[[stages]]\nname = "no-load"\nload_kg = 0.0\nsegments = ["calibration"]\n',
            )

    def _write_exports(self, log, sizes: list[int]) -> None:
        """``import``'s inputs: the desired poses as a Motive export (metres, quaternions, Z-up as
        written) and the strokes as the controller's count log (100 counts/mm, its own clock 5 s ahead)."""
        from scipy.spatial.transform import Rotation

        from stewart_calib.io import atomic_write_text
        from tests.vendor_files import motive_csv

        poses = log.desired_poses
        quaternion = Rotation.from_euler("ZYX", poses[:, [5, 4, 3]]).as_quat()
        atomic_write_text(
            self.import_mapping,
            '[strokes]\ntime = "t_ms"\ntime_unit = "ms"\ncolumns = ["c1", "c2", "c3", "c4", "c5", "c6"]\n'
            'unit = "counts"\ncounts_per_mm = 100.0\nclock_offset_s = 5.0\nmax_gap_s = 0.2\n',
        )
        for n in sizes:
            motive_csv(Path(self.motive(n)), log.t_s[:n], quaternion[:n], poses[:n, :3] / 1000.0)
            header = "t_ms,c1,c2,c3,c4,c5,c6"
            rows = np.column_stack([(log.t_s[:n] + 5.0) * 1000.0, np.round(log.strokes[:n] * 100.0)])
            np.savetxt(self.counts(n), rows, delimiter=",", header=header, comments="", fmt="%.17g")


def _calibrate(method: str):
    return lambda files, n: [
        "calibrate",
        "--platform",
        files.platform,
        "--log",
        files.log(n),
        "--method",
        method,
        "--out",
        files.out(f"calibrate-{method}-{n}.json"),
    ]


#: ``plan``'s candidates for N poses: the command's default 2000 while N ≤ 1000 (the cost is then
#: linear in N at a fixed pool), beyond it twice N so that the design still has a choice.
def plan_candidates(n_poses: int) -> int:
    return max(2000, 2 * n_poses)


def _plan(files: CliInputs, n: int) -> list[str]:
    return [
        "plan",
        "--platform",
        files.platform,
        "--n",
        str(n),
        "--candidates",
        str(plan_candidates(n)),
        "--seed",
        "1",
        "--out",
        files.out(f"plan-{n}.csv"),
    ]


def cli_cases(quick: bool) -> list[CliCase]:
    """The commands and their sizes: 10⁶ samples for the online methods and the streaming commands,
    10³ poses for ``plan`` (its greedy design costs O(N·M) for M candidates: linear in N at the default
    2000; 10⁴ poses from 2·10⁴ candidates take ~10 min, measured), ``reproduce --quick`` once.

    ``quick``: ``calibrate ekf`` at 300 samples (a smoke test of the harness; a fresh process costs seconds).
    """
    every = (CLI_START_SAMPLES, *((300,) if quick else CLI_SIZES))
    batch = tuple(n for n in every if n <= 100_000)
    cases = [
        CliCase("calibrate ekf", _calibrate("ekf"), every),
        CliCase(
            "calibrate ekf [elastic]",
            lambda f, n: [
                *("calibrate", "--platform", f.elastic_platform, "--log", f.log(n), "--method", "ekf"),
                *("--out", f.out(f"calibrate-ekf-elastic-{n}.json")),
            ],
            batch,
        ),
        CliCase("calibrate paper-ekf", _calibrate("paper-ekf"), every),
        CliCase("calibrate isam2", _calibrate("isam2"), batch),
        CliCase("calibrate ls", _calibrate("ls"), batch),
        CliCase("calibrate lm", _calibrate("lm"), batch),
        CliCase(
            "calibrate ekf --trace", lambda f, n: [*_calibrate("ekf")(f, n), "--trace", f.out(f"trace-{n}.csv")], every
        ),
        CliCase(
            "track ekf",
            lambda f, n: [
                "track",
                "--platform",
                f.platform,
                "--method",
                "ekf",
                "--log",
                f.log(n),
                "--out",
                f.out(f"track-{n}.json"),
            ],
            every,
        ),
        CliCase(
            "identifiability", lambda f, n: ["identifiability", "--platform", f.platform, "--log", f.log(n)], every
        ),
        CliCase(
            "compensate",
            lambda f, n: [
                "compensate",
                "--platform",
                f.platform,
                "--result",
                f.out(f"calibrate-ekf-{CLI_START_SAMPLES}.json"),
                "--poses",
                f.poses(n),
                "--out",
                f.out(f"strokes-{n}.csv"),
            ],
            every,
        ),
        CliCase(
            "simulate", lambda f, n: ["simulate", "--experiment", f.experiment(n), "--out", f.out(f"sim-{n}")], every
        ),
        CliCase(
            "validate",
            lambda f, n: [
                "validate",
                "--platform",
                f.platform,
                "--result",
                f.out(f"calibrate-ekf-{CLI_START_SAMPLES}.json"),
                "--log",
                f.log(n),
                "--out",
                f.out(f"validate-{n}.csv"),
            ],
            every,
        ),
        CliCase(
            "import",
            lambda f, n: [
                "import",
                "--motive",
                f.motive(n),
                "--rigid-body",
                "platform",
                "--up",
                "z",
                "--strokes",
                f.counts(n),
                "--mapping",
                f.import_mapping,
                "--out",
                f.out(f"import-{n}.csv"),
            ],
            every,
        ),
        CliCase("plan", _plan, tuple(n for n in every if n <= 1_000), unit="pose"),
        CliCase(
            "reproduce --quick",
            lambda f, n: ["reproduce", "--quick", "--out", f.out("reproduce")],
            (CLI_START_SAMPLES,),
            fixed=True,
        ),
    ]
    return [c for c in cases if c.name in QUICK_CASES] if quick else cases


#: the checkout whose ``stewart_calib`` the CLI runs use (``python -m benchmarks.scale --package-root``).
PACKAGE_ROOT = ROOT
GNU_TIME = Path("/usr/bin/time")


def _run_cli(
    argv: list[str],
    cap_s: float,
    stdout_path: Path,
    python_flags: tuple[str, ...] = (),
    env: dict | None = None,
    root: Path | None = None,
) -> dict:
    """Run ``python [flags] -m stewart_calib ARGV`` as a user would (``env``: variables to set besides;
    ``root``: the checkout whose package runs, :data:`PACKAGE_ROOT` unless given); wall time, CPU
    time, peak RSS, exit status."""
    root = root or PACKAGE_ROOT
    env = {**os.environ, "PYTHONPATH": str(root), **(env or {})}
    command = [sys.executable, *python_flags, "-m", "stewart_calib", *argv]
    # A forked child's ru_maxrss counts the parent's pages until exec; GNU time measures the
    # command from a small process of its own, so only the command's memory is counted.
    rss_path = stdout_path.with_suffix(".rss")
    rss_path.unlink(missing_ok=True)
    if GNU_TIME.exists():
        command = [str(GNU_TIME), "-f", "%M", "-o", str(rss_path), *command]
    with open(stdout_path, "wb") as out, open(stdout_path.with_suffix(".err"), "wb") as err:
        start = time.perf_counter()
        # cwd too: ``python -m`` puts it ahead of PYTHONPATH on sys.path
        proc = subprocess.Popen(
            command, stdout=out, stderr=err, stdin=subprocess.DEVNULL, cwd=root, env=env, start_new_session=True
        )  # its own process group: a capped run is stopped whole
        deadline = start + cap_s
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            if time.perf_counter() > deadline:
                _stop_command(proc.pid)
                _, status, usage = os.wait4(proc.pid, 0)
                proc.returncode = -9
                return {
                    "wall_s": time.perf_counter() - start,
                    "cpu_s": usage.ru_utime + usage.ru_stime,
                    "capped": True,
                    "peak_rss_mib": _peak_kib(rss_path, usage) / 1024,
                }
            time.sleep(0.02)
        proc.returncode = os.waitstatus_to_exitcode(status)
    # CPU time (user + system, of every thread; wait4 counts the reaped command under GNU time)
    # stands a machine shared with other work better than wall time, which a second core can shorten
    return {
        "wall_s": time.perf_counter() - start,
        "cpu_s": usage.ru_utime + usage.ru_stime,
        "capped": False,
        "exit": proc.returncode,
        "peak_rss_mib": _peak_kib(rss_path, usage) / 1024,
    }


def _stop_command(pid: int) -> None:
    """Stop a capped run: the command first, so that GNU time (``pid``) still writes its peak RSS
    (killed with it, it writes nothing, and ``wait4`` would count the harness's pages of the fork),
    then the rest of its process group."""
    try:
        commands = Path(f"/proc/{pid}/task/{pid}/children").read_text().split() if GNU_TIME.exists() else []
    except OSError:
        commands = []
    for command in commands:
        os.kill(int(command), signal.SIGKILL)
    for _ in range(250):  # GNU time writes and exits within milliseconds
        if not commands or os.waitid(os.P_PID, pid, os.WEXITED | os.WNOHANG | os.WNOWAIT) is not None:
            break
        time.sleep(0.02)
    os.killpg(pid, signal.SIGKILL)


def _peak_kib(rss_path: Path, usage) -> float:
    """GNU time's maximum resident set of the command [KiB], else ``wait4``'s (which includes the fork's)."""
    try:
        return float(rss_path.read_text().split()[-1])
    except (OSError, ValueError, IndexError):
        return float(usage.ru_maxrss)


def import_profile(argv: list[str], work: Path) -> dict:
    """``python -X importtime -m stewart_calib ARGV``: total import time [s] and the heavy modules imported."""
    path = work / "importtime.out"
    run = _run_cli(argv, CLI_CAP_S, path, ("-X", "importtime"))
    total_us, modules = 0, set()
    for line in path.with_suffix(".err").read_text(encoding="utf-8", errors="replace").splitlines():
        if not line.startswith("import time:") or "cumulative" in line:
            continue
        _, cumulative, name = line[len("import time:") :].split("|")
        modules.add(name.strip())
        if not name[1:].startswith(" "):  # a top-level import: its cumulative time holds its children's
            total_us += int(cumulative)
    heavy = [m for m in HEAVY_MODULES if m in modules]
    return {
        "imports_s": total_us / 1e6,
        "heavy_imported": heavy,
        "wall_s": run["wall_s"],
        "peak_rss_mib": run["peak_rss_mib"],
    }


def run_cli(quick: bool, seed: int, png_path: Path, only: list[str] | None = None) -> Section:
    """The CLI scale section: every command (or those named in ``only``) at every size, import time of start-up."""
    import tempfile

    cases = [case for case in cli_cases(quick) if only is None or case.name in only]
    sizes = sorted({n for case in cases for n in case.sizes})
    results: dict[str, dict[int, dict]] = {}
    with tempfile.TemporaryDirectory(prefix="stewart-calib-scale-") as tmp:
        files = CliInputs(Path(tmp))
        files.write(sizes, seed, exports=any(case.name == "import" for case in cases))
        _run_cli(_calibrate("ekf")(files, CLI_START_SAMPLES), CLI_CAP_S, files.root / "out" / "stdout")  # warm caches
        imports = {
            "stewart-calib --help": import_profile(["--help"], files.root),
            f"calibrate ekf, {CLI_START_SAMPLES} samples": import_profile(
                _calibrate("ekf")(files, CLI_START_SAMPLES), files.root
            ),
        }
        for case in cases:
            results[case.name] = {}
            if not quick:  # unmeasured: numba's on-disk cache of a fresh checkout is compiled by a first run
                _run_cli(case.argv(files, CLI_START_SAMPLES), CLI_CAP_S, files.root / "out" / "stdout")
            for n in case.sizes:
                run = _run_cli(case.argv(files, n), CLI_CAP_S, files.root / "out" / "stdout")
                results[case.name][n] = run
                print(
                    f"  {case.name}{'' if case.fixed else f' at {n:,}'}: {run['wall_s']:.1f} s, "
                    f"{run['peak_rss_mib']:.0f} MiB",
                    file=sys.stderr,
                )
                if run["capped"] or run.get("exit"):
                    break
    for runs in results.values():
        start = runs[CLI_START_SAMPLES]
        if start["capped"] or start.get("exit"):
            continue
        for n, run in runs.items():
            if n > CLI_START_SAMPLES and not run["capped"]:
                run["marginal_us_per_sample"] = (run["wall_s"] - start["wall_s"]) / (n - CLI_START_SAMPLES) * 1e6
                run["marginal_cpu_us_per_sample"] = (run["cpu_s"] - start["cpu_s"]) / (n - CLI_START_SAMPLES) * 1e6
    _plot_cli(results, png_path)

    rows = []
    for label, profile in imports.items():
        rows.append(
            Row(
                f"imports of `{label}`",
                f"{profile['imports_s'] * 1e3:.0f} ms of imports ({profile['wall_s']:.2f} s wall, "
                f"{profile['peak_rss_mib']:.0f} MiB); heavy modules imported: "
                f"{', '.join(profile['heavy_imported']) or 'none'}",
                f"≤ {IMPORT_TARGET_S:g} s, none of {', '.join(HEAVY_MODULES)}",
                profile["imports_s"] <= IMPORT_TARGET_S and not profile["heavy_imported"],
                profile,
            )
        )
    for case in cases:
        name, runs = case.name, results[case.name]
        for n, run in runs.items():
            if n == CLI_START_SAMPLES and not case.fixed:
                continue
            value = (
                f"over the {CLI_CAP_S:.0f} s cap"
                if run["capped"]
                else f"exit {run['exit']}"
                if run.get("exit")
                else f"{run['wall_s']:.2f} s (CPU {run['cpu_s']:.2f} s)"
                if case.fixed
                else f"{fmt_time_us(run['marginal_us_per_sample'])}/{case.unit}, {run['wall_s']:.2f} s "
                f"(CPU {fmt_time_us(run['marginal_cpu_us_per_sample'])}/{case.unit})"
            )
            value += f", peak RSS {run['peak_rss_mib']:.0f} MiB"
            target, met = "", None
            if (name, n) in CLI_TARGETS:
                limit = CLI_TARGETS[name, n]
                target = f"≤ {fmt_time_us(limit)}/sample"
                met = "marginal_us_per_sample" in run and run["marginal_us_per_sample"] <= limit
            if (name, n) in CLI_RSS_TARGET_MIB:
                limit = CLI_RSS_TARGET_MIB[name, n]
                target = ", ".join(filter(None, [target, f"peak RSS ≤ {limit:.0f} MiB"]))
                met = (met is not False) and not run["capped"] and run["peak_rss_mib"] <= limit
            rows.append(Row(name if case.fixed else f"{name} at {n:,} {case.unit}s", value, target, met, run))
    note = (
        "Each command run as a user runs it (`python -m stewart_calib …` in a fresh process, on files written "
        f"beforehand: a {RATE_HZ:g} Hz Lissajous log, its poses as a pose list, a one-stage experiment). Time per "
        f"sample is marginal: (wall(N) − wall({CLI_START_SAMPLES})) / (N − {CLI_START_SAMPLES}) of the same command, "
        "so start-up is not spread over the samples (CPU: the same of user + system time, all threads); "
        "peak RSS is the command's maximum resident set (GNU time %M). "
        "Imports measured with `python -X importtime` (sum of the top-level imports' cumulative times). "
        f"Runs over {CLI_CAP_S:.0f} s are stopped. No peer: the commands against their own targets — the per-sample "
        "cost at 10⁵ samples of the commands users run on long logs, peak RSS at 10⁶, and a start-up that imports "
        f"in ≤ {IMPORT_TARGET_S:g} s and none of {', '.join(HEAVY_MODULES)}."
    )
    section = Section("Scale through the CLI", note, rows, raw={"runs": results, "imports": imports})
    return explain(section, CLI_WHY)


#: why a target of the CLI section may not be met (a row not met carries its sentence)
#: calibrate measures the in-situ tracker's own geometry on the log's first 2000 samples, the baseline's 100 at 100
GEOMETRY_ESTIMATE_WHY = (
    "calibrate measures the in-situ tracker's own geometry on the log's first 2000 samples, about a second more "
    "than on the 100-sample baseline's 100, which the marginal cost at 10⁵ samples counts as some 10 µs a sample; "
    "the 10⁶-sample row, where it weighs a tenth as much, shows the steady cost"
)
CLI_WHY = {
    "calibrate ekf [elastic]": (
        "with `[elastic]` the filter carries 48 unknowns against 42, solves every reading's tracker FK for the leg "
        "forces and settles the calibrated drive in the residual pass, a few µs a sample over the rigid run; "
        f"{GEOMETRY_ESTIMATE_WHY}; and this shared machine's speed drifts by ±25 % from minute to minute."
    ),
    "calibrate ekf at": f"{GEOMETRY_ESTIMATE_WHY}; and this shared machine's speed drifts by ±25 % from minute to "
    "minute.",
    "track ekf": (
        "track updates its filter one sample at a time, as beside a controller, and on this machine the online "
        "per-sample cost (Speed) is itself above its target."
    ),
}


# ----------------------------------------------------------------------------- start-up
#
# What a new user meets: each command's first run after an installation, with numba's on-disk cache
# empty (every kernel the command uses is compiled), and the runs after it (the kernels loaded from
# the cache), on the README's example: the quick simulation (120 samples) and the paper's settings.

STARTUP_FIRST_TARGET_S = 10.0
STARTUP_FIRST_TARGET_RATIO = 5.0
STARTUP_WARM_TARGET_S = 1.0
REPRODUCE_FIRST_TARGET_S = 40.0
#: warm runs per command; the minimum is reported (a shared machine only ever adds time)
STARTUP_WARM_RUNS = 3


@dataclass(frozen=True)
class StartupCase:
    """A command of the start-up table: its arguments in the work directory ``root``; ``targets``:
    which of the start-up targets apply to it: ``calibrate`` (ekf's), ``reproduce`` (the full one's),
    ``mocap`` (isam2 with the motion-capture preset, warm)."""

    name: str
    argv: Callable[[Path], list[str]]
    targets: str = ""


def _startup_calibrate(method: str) -> Callable[[Path], list[str]]:
    return lambda root: [
        "calibrate",
        "--platform",
        str(root / "sim" / "platform.toml"),
        "--log",
        str(root / "sim" / "log.csv"),
        "--method",
        method,
        "--config",
        "paper",
        "--out",
        str(root / "out" / f"calibrate-{method}.json"),
    ]


def startup_cases(quick: bool) -> list[StartupCase]:
    """``calibrate`` with ekf, isam2 and ls, ``track``, ``validate`` (of the ekf result), ``reproduce --quick``,
    and (not ``quick``) the full ``reproduce``, the README's main job, and ``isam2`` with the motion-capture
    preset on the hobby hexapod's session (:data:`MOCAP_SAMPLES` samples)."""
    cases = [
        StartupCase("calibrate ekf", _startup_calibrate("ekf"), "calibrate"),
        StartupCase("calibrate isam2", _startup_calibrate("isam2")),
        StartupCase("calibrate ls", _startup_calibrate("ls")),
        StartupCase(
            "track ekf",
            lambda root: [
                "track",
                "--platform",
                str(root / "sim" / "platform.toml"),
                "--method",
                "ekf",
                "--config",
                "paper",
                "--log",
                str(root / "sim" / "log.csv"),
                "--out",
                str(root / "out" / "track.json"),
            ],
        ),
        StartupCase(
            "validate",
            lambda root: [
                "validate",
                "--platform",
                str(root / "sim" / "platform.toml"),
                "--result",
                str(root / "out" / "calibrate-ekf.json"),
                "--log",
                str(root / "sim" / "log.csv"),
                "--out",
                str(root / "out" / "validate.csv"),
            ],
        ),
        StartupCase("reproduce --quick", lambda root: ["reproduce", "--quick", "--out", str(root / "out" / "quick")]),
    ]
    if quick:
        return cases[:1]
    return [
        *cases,
        StartupCase("reproduce", lambda root: ["reproduce", "--out", str(root / "out" / "full")], "reproduce"),
        StartupCase(
            f"calibrate isam2 --config motion-capture, {MOCAP_SAMPLES} samples",
            lambda root: [
                "calibrate",
                "--platform",
                str(root / "mocap" / "platform.toml"),
                "--log",
                str(root / "mocap" / "log.csv"),
                "--method",
                "isam2",
                "--config",
                "motion-capture",
                "--out",
                str(root / "out" / "mocap-isam2.json"),
            ],
            "mocap",
        ),
    ]


#: the motion-capture preset's case: the hobby hexapod's simulated session (benchmarks.hobby), 1 Hz
MOCAP_SAMPLES = 200
MOCAP_WARM_TARGET_S = 3.0


def _write_mocap_log(directory: Path) -> None:
    from benchmarks.hobby import HOBBY, simulate
    from stewart_calib.io import write_log

    directory.mkdir()
    (directory / "platform.toml").write_text(HOBBY.read_text(encoding="utf-8"), encoding="utf-8")
    data = simulate(1, n_fit=MOCAP_SAMPLES, n_held_out=1)
    write_log(directory / "log.csv", data.fit, data.platform)


def run_startup(quick: bool) -> Section:
    """The start-up section: every :func:`startup_cases` command once with an empty numba cache of
    its own (``NUMBA_CACHE_DIR``), then :data:`STARTUP_WARM_RUNS` times with that cache."""
    import tempfile

    rows, raw = [], {}
    with tempfile.TemporaryDirectory(prefix="stewart-calib-startup-") as tmp:
        root = Path(tmp)
        (root / "out").mkdir()
        setup_cache = {"NUMBA_CACHE_DIR": str(root / "cache-setup")}
        simulate = _run_cli(
            ["simulate", "--experiment", "quick", "--out", str(root / "sim")],
            CLI_CAP_S,
            root / "out" / "stdout",
            env=setup_cache,
        )
        if simulate.get("exit"):
            raise RuntimeError(f"simulate --experiment quick failed: {(root / 'out' / 'stdout.err').read_text()}")
        _write_mocap_log(root / "mocap")
        for case in startup_cases(quick):
            cache = {"NUMBA_CACHE_DIR": str(root / f"cache-{case.name.replace(' ', '-')}")}
            first = _run_cli(case.argv(root), CLI_CAP_S, root / "out" / "stdout", env=cache)
            warm = [
                _run_cli(case.argv(root), CLI_CAP_S, root / "out" / "stdout", env=cache)
                for _ in range(STARTUP_WARM_RUNS)
            ]
            best = min(warm, key=lambda run: run["wall_s"])
            raw[case.name] = {"first": first, "warm": warm, "load_1min": os.getloadavg()[0]}
            failed = first["capped"] or first.get("exit") or best["capped"] or best.get("exit")
            print(f"  {case.name}: first {first['wall_s']:.1f} s, warm {best['wall_s']:.2f} s", file=sys.stderr)
            value = (
                "failed (over the cap or an exit status)"
                if failed
                else f"first {first['wall_s']:.1f} s (CPU {first['cpu_s']:.1f} s, {first['peak_rss_mib']:.0f} MiB), "
                f"warm {best['wall_s']:.2f} s (CPU {best['cpu_s']:.2f} s, {best['peak_rss_mib']:.0f} MiB): "
                f"{first['wall_s'] / best['wall_s']:.1f}×"
            )
            target, met = "", None
            if case.targets == "calibrate":
                target = (
                    f"first ≤ {STARTUP_FIRST_TARGET_S:g} s and ≤ {STARTUP_FIRST_TARGET_RATIO:g}× warm, "
                    f"warm ≤ {STARTUP_WARM_TARGET_S:g} s"
                )
                met = not failed and (
                    first["wall_s"] <= STARTUP_FIRST_TARGET_S
                    and first["wall_s"] <= STARTUP_FIRST_TARGET_RATIO * best["wall_s"]
                    and best["wall_s"] <= STARTUP_WARM_TARGET_S
                )
            elif case.targets == "mocap":
                target = f"warm ≤ {MOCAP_WARM_TARGET_S:g} s"
                met = not failed and best["wall_s"] <= MOCAP_WARM_TARGET_S
            elif case.targets == "reproduce":
                target = f"first ≤ {REPRODUCE_FIRST_TARGET_S:g} s"
                met = not failed and first["wall_s"] <= REPRODUCE_FIRST_TARGET_S
            rows.append(Row(case.name, value, target, met, raw[case.name]))
    note = (
        "A command as a new user meets it: its first run after an installation, with an empty numba cache "
        "of its own (`NUMBA_CACHE_DIR`: the kernels the installation compiled ahead of time run from its module, "
        "setup.py; any other kernel it uses is compiled), then the minimum of "
        f"{STARTUP_WARM_RUNS} runs with that cache (warm). Input: `simulate --experiment quick` (120 samples), "
        "`--config paper`; validate checks the ekf result on the same log. Wall time of "
        "`python -m stewart_calib …` in a fresh process; CPU: user + system, all threads. No peer: the targets are "
        "a first run that costs little more than a warm one, and warm runs short enough to use interactively."
    )
    return explain(Section("Start-up through the CLI", note, rows, raw=raw), STARTUP_WHY)


#: the wall-clock targets assume an idle machine (a row not met carries this sentence)
LOADED_WALL = (
    "the wall-clock targets are set for an idle machine; with other work on the cores each wall time is a multiple "
    "of its CPU time, which is the better guide here."
)
STARTUP_WHY = {"calibrate": LOADED_WALL, "reproduce": LOADED_WALL}


def _plot_cli(results: dict[str, dict[int, dict]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_time, ax_mem) = plt.subplots(1, 2, figsize=(12, 4.5))
    for name, runs in results.items():
        marginal = sorted((n, r["marginal_us_per_sample"]) for n, r in runs.items() if "marginal_us_per_sample" in r)
        if marginal:
            ax_time.plot(*zip(*marginal, strict=True), "o-", label=name)
        ax_mem.plot(sorted(runs), [runs[n]["peak_rss_mib"] for n in sorted(runs)], "o-", label=name)
    ax_time.set(
        xscale="log",
        yscale="log",
        xlabel="samples N",
        ylabel="marginal time per sample [µs]",
        title="Time per sample (flat = linear)",
    )
    ax_mem.set(xscale="log", yscale="log", xlabel="samples N", ylabel="peak RSS [MiB]", title="Peak memory")
    for ax in (ax_time, ax_mem):
        ax.grid(True, which="both", alpha=0.3)
    ax_mem.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.scale [--quick] [--sizes N …] [--cases NAME …] [--package-root DIR] [--update-report]``:
    the CLI section alone (``python -m benchmarks`` runs it with the others); ``--startup``: the start-up
    section (:func:`run_startup`) instead."""
    import argparse
    import json

    from benchmarks import report
    from benchmarks.report import RESULTS

    global PACKAGE_ROOT, CLI_SIZES, CLI_CAP_S
    parser = argparse.ArgumentParser(prog="python -m benchmarks.scale", description=main.__doc__)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--sizes", type=int, nargs="+", default=list(CLI_SIZES))
    parser.add_argument("--cap-s", type=float, default=CLI_CAP_S, help="stop a run after this many seconds")
    parser.add_argument("--package-root", type=Path, default=ROOT, help="checkout to measure (e.g. an older one)")
    parser.add_argument("--json", type=Path, help="write the section's raw numbers here")
    parser.add_argument("--cases", nargs="+", metavar="NAME", help="only these commands (e.g. 'calibrate ekf')")
    parser.add_argument(
        "--update-report",
        action="store_true",
        help="save this section's results in benchmarks/results/ and regenerate BENCHMARKS.md",
    )
    parser.add_argument("--seed", type=int, default=2024)
    parser.add_argument(
        "--startup", action="store_true", help="the start-up section instead: first run (empty cache) and warm"
    )
    args = parser.parse_args(argv)
    PACKAGE_ROOT, CLI_SIZES, CLI_CAP_S = args.package_root.resolve(), tuple(args.sizes), args.cap_s
    png = RESULTS / "scale-cli-full.png" if args.update_report else Path(args.json or "scale-cli").with_suffix(".png")
    info = report.start(" ".join(["python -m benchmarks.scale", *(sys.argv[1:] if argv is None else argv)]))
    section = run_startup(args.quick) if args.startup else run_cli(args.quick, args.seed, png, args.cases)
    for row in section.rows:
        print(f"| {row.name} | {row.value} | {row.target or '—'} | {row.met} |")
    if args.json:
        args.json.write_text(json.dumps(section.to_dict(), indent=1, default=float), encoding="utf-8")
    if args.update_report:
        section.plot = "" if args.startup else png.name
        report.save("startup" if args.startup else "scale-cli", [section], info, quick=False)
        report.write()
    return 0


if __name__ == "__main__":
    sys.exit(main())
