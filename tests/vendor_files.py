"""Instrument exports written the way the vendors document them, for the ``import`` tests.

* OptiTrack Motive CSV (format 1.2x, "Data Export: CSV" of the Motive documentation): line 1
  ``key,value`` pairs (``Format Version``, ``Rotation Type``, ``Length Units``, …), a blank line,
  then the type, name, ID, property and axis rows, the first two columns ``Frame`` and
  ``Time (Seconds)``; a rigid body's ``Rotation`` ``X Y Z W`` then ``Position`` ``X Y Z`` then
  ``Mean Marker Error``; a frame where it was not tracked has empty cells.
* Vicon Nexus CSV: a section title (``Segments`` / ``Trajectories``), the rate, the
  ``Subject:Name`` row, ``Frame,Sub Frame`` and the axes, a units row, then frames from 1.
* A laser tracker's point list in long form: one row per measured target.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np


def motive_csv(
    path: Path,
    t_s: np.ndarray,
    q_xyzw: np.ndarray,
    position: np.ndarray,
    body: str = "platform",
    unit: str = "Meters",
    rotation_type: str = "Quaternion",
    frames: np.ndarray | None = None,
) -> None:
    """A Motive export with rigid body ``body`` (NaN rows: not tracked) and a second body ``wand``."""
    frames = np.arange(len(t_s)) if frames is None else frames
    info = ["Format Version", "1.23", "Take Name", "take", "Capture Frame Rate", "120.000000"]
    info += ["Export Frame Rate", "120.000000", "Rotation Type", rotation_type, "Length Units", unit]
    info += ["Coordinate Space", "Global"]
    rigid = ["Rotation"] * 4 + ["Position"] * 3 + ["Mean Marker Error"]
    with open(path, "w", newline="") as f:
        writer = csv.writer(f, lineterminator="\r\n")
        writer.writerow(info)
        writer.writerow([])
        writer.writerow(["", "", *["Rigid Body"] * 16])
        writer.writerow(["", "", *["wand"] * 8, *[body] * 8])
        writer.writerow(["", "", *["1"] * 8, *["2"] * 8])
        writer.writerow(["", "", *rigid, *rigid])
        axes = ["X", "Y", "Z", "W", "X", "Y", "Z", ""]
        writer.writerow(["Frame", "Time (Seconds)", *axes, *axes])
        for k in range(len(t_s)):
            wand = ["0", "0", "0", "1", "0.1", "0.2", "0.3", "0.0001"]
            if np.all(np.isfinite(position[k])):
                mine = [*map(repr, q_xyzw[k].tolist()), *map(repr, position[k].tolist()), "0.0002"]
            else:
                mine = [""] * 8
            writer.writerow([int(frames[k]), f"{t_s[k]:.6f}", *wand, *mine])


def vicon_segments_csv(path: Path, rate_hz: float, rotvec_deg: np.ndarray, position_mm: np.ndarray) -> None:
    """A Nexus ``Segments`` export of ``hexapod:platform`` (and ``hexapod:base`` before it)."""
    n = len(position_mm)
    with open(path, "w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(["Segments"])
        writer.writerow([f"{rate_hz:g}"])
        writer.writerow(["", "", "hexapod:base", "", "", "", "", "", "hexapod:platform", "", "", "", "", ""])
        writer.writerow(["Frame", "Sub Frame", *["RX", "RY", "RZ", "TX", "TY", "TZ"] * 2])
        writer.writerow(["", "", *["deg", "deg", "deg", "mm", "mm", "mm"] * 2])
        for k in range(n):
            row = rotvec_deg[k].tolist() + position_mm[k].tolist()
            cells = ["" if not np.isfinite(v) else repr(v) for v in row]
            writer.writerow([k + 1, 0, "0", "0", "0", "0", "0", "0", *cells])


def vicon_trajectories_csv(path: Path, rate_hz: float, markers: dict[str, np.ndarray], unit: str = "mm") -> None:
    """A Nexus ``Trajectories`` export of markers ``hexapod:NAME`` (NaN: not seen, empty cells)."""
    names = list(markers)
    n = len(next(iter(markers.values())))
    with open(path, "w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(["Trajectories"])
        writer.writerow([f"{rate_hz:g}"])
        writer.writerow(["", "", *[cell for name in names for cell in (f"hexapod:{name}", "", "")]])
        writer.writerow(["Frame", "Sub Frame", *["X", "Y", "Z"] * len(names)])
        writer.writerow(["", "", *[unit] * 3 * len(names)])
        for k in range(n):
            cells = ["" if not np.isfinite(v) else repr(float(v)) for name in names for v in markers[name][k]]
            writer.writerow([k + 1, 0, *cells])


def point_list_csv(path: Path, t_s: np.ndarray, targets: dict[str, np.ndarray]) -> None:
    """One row per measured target (``Time,Point,X,Y,Z``), NaN rows not measured, a reference
    nest ``REF`` measured every time as a laser-tracker job does."""
    with open(path, "w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(["Time", "Point", "X", "Y", "Z"])
        for k, t in enumerate(t_s):
            writer.writerow([repr(float(t)), "REF", "1000.0", "0.0", "0.0"])
            for name, values in targets.items():
                if np.all(np.isfinite(values[k])):
                    writer.writerow([repr(float(t)), name, *map(repr, values[k].tolist())])
