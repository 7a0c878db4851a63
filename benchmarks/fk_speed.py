"""Forward-kinematics speed: ``python -m benchmarks.fk_speed [--poses N] [--repeats K]``.

Prints, for the drive and the tracker of configs/platforms/nim-stewart.toml, along a 1 kHz
Lissajous trajectory inside the ±200 mm / ±20° workspace (FK tolerance 1e-9 mm):

* Newton iterations: cold (from home) and warm (from the previous pose of the trajectory);
* µs per single warm solve (median over calls) of ``kinematics.forward_kinematics``, of a
  plain straightforward numpy Newton written here as the peer, and their ratio;
* poses/s of one batched ``forward_kinematics`` call on ``N`` (10 000) poses, cold and warm
  (best of 3 calls);
* a numba-compiled single warm FK (hand-written 6×6 Gaussian elimination), compile time,
  µs per solve and batched poses/s — to tell whether numba reaches ≤ 10 µs. numba is *not* a
  package dependency; this part is skipped when it is not installed.

Nothing here is asserted; the numbers are for the benchmark issue.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from stewart_calib import kinematics as kin
from stewart_calib.platform import LegGeometry, load_platform

PLATFORM_FILE = Path(__file__).resolve().parents[1] / "configs" / "platforms" / "nim-stewart.toml"
TOL_MM = 1e-9
MAX_ITERATIONS = 30


def trajectory(home: np.ndarray, n: int, rate_hz: float = 1000.0) -> np.ndarray:
    """``(n, 6)`` pose6 of a Lissajous path: ±150 mm in x, y, ±100 mm in z, ±15° per axis."""
    time_s = np.arange(n) / rate_hz
    waves = np.stack([np.sin(2 * np.pi * f * time_s + phase) for f, phase in
                      ((0.30, 0.0), (0.20, 1.0), (0.50, 2.0), (0.40, 0.5), (0.25, 1.5), (0.35, 2.5))], axis=-1)
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


# ----------------------------------------------------------------------------- numba


def build_numba(legs: LegGeometry, home: np.ndarray):
    """Compile the numba FK (first call at ``home``); returns ``(single, batched, compile_seconds)`` or None without numba."""
    try:
        import numba
    except ImportError:
        return None

    @numba.njit(cache=False, fastmath=False)
    def solve6(A, b):  # Gaussian elimination with partial pivoting, in place
        for k in range(6):
            p = k
            for i in range(k + 1, 6):
                if abs(A[i, k]) > abs(A[p, k]):
                    p = i
            if p != k:
                for j in range(6):
                    A[k, j], A[p, j] = A[p, j], A[k, j]
                b[k], b[p] = b[p], b[k]
            for i in range(k + 1, 6):
                f = A[i, k] / A[k, k]
                for j in range(k, 6):
                    A[i, j] -= f * A[k, j]
                b[i] -= f * b[k]
        x = np.empty(6)
        for i in range(5, -1, -1):
            s = b[i]
            for j in range(i + 1, 6):
                s -= A[i, j] * x[j]
            x[i] = s / A[i, i]
        return x

    @numba.njit(cache=False)
    def fk_single(base, plat, lengths, R0, t0, tol, max_iterations):
        R = R0.copy()
        t = t0.copy()
        J = np.empty((6, 6))
        err = np.empty(6)
        for iteration in range(max_iterations + 1):
            worst = 0.0
            for i in range(6):
                px, py, pz = plat[i, 0], plat[i, 1], plat[i, 2]
                vx = t[0] + R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz - base[i, 0]
                vy = t[1] + R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz - base[i, 1]
                vz = t[2] + R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz - base[i, 2]
                length = np.sqrt(vx * vx + vy * vy + vz * vz)
                err[i] = lengths[i] - length
                worst = max(worst, abs(err[i]))
                nx = (R[0, 0] * vx + R[1, 0] * vy + R[2, 0] * vz) / length  # Rᵀ n
                ny = (R[0, 1] * vx + R[1, 1] * vy + R[2, 1] * vz) / length
                nz = (R[0, 2] * vx + R[1, 2] * vy + R[2, 2] * vz) / length
                J[i, 0] = py * nz - pz * ny
                J[i, 1] = pz * nx - px * nz
                J[i, 2] = px * ny - py * nx
                J[i, 3], J[i, 4], J[i, 5] = nx, ny, nz
            if worst <= tol:
                return R, t, iteration, True
            if iteration == max_iterations:
                break
            xi = solve6(J, err)
            for a in range(3):
                t[a] += R[a, 0] * xi[3] + R[a, 1] * xi[4] + R[a, 2] * xi[5]
            w0, w1, w2 = xi[0], xi[1], xi[2]
            th2 = w0 * w0 + w1 * w1 + w2 * w2
            th = np.sqrt(th2)
            if th2 < 1e-12:
                ca, cb = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
            else:
                ca, cb = np.sin(th) / th, (1.0 - np.cos(th)) / th2
            K = np.array([[0.0, -w2, w1], [w2, 0.0, -w0], [-w1, w0, 0.0]])
            E = np.eye(3) + ca * K + cb * (K @ K)
            R = R @ E
        return R, t, max_iterations, False

    @numba.njit(cache=False)
    def fk_batch(base, plat, lengths, R0, t0, tol, max_iterations):
        n = lengths.shape[0]
        R_out = np.empty((n, 3, 3))
        t_out = np.empty((n, 3))
        iterations = np.empty(n, dtype=np.int64)
        for k in range(n):
            R, t, it, ok = fk_single(base, plat, lengths[k], R0[k], t0[k], tol, max_iterations)
            R_out[k], t_out[k], iterations[k] = R, t, it if ok else -1
        return R_out, t_out, iterations

    start = time.perf_counter()
    R, t = kin.pose_to_rt(home)
    base, plat, lengths = legs.base_joints.copy(), legs.platform_joints.copy(), legs.initial_lengths.copy()
    fk_single(base, plat, lengths, R, t, TOL_MM, 1)
    fk_batch(base, plat, lengths[None], R[None], t[None], TOL_MM, 1)
    return fk_single, fk_batch, time.perf_counter() - start


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


def bench(name: str, legs: LegGeometry, home: np.ndarray, poses: np.ndarray, repeats: int, numba_fns) -> None:
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
    peer = median_us([lambda k=k: peer_fk(legs.base_joints, legs.platform_joints, lengths[k], R[k - 1], t[k - 1]) for k in idx])
    print(f"  single warm solve:        stewart_calib {ours:8.1f} µs | numpy peer {peer:8.1f} µs | ratio {ours / peer:.2f}")

    for label, guess in (("cold", (home_R, home_t)), ("warm", (np.r_[R[:1], R[:-1]], np.r_[t[:1], t[:-1]]))):
        elapsed = best_seconds(lambda guess=guess: kin.forward_kinematics(legs, strokes, guess=guess, tol_mm=TOL_MM))
        print(f"  batched {label}:             {len(poses) / elapsed:10.0f} poses/s ({elapsed * 1e3:.1f} ms for {len(poses)})")

    if numba_fns is None:
        print("  numba: not installed, skipped")
        return
    fk_single, fk_batch, _ = numba_fns
    base, plat = legs.base_joints.copy(), legs.platform_joints.copy()  # writable: same numba signature
    Rc, tc = np.ascontiguousarray(R), np.ascontiguousarray(t)
    nb_us = median_us([lambda k=k: fk_single(base, plat, lengths[k], Rc[k - 1], tc[k - 1], TOL_MM, MAX_ITERATIONS) for k in idx])
    R_nb, t_nb, it_nb, ok = fk_single(base, plat, lengths[1], Rc[0], tc[0], TOL_MM, MAX_ITERATIONS)
    position_mm, angle_deg = kin.pose_error(R[1], t[1], R_nb, t_nb)
    R0 = np.ascontiguousarray(np.r_[R[:1], R[:-1]])
    t0 = np.ascontiguousarray(np.r_[t[:1], t[:-1]])
    elapsed = best_seconds(lambda: fk_batch(base, plat, lengths, R0, t0, TOL_MM, MAX_ITERATIONS))
    iterations = fk_batch(base, plat, lengths, R0, t0, TOL_MM, MAX_ITERATIONS)[2]
    print(f"  numba single warm solve:  {nb_us:8.1f} µs ({'≤' if nb_us <= 10 else '>'} 10 µs; {it_nb} iterations, "
          f"error {position_mm:.1e} mm / {np.radians(angle_deg):.1e} rad)")
    print(f"  numba batched warm:       {len(poses) / elapsed:10.0f} poses/s (all converged: {bool(np.all(iterations >= 0))})")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=10_000, help="trajectory length (1 kHz samples)")
    parser.add_argument("--repeats", type=int, default=2_000, help="single solves timed (median reported)")
    args = parser.parse_args(argv)

    platform = load_platform(PLATFORM_FILE)
    poses = trajectory(platform.workspace.home, args.poses)
    numba_fns = build_numba(platform.tracker, platform.workspace.home)
    import platform as host

    print(f"python {host.python_version()}, numpy {np.__version__}, {host.machine()}")
    if numba_fns is not None:
        import numba

        print(f"numba {numba.__version__}: first compile {numba_fns[2]:.2f} s (cache=False)")
    for name, legs in (("drive", platform.drive), ("tracker", platform.tracker)):
        bench(name, legs, platform.workspace.home, poses, args.repeats, numba_fns)


if __name__ == "__main__":
    main()
