"""What hexapod controllers read: the calibrated drive as LinuxCNC ``genhexkins`` HAL parameters
and joint settings, or as a plain JSON of joint coordinates and leg lengths (docs/formats.md §13).

**LinuxCNC** (``src/emc/kinematics/genhexkins.c``; the names as in its
``configs/sim/axis/vismach/hexapod-sim/kinematics.hal``): ``setp genhexkins.base.N.x|y|z`` are the
base joints in base (world) coordinates, ``setp genhexkins.platform.N.x|y|z`` the platform joints
in platform coordinates, N = 0..5 our legs 1..6. genhexkins's joint position is the strut's whole
length ``‖t + R a_N − b_N‖`` with ``R`` from roll-pitch-yaw as ours (``pmRpyMatConvert``), so the
leg offset goes where LinuxCNC takes a joint's position at a known stroke: the INI's
``[JOINT_N] HOME`` and ``HOME_OFFSET``, the length ``l_i + (1 + k_i) q_home`` at the stroke
``q_home`` where the joint homes (0 by default: the encoder's zero). The stroke scale cannot be
written as a value (LinuxCNC's ``SCALE`` is the user's counts per unit): the INI fragment says, per
joint, by what to multiply it (``1 / (1 + k_i)``). Lengths in the machine's ``LINEAR_UNITS``
(mm or inch).

**JSON**: ``{"format": "stewart-calib/controller@1", "units": "mm", "legs": [{"leg": 1,
"base_joint": [x, y, z], "platform_joint": [x, y, z], "length_at_zero_stroke": l,
"stroke_per_logged_unit": 1 + k}, …], …}``: a leg is ``length_at_zero_stroke +
stroke_per_logged_unit · q`` long at the logged stroke q. A rotary drive's (spec §15): ``"kind":
"rotary"`` and per servo ``"crank_centre"``, ``"crank_axis"``, ``"zero_direction"`` (unit vectors in
{J}), ``"horn_length"``, ``"rod_length"``, ``"platform_joint"``, ``"zero_trim_deg"`` (o_i: the
horn's angle from its zero direction at the command 0) and ``"angle_per_commanded_degree"`` (1 + k_i):
at the commanded angle θ the horn stands at ``(1 + k_i) θ + o_i`` about its axis, right-handed.
"""

from __future__ import annotations

import json
import math
import re

import numpy as np

from ..errors import CalibError, without_noise
from ..model.platform import LegGeometry

#: millimetres per controller length unit
MM_PER_UNIT = {"mm": 1.0, "inch": 25.4}
CONTROLLER_FORMAT = "stewart-calib/controller@1"
#: genhexkins's struts (its NUM_STRUTS): the HAL and INI name joints 0 … 5
GENHEXKINS_STRUTS = 6
_SETP = re.compile(r"^\s*setp\s+genhexkins\.(base|platform)\.([0-5])\.([xyz])\s+(\S+)\s*(#.*)?$")


def _number(value: float) -> str:
    return repr(without_noise(float(value)))


def linuxcnc_hal_text(drive: LegGeometry, units: str, source: str) -> str:
    """The ``setp`` lines of genhexkins's joint coordinates (``kinematics.hal``)."""
    scale = 1.0 / MM_PER_UNIT[units]
    lines = [
        f"# genhexkins joint coordinates from stewart-calib ({source}); lengths in {units}",
        "# Base joints positions in base (world) coordinates",
    ]
    for name, joints in (("base", drive.base_joints), ("platform", drive.platform_joints)):
        if name == "platform":
            lines += ["", "# Platform joints positions in platform coordinates"]
        for n in range(drive.n_legs):
            lines += [
                f"setp genhexkins.{name}.{n}.{axis} {_number(joints[n, a] * scale)}" for a, axis in enumerate("xyz")
            ]
            lines.append("")
    return "\n".join(lines).rstrip() + "\n"


def linuxcnc_ini_text(drive: LegGeometry, stroke_scale: np.ndarray, units: str, home_stroke_mm: float) -> str:
    """``[JOINT_N]`` ``HOME`` and ``HOME_OFFSET`` (the strut length at the homing stroke) and the
    factor for each joint's ``SCALE`` (a comment: the user's SCALE is not known here)."""
    scale = 1.0 / MM_PER_UNIT[units]
    lines = [
        f"# stewart-calib: genhexkins strut lengths at the homing stroke {home_stroke_mm!r} mm, in {units};",
        "# merge into the machine's INI file",
    ]
    for n in range(drive.n_legs):
        home = (drive.initial_lengths[n] + (1.0 + stroke_scale[n]) * home_stroke_mm) * scale
        lines += [
            "",
            f"[JOINT_{n}]",
            f"# multiply this joint's SCALE (counts per {units}) by {_number(1.0 / (1.0 + stroke_scale[n]))}: "
            f"the leg moves {_number(1.0 + stroke_scale[n])} × what its encoder's nominal scale says",
            f"HOME = {_number(home)}",
            f"HOME_OFFSET = {_number(home)}",
        ]
    return "\n".join(lines) + "\n"


