"""Mistakes in a log named by their cause, before any solver runs.

A log converted by hand goes wrong in a few typical ways, and each makes a solver fail far from
the cause (a non-converging Levenberg–Marquardt for positions left in metres, a registration
that "does not rotate about two axes" for angles left in radians or two stroke columns swapped).
:func:`diagnose_log` looks at the log the way an engineer would, in this order, and refuses it
with one line naming the cause and its evidence:

1. **too few samples** — fewer distinct samples than the unknowns need (how many are needed);
2. **a log that does not move** — the strokes and the readings both stay within a sliver
   (:data:`~.plausibility.REST_FRACTION`) of the stroke range: a robot at rest, however many samples, fixes no
   parameter (the span of its poses is named, and what a calibration needs);
3. **strokes in another unit** — the strokes barely move the platform while the instrument saw
   it move (or the strokes fill a sliver of the stroke range);
4. **too few directions** — an outside instrument's frame and target orientations are told
   apart only by poses that rotate about two axes; the missing ones are named;
5. **readings in another unit** — the spread of the measured positions (or angles, or tracker
   readings) against the spread the logged strokes give the nominal model: a rigid change of
   frame keeps distances between positions and angles between orientations, so the two spreads
   agree within the drive's errors whatever the frame; a ratio near 1/1000 is metres, near
   π/180 radians; readings that do not move at all are named as such
   (:func:`~.plausibility.check_readings_follow`, the check ``track`` makes too);
6. **stroke columns swapped or a leg's sign reversed** — each leg's length, from the measured
   poses (the tracker's forward kinematics, or the registration of an outside instrument),
   should follow its own stroke column with slope ≈ 1; a leg that follows another column, or
   follows its own backwards, is named with the residuals of both wirings;
7. **orientations mirrored** — a pose instrument's turns between poses against the strokes':
   a rotation apart whatever the frame, a mirror image when a quaternion was read in the wrong
   order;
8. **strokes of another platform** — the angle of the rotation between two poses is the same in
   any instrument frame and for any target, so over pairs of poses a pose instrument's angles and
   the strokes' (through the nominal model) correlate, within the drive's errors; and where the
   registration fails although both the strokes' poses and the readings rotate about two axes, the
   misfit of the best frame and target is named, not the poses;
Every test uses at most :data:`DIAGNOSED_SAMPLES` samples evenly spread over the log, so its
cost does not grow with the log. Thresholds are ratios far from 1 (a factor
:data:`UNIT_TOLERANCE` about a unit's factor, :data:`WIRING_GAIN` between two wirings), not
tuned to one robot: the spreads compared are those of the same motions.
"""

from __future__ import annotations

import math
from itertools import combinations

import numpy as np

from ..analysis.plausibility import REST_FRACTION, check_readings_follow
from ..errors import CalibError
from ..instruments import instrument_kind
from ..model import kinematics as kin
from ..model.drive import drive_model, plain_drive
from ..model.platform import Platform, give_reference_mm
from ..model.rotations import rotation_axis_sin, rpy_to_rotation, so3_log

#: samples the diagnosis looks at, evenly spread over the log
DIAGNOSED_SAMPLES = 400
#: a spread ratio within this factor of a unit's conversion factor names that unit
UNIT_TOLERANCE = 2.0
#: a spread ratio beyond this factor from 1 (either way) matching no unit is refused as such
SPREAD_LIMIT = 5.0
#: samples the wiring test registers (27 wirings: every pair of columns swapped, every leg reversed two ways)
WIRING_SAMPLES = 120
#: another wiring must explain the leg lengths this many times better to be named
WIRING_GAIN = 5.0
#: the two ways a leg's stroke is reversed in :func:`_wirings`' sign: mirrored within the stroke
#: range (counting down from its far end), or negated (counting down from the same zero)
MIRRORED, NEGATED = -1.0, -2.0
#: a rotation whose spread is below this fraction of the log's largest (or of a third of the
#: workspace's rotation limit, if larger) counts as not excited
EXCITED_FRACTION = 0.2

