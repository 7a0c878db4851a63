"""Which poses should a user measure? Optimal experimental design over random workspace poses.

Each candidate pose contributes a block of six rows ``U_k`` to the stacked identification
Jacobian (see :mod:`stewart_calib.analysis.identifiability`), so the information of a design is
``F = F₀ + Σ U_kᵀ U_k``. Criteria (bigger is better):

* ``A`` (default): ``−tr F⁻¹`` of the whitened leg-length form — minimises the sum of the 42
  predicted variances, i.e. the RMS predicted standard deviation a user sees in the report.
* ``D``: ``log det F`` of the whitened leg-length form — minimises the volume of the
  parameters' confidence ellipsoid (what ``ekf``/``isam2``/``lm`` identify).
* ``O1``: Borm & Menq's O1 of the paper's ``J_p`` form with scaled rotation rows (what ``ls`` and
  ``paper-ekf`` fit). For a fixed number of poses O1 = (det F)^(1/84)/√(6N), so it ranks
  designs as ``log det`` of that form does.
* ``E``: ``λmin(F)`` of the whitened leg-length form — the weakest direction's information.

Search: greedy by ``log det`` (``A`` and ``E`` are flat until 7 poses make F full rank, so its greedy
phase uses D too), then DETMAX-style exchanges (Mitchell 1974) by the chosen criterion: add the
best candidate, drop the design point whose removal costs least, until the one dropped is the
one just added. Adding or removing a six-row block changes ``log det`` by
``log det(I₆ ± U F⁻¹ Uᵀ)`` (matrix determinant lemma) and ``F⁻¹`` by a Woodbury update, so a
step costs one batched 6×6 determinant (``A``: a 6×6 solve) over the candidates instead of a
42×42 factorisation each. ``E`` needs 42×42 eigenvalues; an upper bound (the weakest
eigenvector's Rayleigh quotient) limits them to the few candidates that could win.

Cost: O(N·M) for N poses from M candidates — about 1.25 N steps (N greedy, then the
exchanges: 59 for N = 100, 253 for 1000, 515 for 2000), each a few µs of CPU a candidate.
Linear in N at the default 2000 candidates; quadratic when M grows with N (BENCHMARKS.md,
"Planned poses", for the times). The blocks hold 2 kB a candidate.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from ..analysis.accuracy import (
    PredictedError,
    closed_loop_jacobian,
    error_weight,
    predicted_error,
    reachable_poses,
    within_ranges,
)
from ..analysis.identifiability import RANK_RTOL, scaled_paper_jacobian, whitened_leg_jacobian
from ..config import NoiseConfig
from ..errors import CalibError
from ..instruments import instrument_kind, outside_model
from ..model import kinematics as kin
from ..model.platform import LegGeometry, Platform
from ..model.rotary import RotaryLegs

CRITERIA = ("A", "D", "O1", "E", "I")
#: the tracker's default (its designs and tests predate ``I``); outside instruments default to ``I``
DEFAULT_CRITERION = "A"
#: the criteria ``−tr(W F⁻¹)``, linear in the covariance
LINEAR = ("A", "I")

#: Bisection steps that pull an extreme pose of the box back along its ray from home until its
#: strokes are in range: 2⁻²⁰ of the offset, below a micrometre on any hexapod.
EXTREME_BISECTIONS = 20

#: Fedorov passes over the design at most (each costs a best-addition search per design point); a
#: swap counts when it improves the criterion by more than SWAP_GAIN_REL (round-off ties otherwise
#: could cycle). Measured on 60 poses of the shipped and test geometries: 2–4 passes to settle.
FEDOROV_PASSES = 5
SWAP_GAIN_REL = 1e-9

#: Ridge added to the information, relative to the mean per-pose information: it makes the
#: first greedy picks (fewer than 7 poses, singular F) well posed; at 1e-6 of one pose's
#: information it changes a 7-pose design's log det by < 1e-4.
RIDGE_REL = 1e-6

#: An outside instrument's plan keeps each nominal stroke this many prior σ (``noise.prior_sigma_mm``,
#: the zeros' and joints' uncertainty before calibration) inside the stroke range: the true robot
#: needs other strokes for the same pose, and a pose planned at the nominal limit is beyond the
#: real one about half the time — calibrate refuses it as out of range, the robot's end stop stops
#: it. Measured (benchmarks.plan_poses, hobby hexapod, zeros off by σ 3 mm, joints 0.5 mm, scale
#: 2 %): 21–23 of 60 poses planned at the nominal limits out of range, the fit then at 1.3–1.6×
#: the plan's prediction.
STROKE_MARGIN_SIGMAS = 2.0

#: The in-situ tracker's readings keep as many σ of the spread the true robot's offsets put on them
#: inside the reading range (:func:`with_reading_margin`): the true robot reaches another pose for the
#: nominal strokes, and a planned pose whose nominal readings sit at the range's end reads beyond it
#: about half the time. Measured (benchmarks.prediction, nim-stewart, parameters off by σ 0.5 mm,
#: 10 seeds of 60 planned poses, no margin): 5–7 poses read beyond the range and were skipped.
READING_MARGIN_SIGMAS = STROKE_MARGIN_SIGMAS

#: Candidates are drawn denser near the faces of the workspace box, where optimal designs put
#: their poses (the legs' directions spread most there); every candidate stays inside the box.
#: Measured on nim-stewart, 30 poses from 2000 candidates, criterion A: RMS predicted σ
#: 0.0139 mm with uniform candidates (exponent 1), 0.0123 with 1/2, 0.0116 with 0.3.
FACE_BIAS_EXPONENT = 0.3


def candidate_poses(
    platform: Platform, n: int, rng: np.random.Generator, ranges: str = "the stroke and reading ranges"
) -> np.ndarray:
    """``(n, 6)`` random reachable poses in the workspace box, denser near its faces
    (:data:`FACE_BIAS_EXPONENT`; :func:`stewart_calib.analysis.accuracy.reachable_poses`, whose
    refusal names ``ranges``).

    Raises:
        CalibError: the platform has no ``[workspace]``, or almost no pose of the box is reachable.
    """
    return reachable_poses(platform, n, rng, FACE_BIAS_EXPONENT, ranges)


def extreme_poses(platform: Platform) -> np.ndarray:
    """The workspace box's extremes, translation and orientation combined: every pose
    ``home + (a · translation_limit, b · rotation_limit)`` with each of the six ``a, b`` in
    {−1, 0, 1} (3⁶ = 729, home included), each pulled back along its ray from home to the
    farthest point whose strokes (and tracker readings) are in range. Optimal designs for the
    unknowns an outside instrument shares with the drive sit there: the leg lengths trade against
    the instrument frame's height, a direction only poses that tilt and reach far see.

    Raises:
        CalibError: the platform has no ``[workspace]``.
    """
    ws = platform.workspace
    if ws is None:
        raise CalibError(f"{platform.source}: key 'workspace': expected a [workspace] table to draw poses from")
    levels = np.array(np.meshgrid(*[[-1.0, 0.0, 1.0]] * 6, indexing="ij")).reshape(6, -1).T
    offsets = levels * np.r_[[ws.translation_limit] * 3, [ws.rotation_limit] * 3]
    reach = np.where(within_ranges(platform, ws.home + offsets), 1.0, 0.0)  # home itself is in range
    lo, hi = reach.copy(), np.ones(len(offsets))
    for _ in range(EXTREME_BISECTIONS):
        mid = 0.5 * (lo + hi)
        ok = within_ranges(platform, ws.home + mid[:, None] * offsets)
        lo, hi = np.where(ok, mid, lo), np.where(ok, hi, mid)
    return ws.home + lo[:, None] * offsets


def _design(platform: Platform, poses: np.ndarray, criterion: str, noise: NoiseConfig):
    """Six-row (tracker) or m-row (outside instrument) information blocks ``U_k`` ``(M, m, p)``
    and the weight of a linear criterion (``A``, ``I``; None: the identity of the tracker's ``A``).

    The tracker's blocks are the drive parameters δM's (whitened leg-length form, or the paper's
    ``J_p`` form for ``O1``); an outside instrument's are every unknown of the batch fit
    (:meth:`stewart_calib.instruments.external.OutsideModel.information_rows`). ``A`` weighs the drive
    parameters alike, ``I`` by the closed-loop error they cause (:func:`accuracy.error_weight`).
    """
    if not instrument_kind(platform).outside:
        if criterion == "O1":
            return scaled_paper_jacobian(platform, poses), None
        blocks = whitened_leg_jacobian(platform, poses, noise)
        n_params = platform.drive.n_params
        return blocks, error_weight(platform)[:n_params, :n_params] if criterion == "I" else None
    if criterion == "O1":
        raise CalibError(
            f"criterion: O1 is of the paper's J_p form, the in-situ tracker's; expected one of "
            f"{', '.join(c for c in CRITERIA if c != 'O1')} for a '{platform.instrument.kind}' instrument"
        )
    blocks, lift = outside_model(platform).information_rows(poses)
    if criterion == "I":
        W = error_weight(platform)
        weight = lift[: len(W)].T @ W @ lift[: len(W)]
    else:
        n_params = platform.drive.n_params
        weight = lift[:n_params].T @ lift[:n_params]
    # mm, rad and dimensionless columns: equilibrated, so that the ridge weighs them alike
    # (−tr(W F⁻¹) and log det rank designs as before, with W and F scaled alike)
    scale = np.sqrt(np.mean(np.sum(blocks**2, axis=1), axis=0))
    scale = np.where(scale > 0, scale, 1.0)
    return blocks / scale, weight / np.outer(scale, scale)


def _blocks_times(U: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """``U[k] @ matrix`` for every block of ``U`` ``(K, m, p)``, as one ``(K·m, p)`` product: numpy
    multiplies a stack by a matrix a block at a time, ~2.5× slower on plan's ~2700 candidates of
    6 rows, each row's sums the same."""
    K, m, p = U.shape
    return (U.reshape(K * m, p) @ matrix).reshape(K, m, matrix.shape[-1])


def _logdet_change(cov: np.ndarray, U: np.ndarray, sign: float) -> np.ndarray:
    """``log det(F ± UᵀU) − log det F = log det(I₆ ± U F⁻¹ Uᵀ)`` per block ``(K,)``."""
    S = np.eye(U.shape[1]) + sign * _blocks_times(U, cov) @ np.swapaxes(U, -1, -2)
    if sign > 0:  # S is then positive definite: Cholesky is ~10× cheaper than slogdet
        return 2.0 * np.sum(np.log(np.diagonal(np.linalg.cholesky(S), axis1=-2, axis2=-1)), axis=-1)
    sign_det, logdet = np.linalg.slogdet(S)
    # Removing a block that carries all the information in some direction makes S singular.
    return np.where(sign_det > 0, logdet, -np.inf)


def _trace_change(cov: np.ndarray, U: np.ndarray, sign: float, weight: np.ndarray | None = None) -> np.ndarray:
    """``tr W(F ± UᵀU)⁻¹ − tr W F⁻¹ = ∓ tr(S⁻¹ U F⁻¹ W F⁻¹ Uᵀ)`` with ``S = I ± U F⁻¹ Uᵀ``, per
    block (``W``: ``weight``, the identity when None)."""
    UC = _blocks_times(U, cov)
    S = np.eye(U.shape[1]) + sign * UC @ np.swapaxes(U, -1, -2)
    UCW = UC if weight is None else _blocks_times(UC, weight)
    change = -sign * np.trace(np.linalg.solve(S, UCW @ np.swapaxes(UC, -1, -2)), axis1=-2, axis2=-1)
    if sign > 0:
        return change
    sign_det, _ = np.linalg.slogdet(S)
    return np.where(sign_det > 0, change, np.inf)


def _woodbury(cov: np.ndarray, U: np.ndarray, sign: float) -> np.ndarray:
    """``(F ± UᵀU)⁻¹`` from ``cov = F⁻¹``: ``cov ∓ cov Uᵀ (I ± U cov Uᵀ)⁻¹ U cov``."""
    CU = cov @ U.T
    S = np.eye(U.shape[0]) + sign * U @ CU
    updated = cov - sign * CU @ np.linalg.solve(S, CU.T)
    return 0.5 * (updated + updated.T)  # round-off asymmetry would grow over many updates


def _best_lambda_min(info: np.ndarray, U: np.ndarray, allowed: np.ndarray, chunk: int = 64) -> int:
    """Index of the allowed block maximising ``λmin(F + UᵀU)``, exactly, by branch and bound.

    ``λmin(F + UᵀU) ≤ vᵀ(F + UᵀU)v = λmin(F) + ‖U v‖²`` for F's weakest eigenvector v, so
    candidates are evaluated (42×42 eigenvalues, the costly part) in order of that bound
    until the best value found beats every remaining bound.
    """
    eigenvalues, eigenvectors = np.linalg.eigh(info)
    bound = np.where(allowed, eigenvalues[0] + np.sum((U @ eigenvectors[:, 0]) ** 2, axis=-1), -np.inf)
    order = np.argsort(-bound)
    best, best_value = -1, -np.inf
    for start in range(0, int(allowed.sum()), chunk):
        if best_value >= bound[order[start]]:
            break
        idx = order[start : start + chunk]
        idx = idx[allowed[idx]]
        values = np.linalg.eigvalsh(info + np.swapaxes(U[idx], -1, -2) @ U[idx])[:, 0]
        if values.max() > best_value:
            best, best_value = int(idx[np.argmax(values)]), float(values.max())
    return best


def _best_addition(
    criterion: str, info: np.ndarray, cov: np.ndarray, U: np.ndarray, free: np.ndarray, weight=None
) -> int:
    """The free candidate whose block improves the criterion most."""
    if criterion == "E":
        return _best_lambda_min(info, U, free)
    gain = -_trace_change(cov, U, +1.0, weight) if criterion in LINEAR else _logdet_change(cov, U, +1.0)
    return int(np.argmax(np.where(free, gain, -np.inf)))


def _cheapest_removal(criterion: str, info: np.ndarray, cov: np.ndarray, U: np.ndarray, weight=None) -> int:
    """Position (in ``U``) of the design block whose removal costs the criterion least."""
    if criterion == "E":
        kept = np.linalg.eigvalsh(info - np.swapaxes(U, -1, -2) @ U)[:, 0]
    elif criterion in LINEAR:
        kept = -_trace_change(cov, U, -1.0, weight)
    else:
        kept = _logdet_change(cov, U, -1.0)
    return int(np.argmax(kept))


def select_poses(
    blocks: np.ndarray,
    n: int,
    criterion: str = DEFAULT_CRITERION,
    max_exchanges: int | None = None,
    weight: np.ndarray | None = None,
    criterion_greedy: bool = False,
) -> np.ndarray:
    """Indices of ``n`` distinct candidates maximising the criterion (greedy, then exchanges).

    Args:
        blocks: ``(M, m, p)`` each candidate's rows of the stacked identification Jacobian.
        n: poses to pick (≤ M).
        criterion: ``A``/``I`` (−trace of the weighted inverse), ``D``/``O1`` (log det of the
            blocks' information) or ``E`` (its λmin).
        max_exchanges: cap on accepted exchanges (default ``10 n``); each strictly improves
            the criterion, so the cap only guards against cycling on exact ties.
        weight: ``(p, p)`` ``W`` of the linear criteria ``−tr(W F⁻¹)`` (None: the identity).
        criterion_greedy: the greedy phase follows the criterion once the design has as many rows
            as unknowns, and Fedorov's swaps follow DETMAX's exchanges (the tracker's designs
            predate both: False).
    Returns:
        ``(n,)`` candidate indices in the order of the final design.
    """
    M, n_rows, n_params = blocks.shape
    gram = np.einsum("kri,krj->ij", blocks, blocks) / M
    info = RIDGE_REL * np.trace(gram) / n_params * np.eye(n_params)
    cov = np.linalg.inv(info)
    chosen: list[int] = []
    free = np.ones(M, dtype=bool)
    for step in range(n):
        # log det picks the first poses (A, I and E are flat until F has full rank); with
        # criterion_greedy the criterion takes over once the design could have it
        by = criterion if criterion_greedy and step * n_rows >= n_params else "D"
        k = _best_addition(by, info, cov, blocks, free, weight)
        chosen.append(k)
        free[k] = False
        info += blocks[k].T @ blocks[k]
        cov = _woodbury(cov, blocks[k], +1.0)

    for _ in range(10 * n if max_exchanges is None else max_exchanges):
        k = _best_addition(criterion, info, cov, blocks, free, weight)
        info_plus = info + blocks[k].T @ blocks[k]
        cov_plus = _woodbury(cov, blocks[k], +1.0)
        members = np.array(chosen + [k])
        drop = int(members[_cheapest_removal(criterion, info_plus, cov_plus, blocks[members], weight)])
        if drop == k:
            break
        chosen[chosen.index(drop)] = k
        free[k], free[drop] = False, True
        info = info_plus - blocks[drop].T @ blocks[drop]
        cov = _woodbury(cov_plus, blocks[drop], -1.0)
    if criterion_greedy:
        _fedorov_swaps(criterion, chosen, free, info, cov, blocks, weight)
    return np.array(chosen)


def _fedorov_swaps(criterion, chosen, free, info, cov, blocks, weight) -> None:
    """Fedorov's exchange after DETMAX's (which stops when the best addition is the cheapest
    removal, though another pair may still improve): for each design point in turn, its best
    replacement among the free candidates, taken when it improves the criterion; until a pass over
    the design changes nothing (at most :data:`FEDOROV_PASSES`). ``chosen``/``free`` in place."""
    value = _value(criterion, info, weight)
    for _ in range(FEDOROV_PASSES):
        improved = False
        for position in range(len(chosen)):
            drop = chosen[position]
            info_minus = info - blocks[drop].T @ blocks[drop]
            if np.linalg.eigvalsh(info_minus)[0] <= 0:
                continue  # the design point carries all the information in some direction
            cov_minus = _woodbury(cov, blocks[drop], -1.0)
            k = _best_addition(criterion, info_minus, cov_minus, blocks, free, weight)
            info_swapped = info_minus + blocks[k].T @ blocks[k]
            swapped = _value(criterion, info_swapped, weight)
            if swapped > value + SWAP_GAIN_REL * abs(value):
                chosen[position], free[k], free[drop] = k, False, True
                info, cov, value = info_swapped, _woodbury(cov_minus, blocks[k], +1.0), swapped
                improved = True
        if not improved:
            return


def _value(criterion: str, info: np.ndarray, weight: np.ndarray | None) -> float:
    """The criterion of an information matrix (bigger is better)."""
    if criterion == "E":
        return float(np.linalg.eigvalsh(info)[0])
    if criterion in LINEAR:
        cov = np.linalg.inv(info)
        return -float(np.trace(cov if weight is None else weight @ cov))
    return float(np.linalg.slogdet(info)[1])


def design_covariance(
    platform: Platform,
    poses: np.ndarray,
    noise: NoiseConfig | None = None,
    seen: np.ndarray | None = None,
    channels=None,
) -> np.ndarray | None:
    """Cramér–Rao covariance of the unknowns from a pose list, at the nominal model: over the 42
    drive parameters for the tracker (whitened leg-length form), over ``[δM (42), k (6),
    instrument]`` for an outside instrument (its batch fit's unknowns, gauge held). None when the
    poses do not identify every unknown (singular values below ``RANK_RTOL`` of the largest).
    ``seen``: ``(N, m)`` the instrument's channels read at each pose (a log's finite readings;
    default: those in view, :meth:`~stewart_calib.instruments.external.OutsideModel.information_rows`);
    ``channels``: the poses' input channels (a log's payloads and temperatures, row for row; default none)."""
    poses = np.asarray(poses, dtype=float).reshape(-1, 6)
    if not instrument_kind(platform).outside:
        rows, lift = whitened_leg_jacobian(platform, poses, noise or NoiseConfig()), np.eye(platform.drive.n_params)
    else:
        rows, lift = outside_model(platform).information_rows(poses, seen, channels)
    _, s, Vt = np.linalg.svd(rows.reshape(-1, rows.shape[-1]), full_matrices=False)
    if s[-1] <= RANK_RTOL * s[0]:
        return None
    return lift @ ((Vt.T / s**2) @ Vt) @ lift.T


def noise_words(platform: Platform, noise: NoiseConfig, config: str | None) -> str:
    """The noise :func:`design_covariance` takes, named as the prediction lines of ``plan`` and
    ``identifiability`` print it: an outside instrument's σ from the platform file's ``[instrument]``
    (``calibrate`` re-estimates it from the log's residuals), the in-situ tracker's readings' and the drive's
    coordinates' from the estimator configuration's ``[noise]`` (``config``: ``--config``'s name; None, the
    default configuration) — a prediction is as small as the noise it is given."""
    if instrument_kind(platform).outside:
        sigma = f"{platform.instrument.position_sigma_mm:g} mm"
        if instrument_kind(platform).measures_orientation:
            sigma += f" / {math.degrees(platform.instrument.orientation_sigma_rad):g}°"
        return f"for the instrument's σ {sigma}, the platform file's [instrument]"
    legs = platform.drive
    coordinate = legs.coordinate_sigma(noise)
    drive = f"{coordinate:g} mm" if legs.coordinate_unit == "mm" else f"{math.degrees(coordinate):g}°"
    source = f"--config {config}'s" if config else "the default configuration's: --config names your estimator's"
    return f"for tracker readings of σ {noise.reading_sigma_mm:g} mm and drive coordinates of σ {drive}, {source}"


def noise_floor(platform: Platform, n_poses: int, noise: NoiseConfig | None = None) -> PredictedError | None:
    """What the instrument's noise leaves with ``n_poses`` poses spread over the workspace box's
    :func:`extreme_poses` (their Cramér–Rao covariance × 729 / n): the closed-loop error a
    calibration of that size can expect, the yardstick of :func:`stewart_calib.analysis.accuracy.summary_line`.
    None without ``[workspace]``, or where the extremes do not identify every unknown."""
    if platform.workspace is None or n_poses < 1:
        return None
    extremes = extreme_poses(platform)
    covariance = design_covariance(platform, extremes, noise)
    if covariance is None:
        return None
    return predicted_error(platform, covariance * (len(extremes) / n_poses))


def with_stroke_margin(platform: Platform, noise: NoiseConfig) -> Platform:
    """The platform whose stroke range is :data:`STROKE_MARGIN_SIGMAS` prior σ narrower at each end
    (at most a quarter of the range): where plan puts an outside instrument's poses. A rotary drive's
    angle range (spec §15) narrows by as many ``noise.angle_prior_sigma_deg``, the zero trims' σ, and
    its poses keep as much crank angle from a rod's full stretch or fold (``RotaryLegs.reach_margin``)."""
    if isinstance(platform.drive, RotaryLegs):
        low, high = platform.drive.angle_range
        margin = _margin(math.radians(noise.angle_prior_sigma_deg), high - low)
        narrowed = replace(platform.drive, angle_range=(low + margin, high - margin), reach_margin=margin)
        return replace(platform, drive=narrowed)
    if platform.stroke_range is None:
        return platform
    low, high = platform.stroke_range
    margin = _margin(noise.prior_sigma_mm, high - low)
    return replace(platform, stroke_range=(low + margin, high - margin))


def margin_words(platform: Platform, reach: Platform, noise: NoiseConfig) -> str:
    """The ranges ``reach`` (``platform`` narrowed by :func:`with_stroke_margin` and
    :func:`with_reading_margin`) keeps plan's poses in, in words, with the prior σ that sets each
    margin: ``"the ranges plan keeps its poses in (the strokes 25–75 mm, 25 mm inside the stroke range at
    each end (2 × noise.prior_sigma_mm 20 mm, …); …)"``."""
    parts = []
    if isinstance(platform.drive, RotaryLegs) and isinstance(reach.drive, RotaryLegs):
        (low, _), (inner_low, inner_high) = platform.drive.angle_range, reach.drive.angle_range
        if inner_low > low:
            parts.append(
                f"the servo angles {math.degrees(inner_low):.3g}–{math.degrees(inner_high):.3g}°, "
                f"{math.degrees(inner_low - low):.3g}° inside their range at each end ({STROKE_MARGIN_SIGMAS:g} × "
                f"noise.angle_prior_sigma_deg {noise.angle_prior_sigma_deg:g}°, at most a quarter of the range)"
            )
    elif platform.stroke_range is not None and reach.stroke_range is not None:
        (low, _), (inner_low, inner_high) = platform.stroke_range, reach.stroke_range
        if inner_low > low:
            parts.append(
                f"the strokes {inner_low:.3g}–{inner_high:.3g} mm, {inner_low - low:.3g} mm inside the stroke range at "
                f"each end ({STROKE_MARGIN_SIGMAS:g} × noise.prior_sigma_mm {noise.prior_sigma_mm:g} mm, at most a "
                "quarter of the range)"
            )
    if platform.reading_range is not None and reach.reading_range is not None:
        (low, _), (inner_low, inner_high) = platform.reading_range, reach.reading_range
        if inner_low > low:
            parts.append(
                f"the tracker's readings {inner_low:.4g}–{inner_high:.4g} mm, {inner_low - low:.3g} mm inside their "
                "range at each end (the spread a robot built within the prior σ gives them)"
            )
    if not parts:
        return "the stroke and reading ranges"
    return (
        f"the ranges plan keeps its poses in ({'; '.join(parts)}; a smaller prior σ in the config, as small as "
        "the robot's build allows, widens them)"
    )


def _margin(prior_sigma: float, width: float) -> float:
    """:data:`STROKE_MARGIN_SIGMAS` × ``prior_sigma``, at most a quarter of the range's ``width``."""
    return min(STROKE_MARGIN_SIGMAS * prior_sigma, 0.25 * width)


def with_reading_margin(platform: Platform, noise: NoiseConfig) -> Platform:
    """The platform whose in-situ tracker's reading range is :func:`reading_margin_mm` narrower at each
    end (unchanged without a tracker or a reading range): where plan puts the tracker's poses."""
    margin = reading_margin_mm(platform, noise)
    if margin is None or platform.reading_range is None:
        return platform
    low, high = platform.reading_range
    return replace(platform, reading_range=(low + margin, high - margin))


def reading_margin_mm(platform: Platform, noise: NoiseConfig) -> float | None:
    """:data:`READING_MARGIN_SIGMAS` σ [mm], at most a quarter of the reading range; None without a
    tracker or a reading range. σ is the largest spread of a reading over the box's
    :func:`extreme_poses`, where the range binds, for a robot built within its prior: the pose the
    robot reaches for the nominal strokes moves by ``D δθ`` (``closed_loop_jacobian``, δθ under the
    prior of :func:`prior_sigmas`), which moves reading i by row i of ``J_t D δθ`` (``J_t`` the
    tracker's leg–pose Jacobian); the tracker's own geometry (``[tracker] geometry_sigma_mm``, else
    ``noise.tracker_geometry_sigma_mm``) moves it by ``√3 σ_g`` besides (its two joints along the leg,
    its zero)."""
    if platform.tracker is None or platform.reading_range is None:
        return None
    poses = extreme_poses(platform)
    R, t = kin.pose_to_rt(poses)
    sigma = prior_sigmas(platform, noise)
    carried = kin.leg_pose_jacobian(platform.tracker, R, t) @ closed_loop_jacobian(platform, poses)[..., : len(sigma)]
    geometry_sigma_mm = platform.tracker_geometry_sigma_mm or noise.tracker_geometry_sigma_mm
    spread_mm = np.sqrt(np.sum((carried * sigma) ** 2, axis=-1) + 3.0 * geometry_sigma_mm**2)
    low, high = platform.reading_range
    return min(READING_MARGIN_SIGMAS * float(spread_mm.max()), 0.25 * (high - low))


def prior_sigmas(platform: Platform, noise: NoiseConfig) -> np.ndarray:
    """The prior σ of the drive's unknowns before calibration, for a robot built within the prior:
    ``noise.prior_sigma_mm`` on each δM (another leg model's own ``prior_sigmas``: a servo's angles in
    rad) and, with an outside instrument, the stroke scale's prior σ
    (:func:`~stewart_calib.model.drive.drive_model`'s): the terms up to the first known one, in the
    order of :func:`~stewart_calib.analysis.accuracy.closed_loop_jacobian`'s columns."""
    from ..model.drive import drive_model

    drive = drive_model(platform, noise, instrument_kind(platform).outside)
    legs = platform.drive  # the prismatic legs' prior is noise.prior_sigma_mm on every entry
    sigma = [noise.prior_sigma_mm] * legs.n_params if type(legs) is LegGeometry else list(legs.prior_sigmas(noise))
    for term in drive.terms:  # the terms up to the first known one, as predicted_error takes them
        if term.prior_sigma is None:
            break
        sigma += [term.prior_sigma] * platform.drive.n_legs
    return np.array(sigma)


def nominal_error(platform: Platform, noise: NoiseConfig) -> PredictedError:
    """What the nominal model is expected to leave, for a robot built within the prior: the
    predicted error (:func:`~stewart_calib.analysis.accuracy.predicted_error`) of the prior covariance
    (:func:`prior_sigmas`) — the yardstick a plan must clearly beat."""
    return predicted_error(platform, np.diag(np.square(prior_sigmas(platform, noise))))


#: A plan is clearly better than the nominal model when the upper end of its predicted error's
#: 90 % band is below this fraction of the nominal model's expected error.
CLEARLY_BETTER = 0.5


def plan_warning(platform: Platform, noise: NoiseConfig, predicted: PredictedError, n_poses: int) -> str | None:
    """The warning of a plan whose predicted error is not clearly better than the nominal model's
    (:func:`nominal_error`, :data:`CLEARLY_BETTER`) in motion or in absolute place, or whose stroke
    margin (:func:`with_stroke_margin`) is capped at a quarter of the range — a prior σ wider than the
    robot's build shrinks the poses' spread — with what to change; None otherwise."""
    nominal = nominal_error(platform, noise)
    worse = [
        f"{what} {after:.3g} mm (90 %: up to {high:.3g} mm) against the nominal model's {before:.3g} mm"
        for what, after, high, before in (
            (
                "motion from home",
                predicted.motion_position_mm,
                predicted.motion_position_band_mm[1],
                nominal.motion_position_mm,
            ),
            ("absolute place in {J}", predicted.position_mm, predicted.position_band_mm[1], nominal.position_mm),
        )
        if high >= CLEARLY_BETTER * before
    ]
    cramped = None
    if platform.stroke_range is not None and instrument_kind(platform).outside:
        low, high = platform.stroke_range
        if STROKE_MARGIN_SIGMAS * noise.prior_sigma_mm >= 0.25 * (high - low):
            cramped = (
                f"its strokes keep {0.25 * (high - low):.3g} mm inside the range at each end, a quarter of it (the cap "
                f"of {STROKE_MARGIN_SIGMAS:g} × noise.prior_sigma_mm {noise.prior_sigma_mm:g} mm), which shrinks the "
                "poses' spread"
            )
    if not worse and cramped is None:
        return None
    advice = [f"more than {n_poses} poses", "a less noisy instrument"]
    if cramped:
        advice.insert(0, "a noise.prior_sigma_mm as small as the robot's build allows (a narrower stroke margin)")
    if predicted.limited_by and any(text.startswith("absolute") for text in worse):
        advice.append(f"a wider workspace, whose poses see {predicted.limited_by.split(' (σ')[0]}")
    what = (
        f"this plan is not clearly better than the nominal model (built to prior σ {noise.prior_sigma_mm:g} mm): "
        + "; ".join(worse)
        if worse
        else "this plan's poses are cramped"
    )
    return f"warning: {what}{'; ' + cramped if cramped else ''}; change: {', '.join(advice)}"


def default_criterion(platform: Platform) -> str:
    """``I`` (the predicted closed-loop error) for an outside instrument, ``A`` for the tracker."""
    return "I" if instrument_kind(platform).outside else DEFAULT_CRITERION


def plan_poses(
    platform: Platform,
    n: int,
    criterion: str | None = None,
    rng: np.random.Generator | None = None,
    n_candidates: int = 2000,
    noise: NoiseConfig | None = None,
) -> np.ndarray:
    """Pick ``n`` calibration poses from ``n_candidates`` random reachable workspace poses (and,
    for an outside instrument, the box's :func:`extreme_poses`; its poses keep a margin from the
    stroke limits, :func:`with_stroke_margin`, the in-situ tracker's from its reading limits,
    :func:`with_reading_margin`).

    Args:
        platform: nominal geometry with a ``[workspace]``.
        n: poses to plan (≥ 1, ≤ ``n_candidates``).
        criterion: one of :data:`CRITERIA` (default :func:`default_criterion`).
        rng: randomness of the candidates (default ``np.random.default_rng()``).
        n_candidates: random candidate poses to choose from.
        noise: weights of the leg-length form, and the prior σ of the stroke and reading margins
            (default :class:`NoiseConfig`).
    Returns:
        ``(n, 6)`` desired poses ``[mm, rad]``, in the order drawn (a usable driving order).
    Raises:
        CalibError: a bad ``n``, criterion or candidate count, or no workspace.
    """
    criterion = default_criterion(platform) if criterion is None else criterion
    if criterion not in CRITERIA:
        raise CalibError(f"criterion: expected one of {', '.join(CRITERIA)}, got {criterion!r}")
    if n < 1 or n_candidates < n:
        raise CalibError(f"n = {n}, candidates = {n_candidates}: expected 1 ≤ n ≤ candidates")
    rng = np.random.default_rng() if rng is None else rng
    noise = noise or NoiseConfig()
    outside = instrument_kind(platform).outside
    reach = with_reading_margin(with_stroke_margin(platform, noise) if outside else platform, noise)
    candidates = candidate_poses(reach, n_candidates, rng, margin_words(platform, reach, noise))
    if outside:
        candidates = np.concatenate([extreme_poses(reach), candidates])
    blocks, weight = _design(platform, candidates, criterion, noise)
    return candidates[np.sort(select_poses(blocks, n, criterion, weight=weight, criterion_greedy=outside))]
