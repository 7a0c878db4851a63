"""Write the raw motion-capture example of the README: what a hobbyist's logger records.

``python examples/hobby-mocap/make_raw.py`` (re)writes ``fit_raw.csv`` (108 poses) and
``heldout_raw.csv`` (60 poses, another day: the motion-capture frame moved by a few mm and a
degree) next to itself, from the simulated hobby hexapod of ``configs/platforms/hobby-hexapod.toml``
with a known truth (printed): joints 0.5 mm off, initial lengths about 15 mm off, every leg's
real mm per count a few per cent from the builders' nominal 8 mm/rev over 4096 counts/rev, the
rigid body's frame turned 90° on the platform, the mocap frame 40 mm and 30° from the base.

Columns: ``time_s``, ``enc1 … enc6`` (encoder counts), ``x_m y_m z_m`` (the rigid body's position
in the mocap frame, metres) and ``qw qx qy qz`` (its orientation); pose noise 0.2 mm / 0.05°.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from stewart_calib.io.platform_file import load_platform
from stewart_calib.model import kinematics as kin
from stewart_calib.resources import CONFIGS
from stewart_calib.simulation.instrument import InstrumentTruth, SimulatedInstrument

HERE = Path(__file__).resolve().parent
MM_PER_COUNT = 8.0 / 4096  # the builders' nominal lead over the encoder's counts per revolution
SEED = 2024
STROKE_MARGIN_MM = 2.0  # keep the logged strokes inside the actuators' 0-90 mm


def main() -> None:
    rng = np.random.default_rng(SEED)
    platform = load_platform(CONFIGS / "platforms" / "hobby-hexapod.toml")
    delta = rng.normal(0.0, 0.5, 42)
    delta[6::7] = rng.normal(0.0, 15.0, 6)
    true_drive = platform.drive.perturbed(delta)
    scale = rng.normal(0.0, 0.03, 6)  # real mm per count = nominal × (1 + k)
    target = np.array([12.0, -8.0, 35.0, 0.0, 0.0, 90.0])
    sessions = {
        "fit": (108, np.array([40.0, -25.0, 15.0, 5.0, -3.0, 30.0])),
        "heldout": (60, np.array([48.0, -30.0, 18.0, 6.0, -2.5, 28.0])),
    }
    ws = platform.workspace
    half = 0.7 * np.r_[[ws.translation_limit] * 3, [ws.rotation_limit] * 3]
    for name, (n, frame) in sessions.items():
        instrument = SimulatedInstrument.build(platform.instrument, InstrumentTruth(frame, target), rng)
        poses = np.empty((0, 6))
        while len(poses) < n:
            candidates = ws.home + rng.uniform(-1.0, 1.0, (2 * n, 6)) * half
            logged = kin.inverse_kinematics(true_drive, *kin.pose_to_rt(candidates)) / (1.0 + scale)
            ok = np.all((logged > STROKE_MARGIN_MM) & (logged < 90.0 - STROKE_MARGIN_MM), axis=1)
            poses = np.vstack([poses, candidates[ok]])
        R, t = kin.pose_to_rt(poses[:n])
        counts = np.round(kin.inverse_kinematics(true_drive, R, t) / ((1.0 + scale) * MM_PER_COUNT)).astype(int)
        reading = instrument.read(R, t, instrument.draw(n, rng))
        quaternion = Rotation.from_matrix(kin.rpy_to_rotation(reading[:, 3:])).as_quat()  # x, y, z, w
        with open(HERE / f"{name}_raw.csv", "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["time_s", *(f"enc{i}" for i in range(1, 7)), "x_m", "y_m", "z_m", "qw", "qx", "qy", "qz"])
            for k in range(n):
                writer.writerow(
                    [
                        f"{0.5 * k:.2f}",
                        *counts[k],
                        *(f"{v / 1000.0:.7f}" for v in reading[k, :3]),
                        *(f"{v:.9f}" for v in quaternion[k, [3, 0, 1, 2]]),
                    ]
                )
    print("true stroke scale k:", np.round(scale, 4).tolist())
    print("true initial-length errors [mm]:", np.round(delta[6::7], 2).tolist())


if __name__ == "__main__":
    main()