#: what a position (or stroke) ratio measured / expected points to: the unit the values look like
LENGTH_UNITS = {1e-3: "metres", 0.1: "centimetres", 1 / 25.4: "inches", 1e3: "micrometres"}
#: the same for angles written as degrees
ANGLE_UNITS = {math.pi / 180.0: "radians"}
POSE_DIRECTIONS = ("x", "y", "z", "roll", "pitch", "yaw")


def _evenly(n: int, most: int = DIAGNOSED_SAMPLES) -> np.ndarray:
    return np.unique(np.linspace(0, n - 1, min(n, most)).round().astype(int)) if n else np.zeros(0, dtype=int)


def _named_unit(ratio: float, units: dict[float, str]) -> str | None:
    for factor, name in units.items():
        if math.isfinite(ratio) and abs(math.log(ratio / factor)) < math.log(UNIT_TOLERANCE):
            return name
    return None


def _columns(names: list[str]) -> str:
    return names[0] if len(names) == 1 else f"{names[0]}…{names[-1]}"


def _refuse(where: str, message: str) -> None:
    raise CalibError(f"{where}: {message}")


def required_samples(platform: Platform) -> tuple[int, int, str]:
    """``(samples needed, unknowns, what they are)`` for a calibration of ``platform``'s drive
    with its instrument: the unknowns the data must fix (gauge directions excluded) over the
    values one sample measures."""
    from ..instruments import outside_model

    n_params, legs = platform.drive.n_params, platform.drive.n_legs
    if not instrument_kind(platform).outside:
        return math.ceil(n_params / legs), n_params, f"{n_params} drive parameters"
    model = outside_model(platform)
    own, per_sample = model.nominal_unknowns().size, model.channel_sigma.size
    unknowns = n_params + legs + own - 12  # a stroke scale a leg (a servo's angle scale)
    scales = "stroke" if platform.drive.coordinate_unit == "mm" else "angle"
    what = f"{n_params} drive parameters, {legs} {scales} scales and {own} of the instrument, less 12 gauge directions"
    return math.ceil(unknowns / per_sample), unknowns, what


def require_poses(
    platform: Platform, n: int, where: str, counted: str = "distinct sample(s)", noun: str = "samples"
) -> None:
    """Refuse ``n`` poses (of a log, a pose list, a plan) too few to calibrate ``platform``
    (:func:`required_samples`), naming ``where`` and what was counted.

    Raises:
        CalibError: one line with the count, the unknowns and the poses they need.
    """
    needed, unknowns, what = required_samples(platform)
    if n < needed:
        _refuse(
            where,
            f"too few {noun}: {n} {counted} for {unknowns} unknowns ({what}); "
            f"expected at least {needed} distinct poses, better several times that",
        )


def _check_count(platform: Platform, readings: np.ndarray, where: str) -> None:
    from ..instruments.registration import distinct_count

    needed, _, _ = required_samples(platform)
    finite = readings[np.any(np.isfinite(readings), axis=1)]
    scale = np.full(readings.shape[1], 1e-9)
    require_poses(platform, distinct_count(finite[_evenly(len(finite), 4 * needed)], scale, needed), where)


def _fk(platform: Platform, strokes: np.ndarray):
    drive = drive_model(platform)
    return drive.settled_kinematics(strokes, strict=False)[0]


def _stroke_reference(platform: Platform) -> tuple[float, str]:
    """``(span in code units, what it is)`` the drive's coordinates' span is measured against: a
    prismatic drive's length [mm] (:func:`~.platform.give_reference_mm`), a rotary drive's angle
    range [rad] (spec §15)."""
    if platform.drive.coordinate_unit == "deg":
        low, high = platform.drive.angle_range  # type: ignore[union-attr]  # a rotary drive's
        return high - low, "the angle range"
    return give_reference_mm(platform.drive, platform.stroke_range)


