"""Write the raw example again as a hobbyist's two machines export it (``stewart-calib import``).

``python examples/hobby-mocap/make_exports.py`` reads ``fit_raw.csv`` and ``heldout_raw.csv`` and
writes, next to them, for each day:

* ``NAME_motive.csv`` — what OptiTrack Motive exports (CSV format 1.23): the 7-row header, Y-up
  (Motive's convention), metres, quaternions ``X Y Z W``, the platform's rigid body ``platform``
  beside a second one (``wand``) and the platform's marker columns; after the robot stopped the
  take ran on for three frames in which the platform was not tracked (empty cells);
* ``NAME_counts.csv`` — the controller's log: its own clock (``uptime_s``, seconds since it
  booted: the motion-capture time plus 1234.5 s on the fit day, 873.25 s on the held-out day), the
  six encoders' counts at 10 Hz, holding each pose from its camera frame for 0.2 s, then moving
  straight to the next one.

``controller.toml`` maps the controller's columns (counts, the builders' 8 mm per revolution over
4096 counts per revolution). The README's worked example imports these and calibrates to the same
result as the raw files converted by hand (tests/test_import.py checks it to 1e-9).
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
#: controller clock minus motion-capture clock [s] (exact in binary, so the stamps line up exactly)
CLOCK_OFFSET_S = {"fit": 1234.5, "heldout": 873.25}
CONTROLLER_PERIOD_STEPS = 5  # rows per 0.5 s camera period: 10 Hz
LOST_FRAMES = 3
#: Y-up (Motive) from Z-up: the inverse of import's x' = x, y' = −z, z' = y
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def quaternion_product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of ``(n, 4)`` quaternions ``w x y z``."""
    aw, ax, ay, az = a.T
    bw, bx, by, bz = b.T
    return np.column_stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def write_motive(path: Path, raw: np.ndarray) -> None:
    n = len(raw)
    position_yup = np.column_stack([raw["x_m"], raw["y_m"], raw["z_m"]]) @ Z_UP_TO_Y_UP.T
    turn = np.tile([np.sqrt(0.5), -np.sqrt(0.5), 0.0, 0.0], (n, 1))  # −90° about x: Z-up → Y-up
    q_yup = quaternion_product(turn, np.column_stack([raw["qw"], raw["qx"], raw["qy"], raw["qz"]]))
    frames = n + LOST_FRAMES
    info = [
        "Format Version", "1.23", "Take Name", "hexapod calibration", "Take Notes", "",
        "Capture Frame Rate", "2.000000", "Export Frame Rate", "2.000000",
        "Capture Start Time", "2024-05-04 02.13.09.000 PM", "Capture Start Frame", "0",
        "Total Frames in Take", str(frames), "Total Exported Frames", str(frames),
        "Rotation Type", "Quaternion", "Length Units", "Meters", "Coordinate Space", "Global",
    ]  # fmt: skip
    body = ["Rigid Body"] * 8
    marker = ["Rigid Body Marker"] * 4
    types = ["", "", *body, *marker, *body]
    names = ["", "", *["platform"] * 8, *["platform:Marker1"] * 4, *["wand"] * 8]
    ids = ["", "", *["1"] * 8, *["1-1"] * 4, *["2"] * 8]
    rigid = ["Rotation"] * 4 + ["Position"] * 3 + ["Mean Marker Error"]
    properties = ["", "", *rigid, "Position", "Position", "Position", "Marker Quality", *rigid]
    axes = ["Frame", "Time (Seconds)", "X", "Y", "Z", "W", "X", "Y", "Z", "", "X", "Y", "Z", "", "X", "Y", "Z", "W"]
    axes += ["X", "Y", "Z", ""]
    wand = ["0.0", "0.0", "0.0", "1.0", "0.5", "1.2", "-0.3", "0.0001"]
    with open(path, "w", newline="") as f:
        writer = csv.writer(f, lineterminator="\r\n")
        writer.writerows([info, [], types, names, ids, properties, axes])
        for k in range(frames):
            if k < n:
                q = [repr(float(v)) for v in q_yup[k, [1, 2, 3, 0]]]
                p = [repr(float(v)) for v in position_yup[k]]
                marker_cells = [repr(float(v) + 0.01) for v in position_yup[k]] + ["1.0"]
                platform = [*q, *p, "0.00021", *marker_cells]
            else:
                platform = [""] * 12
            writer.writerow([k, f"{0.5 * k:.6f}", *platform, *wand])


def write_counts(path: Path, raw: np.ndarray, offset_s: float) -> None:
    counts = np.column_stack([raw[f"enc{i}"] for i in range(1, 7)]).astype(int)
    with open(path, "w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(["uptime_s", *(f"enc{i}" for i in range(1, 7)), "state"])
        for k in range(len(raw)):
            stamp = float(raw["time_s"][k]) + offset_s
            for step in range(CONTROLLER_PERIOD_STEPS):
                after = step * 0.1  # held for 0.2 s, then moving towards the next pose
                if step <= 2 or k + 1 == len(raw):
                    row, state = counts[k], "hold"
                else:
                    w = (after - 0.2) / 0.3
                    row, state = np.round(counts[k] * (1 - w) + counts[k + 1] * w).astype(int), "move"
                writer.writerow([repr(stamp + after) if step else repr(stamp), *row, state])


def main() -> None:
    for name, offset in CLOCK_OFFSET_S.items():
        raw = np.genfromtxt(HERE / f"{name}_raw.csv", delimiter=",", names=True)
        write_motive(HERE / f"{name}_motive.csv", raw)
        write_counts(HERE / f"{name}_counts.csv", raw, offset)


if __name__ == "__main__":
    main()
