"""The simulated "hobby hexapod" check of issue 13: our fit against a plain 48-parameter peer.

A small 6-6 hexapod (``configs/platforms/hobby-hexapod.toml``: base radius 150 mm, platform
80 mm) measured by motion capture, as the real data the project is scored on is described:
108 poses to fit and 60 held-out poses recorded on another day with the motion-capture frame
moved; pose noise 0.2 mm / 0.05°; strokes logged through the builders' nominal mm/rev (true
stroke scale off by a few per cent per leg); initial lengths about 15 mm off; the mocap frame
tens of mm and any rotation from the nominal base frame, the rigid body's frame arbitrary.

**The peer** is what a user writes with scipy when no tool exists: ``least_squares`` over 48
parameters — base joints in the mocap frame (18), platform joints in the rigid body's frame
(18), leg offsets (6), mm/rev factors (6) — minimising the plain residual of the file's units
(position mm, orientation degrees), forward kinematics warm-started at the measured pose, and
started from the same closed-form registration as ours (a fair start). Its held-out prediction
is re-registered the same way as ours (a rigid frame fitted to the held-out log).

``python -m benchmarks.hobby [--seeds N]`` prints, per seed and on average, the held-out position
and orientation RMS of ``ls`` and of the peer: without re-registration on a log from the same
session (frame not moved), and re-registered on the other day's log.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import numpy as np
import scipy.optimize

from stewart_calib import kinematics as kin
from stewart_calib.config import EstimatorConfig
from stewart_calib.instruments import lie, pose
from stewart_calib.instruments.external import model_for
from stewart_calib.platform import LegGeometry, Platform, load_platform
from stewart_calib.resources import CONFIGS
from stewart_calib.samples import Log
from stewart_calib.simulation.instrument import InstrumentTruth, SimulatedInstrument

HOBBY = CONFIGS / "platforms" / "hobby-hexapod.toml"
N_FIT, N_HELD_OUT = 108, 60
JOINT_SPREAD_MM = 0.5
LENGTH_SPREAD_MM = 15.0
SCALE_SPREAD = 0.03
FRAME_OFFSET = np.array([40.0, -25.0, 15.0, 5.0, -3.0, 30.0])  # mocap frame vs nominal [mm, deg]
TARGET_OFFSET = np.array([12.0, -8.0, 35.0, 0.0, 0.0, 90.0])  # rigid body's frame in {D} [mm, deg]
FRAME_MOVE = np.array([8.0, -5.0, 3.0, 1.0, 0.5, -2.0])  # the other day's move of the mocap frame


@dataclass(frozen=True)
class HobbyData:
    platform: Platform
    fit: Log
    same_session: Log
    other_day: Log
    true_drive: LegGeometry
    true_scale: np.ndarray


def random_poses(platform: Platform, n: int, rng: np.random.Generator) -> np.ndarray:
    ws = platform.workspace
    half = np.r_[[ws.translation_limit] * 3, [ws.rotation_limit] * 3]
    return ws.home + rng.uniform(-1.0, 1.0, (n, 6)) * half


def reachable_poses(platform: Platform, legs: LegGeometry, scale: np.ndarray, n: int, rng: np.random.Generator):
    """``(R, t, encoder strokes)`` of ``n`` random workspace poses whose strokes lie within the
    platform's stroke range: a real log holds only poses the actuators reach (a pose drawn
    regardless would be refused by every method of ours, spec §3, but not by the peer)."""
    lo, hi = platform.stroke_range
    R, t, strokes = np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, 6))
    while len(strokes) < n:
        R_new, t_new = kin.pose_to_rt(random_poses(platform, n, rng))
        q = kin.inverse_kinematics(legs, R_new, t_new) / (1.0 + scale)
        reached = np.all((q >= lo) & (q <= hi), axis=1)
        R, t, strokes = np.r_[R, R_new[reached]], np.r_[t, t_new[reached]], np.r_[strokes, q[reached]]
    return R[:n], t[:n], strokes[:n]


def simulate(seed: int, n_fit: int = N_FIT, n_held_out: int = N_HELD_OUT) -> HobbyData:
    """Fit log, a held-out log of the same session and one of another day (frame moved)."""
    rng = np.random.default_rng(seed)
    platform = load_platform(HOBBY)
    delta = rng.normal(0.0, JOINT_SPREAD_MM, 42)
    delta[6::7] = rng.normal(0.0, LENGTH_SPREAD_MM, 6)
    true_drive = platform.drive.perturbed(delta)
    scale = rng.normal(0.0, SCALE_SPREAD, 6)

    def session(n: int, frame_offset: np.ndarray) -> Log:
        instrument = SimulatedInstrument.build(platform.instrument, InstrumentTruth(frame_offset, TARGET_OFFSET), rng)
        R, t, strokes = reachable_poses(platform, true_drive, scale, n, rng)
        return Log(np.arange(n) * 1.0, strokes, instrument.read(R, t, instrument.draw(n, rng)))

    fit = session(n_fit, FRAME_OFFSET)
    return HobbyData(
        platform,
        fit,
        session(n_held_out, FRAME_OFFSET),
        session(n_held_out, FRAME_OFFSET + FRAME_MOVE),
        true_drive,
        scale,
    )


# ----------------------------------------------------------------------------- the peer


def _peer_unpack(theta: np.ndarray) -> tuple[LegGeometry, np.ndarray]:
    return LegGeometry(theta[:18].reshape(6, 3), theta[18:36].reshape(6, 3), theta[36:42]), theta[42:48]


def peer_poses(theta: np.ndarray, strokes: np.ndarray, guess) -> tuple[np.ndarray, np.ndarray]:
    """The peer's model: FK of ``l + s q`` with joints in the mocap and rigid-body frames."""
    legs, s = _peer_unpack(theta)
    sol = kin.forward_kinematics(legs, strokes * s, guess=guess, strict=False)
    return sol.R, sol.t