def _drive_words(platform: Platform) -> tuple[list[str], str, str, float]:
    """``(the log's drive columns, what they hold, their file unit, file units per code unit)``:
    ``q1_mm …``, strokes in mm; a rotary drive's ``q1_deg …``, angles in degrees (radians in code)."""
    from ..io.logs import drive_columns

    columns = list(drive_columns(platform))
    if platform.drive.coordinate_unit == "deg":
        return columns, "angles", "deg", math.degrees(1.0)
    return columns, "strokes", "mm", 1.0


def _check_moves(platform: Platform, strokes: np.ndarray, readings: np.ndarray, where: str, n_samples: int) -> None:
    """Refuse a log at rest: strokes and readings (``strokes``, ``readings``: evenly spread samples of
    the log's ``n_samples``) within :data:`REST_FRACTION` of the stroke range (the readings' spread,
    not only the strokes', so that strokes in metres are named as such)."""
    span = float(np.nanmax(np.ptp(strokes, axis=0))) if len(strokes) else 0.0
    reference, what = _stroke_reference(platform)
    limit = REST_FRACTION * reference
    _, noun, unit, scale = _drive_words(platform)
    fk = _fk(platform, strokes)
    ok = fk.converged
    if span >= limit or ok.sum() < 2:
        return
    spreads = instrument_kind(platform).spreads(platform, fk.R[ok], fk.t[ok], readings[ok])
    lengths = [spread for spread in spreads if not spread.angle]
    if any(not spread.measured < limit for spread in lengths):  # NaN: nothing to say it rests
        return
    poses = kin.rt_to_pose(fk.R[ok], fk.t[ok])
    span_mm = float(np.max(np.ptp(poses[:, :3], axis=0)))
    span_deg = float(np.degrees(np.max(np.ptp(poses[:, 3:], axis=0))))
    needed, unknowns, _ = required_samples(platform)
    measured = ", ".join(f"the {spread.what} {spread.measured:.3g} mm" for spread in lengths)
    _refuse(
        where,
        f"the log does not move: its {n_samples} samples' {noun} span {span * scale:.3g} {unit} and their poses "
        f"{span_mm:.3g} mm / {span_deg:.3g}° ({measured} RMS); a calibration of {unknowns} unknowns needs at "
        f"least {needed} distinct poses spread over the workspace, {noun} spanning well over "
        f"{limit * scale:.3g} {unit} ({REST_FRACTION:g} of {what})",
    )


def check_moves(platform: Platform, strokes: np.ndarray, readings: np.ndarray, where: str, n_samples: int) -> None:
    """Refuse a log that holds too few distinct poses to calibrate, or rests (:func:`diagnose_log`'s checks of a
    log to calibrate from): ``strokes`` ``(N, legs)`` and ``readings`` ``(N, m)`` are its samples or a pick of
    them (a stream's :class:`~stewart_calib.samples.HeldPoseSamples`), of ``n_samples`` in all."""
    _check_count(platform, readings, where)
    pick = _evenly(len(strokes))
    _check_moves(platform, strokes[pick], readings[pick], where, n_samples)


def _check_strokes_unit(platform: Platform, strokes: np.ndarray, where: str, stroke_columns: list[str]) -> None:
    """Strokes in metres fill a thousandth of the stroke range (without a range: of the legs'
    initial length), a servo's angles in radians (spec §15: the log holds degrees) π/180 of its
    angle range; a log that really moves so little identifies nothing anyway."""
    span = float(np.nanmax(strokes) - np.nanmin(strokes)) if strokes.size else 0.0
    reference, what = _stroke_reference(platform)
    _, noun, unit, scale = _drive_words(platform)
    factor, other = (1e-3, "metres") if unit == "mm" else (math.radians(1.0), "radians")
    if 0 < span < factor * UNIT_TOLERANCE * reference:
        _refuse(
            where,
            f"the {noun} {_columns(stroke_columns)} look like {other}, not {unit}: they span {span * scale:.4g} "
            f"against {reference * scale:.4g} {unit} of {what} (×{1 / factor:.4g}: {span * scale / factor:.4g} {unit})",
        )