def read_linuxcnc(hal_text: str, ini_text: str, units: str, home_stroke_mm: float, source: str) -> tuple:
    """``(drive, stroke_scale)`` back from :func:`linuxcnc_hal_text` and :func:`linuxcnc_ini_text`.

    Raises:
        CalibError: a missing coordinate or joint, named.
    """
    mm = MM_PER_UNIT[units]
    joints = {"base": np.full((GENHEXKINS_STRUTS, 3), np.nan), "platform": np.full((GENHEXKINS_STRUTS, 3), np.nan)}
    for line in hal_text.splitlines():
        match = _SETP.match(line)
        if match:
            name, n, axis, value = match.group(1), int(match.group(2)), match.group(3), float(match.group(4))
            joints[name][n, "xyz".index(axis)] = value * mm
    for name, values in joints.items():
        if not np.all(np.isfinite(values)):
            n, a = np.argwhere(~np.isfinite(values))[0]
            raise CalibError(f"{source}: no 'setp genhexkins.{name}.{n}.{'xyz'[a]}' line")
    home, factor = np.full(GENHEXKINS_STRUTS, np.nan), np.full(GENHEXKINS_STRUTS, np.nan)
    joint = None
    for line in ini_text.splitlines():
        section = re.match(r"^\s*\[JOINT_([0-5])\]", line)
        if section:
            joint = int(section.group(1))
        elif joint is not None and re.match(r"^\s*HOME\s*=", line):
            home[joint] = float(line.split("=", 1)[1]) * mm
        elif joint is not None and "multiply this joint's SCALE" in line:
            factor[joint] = float(line.split(" by ", 1)[1].split(":", 1)[0])
    if not (np.all(np.isfinite(home)) and np.all(np.isfinite(factor))):
        raise CalibError(f"{source}: expected HOME and the SCALE factor of [JOINT_0] … [JOINT_5]")
    stroke_scale = 1.0 / factor - 1.0
    lengths = home - (1.0 + stroke_scale) * home_stroke_mm
    return LegGeometry(joints["base"], joints["platform"], lengths), stroke_scale


def controller_json_text(drive: LegGeometry, stroke_scale: np.ndarray, units: str, extra: dict) -> str:
    """The plain JSON of the calibrated legs in ``units`` (see the module)."""
    scale = 1.0 / MM_PER_UNIT[units]
    legs = [
        {
            "leg": n + 1,
            "base_joint": (drive.base_joints[n] * scale).tolist(),
            "platform_joint": (drive.platform_joints[n] * scale).tolist(),
            "length_at_zero_stroke": float(drive.initial_lengths[n] * scale),
            "stroke_per_logged_unit": float(1.0 + stroke_scale[n]),
        }
        for n in range(drive.n_legs)
    ]
    document = {"format": CONTROLLER_FORMAT, "units": units, **extra, "legs": legs}
    return json.dumps(without_noise(document), indent=1) + "\n"


def rotary_controller_json_text(legs, angle_scale: np.ndarray, units: str, extra: dict) -> str:
    """The plain JSON of calibrated rotary legs (spec §15, :class:`~stewart_calib.model.rotary.RotaryLegs`)
    in ``units``, with each servo's zero trim [deg] (see the module)."""
    scale = 1.0 / MM_PER_UNIT[units]
    servos = [
        {
            "leg": n + 1,
            "crank_centre": (legs.crank_centres[n] * scale).tolist(),
            "crank_axis": legs.crank_axes[n].tolist(),
            "zero_direction": legs.zero_directions[n].tolist(),
            "horn_length": float(legs.horn_lengths[n] * scale),
            "rod_length": float(legs.rod_lengths[n] * scale),
            "platform_joint": (legs.platform_joints[n] * scale).tolist(),
            "zero_trim_deg": math.degrees(legs.angle_offsets[n]),
            "angle_per_commanded_degree": float(1.0 + angle_scale[n]),
        }
        for n in range(legs.n_legs)
    ]
    document = {
        "format": CONTROLLER_FORMAT,
        "kind": "rotary",
        "units": units,
        **extra,
        "angle_range_deg": np.degrees(legs.angle_range).tolist(),
        "legs": servos,
    }
    return json.dumps(without_noise(document), indent=1) + "\n"


def read_controller_json(text: str, source: str) -> tuple:
    """``(drive [mm], stroke_scale)`` back from :func:`controller_json_text`."""
    try:
        data = json.loads(text)
        if data.get("format") != CONTROLLER_FORMAT or data.get("units") not in MM_PER_UNIT:
            raise CalibError(f"{source}: expected 'format' {CONTROLLER_FORMAT!r} and 'units' mm or inch")
        mm = MM_PER_UNIT[data["units"]]
        legs = sorted(data["legs"], key=lambda leg: leg["leg"])
        base = np.array([leg["base_joint"] for leg in legs], dtype=float) * mm
        platform = np.array([leg["platform_joint"] for leg in legs], dtype=float) * mm
        lengths = np.array([leg["length_at_zero_stroke"] for leg in legs], dtype=float) * mm
        scale = np.array([leg["stroke_per_logged_unit"] for leg in legs], dtype=float) - 1.0
    except (ValueError, KeyError, TypeError, AttributeError) as err:
        raise CalibError(f"{source}: not a controller JSON of six legs ({err})") from None
    try:  # the leg set's own checks of its shapes
        geometry = LegGeometry(base, platform, lengths)
    except ValueError:
        geometry = None
    if geometry is None or not all(math.isfinite(v) for v in np.concatenate([base.ravel(), lengths])):
        raise CalibError(f"{source}: expected six legs with finite joints and lengths")
    return geometry, scale
