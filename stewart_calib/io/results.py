"""Calibration results (spec §5, with the blocks of §7, §10 and §17) and traces (spec §6).

Every refusal is one :class:`~stewart_calib.errors.CalibError` line naming the file and the key;
every writer goes through :func:`~.atomic.atomic_write_text`, so a bad result writes nothing.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..errors import CalibError, shown, without_noise
from ..estimate import Estimate
from ..inputs import parse_json, read_input_text
from ..model.drive import THERMAL, DriveModel, drive_model, thermal_term
from ..model.platform import EXPANSION_LIMIT_PPM_PER_K, PARAMETER_FIELDS, PARAMETER_NAMES, Platform
from ..model.rotary import PARAMETER_FIELDS as ROTARY_FIELDS
from .atomic import atomic_write_text
from .tables import csv_text

RESULT_FORMAT = "stewart-calib/result@1"

#: a rotary drive's 66 parameter names ``a1x … tw6`` (spec §15), which a result may hold without a platform at hand
ROTARY_PARAMETER_NAMES: tuple[str, ...] = tuple(
    f"{prefix}{leg}{suffix}"
    for leg in range(1, len(PARAMETER_NAMES) // len(PARAMETER_FIELDS) + 1)
    for prefix, suffix in ROTARY_FIELDS
)


def parameter_unit(legs) -> str:
    """The unit of a drive's parameters in files (of :func:`nominal_gap`): mm, or mm / deg where the leg
    model ``legs`` has angles."""
    return "mm / deg" if np.any(legs.parameter_degrees) else "mm"


#: |estimate − (nominal + error)| a result file may show before it is refused [mm]: JSON
#: writers that round to the nanometre still pass.
RESULT_SUM_TOLERANCE_MM = 1e-6


def trace_text(
    t_s: np.ndarray, params: np.ndarray, header: bool = True, names: tuple[str, ...] = PARAMETER_NAMES
) -> str:
    """Trace CSV (spec §6): ``t_s`` plus the estimated absolute parameters [mm] per sample, one
    column each of the drive's ``names`` (``DriveModel.parameter_names``: the 42 of spec §5 by default).

    ``header=False``: the rows only, to append to a trace written block by block.
    """
    t_s = np.asarray(t_s, dtype=float)
    params = np.asarray(params, dtype=float)
    if t_s.ndim != 1 or params.shape != (len(t_s), len(names)):
        raise ValueError(f"trace needs t_s (N,) and params (N, {len(names)}), got {t_s.shape} and {params.shape}")
    text = csv_text(["t_s", *names], [t_s, *params.T])
    return text if header else text.split("\n", 1)[1]


def write_trace(
    path: str | Path, t_s: np.ndarray, params: np.ndarray, names: tuple[str, ...] = PARAMETER_NAMES
) -> None:
    """Write a trace CSV (spec §6); see :func:`trace_text`."""
    atomic_write_text(path, trace_text(t_s, params, names=names))


# ----------------------------------------------------------------------------- results


def parameters_to_file(values: np.ndarray, legs) -> np.ndarray:
    """``(..., n_params)`` drive parameters of leg model ``legs`` in code units → file units: the
    entries ``legs.parameter_degrees`` marks (a rotary drive's o, tu, tw, spec §15) in degrees."""
    values = np.asarray(values, dtype=float)
    return np.where(legs.parameter_degrees, np.degrees(values), values)


def parameters_from_file(values, legs) -> np.ndarray:
    """:func:`parameters_to_file` undone: file units → code units (degrees → radians)."""
    values = np.asarray(values, dtype=float)
    return np.where(legs.parameter_degrees, np.radians(values), values)


def parameter_file_scale(legs) -> np.ndarray:
    """``(n_params,)`` the factor from code to file units of each drive parameter (180/π for an
    angle, else 1): what a covariance's rows and columns are scaled by."""
    return parameters_to_file(np.ones(len(legs.parameter_names)), legs)


def result_dict(estimate: Estimate, platform: Platform, samples_skipped: int = 0, extra: dict | None = None) -> dict:
    """The spec §5 result of ``estimate`` on ``platform`` (``estimate = nominal + error``), in file
    units: mm, and degrees for a rotary drive's angles (spec §15).

    ``extra`` adds optional fields; it may not replace the spec's.
    """
    legs = platform.drive
    nominal = parameters_to_file(legs.as_vector(), legs)
    error = parameters_to_file(estimate.error, legs)
    stddev = None if estimate.stddev is None else estimate.stddev * parameter_file_scale(legs)
    result = {
        "format": RESULT_FORMAT,
        "method": estimate.method,
        "platform": platform.name,
        "parameter_names": list(platform.drive.parameter_names),
        "nominal": nominal.tolist(),
        "estimate": (nominal + error).tolist(),
        "error": error.tolist(),
        "stddev": None if stddev is None else stddev.tolist(),
        "samples_used": int(estimate.samples_used),
        "samples_skipped": int(samples_skipped),
    }
    result.update(estimate.block_results())  # spec §7: "stroke_scale", "instrument" where identified
    if platform.thermal is not None and THERMAL not in result:
        result[THERMAL] = held_thermal_block(platform)
    extra = {**(estimate.details or {}), **(extra or {})}
    clash = set(extra) & set(result)
    if clash:
        raise ValueError(f"extra result fields may not replace spec fields: {', '.join(sorted(clash))}")
    return {**result, **extra}


def held_thermal_block(platform: Platform) -> dict:
    """The result's ``"thermal"`` block (spec §17: present whenever ``[thermal]`` is declared) of a
    calibration that held the expansion at its nominal (``expansion_sigma_ppm_per_K = 0``): the
    nominal ``alpha1 … alpha6`` [ppm/K], known exactly (σ 0)."""
    term = thermal_term(platform.thermal, 0)  # type: ignore[arg-type]  # declared: the caller's check
    return {"names": list(term.names), "estimate": term.nominal.tolist(), "stddev": [0.0] * len(term.names)}


#: the names of the blocks whose names the spec fixes (§7 the stroke scale, §10 the compliance, §17 the expansion)
BLOCK_NAMES = {
    "stroke_scale": tuple(f"k{i}" for i in range(1, 7)),
    "compliance": tuple(f"c{i}" for i in range(1, 7)),
    THERMAL: tuple(f"alpha{i}" for i in range(1, 7)),
}


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def validate_result(result, source: str) -> None:
    """Check a result against spec §5.

    Raises:
        CalibError: ``source`` and the offending key, with what was expected.
    """
    refuse = lambda key, expected: CalibError(f"{source}: key '{key}': expected {expected}")  # noqa: E731
    if not isinstance(result, dict):
        raise CalibError(f"{source}: expected a JSON object (spec §5 result)")
    missing = [
        key
        for key in (
            "format",
            "method",
            "platform",
            "parameter_names",
            "nominal",
            "estimate",
            "error",
            "stddev",
            "samples_used",
            "samples_skipped",
        )
        if key not in result
    ]
    if missing:
        raise refuse(missing[0], "a value (missing)")
    if result["format"] != RESULT_FORMAT:
        raise refuse("format", f"{RESULT_FORMAT!r}, got {result['format']!r}")
    for key in ("method", "platform"):
        if not isinstance(result[key], str) or not result[key]:
            raise refuse(key, "a non-empty string")
    names = result["parameter_names"]
    if not any(names == list(known) for known in _parameter_names()):
        raise refuse(
            "parameter_names",
            f"the {len(PARAMETER_NAMES)} names j1x ... l6 in the paper's order (spec §5), or a rotary drive's "
            f"{len(ROTARY_PARAMETER_NAMES)} a1x ... tw6 (spec §15)",
        )
    for key in ("nominal", "estimate", "error", "stddev"):
        value = result[key]
        if key == "stddev" and value is None:
            continue
        if not isinstance(value, list) or len(value) != len(names) or not all(_is_number(v) for v in value):
            raise refuse(key, f"a list of {len(names)} finite numbers" + (" or null" if key == "stddev" else ""))
    if result["stddev"] is not None and min(result["stddev"]) < 0:
        raise refuse("stddev", "non-negative numbers")
    for key in ("samples_used", "samples_skipped"):
        value = result[key]
        if not isinstance(value, int) or isinstance(value, bool) or value < 0:
            raise refuse(key, f"a non-negative whole number, got {value!r}")
    for key in ("stroke_scale", "compliance", THERMAL, "instrument", "payload"):
        if key in result:
            _validate_block(result[key], key, refuse)
    gap = np.abs(np.array(result["estimate"]) - np.array(result["nominal"]) - np.array(result["error"]))
    if gap.max() > RESULT_SUM_TOLERANCE_MM:
        i = int(gap.argmax())
        raise refuse("estimate", f"nominal + error; {names[i]} differs by {gap[i]:.3g} mm")


#: the largest |k_i| a result's stroke scale may hold: an encoder off by half its scale is a wrong
#: unit or a broken calibration, not a scale error (real ones are a few per cent).
MAX_STROKE_SCALE = 0.5


def _validate_block(block, key: str, refuse) -> None:
    """A spec §7 block ``{"names": [...], "estimate": [...], "stddev": [...] or null}``."""
    if not isinstance(block, dict) or not isinstance(block.get("names"), list) or not block["names"]:
        raise refuse(key, '{"names": [...], "estimate": [...], "stddev": [...] or null}')
    if not all(isinstance(name, str) for name in block["names"]):
        raise refuse(f"{key}.names", "a list of strings")
    n = len(block["names"])
    names = BLOCK_NAMES.get(key)
    if names is not None and block["names"] != list(names):
        raise refuse(f"{key}.names", f'["{names[0]}", ..., "{names[-1]}"]')
    for part in ("estimate", "stddev"):
        value = block.get(part)
        if part == "stddev" and value is None:
            continue
        if not isinstance(value, list) or len(value) != n or not all(_is_number(v) for v in value):
            raise refuse(f"{key}.{part}", f"a list of {n} finite numbers" + (" or null" if part == "stddev" else ""))
    if key == "stroke_scale" and max(abs(k) for k in block["estimate"]) > MAX_STROKE_SCALE:
        raise refuse(
            f"{key}.estimate",
            f"scale errors k_i within ±{MAX_STROKE_SCALE:g} (a leg moving (1 + k_i) mm per logged mm), "
            f"got {block['estimate']}",
        )
    if key == THERMAL and max(abs(alpha) for alpha in block["estimate"]) > EXPANSION_LIMIT_PPM_PER_K:
        raise refuse(
            f"{key}.estimate",
            f"expansion coefficients α_i within ±{EXPANSION_LIMIT_PPM_PER_K:g} ppm/K (spec §17; what a platform "
            f"file's [thermal] takes), got {block['estimate']}",
        )


def result_text(result: dict, source: str) -> str:
    """The JSON text of a validated result (see :func:`validate_result`), its numbers to 15 significant
    digits (:func:`~stewart_calib.errors.without_noise`; a covariance's too, whose 16th digit is the
    arithmetic's noise)."""
    validate_result(result, source)
    return json.dumps(without_noise(result), indent=2) + "\n"


def write_result(path: str | Path, result: dict) -> None:
    """Validate and write a result JSON (spec §5) atomically; a bad result writes nothing."""
    atomic_write_text(path, result_text(result, str(path)))


def read_result(path: str | Path) -> dict:
    """Read and validate a result JSON (spec §5); returns the parsed object.

    Raises:
        CalibError: unreadable or not JSON; a wrong format, length or non-finite number, naming the key.
    """
    path = Path(path)
    result = parse_json(read_input_text(path, "result file"), path)
    validate_result(result, shown(path))
    return result


#: |result nominal − platform nominal| above which a result belongs to another platform [mm].
NOMINAL_TOLERANCE_MM = 1e-6


def calibrated_drive(platform: Platform, result: dict, source: str) -> DriveModel:
    """The drive model a result (spec §5, §7) identified: ``nominal + error``, and the values of each
    of the drive's terms where the result has their block (else the platform file's nominal).

    Raises:
        CalibError: a block whose names are not the drive term's (``source`` names the file).
    """
    drive = drive_model(platform)
    _check_names(platform, result, source)
    values = {}
    for term in drive.terms:
        block = result.get(term.key)
        if block is None:
            continue
        if list(block["names"]) != list(term.names):
            raise CalibError(
                f"{source}: key '{term.key}.names': expected {', '.join(term.names)}, got {', '.join(block['names'])}"
            )
        values[term.key] = np.array(block["estimate"], dtype=float)
    return drive.calibrated(parameters_from_file(result["error"], platform.drive), values)


def _parameter_names() -> tuple[tuple[str, ...], ...]:
    """The parameter names a result may hold: a prismatic drive's 42, a rotary drive's 66."""
    return PARAMETER_NAMES, ROTARY_PARAMETER_NAMES


def _check_names(platform: Platform, result: dict, source: str) -> None:
    """Refuse a result whose ``parameter_names`` (where it has them: a result being made may not yet)
    are another drive kind's than ``platform``'s."""
    names = result.get("parameter_names")
    if names is not None and list(names) != list(platform.drive.parameter_names):
        raise CalibError(
            f"{source}: key 'parameter_names': expected the {platform.drive.n_params} parameters of the "
            f"{platform.drive.kind} drive of platform '{platform.name}', got {len(names)} "
            "(a result for another platform?)"
        )


def nominal_gap(result: dict, platform: Platform) -> float:
    """The largest |result nominal − ``platform``'s nominal drive| in file units [mm, deg]."""
    nominal = parameters_to_file(platform.drive.as_vector(), platform.drive)
    return float(np.max(np.abs(np.array(result["nominal"], dtype=float) - nominal)))


def read_calibrated_drive(path: str | Path, platform: Platform) -> DriveModel:
    """The drive model of a result JSON (spec §5, §7) made for ``platform`` (:func:`calibrated_drive`).

    Raises:
        CalibError: an invalid result, or one whose ``platform`` names another platform or whose
            ``nominal`` is not ``platform``'s drive.
    """
    result = read_result(path)
    if result["platform"] != platform.name:
        raise CalibError(
            f"{path}: key 'platform': expected '{platform.name}' (the platform given), got '{result['platform']}' "
            "(a result for another platform?)"
        )
    _check_names(platform, result, str(path))
    gap = nominal_gap(result, platform)
    if gap > NOMINAL_TOLERANCE_MM:
        raise CalibError(
            f"{path}: key 'nominal': expected the nominal drive of platform '{platform.name}'; "
            f"it differs by {gap:.3g} {parameter_unit(platform.drive)} (a result for another platform?)"
        )
    return calibrated_drive(platform, result, str(path))