def _check_directions(platform: Platform, R: np.ndarray, t: np.ndarray, where: str) -> None:
    """Why an outside instrument does not register: its frame and target orientations are told
    apart only by poses that rotate about two axes. Called once the registration failed."""
    spread_deg = np.degrees(np.std(kin.rt_to_pose(R, t)[:, 3:], axis=0))
    reference = float(np.max(spread_deg))
    if platform.workspace is not None:
        reference = max(reference, math.degrees(platform.workspace.rotation_limit) / 3.0)
    missing = [k for k in range(3) if spread_deg[k] < EXCITED_FRACTION * reference]
    if len(missing) >= 2:
        names = [POSE_DIRECTIONS[3 + k] for k in missing]
        spreads = ", ".join(f"{POSE_DIRECTIONS[3 + k]} {spread_deg[k]:.3g}°" for k in missing)
        _refuse(
            where,
            f"the poses excite too few directions: no rotation about {' or '.join(names)} (σ {spreads}, from "
            "the strokes); the instrument's frame and target orientations are told apart only by poses that rotate "
            "about two axes: expected poses with roll, pitch and yaw varied",
        )


def _check_handedness(platform: Platform, R: np.ndarray, readings: np.ndarray, where: str, columns) -> None:
    """A pose instrument's orientations turning as a mirror image of the strokes' (a quaternion
    read in the wrong order: a cyclic shift of its four parts is an improper map of the
    quaternions, which turns each rotation between two poses into its inverse seen through a fixed
    rotation). Whatever the instrument's frame and target, the turn between two measured poses is
    the turn between the strokes' poses seen through the target's fixed rotation: the best linear
    map between the two sets of turns is a rotation (determinant +1); a mirrored log gives −1.
    Refused only where the best mirror fits the turns :data:`WIRING_GAIN` times better than the best
    rotation (poses that turn about fewer than three axes, or by no more than the noise, fit both)."""
    if platform.instrument is None or platform.instrument.kind != "pose":
        return
    R_m = rpy_to_rotation(readings[:, 3:6])
    usable = np.all(np.isfinite(readings[:, 3:6]), axis=1)
    if usable.sum() < 4:
        return
    R, R_m = R[usable], R_m[usable]

    def turns(rotations: np.ndarray) -> np.ndarray:  # sin θ × axis of R₀ᵀ R
        return rotation_axis_sin(np.einsum("ji,njk->nik", rotations[0], rotations[1:]))

    m, f = turns(R_m), turns(R)
    H = m.T @ f
    if np.linalg.det(H) >= 0:
        return
    # the best rotation and the best mirror between the turns (Kabsch): their squared misfits
    # differ by 4 s₃, s₃ the smallest singular value of H; a mirror must fit far better, not by noise
    s1, s2, s3 = np.linalg.svd(H, compute_uv=False)
    total = float(np.sum(m**2) + np.sum(f**2))
    rotation, mirror = total - 2 * (s1 + s2 - s3), total - 2 * (s1 + s2 + s3)
    if not rotation > WIRING_GAIN * max(mirror, 0.0):
        return
    _refuse(
        where,
        f"the measured orientations {_columns(list(columns[3:6]))} turn as a mirror image of the strokes' poses "
        f"(a mirror maps the turns between poses {rotation / max(mirror, 1e-300):.3g}× better than a rotation, where a "
        "frame and a target only rotate them): a "
        "quaternion read in the wrong order (w x y z against x y z w), or Euler angles of the other handedness?",
    )


#: the angles between pairs of poses, from the strokes and from the instrument, must correlate at
#: least this much (a drive's errors leave 0.94–0.99 on the shipped hobby example and simulations;
#: the strokes of other rows, 0.0 ± 0.02)
FIT_CORRELATION = 0.5
#: and the instrument's angles must exceed its orientation noise this many times
FIT_SIGMAS = 10.0