def _peer_residual(theta: np.ndarray, strokes: np.ndarray, measured: np.ndarray) -> np.ndarray:
    R_m, t_m = kin.pose_to_rt(measured)
    R, t = peer_poses(theta, strokes, (R_m, t_m))
    rot_deg = np.degrees(lie.so3_log(np.swapaxes(R_m, -1, -2) @ R))
    return np.concatenate([t - t_m, rot_deg], axis=1).reshape(-1)


def peer_fit(platform: Platform, log: Log) -> np.ndarray:
    """The 48-parameter plain least squares (see the module docstring), from our closed-form start."""
    model = model_for(platform)
    fk = kin.forward_kinematics(platform.drive, log.strokes, strict=False)
    start = model.register(fk.R, fk.t, log.readings)
    R_Fi, t_Fi = lie.inverse(start.R_frame, start.t_frame)
    R_Gi, t_Gi = lie.inverse(start.R_target, start.t_target)
    theta0 = np.concatenate(
        [
            kin.transform_points(R_Fi, t_Fi, platform.drive.base_joints).reshape(-1),
            kin.transform_points(R_Gi, t_Gi, platform.drive.platform_joints).reshape(-1),
            platform.drive.initial_lengths,
            np.ones(6),
        ]
    )
    solution = scipy.optimize.least_squares(
        _peer_residual, theta0, args=(log.strokes, log.readings), method="lm", x_scale="jac"
    )
    return solution.x


def peer_held_out(theta: np.ndarray, log: Log, register: bool) -> tuple[float, float]:
    """Held-out position RMS [mm] and orientation RMS [deg] of the peer."""
    R_m, t_m = kin.pose_to_rt(log.readings)
    R, t = peer_poses(theta, log.strokes, (R_m, t_m))
    if register:  # a rigid frame fitted to this log, as ours is: the same refit with X = the peer's pose
        identity = pose.PoseUnknowns(np.eye(3), np.zeros(3), np.eye(3), np.zeros(3))
        platform = load_platform(HOBBY)
        frame = model_for(platform).refit_frame(identity, R, t, log.readings)
        R, t = pose.predict(frame, R, t)
    position, orientation = kin.pose_error(R_m, t_m, R, t)
    return _rms(position), _rms(orientation)


# ----------------------------------------------------------------------------- ours


def ours_fit(platform: Platform, log: Log, method: str = "ls", config: EstimatorConfig | None = None):
    """``calibrate``'s run of ``method`` (closed-form registration first), its estimate."""
    from stewart_calib.calibration import run_calibration

    return run_calibration(platform, log, method, config).estimate


def ours_held_out(platform: Platform, estimate, log: Log, register: bool) -> tuple[float, float]:
    from stewart_calib.io import result_dict
    from stewart_calib.pipelines.validate import validate

    _, position, orientation = validate(platform, result_dict(estimate, platform), log, register)
    return _rms(position), _rms(orientation)


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.asarray(values) ** 2)))


METHODS = ("ls", "ekf", "isam2", "lm")


def compare(seed: int, methods=METHODS) -> dict:
    """Held-out RMS ``(position mm, orientation deg)`` of each method and of the peer on one
    simulated hobby hexapod: ``{name: {"same": …, "registered": …}}``."""
    data = simulate(seed)
    out = {}
    for method in methods:
        estimate = ours_fit(data.platform, data.fit, method)
        out[method] = {
            "same": ours_held_out(data.platform, estimate, data.same_session, register=False),
            "registered": ours_held_out(data.platform, estimate, data.other_day, register=True),
        }
    theta = peer_fit(data.platform, data.fit)
    out["peer (48-parameter scipy)"] = {
        "same": peer_held_out(theta, data.same_session, register=False),
        "registered": peer_held_out(theta, data.other_day, register=True),
    }
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--methods", default=",".join(METHODS), help="comma-separated methods to compare with the peer")
    args = parser.parse_args(argv)
    rows = [compare(seed, tuple(args.methods.split(","))) for seed in range(args.seeds)]
    print(f"held-out RMS over {args.seeds} simulated hobby hexapods, position mm / orientation deg")
    print("  (same session, not re-registered | other day, frame moved, re-registered)")
    for key in rows[0]:
        same = np.mean([r[key]["same"] for r in rows], axis=0)
        reg = np.mean([r[key]["registered"] for r in rows], axis=0)
        print(f"  {key:28s} {same[0]:.4f} mm / {same[1]:.4f}°  |  {reg[0]:.4f} mm / {reg[1]:.4f}°")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
