"""``stewart-calib export``: the calibrated drive in what a hexapod controller reads (docs/formats.md §13).

    stewart-calib export --platform P.toml [--result R.json] --format linuxcnc|json --out F
                         [--units mm|inch] [--home-stroke-mm Q]

The calibrated model is the result's on its nominal platform, or the calibrated platform file's
alone (``calibrate --platform-out``). ``linuxcnc`` writes ``F`` (``kinematics.hal``: genhexkins's
``setp`` lines) and ``F`` with the suffix ``.ini`` (``[JOINT_N] HOME``/``HOME_OFFSET`` and each
joint's ``SCALE`` factor); ``json`` writes the plain JSON of joints and leg lengths — a rotary drive's
(spec §15): its servos' geometry and zero trims; genhexkins, prismatic, refuses a rotary drive. Both are
rendered before either is written. Neither holds a leg compliance (spec §10): with ``[elastic]`` a
warning line says how much the legs give that the controller leaves out. With ``[thermal]`` (spec §17)
the JSON adds ``"thermal"`` (the reference temperature and each leg's expansion α_i [ppm/K], which
scales its length from joint to joint by ``1 + α_i (T_i − T_ref) · 1e-6``), genhexkins has no place
for it, and a warning line says how much a controller without thermal compensation leaves out over
±:data:`THERMAL_SPAN_K` about the reference: the largest ``|α_i| · 10 K · L_i`` of the legs at the
workspace's home (its middle; without a ``[workspace]``, at zero stroke).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from .. import io
from ..errors import CalibError
from ..io import controllers
from ..io.platform_file import load_platform
from ..model import kinematics as kin
from ..model.drive import COMPLIANCE, THERMAL
from . import ini_sibling, run_command
from .handover import calibrated_model, term_values

#: the temperature either side of the reference the export's thermal warning sizes the legs' growth over [K]
THERMAL_SPAN_K = 10.0


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "export",
        description="Write the calibrated drive for a controller: LinuxCNC genhexkins HAL setp lines and INI joint "
        "settings, or a plain JSON of joint coordinates and leg lengths (docs/formats.md §13).",
    )
    parser.add_argument(
        "--platform", required=True, metavar="P.toml", help="nominal platform, or the calibrated one alone (spec §8)"
    )
    parser.add_argument(
        "--result", metavar="R.json", help="calibration result (spec §5); omit with a calibrated platform"
    )
    parser.add_argument("--format", required=True, choices=("linuxcnc", "json"), help="what the controller reads")
    parser.add_argument("--out", required=True, metavar="F", help="file to write (linuxcnc: also F with suffix .ini)")
    parser.add_argument(
        "--units", choices=tuple(controllers.MM_PER_UNIT), default="mm", help="controller's length unit"
    )
    parser.add_argument(
        "--home-stroke-mm",
        type=float,
        default=0.0,
        metavar="Q",
        help="linuxcnc: the logged stroke at which the joints home (default 0: the encoders' zero)",
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if not out.parent.is_dir():
        raise CalibError(f"--out {out}: directory {out.parent} does not exist")
    if not math.isfinite(args.home_stroke_mm):
        raise CalibError(f"--home-stroke-mm: expected a finite stroke [mm], got {args.home_stroke_mm!r}")
    platform = load_platform(args.platform)
    rotary = platform.drive.kind == "rotary"
    if rotary and args.format == "linuxcnc":
        raise CalibError(
            f"--format linuxcnc: genhexkins models prismatic struts; {args.platform} has a rotary drive "
            "(spec §15): use --format json"
        )
    model = calibrated_model(platform, args.result)
    drive, k = model.legs, model.extension_per_stroke() - 1.0  # a leg moves 1 + k mm a logged mm
    source = f"{args.platform}" + (f" + {args.result}" if args.result else "")
    if args.format == "linuxcnc":
        ini = Path(ini_sibling(out))
        if ini == out:
            raise CalibError(f"--out {out}: expected a name whose .ini sibling is another file (e.g. kinematics.hal)")
        legs = model.prismatic()
        files = {
            out: controllers.linuxcnc_hal_text(legs, args.units, source),
            ini: controllers.linuxcnc_ini_text(legs, k, args.units, args.home_stroke_mm),
        }
    else:
        extra: dict = {"source": source, "platform": platform.name}
        alpha = term_values(model, THERMAL)
        if alpha is not None and platform.thermal is not None:  # the expansion the model carries (spec §17)
            extra["thermal"] = {
                "reference_temperature_C": platform.thermal.reference_temperature_C,
                "expansion_ppm_per_K": alpha.tolist(),
            }
        text = (
            controllers.rotary_controller_json_text(drive, k, args.units, extra)
            if rotary
            else controllers.controller_json_text(model.prismatic(), k, args.units, extra)
        )
        files = {out: text}
    with io.atomic_paths(list(files)) as temporaries:  # both files or neither
        for tmp, text in zip(temporaries, files.values(), strict=True):
            tmp.write_text(text, encoding="utf-8")
    print(f"stewart-calib export: wrote {', '.join(map(str, files))} ({args.format}, {args.units})", file=sys.stderr)
    if platform.elastic is not None:
        give = _give_mm(platform, model)
        if give is not None:
            print(
                f"stewart-calib export: warning: {args.format} has no leg compliance: the controller leaves out the "
                f"legs' give c_i f_i under the platform's own weight, {give[0]:.3g}–{give[1]:.3g} mm over the "
                "workspace (more under a payload); stewart-calib compensate --payload-kg gives strokes with it",
                file=sys.stderr,
            )
    growth = _growth_um(platform, model)
    if growth is not None and platform.thermal is not None:
        um, leg = growth
        carried = (
            'carries the expansion ("thermal") that a controller must apply'
            if args.format == "json"
            else "has no thermal expansion"
        )
        print(
            f"stewart-calib export: warning: {args.format} {carried}: a controller without thermal compensation "
            f"leaves out the legs' growth α_i ΔT_i L_i, up to {um:.3g} µm (leg {leg}) at ±{THERMAL_SPAN_K:g} K "
            f"from the reference {platform.thermal.reference_temperature_C:g} °C; stewart-calib compensate "
            "--temperature-C gives strokes with it",
            file=sys.stderr,
        )
    return 0


def _growth_um(platform, model) -> tuple[float, int] | None:
    """``(µm, leg)``: the most a leg of the calibrated thermal ``model`` grows over ±:data:`THERMAL_SPAN_K`
    about the reference, ``|α_i| · 10 K · 1e-6 · L_i`` with ``L_i`` its length from joint to joint at the
    workspace's home (at zero stroke without a ``[workspace]``), and that leg (1-based); None without
    ``[thermal]`` or for an expansion of 0."""
    alpha = term_values(model, THERMAL)
    if alpha is None or not np.any(alpha):
        return None
    if platform.workspace is not None:
        lengths = model.legs.joint_lengths(model.legs.coordinates(*kin.pose_to_rt(platform.workspace.home)))
    else:
        lengths = model.legs.joint_lengths(np.zeros(model.rows))
    growth_um = np.abs(alpha) * THERMAL_SPAN_K * lengths * 1e-3  # ppm/K · K · mm = nm
    leg = int(np.argmax(growth_um))
    return float(growth_um[leg]), leg + 1


def _give_mm(platform, model) -> tuple[float, float] | None:
    """The least and the most any leg of the calibrated elastic ``model`` gives, ``c_i f_i`` [mm], at the
    fixed workspace poses of the prediction without a payload; None for a compliance of 0."""
    from ..analysis.accuracy import evaluation_poses

    compliance = term_values(model, COMPLIANCE)
    if compliance is None or not np.any(compliance):
        return None
    give = compliance * model.leg_forces(*kin.pose_to_rt(evaluation_poses(platform))) / 1000.0
    return float(np.min(give)), float(np.max(give))


def main(argv: list[str] | None = None) -> int:
    return run_command("export", argv)