def _seen_rotations(R: np.ndarray, readings: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """``(R, R_M)``: the strokes' pose orientations and the pose instrument's, at the rows whose readings
    are all finite; None where fewer than 3 are (too few to tell a misfit)."""
    seen = np.all(np.isfinite(readings), axis=1)
    if seen.sum() < 3:
        return None
    R_M, _ = kin.pose_to_rt(readings[seen])
    return R[seen], R_M


def _stroke_words(platform: Platform) -> tuple[list[str], str, str, str]:
    """:func:`_drive_words`' columns, noun and unit, and the other drive whose values a log of the
    wrong robot may hold in those columns (the refusals of strokes that do not fit the legs)."""
    columns, noun, unit, _ = _drive_words(platform)
    other = "a rotary robot's angles in the stroke columns" if unit == "mm" else "another robot's servos"
    return columns, noun, unit, other


def _check_strokes_fit(platform: Platform, R: np.ndarray, readings: np.ndarray, where: str) -> None:
    """Strokes that are not this platform's (another robot's log, a rotary robot's angles in the
    stroke columns), which a registration would meet as poses that "do not rotate": the angle of
    the rotation between two poses is the same in any frame and for any target (``F⁻¹ X G``: the
    relative rotation is only conjugated), so over every pair of poses the angles from the strokes
    through the nominal model and from a pose instrument follow each other within the drive's errors."""
    if not instrument_kind(platform).measures_orientation:
        return
    rotations = _seen_rotations(R, readings)
    if rotations is None:
        return
    R, R_M = rotations
    i, j = np.triu_indices(len(R), 1)
    angle = lambda A: np.linalg.norm(so3_log(np.einsum("nji,njk->nik", A[i], A[j])), axis=1)  # noqa: E731
    measured, modelled = angle(R_M), angle(R)
    if not np.sqrt(np.mean(measured**2)) > FIT_SIGMAS * float(platform.instrument.orientation_sigma_rad):
        return
    correlation = float(np.corrcoef(measured, modelled)[0, 1]) if np.std(modelled) > 0 else 0.0
    if correlation < FIT_CORRELATION:
        mismatch = math.degrees(float(np.sqrt(np.mean((measured - modelled) ** 2))))
        columns, noun, unit, other = _stroke_words(platform)
        _refuse(
            where,
            f"the {noun} {_columns(columns)} do not fit this platform's legs: the angles between pairs of poses "
            f"that they give the nominal model differ from the instrument's by {mismatch:.3g}° RMS (correlation "
            f"{correlation:.2f}, expected above {FIT_CORRELATION:g}); expected {noun} [{unit}] of this platform's "
            f"legs (a log of another robot, {other}, or another --platform?)",
        )


def _check_strokes_register(platform: Platform, R: np.ndarray, readings: np.ndarray, where: str) -> None:
    """Strokes that no frame and target map onto a pose instrument's readings, where both the
    strokes' poses (:func:`_check_directions`) and the readings rotate about two axes: the registration
    failed for the misfit, not for the poses (another robot's log, a rotary robot's angles in the
    stroke columns). Called once the registration failed; the misfit is the closed form's,
    :func:`~stewart_calib.instruments.pose.hand_eye_rotations`."""
    from ..instruments.pose import hand_eye_rotations

    if platform.instrument is None or platform.instrument.kind != "pose":
        return
    rotations = _seen_rotations(R, readings)
    if rotations is None:
        return
    R, R_M = rotations
    turns = so3_log(np.einsum("ji,njk->nik", R_M[0], R_M))  # the readings' turns from the first, any frame
    principal = np.linalg.svd(turns - turns.mean(axis=0), compute_uv=False) / math.sqrt(len(turns))
    sigma = float(platform.instrument.orientation_sigma_rad)
    if not principal[1] > FIT_SIGMAS * sigma:  # they do turn about one axis only: the registration's words hold
        return
    R_G, R_F, _ = hand_eye_rotations(R, R_M)
    misfit = np.linalg.norm(so3_log(np.einsum("nji,kj,nkl,lm->nim", R_M, R_F, R, R_G)), axis=1)  # (F M)ᵀ X G
    left = math.degrees(float(np.sqrt(np.mean(misfit**2))))
    columns, noun, unit, other = _stroke_words(platform)
    axes = "every axis" if principal[2] > FIT_SIGMAS * sigma else "two axes"
    _refuse(
        where,
        f"the {noun} {_columns(columns)} do not fit this platform's legs: the readings turn about {axes} "
        f"({', '.join(f'{math.degrees(v):.3g}°' for v in principal)} RMS), but no frame and target of the "
        f"instrument turn the poses the {noun} give the nominal model onto them: the best leaves {left:.3g}° RMS, "
        f"{left / math.degrees(sigma):.3g}× the instrument's σ; expected {noun} [{unit}] of this platform's legs "
        f"(a log of another robot, {other}, or another --platform?)",
    )


def _check_ratio(
    where: str, what: str, columns: str, measured: float, expected: float, units, unit_word: str, noun: str
) -> None:
    # readings that do not move are no unit: check_readings_follow names them
    if not (math.isfinite(measured) and math.isfinite(expected)) or expected <= 0 or measured <= 0:
        return
    ratio = measured / expected
    unit = _named_unit(ratio, units)
    evidence = (
        f"they spread {measured:.4g} {unit_word} where the logged {noun} through the nominal model give "
        f"{expected:.4g} {unit_word}"
    )
    if unit is not None:
        _refuse(where, f"the {what} {columns} look like {unit}, not {unit_word}: {evidence}")
    if ratio > SPREAD_LIMIT or ratio < 1 / SPREAD_LIMIT:
        _refuse(
            where,
            f"the {what} {columns} do not match the {noun}: {evidence} ({ratio:.3g}×); expected the same "
            f"spread in {unit_word} (another unit, other columns, or a log of another platform)",
        )


def _check_reading_units(platform: Platform, R: np.ndarray, t: np.ndarray, readings: np.ndarray, where: str, columns):
    noun = _drive_words(platform)[1]
    for spread in instrument_kind(platform).spreads(platform, R, t, readings):
        units, unit_word = (ANGLE_UNITS, "degrees") if spread.angle else (LENGTH_UNITS, "mm")
        named = _columns(columns[spread.channels])
        _check_ratio(where, spread.what, named, spread.measured, spread.expected, units, unit_word, noun)


def _leg_residuals_mm(lengths: np.ndarray, strokes: np.ndarray) -> np.ndarray:
    """``(legs,)`` RMS [mm] of each leg's length less its stroke about their mean difference: the
    offset absorbs ``l_i``; a stroke scale a few per cent off leaves a few per cent of the
    stroke's spread, a reversed or another leg's stroke the whole of it."""
    difference = lengths - strokes
    return np.sqrt(np.mean((difference - difference.mean(axis=0)) ** 2, axis=0))


def _wirings(legs: int) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """``(description, column order, sign)`` of every single mistake among ``legs`` stroke columns:
    two columns swapped, one leg reversed (``sign`` :data:`MIRRORED` or :data:`NEGATED` there)."""
    out = []
    for i, j in combinations(range(legs), 2):
        order = np.arange(legs)
        order[[i, j]] = order[[j, i]]
        out.append((f"swap {i} {j}", order, np.ones(legs)))
    for i in range(legs):
        for reversal in (MIRRORED, NEGATED):
            sign = np.ones(legs)
            sign[i] = reversal
            out.append((f"sign {i}", np.arange(legs), sign))
    return out


def _rewired(strokes: np.ndarray, order: np.ndarray, sign: np.ndarray, platform: Platform) -> np.ndarray:
    """The strokes with columns reordered and reversed legs mirrored within the stroke range (or
    their own span: a reversed encoder counts down from where a correct one counts up) or negated
    (a sign of −1 about the same zero: the strokes run below zero)."""
    q = strokes[:, order].copy()
    for i in np.flatnonzero(sign == MIRRORED):
        low, high = platform.stroke_range if platform.stroke_range is not None else (np.min(q[:, i]), np.max(q[:, i]))
        q[:, i] = low + high - q[:, i]
    q[:, sign == NEGATED] *= -1.0
    return q


def _wiring_message(order, sign, words, as_logged: float, rewired: float) -> str:
    """The cause and evidence of one rewiring; ``words``: :func:`_drive_words`' (columns, noun, unit, scale)."""
    columns, noun, unit, scale = words
    one = noun[:-1]  # "stroke", "angle"
    swapped = [i for i in range(len(order)) if order[i] != i]
    if swapped:
        a, b = (columns[i] for i in swapped)
        cause, change = f"{one} columns {a} and {b} look swapped", f"with {a} and {b} exchanged"
    else:
        leg = int(np.flatnonzero(sign < 0)[0])
        cause = f"leg {leg + 1}'s {one} looks reversed ({columns[leg]} counts the wrong way)"
        change = f"with {columns[leg]} reversed"
    legs = "leg lengths" if unit == "mm" else "servo angles"
    logged = (
        f"the readings do not register onto the poses of the {noun} as logged"
        if math.isinf(as_logged)
        else f"the {legs} of the measured poses follow the {noun} as logged to {as_logged * scale:.3g} {unit} RMS"
    )
    return f"{cause}: {logged}; {change} they follow them to {rewired * scale:.3g} {unit}"


def _pose_lengths(platform: Platform, strokes: np.ndarray, readings: np.ndarray):
    """The nominal legs' coordinates (:func:`_coordinates`) at the platform poses the readings give ``(N, legs)``
    (NaN rows where no pose), and the whitened RMS of the registration that mapped them."""
    from ..instruments import outside_model

    reading_legs = instrument_kind(platform).reading_legs(platform)
    if reading_legs is not None:
        fk = kin.forward_kinematics(reading_legs, readings, strict=False)
        lengths = _coordinates(platform, fk.R, fk.t)
        lengths[~fk.converged] = np.nan
        return lengths, None
    model = outside_model(platform)
    fk = _fk(platform, strokes)
    usable = fk.converged & np.any(np.isfinite(readings), axis=1)
    if usable.sum() < 3:
        return None, None
    try:
        unknowns = model.register(fk.R[usable], fk.t[usable], readings[usable])
    except CalibError:
        return None, None
    e = model.readings_residual(unknowns, readings[usable], fk.R[usable], fk.t[usable])[0] / model.channel_sigma
    whitened = float(np.sqrt(np.nanmean(e**2)))
    poses = model.platform_poses(unknowns, readings[usable])
    if poses is None:
        return None, whitened  # the readings fix no pose each: only the registration's fit tells
    R_P, t_P = poses
    lengths = np.full((len(strokes), platform.drive.n_legs), np.nan)
    lengths[usable] = _coordinates(platform, R_P, t_P)
    return lengths, whitened


def _coordinates(platform: Platform, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(N, legs)`` the nominal legs' own coordinates at poses ``(R, t)``, no stroke scale nor any
    other term (a prismatic leg's length less its initial length [mm]): what the strokes follow on
    a straight line per leg where they are wired right."""
    return plain_drive(platform.drive).inverse_kinematics(R, t)


def _wiring_score(platform: Platform, strokes: np.ndarray, readings: np.ndarray) -> float:
    """How well the strokes explain the measured poses: the worst leg's straight-line residual
    [mm] (pose, tracker) or the registration's whitened RMS (points); inf where nothing registers."""
    lengths, whitened = _pose_lengths(platform, strokes, readings)
    if lengths is None:
        return math.inf if whitened is None else whitened
    rows = np.all(np.isfinite(lengths), axis=1)
    if rows.sum() < 3:
        return math.inf
    return float(np.max(_leg_residuals_mm(lengths[rows], strokes[rows])))


def _check_wiring(platform: Platform, strokes: np.ndarray, readings: np.ndarray, where: str) -> bool:
    """Refuse a log that one rewiring (two columns swapped, a leg reversed) explains far better
    than every other; returns whether the log as written registers."""
    pick = _evenly(len(strokes), WIRING_SAMPLES)
    strokes, readings = strokes[pick], readings[pick]
    as_logged = _wiring_score(platform, strokes, readings)
    wirings = _wirings(strokes.shape[1])
    scores = sorted(
        (_wiring_score(platform, _rewired(strokes, order, sign, platform), readings), k)
        for k, (_, order, sign) in enumerate(wirings)
    )
    best, k = scores[0]
    # the other way of reversing the same leg differs by an offset only, which some instruments
    # cannot see: the runner-up is the best of the other mistakes
    second = next(score for score, j in scores[1:] if wirings[j][0] != wirings[k][0])
    if best * WIRING_GAIN < min(as_logged, second):  # one rewiring alone explains the log
        _, order, sign = wirings[k]
        _refuse(where, _wiring_message(order, sign, _drive_words(platform), as_logged, best))
    return math.isfinite(as_logged)


def diagnose_log(
    platform: Platform, strokes: np.ndarray, readings: np.ndarray, where: str, reading_columns=None, count: bool = True
) -> None:
    """Refuse a log whose mistake has a nameable cause (see the module), before any solver runs.

    Args:
        strokes: ``(N, legs)`` logged strokes [mm]; readings: ``(N, m)`` the instrument's readings in
            code units (mm, rad; NaN where a point target was not seen).
        where: names the log in the message (its path).
        reading_columns: the log's reading column names (default: the platform's).
        count: whether to check that the samples are enough to calibrate (not for a held-out log).
    Raises:
        CalibError: one line naming the cause and its evidence.
    """
    from ..io.logs import reading_columns as columns_of

    strokes = np.asarray(strokes, dtype=float)
    readings = np.asarray(readings, dtype=float)
    columns = list(reading_columns or columns_of(platform))
    stroke_columns = _drive_words(platform)[0]
    if count:  # a held-out log may well hold one pose
        check_moves(platform, strokes, readings, where, len(strokes))
    pick = _evenly(len(strokes))
    strokes, readings = strokes[pick], readings[pick]
    _check_strokes_unit(platform, strokes, where, stroke_columns)
    fk = _fk(platform, strokes)
    ok = fk.converged
    # readings are compared with the motion the strokes give: a log that holds one pose (a held-out
    # log, track's first rows of a robot waiting) has none, and its readings spread by their noise alone
    moves = (
        bool(len(strokes))
        and float(np.nanmax(np.ptp(strokes, axis=0))) >= REST_FRACTION * _stroke_reference(platform)[0]
    )
    if ok.sum() >= 3 and moves:
        _check_reading_units(platform, fk.R[ok], fk.t[ok], readings[ok], where, columns)
        check_readings_follow(platform, fk.R[ok], fk.t[ok], readings[ok], where, columns)
    registers = _check_wiring(platform, strokes, readings, where)
    if instrument_kind(platform).outside and ok.sum() >= 3:  # after the wiring: a leg reversed is named as such
        _check_strokes_fit(platform, fk.R[ok], readings[ok], where)
    if ok.sum() >= 3:  # after the wiring: a reversed leg's poses turn wrongly too, and its cause is named there
        _check_handedness(platform, fk.R[ok], readings[ok], where, columns)
    if not registers and instrument_kind(platform).outside and ok.sum() >= 3:
        _check_directions(platform, fk.R[ok], fk.t[ok], where)
        _check_strokes_register(platform, fk.R[ok], readings[ok], where)
