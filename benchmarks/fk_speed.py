"""Forward-kinematics and online per-sample speed.

``python -m benchmarks.fk_speed [--poses N] [--repeats K] [--samples S]``

Prints, for the drive and the tracker of configs/platforms/nim-stewart.toml, along a 1 kHz
Lissajous trajectory inside the ±200 mm / ±20° workspace (FK tolerance 1e-9 mm):

* Newton iterations: cold (from home) and warm (from the previous pose of the trajectory);
* µs per single warm solve (median over calls) of ``kinematics.forward_kinematics`` (the
  package's one path: a cached numba kernel, ``stewart_calib.model._kernels.fk_newton``), of a
  plain straightforward numpy Newton written here as the peer, and their ratio;
* poses/s of one batched ``forward_kinematics`` call on ``N`` (10 000) poses, cold and warm
  (best of 3 calls);
* the online per-sample cost of both EKFs (``LegEKF.update``, ``PaperEKF.update``: sample
  check, FK, Jacobians, Kalman update) along the same 1 kHz trajectory, median over samples,
  and of the shared ``kalman_update`` alone;
* the time of the first call in this process (numba loading its on-disk cache, or compiling
  when the cache is cold: delete ``stewart_calib/**/__pycache__/*.nb[ic]`` to see that).

Nothing here is asserted; the numbers are for reading beside BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from stewart_calib.io.platform_file import load_platform
from stewart_calib.model import kinematics as kin
from stewart_calib.model.platform import LegGeometry

PLATFORM_FILE = Path(__file__).resolve().parents[1] / "configs" / "platforms" / "nim-stewart.toml"
TOL_MM = 1e-9
MAX_ITERATIONS = 30


def trajectory(home: np.ndarray, n: int, rate_hz: float = 1000.0) -> np.ndarray:
    """``(n, 6)`` pose6 of a Lissajous path: ±150 mm in x, y, ±100 mm in z, ±15° per axis."""
    time_s = np.arange(n) / rate_hz
    waves = np.stack(
        [
            np.sin(2 * np.pi * f * time_s + phase)
            for f, phase in ((0.30, 0.0), (0.20, 1.0), (0.50, 2.0), (0.40, 0.5), (0.25, 1.5), (0.35, 2.5))
        ],
        axis=-1,
    )
    return home + waves * np.r_[150.0, 150.0, 100.0, [np.radians(15.0)] * 3]


# ----------------------------------------------------------------------------- the numpy peer


def peer_fk(base, platform_joints, lengths, R, t, tol_mm=TOL_MM, max_iterations=MAX_ITERATIONS):
    """Plain Newton–Raphson on the six leg lengths, body-tangent steps; returns ``(R, t, iterations)``."""
    for iteration in range(max_iterations + 1):
        vec = t + platform_joints @ R.T - base
        length = np.linalg.norm(vec, axis=1)
        err = lengths - length
        if np.max(np.abs(err)) <= tol_mm:
            return R, t, iteration
        n_body = (vec / length[:, None]) @ R  # rows Rᵀ n_i
        J = np.hstack([np.cross(platform_joints, n_body), n_body])
        xi = np.linalg.solve(J, err)
        t = t + R @ xi[3:]
        R = R @ kin.so3_exp(xi[:3])
    raise RuntimeError("peer FK did not converge")


# ----------------------------------------------------------------------------- measurement


def median_us(calls) -> float:
    """Median wall time of each zero-argument call [µs]."""
    times = np.empty(len(calls))
    for k, call in enumerate(calls):
        start = time.perf_counter_ns()
        call()
        times[k] = time.perf_counter_ns() - start
    return float(np.median(times)) / 1e3


def best_seconds(call, repeats: int = 3) -> float:
    """Fastest of ``repeats`` wall times of ``call()`` [s] (least disturbed by other load)."""
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        best = min(best, time.perf_counter() - start)
    return best


def bench(name: str, legs: LegGeometry, home: np.ndarray, poses: np.ndarray, repeats: int) -> None:
    R, t = kin.pose_to_rt(poses)
    strokes = kin.inverse_kinematics(legs, R, t)
    lengths = strokes + legs.initial_lengths
    home_R, home_t = kin.pose_to_rt(home)
    n_single = min(repeats, len(poses) - 1)
    idx = np.arange(1, n_single + 1)

    cold = kin.forward_kinematics(legs, strokes, guess=(home_R, home_t), tol_mm=TOL_MM).iterations
    warm = kin.forward_kinematics(legs, strokes[1:], guess=(R[:-1], t[:-1]), tol_mm=TOL_MM).iterations
    print(f"\n[{name}] {len(poses)} poses at 1 kHz, FK tol {TOL_MM:g} mm")
    print(f"  iterations cold (home):   median {np.median(cold):.0f}, mean {cold.mean():.2f}, max {cold.max()}")
    print(f"  iterations warm (prev.):  median {np.median(warm):.0f}, mean {warm.mean():.2f}, max {warm.max()}")

    ours = median_us([lambda k=k: kin.forward_kinematics(legs, strokes[k], guess=(R[k - 1], t[k - 1])) for k in idx])
    peer = median_us(
        [lambda k=k: peer_fk(legs.base_joints, legs.platform_joints, lengths[k], R[k - 1], t[k - 1]) for k in idx]
    )
    print(
        f"  single warm solve:        stewart_calib {ours:8.1f} µs | numpy peer {peer:8.1f} µs | ratio "
        f"{ours / peer:.2f}"
    )

    for label, guess in (("cold", (home_R, home_t)), ("warm", (np.r_[R[:1], R[:-1]], np.r_[t[:1], t[:-1]]))):
        elapsed = best_seconds(lambda guess=guess: kin.forward_kinematics(legs, strokes, guess=guess, tol_mm=TOL_MM))
        print(
            f"  batched {label}:             {len(poses) / elapsed:10.0f} poses/s ({elapsed * 1e3:.1f} ms for "
            f"{len(poses)})"
        )


def bench_online(platform, poses: np.ndarray, samples: int) -> None:
    """Median µs per ``update`` of both EKFs on noisy samples of the 1 kHz trajectory."""
    from stewart_calib.config import config_from_dict
    from stewart_calib.estimators import make_estimator
    from stewart_calib.estimators.kalman import kalman_update
    from stewart_calib.samples import Sample

    rng = np.random.default_rng(0)
    R, t = kin.pose_to_rt(poses[:samples])
    strokes = kin.inverse_kinematics(platform.drive, R, t) + rng.normal(0.0, 0.001, (len(R), 6))
    readings = kin.inverse_kinematics(platform.tracker, R, t) + rng.normal(0.0, 0.002, (len(R), 6))
    stream = [Sample(k * 1e-3, strokes[k], readings[k]) for k in range(len(R))]
    print(f"\n[online] {len(stream)} samples at 1 kHz, median µs per update (first 100 skipped)")
    for method in ("ekf", "paper-ekf"):
        estimator = make_estimator(method, platform, config_from_dict({}))
        times = np.array([median_us([lambda s=s, estimator=estimator: estimator.update(s)]) for s in stream])
        print(f"  {method:10s} update:      {np.median(times[100:]):8.1f} µs (first sample {times[0] / 1e3:.1f} ms)")
    x, P, Q = np.zeros(42), np.eye(42), np.eye(42) * 1e-9
    H, R_meas, nu = rng.normal(size=(6, 42)), np.eye(6), rng.normal(size=6)
    kf = median_us([lambda: kalman_update(x, P, H, nu, R_meas, Q, np.inf)] * 2000)
    print(f"  kalman_update alone:   {kf:8.1f} µs")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=10_000, help="trajectory length (1 kHz samples)")
    parser.add_argument("--repeats", type=int, default=2_000, help="single solves timed (median reported)")
    parser.add_argument("--samples", type=int, default=2_000, help="samples fed to each EKF (median reported)")
    args = parser.parse_args(argv)

    platform = load_platform(PLATFORM_FILE)
    poses = trajectory(platform.workspace.home, args.poses)
    import platform as host

    import numba

    print(f"python {host.python_version()}, numpy {np.__version__}, numba {numba.__version__}, {host.machine()}")
    home_R, home_t = kin.pose_to_rt(platform.workspace.home)
    start = time.perf_counter()
    kin.forward_kinematics(platform.tracker, np.zeros(6), guess=(home_R, home_t))
    print(f"first forward_kinematics call: {time.perf_counter() - start:.2f} s (cache load, or compile when cold)")
    for name, legs in (("drive", platform.drive), ("tracker", platform.tracker)):
        bench(name, legs, platform.workspace.home, poses, args.repeats)
    bench_online(platform, poses, args.samples)


if __name__ == "__main__":
    main()
