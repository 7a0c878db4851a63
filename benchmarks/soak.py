"""Soak test (benchmark, not CI): long runs must stay healthy and bounded.

    python -m benchmarks.soak [--ekf-updates 1000000] [--isam2-samples 100000] [--time-limit-s 600]

* ``ekf``: 10⁶ updates of the leg-length EKF on a smooth 1 kHz trajectory; every checkpoint
  interval: the covariance's asymmetry ``max |P − Pᵀ|`` and least eigenvalue (must stay > 0),
  Python heap (tracemalloc) and process RSS, which must not grow after warm-up.
* ``isam2``: the resumable fixed-lag smoother
  (:class:`~stewart_calib.estimators.isam2.ISAM2Estimator`, as ``track`` runs it) on a 10 Hz trajectory,
  as many samples as fit in ``--time-limit-s``: graph size, replay
  buffer, RSS and update time, all of which must stay flat.

Data come from the kinematics directly (true drive = nominal + δM, tracker readings with
2 µm noise): the point is the estimators' long-run behaviour, not the physics.
"""

from __future__ import annotations

import argparse
import time
import tracemalloc

import numpy as np

from stewart_calib.config import EstimatorConfig
from stewart_calib.estimators import make_estimator
from stewart_calib.io.platform_file import load_platform
from stewart_calib.model import kinematics as kin
from stewart_calib.model.platform import Platform
from stewart_calib.samples import Sample

PLATFORM = "configs/platforms/nim-stewart.toml"
CHUNK = 10_000  # samples generated at once (vectorised IK)
#: trajectory: each axis a sine of this amplitude fraction of the workspace box, at
#: incommensurate frequencies so the poses never repeat exactly [Hz].
FREQUENCIES_HZ = np.array([0.05, 0.071, 0.037, 0.043, 0.061, 0.029])
AMPLITUDE = 0.6


def rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def samples(platform: Platform, true_error: np.ndarray, n: int, dt_s: float, rng: np.random.Generator):
    """``n`` samples of a smooth trajectory, generated ``CHUNK`` at a time (memory stays flat)."""
    ws = platform.workspace
    half = AMPLITUDE * np.r_[[ws.translation_limit] * 3, [ws.rotation_limit] * 3]
    drive = platform.drive.perturbed(true_error)
    for start in range(0, n, CHUNK):
        t_s = np.arange(start, min(n, start + CHUNK)) * dt_s
        poses = ws.home + half * np.sin(2 * np.pi * FREQUENCIES_HZ * t_s[:, None])
        R, t = kin.pose_to_rt(poses)
        strokes = kin.inverse_kinematics(drive, R, t) + rng.normal(0.0, 0.001, (len(t_s), 6))
        readings = kin.inverse_kinematics(platform.tracker, R, t) + rng.normal(0.0, 0.002, (len(t_s), 6))
        for k in range(len(t_s)):
            yield Sample(float(t_s[k]), strokes[k], readings[k])


def soak_ekf(platform: Platform, n: int, rng: np.random.Generator, report_every: int) -> None:
    true_error = rng.normal(0.0, 1.0, 42)
    ekf = make_estimator("ekf", platform, EstimatorConfig())
    tracemalloc.start()
    start = time.perf_counter()
    print("ekf: updates  rate[/s]  max|P-P^T|  min eig(P)[mm^2]  rms err[mm]  heap[MB]  RSS[MB]")
    for k, sample in enumerate(samples(platform, true_error, n, 1e-3, rng), start=1):
        ekf.update(sample)
        if k % report_every == 0 or k == n:
            P = ekf.filter.P
            heap = tracemalloc.get_traced_memory()[0] / 2**20
            rms = float(np.sqrt(np.mean((ekf.filter.x - true_error) ** 2)))
            print(
                f"ekf: {k:8d}  {k / (time.perf_counter() - start):8.0f}  {np.max(np.abs(P - P.T)):.1e}  "
                f"{np.linalg.eigvalsh(P)[0]:.3e}  {rms:.2e}  {heap:7.2f}  {rss_mb():7.1f}",
                flush=True,
            )
    tracemalloc.stop()


def soak_isam2(platform: Platform, n: int, rng: np.random.Generator, report_every: int, time_limit_s: float) -> None:
    true_error = rng.normal(0.0, 1.0, 42)
    isam2 = make_estimator("isam2", platform, EstimatorConfig())
    start = time.perf_counter()
    worst_s, last = 0.0, start
    print("isam2: samples  rate[/s]  worst update[ms]  factors  variables  replay  rms err[mm]  RSS[MB]")
    for k, sample in enumerate(samples(platform, true_error, n, 0.1, rng), start=1):
        t0 = time.perf_counter()
        isam2.update(sample)
        last = time.perf_counter()
        worst_s = max(worst_s, last - t0)
        done = last - start > time_limit_s
        if k % report_every == 0 or k == n or done:
            factors, variables = isam2.graph_size()
            rms = float(np.sqrt(np.mean((isam2.estimate().error - true_error) ** 2)))
            print(
                f"isam2: {k:7d}  {k / (last - start):7.0f}  {1e3 * worst_s:8.1f}  {factors:7d}  {variables:7d}  "
                f"{len(isam2.export_state()['replay']['t_s']):6d}  {rms:.2e}  {rss_mb():7.1f}",
                flush=True,
            )
            worst_s = 0.0
        if done:
            print(f"isam2: stopped at the time limit ({time_limit_s:.0f} s) after {k} samples")
            break


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ekf-updates", type=int, default=1_000_000)
    parser.add_argument("--isam2-samples", type=int, default=100_000)
    parser.add_argument("--time-limit-s", type=float, default=600.0, help="isam2 stops here")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    platform = load_platform(PLATFORM)
    rng = np.random.default_rng(args.seed)
    if args.ekf_updates:
        soak_ekf(platform, args.ekf_updates, rng, max(1, args.ekf_updates // 10))
    if args.isam2_samples:
        soak_isam2(platform, args.isam2_samples, rng, max(1, args.isam2_samples // 10), args.time_limit_s)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
