"""Batch maximum-likelihood fit of the drive model and an outside instrument's unknowns.

What ``ls`` runs for the instruments of spec §7 other than the tracker (``pose``, ``points``).
The unknowns are the drive model's ``x_drive`` (the 42 errors δM in paper order, then its unknown
blocks, :mod:`stewart_calib.model.drive`: the stroke scale ``k_1..k_6``) and the instrument's frame and
target(s); the 12 directions no outside instrument can see are fixed by
:mod:`stewart_calib.instruments.gauge` (30 free drive directions). For every logged sample the
drive model's forward kinematics gives the platform pose X, the instrument model predicts its
reading, and the whitened residuals of all samples are minimised by Levenberg–Marquardt, with the
pose's dependence on ``x_drive`` from the implicit function theorem
(:meth:`~stewart_calib.model.drive.DriveModel.pose_jacobian`).

Robust by construction, with nothing for a user to tune:

* **closed-form start** (:mod:`stewart_calib.instruments.registration`): the instrument's
  unknowns that map the nominal FK poses onto the readings, so a frame 100 mm and any rotation
  away from its nominal value starts the iteration near the answer;
* **Levenberg–Marquardt** with Marquardt's column scaling (mm, rad and dimensionless unknowns
  together), so 20 mm encoder-zero errors and 10 % scale errors converge from the nominal drive;
* **noise from the data**: the σ of each channel (position, orientation) starts at the platform
  file's value and is re-estimated from the residuals (variance components), so the weighting
  of position against orientation is the data's own and the covariance is honest even when the
  file's σ is a guess;
* **Huber weights per reading** (``ls.robust_k`` σ, on the RMS of its whitened components) keep
  a glitch of the instrument (a swapped marker, a lost reflector) from pulling the fit.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike
from threadpoolctl import threadpool_limits

from ..config import LSConfig
from ..errors import CalibError, SampleRejected, number
from ..instruments import OutsideModel, gauge, outside_model
from ..model import kinematics as kin
from ..model import rotations
from ..model.drive import DriveModel
from ..samples import Inputs, input_rows

#: a singular value below this fraction of the largest counts as zero
RANK_TOLERANCE = 1e-10
#: outer rounds of (Levenberg–Marquardt, then noise and robust weights re-estimated)
MAX_ROUNDS = 6
#: the σ re-estimates have settled when no channel's moved more than this fraction
NOISE_SETTLED = 1e-3
#: LM evaluations (accepted and refused steps) per round
MAX_EVALUATIONS = 200
#: Gauss–Newton steps that finish each round once Levenberg–Marquardt has stopped (:func:`_polished`)
MAX_POLISH_STEPS = 8


@dataclass(frozen=True)
class BatchProblem:
    """One instrument's log, ready to fit.

    Attributes:
        drive: the drive model (its unknown blocks are fitted where identifiable).
        inputs: ``(N, width)`` the samples' drive inputs (the logged strokes q [mm]).
        measured: ``(N, m)`` readings in code units (NaN: a point target not seen).
        model: the instrument's model (:class:`~stewart_calib.instruments.external.OutsideModel`):
            its readings' residual, closed-form start (``register``), the σ of a reading's
            components from the platform file (``channel_sigma``) and the noise channel each
            belongs to (``noise_channels``, named by ``noise_channel_names``).
        t_s: ``(N,)`` sample times [s].
        channels: the samples' input channels (``Log.inputs``, each ``(N, ...)``): an elastic drive's
            leg forces under their payload are taken at the drive's forward-kinematics poses of each
            step of the fit.
    """

    drive: DriveModel
    inputs: np.ndarray
    measured: np.ndarray
    model: OutsideModel
    t_s: np.ndarray
    channels: Mapping[str, np.ndarray] = field(default_factory=dict)

    @classmethod
    def of_log(
        cls, platform, strokes: ArrayLike, measured: ArrayLike, t_s: ArrayLike, channels: Inputs | None = None
    ) -> BatchProblem:
        """The problem of a log of ``platform``'s outside instrument, with the platform file's σ
        and the drive model's unknowns (an elastic drive's under the samples' input ``channels``)."""
        from ..model.drive import drive_model

        drive = drive_model(platform).identifying()
        arrays = {name: np.asarray(values, dtype=float) for name, values in (channels or {}).items()}
        return cls(
            drive,
            drive.inputs_near(np.asarray(strokes, dtype=float), arrays),
            np.asarray(measured, dtype=float),
            outside_model(platform),
            np.asarray(t_s, dtype=float),
            arrays,
        )


@dataclass(frozen=True)
class BatchSolution:
    """Result of :func:`fit`.

    Attributes:
        x_drive: the drive's errors: δM [mm] (in the gauge of :mod:`~stewart_calib.instruments.gauge`)
            and its blocks'.
        unknowns: the instrument's fitted unknowns.
        covariance: full covariance over ``[x_drive, instrument tangent]``, or None when the fit is
            rank deficient.
        drive_blocks_fitted: by block key, False where the block was held at its nominal values (not
            identifiable from the log: the expansion of a log at one temperature), the others fitted.
        noise_sigmas: ``{channel: σ}`` estimated from the residuals.
        residual_rms: ``{channel: RMS}`` of the residuals at the start (registered nominal
            model) and at the solution, file units.
        singular_values: of the whitened reduced Jacobian at the solution (descending).
        used: ``(N,)`` mask of the samples in the fit.
        rejected: ``(index, SampleRejected)`` of the samples left out.
        downweighted: readings given less than full weight by the Huber kernel (``rejected_as_gross``
            of them none at all).
        iterations: LM evaluations in all.
    """

    x_drive: np.ndarray
    unknowns: object
    covariance: np.ndarray | None
    drive_blocks_fitted: dict[str, bool]
    noise_sigmas: dict
    residual_rms: dict
    singular_values: np.ndarray
    used: np.ndarray
    rejected: list = field(default_factory=list)
    downweighted: int = 0
    rejected_as_gross: int = 0
    iterations: int = 0


class _State:
    """A point of the fit: the drive's errors, the instrument's unknowns, the FK poses there and the
    drive inputs at them (an elastic drive's forces change with the pose)."""

    def __init__(self, x_drive, unknowns, R, t, inputs):
        self.x_drive, self.unknowns, self.R, self.t, self.inputs = x_drive, unknowns, R, t, inputs


def _fk(problem: BatchProblem, x_drive: np.ndarray, guess) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    if not problem.drive.needs_pose:
        sol, inputs = (
            problem.drive.forward_kinematics(problem.inputs, x_drive, guess=guess, strict=False),
            problem.inputs,
        )
    else:
        strokes = problem.inputs[:, : problem.drive.rows]  # the stroke term reads the first inputs, one a leg
        sol, inputs = problem.drive.settled_kinematics(strokes, problem.channels, x_drive, guess, strict=False)
    return sol.R, sol.t, sol.converged, inputs


def fit(
    problem: BatchProblem, robust_k: float, estimate_noise: bool, drive_blocks: str, tolerance_mm: float
) -> BatchSolution:
    """Fit the drive model and the instrument unknowns to the log (see the module docstring).

    Args:
        robust_k: Huber threshold on a reading's RMS whitened residual [σ]; 0 = plain least squares.
        estimate_noise: re-estimate each channel's σ from the residuals.
        drive_blocks: fit the drive's blocks ``"auto"`` (where identifiable), ``"on"`` or ``"off"``.
        tolerance_mm: stop when no drive or instrument length moves more than this [mm].
    Raises:
        CalibError: the log cannot be registered, or the fit diverges.
    """
    # its factorisations are small (a few hundred rows by ~80): on one BLAS thread, as ls.CHUNK_SAMPLES says
    # why (on a busy two-core machine OpenBLAS's waiting threads make them several times slower)
    with threadpool_limits(limits=1):
        return _fit(problem, robust_k, estimate_noise, drive_blocks, tolerance_mm)


def _fit(
    problem: BatchProblem, robust_k: float, estimate_noise: bool, drive_blocks: str, tolerance_mm: float
) -> BatchSolution:
    n = len(problem.inputs)
    start = np.zeros(problem.drive.size)
    R0, t0, ok, inputs0 = _fk(problem, start, None)
    rejected = [
        (
            int(k),
            SampleRejected(
                f"sample at t = {number(problem.t_s[k])} s: nominal forward kinematics did not converge",
                SampleRejected.FK_FAILED,
            ),
        )
        for k in np.flatnonzero(~ok)
    ]
    if not np.any(ok):
        raise CalibError(
            "ls: nominal forward kinematics failed for every sample; expected strokes the nominal drive can reach"
        )
    if rejected:
        problem = _subset(problem, ok)
        R0, t0, inputs0 = R0[ok], t0[ok], inputs0[ok]
    unknowns = problem.model.best_registration(R0, t0, problem.measured)
    state = _State(start, unknowns, R0, t0, inputs0)

    basis = gauge.free_basis(problem.drive.legs)
    sigmas = np.array(problem.model.channel_sigma, dtype=float)
    start_rms = _channel_rms(problem, problem.model.readings_residual(unknowns, problem.measured, R0, t0)[0])
    fitted = {block.key: drive_blocks != "off" for block in problem.drive.blocks}
    if drive_blocks == "auto":  # each block that the log sees is fitted, the others held at nominal
        fitted = _blocks_identifiable(problem, state, basis, sigmas)
    fit_blocks = _fitted_columns(problem, fitted)
    weights = np.ones(len(problem.inputs))
    evaluations = 0
    for _ in range(MAX_ROUNDS):
        state, evaluated = _levenberg_marquardt(problem, state, basis, sigmas, weights, fit_blocks, tolerance_mm)
        evaluations += evaluated
        e = problem.model.readings_residual(state.unknowns, problem.measured, state.R, state.t)[0]
        absorbed = _absorbed(problem, state, basis, sigmas, weights, fit_blocks, e) if estimate_noise else None
        new_sigmas = _channel_sigmas(problem, e, weights, sigmas, absorbed) if absorbed is not None else sigmas
        # weights from a robust scale (MAD): a gross error inflates the RMS that would judge it
        scale = _robust_channel_scale(problem, e, absorbed) if absorbed is not None else sigmas
        new_weights = _robust_weights(e / scale, robust_k)
        settled = np.all(np.abs(new_sigmas / sigmas - 1.0) < NOISE_SETTLED) and np.allclose(
            new_weights, weights, atol=1e-3
        )
        sigmas, weights = new_sigmas, new_weights
        if settled:
            break
    A, _ = _system(problem, state, basis, sigmas, weights, fit_blocks)
    _, s, Vt = np.linalg.svd(A, full_matrices=False)
    covariance = None
    if s[-1] > RANK_TOLERANCE * s[0]:
        reduced = (Vt.T / s**2) @ Vt
        lift = _lift(problem, basis, fit_blocks, state.unknowns.size)
        covariance = lift @ reduced @ lift.T
    e = problem.model.readings_residual(state.unknowns, problem.measured, state.R, state.t)[0]
    used = np.ones(n, dtype=bool)
    used[[k for k, _ in rejected]] = False
    return BatchSolution(
        x_drive=state.x_drive,
        unknowns=state.unknowns,
        covariance=covariance,
        drive_blocks_fitted=fitted,
        noise_sigmas={
            name: float(sigmas[problem.model.noise_channels == c][0])
            for c, name in enumerate(problem.model.noise_channel_names)
        },
        residual_rms={"before": start_rms, "after": _channel_rms(problem, e)},
        singular_values=s,
        used=used,
        rejected=rejected,
        downweighted=int(np.sum(weights < 1)),
        rejected_as_gross=int(np.sum(weights == 0)),
        iterations=evaluations,
    )


def cramer_rao(problem: BatchProblem, x_drive: np.ndarray, unknowns, fit_blocks: bool = True) -> np.ndarray:
    """Cramér–Rao bound at a point (e.g. the simulator's truth moved into the gauge): the inverse
    Fisher information of the whitened residuals with the problem's σ, lifted to the full
    ``[x_drive, instrument tangent]`` covariance (the 12 gauge directions carry none).

    Raises:
        CalibError: forward kinematics fails at that point.
        numpy.linalg.LinAlgError: the information is singular (unknowns not identifiable).
    """
    x_drive = np.asarray(x_drive, dtype=float)
    R, t, ok, inputs = _fk(problem, x_drive, None)
    if not np.all(ok):
        raise CalibError("Cramér–Rao bound: forward kinematics failed at the given parameters")
    state = _State(x_drive, unknowns, R, t, inputs)
    basis = gauge.free_basis(problem.drive.legs)
    A, _ = _system(
        problem,
        state,
        basis,
        np.asarray(problem.model.channel_sigma, dtype=float),
        np.ones(len(problem.inputs)),
        fit_blocks,
    )
    lift = _lift(problem, basis, fit_blocks, unknowns.size)
    return lift @ np.linalg.inv(A.T @ A) @ lift.T


def identifiability(problem: BatchProblem, unknowns, names: tuple[str, ...], file_jacobian: np.ndarray) -> dict:
    """How well the problem's poses identify the drive model and the instrument (at the nominal
    drive and the given instrument unknowns, with the problem's σ): rank and condition number of
    the whitened gauge-reduced Jacobian and the Cramér–Rao σ of every unknown.

    Args:
        names: the instrument unknowns' names; file_jacobian: ``∂ file values / ∂ tangent``.
    Returns:
        JSON-ready ``{"unknowns", "rank", "condition_number", "condition_number_equilibrated"
        (:func:`equilibrated_condition_number`), "verdict" (of the equilibrated number, with the
        thresholds of :mod:`stewart_calib.analysis.identifiability`), "null_space_dimension",
        "weakest_directions" and "null_space" (named, :func:`_named_directions`), "<block>_identifiable"
        per drive block, "predicted_stddev": {name: σ in file units (a servo's angles in degrees; None:
        not identified)}}``.
    """
    drive = problem.drive
    R, t, ok, inputs = _fk(problem, np.zeros(drive.size), None)
    if not np.all(ok):
        problem, R, t, inputs = _subset(problem, ok), R[ok], t[ok], inputs[ok]
    state = _State(np.zeros(drive.size), unknowns, R, t, inputs)
    basis = gauge.free_basis(drive.legs)
    sigmas = np.asarray(problem.model.channel_sigma, dtype=float)
    A, _ = _system(problem, state, basis, sigmas, np.ones(len(problem.inputs)), True)
    W = _centred(state, A.shape[1])
    A = A @ W
    # A's square triangular factor (rows padded to the columns): the same singular values, right
    # singular vectors and column norms as the (6N × 48) A at a fraction of the cost
    A = np.asarray(np.linalg.qr(np.vstack([A, np.zeros((max(0, A.shape[1] - A.shape[0]), A.shape[1]))]), mode="r"))
    s = np.linalg.svd(A, compute_uv=False)
    rank = int(np.sum(s > 1e-8 * s[0]))
    equilibrated = equilibrated_condition_number(A) if rank == A.shape[1] else None
    all_names = [*drive.parameter_names, *(name for block in drive.blocks for name in block.names), *names]
    weakest, null_space = _named_directions(problem, state, basis, sigmas, A, rank, all_names)
    stddev: list[float | None] = [None] * len(all_names)
    if rank == A.shape[1]:
        lift = _lift(problem, basis, True, unknowns.size)
        covariance = lift @ W @ np.linalg.inv(A.T @ A) @ W.T @ lift.T
        n = drive.size
        variance = np.r_[np.diag(covariance)[:n], np.diag(file_jacobian @ covariance[n:, n:] @ file_jacobian.T)]
        sd = np.sqrt(np.clip(variance, 0.0, None))
        sd[: drive.n_params] *= np.where(drive.legs.parameter_degrees, np.degrees(1.0), 1.0)  # file units
        stddev = [float(v) for v in sd]
    return {
        "unknowns": int(A.shape[1]),
        "gauge": gauge.gauge_statement(drive.legs.kind),
        "rank": rank,
        "condition_number": float(s[0] / s[-1]) if rank == A.shape[1] else None,
        "condition_number_equilibrated": equilibrated,
        "verdict": "rank-deficient" if equilibrated is None else _verdict(equilibrated),
        "null_space_dimension": len(null_space),
        "weakest_directions": weakest,
        "null_space": null_space,
        **{f"{key}_identifiable": value for key, value in _blocks_identifiable(problem, state, basis, sigmas).items()},
        "predicted_stddev": dict(zip(all_names, stddev, strict=True)),
    }


def instrument_identifiability(platform, strokes: np.ndarray, readings: np.ndarray, channels: Inputs | None) -> dict:
    """:func:`identifiability` of an outside instrument's samples (``strokes`` [mm], ``readings`` in
    file units, NaN: a target not seen; the log's input ``channels`` or None) at the nominal drive and the
    platform's instrument as it stands — register it on a log first
    (:func:`~stewart_calib.instruments.registered`)."""
    from ..model.drive import drive_model

    model = outside_model(platform)
    drive = drive_model(platform).identifying()
    unknowns = model.nominal_unknowns()
    arrays = {name: np.asarray(values, dtype=float) for name, values in (channels or {}).items()}
    problem = BatchProblem(
        drive,
        drive.inputs_near(strokes, arrays),
        readings,
        model,
        np.arange(len(strokes), dtype=float),
        arrays,
    )
    return identifiability(problem, unknowns, model.unknown_names, unknowns.file_jacobian())


def _named_directions(
    problem: BatchProblem, state: _State, basis, sigmas, A: np.ndarray, rank: int, names: list[str]
) -> tuple[list[str], list[str]]:
    """The weakest identified directions (up to :data:`~stewart_calib.analysis.identifiability.N_WEAKEST`,
    weakest first) and the ``A.shape[1] − rank`` unidentified ones of the gauge-reduced Jacobian
    (``A``: its square triangular factor, the frame turned about the platform's place, :func:`_centred`)
    with unit columns, each named in the unknowns
    (:func:`~stewart_calib.analysis.identifiability.name_direction`).

    A direction of the reduced unknowns is lifted to all of them (δM through the gauge's basis) and
    each component weighed by its unknown's own whitened column norm: the share, in σ of the
    readings, each unknown takes in it — mm, rad and k made comparable as the verdict's unit
    columns make them.
    """
    from ..analysis.identifiability import N_WEAKEST, name_direction

    norms = np.linalg.norm(A, axis=0)
    if np.any(norms == 0):
        norms = np.where(norms == 0, 1.0, norms)
    _, _, Vt = np.linalg.svd(A / norms)  # A square: Vᵀ holds the null space's rows too
    full = np.eye(problem.drive.n_params)  # every δM column, the gauge's directions too
    A_full = _system(problem, state, full, sigmas, np.ones(len(problem.inputs)), True)[0]
    own = np.linalg.norm(A_full @ _centred(state, A_full.shape[1]), axis=0)
    lift = _lift(problem, basis, True, state.unknowns.size)

    def named(v: np.ndarray) -> str:
        share = own * (lift @ (v / norms))
        share /= np.linalg.norm(share)
        return name_direction(share * np.sign(share[np.argmax(np.abs(share))]), names=names)

    weakest = [named(Vt[k]) for k in range(rank - 1, max(rank - 1 - N_WEAKEST, -1), -1)]
    return weakest, [named(v) for v in Vt[rank:]]


def equilibrated_condition_number(A: np.ndarray) -> float | None:
    """σmax/σmin of ``A`` with every column scaled to unit norm (None: rank-deficient).

    The unknowns of an outside instrument's fit are in mm, rad and dimensionless stroke scale
    together, so ``A``'s own condition number depends on the units chosen (a stroke scale in
    per cent would change it a hundredfold); with unit columns it does not, and it is within
    √p of the smallest over all column scalings (van der Sluis 1969). Measured: 260–800 for
    planned or rich random designs of the shipped and test geometries, 1.8·10³ for 60 poses
    within ±30 mm / ±8° of the hobby hexapod (frame height against leg lengths).
    """
    norms = np.linalg.norm(A, axis=0)
    if np.any(norms == 0):
        return None
    s = np.linalg.svd(A / norms, compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > RANK_TOLERANCE * s[0] else None


def _verdict(condition_number: float) -> str:
    from ..analysis.identifiability import poorly_conditioned

    return "poorly conditioned" if poorly_conditioned(condition_number) else "identifiable"


def _subset(problem: BatchProblem, keep: np.ndarray) -> BatchProblem:
    from dataclasses import replace

    return replace(
        problem,
        inputs=problem.inputs[keep],
        measured=problem.measured[keep],
        t_s=problem.t_s[keep],
        channels=input_rows(problem.channels, keep),
    )


def _fitted_columns(problem: BatchProblem, fitted: dict[str, bool] | bool) -> np.ndarray:
    """``(size − n_params,)`` bool: the drive's block columns a fit takes, from whether each block is
    fitted (by key, or one answer for all)."""
    blocks = problem.drive.blocks
    if isinstance(fitted, bool):
        fitted = {block.key: fitted for block in blocks}
    if not blocks:
        return np.zeros(0, dtype=bool)
    return np.concatenate([np.full(block.size, bool(fitted[block.key])) for block in blocks])


def _lift(problem: BatchProblem, basis: np.ndarray, fit_blocks: np.ndarray | bool, n_unknowns: int) -> np.ndarray:
    """Reduced unknowns ``[z_M (30), the drive's fitted block columns, u]`` → full ``[x_drive, u]``
    (a held block's rows zero)."""
    if isinstance(fit_blocks, bool):
        fit_blocks = _fitted_columns(problem, fit_blocks)
    n_free, n_drive, n_params = basis.shape[1], problem.drive.size, problem.drive.n_params
    columns = n_params + np.flatnonzero(fit_blocks)
    n_blocks = len(columns)
    lift = np.zeros((n_drive + n_unknowns, n_free + n_blocks + n_unknowns))
    lift[:n_params, :n_free] = basis
    lift[columns, n_free + np.arange(n_blocks)] = 1.0
    lift[n_drive:, n_free + n_blocks :] = np.eye(n_unknowns)
    return lift


def _system(problem: BatchProblem, state: _State, basis, sigmas, weights, fit_blocks: np.ndarray | bool):
    """Whitened, weighted Jacobian ``A`` (finite rows) and residual ``b`` at ``state``, the drive's block
    columns ``fit_blocks`` (a mask over them, or all / none)."""
    if isinstance(fit_blocks, bool):
        fit_blocks = _fitted_columns(problem, fit_blocks)
    e, H_X, H_u = problem.model.readings_residual(state.unknowns, problem.measured, state.R, state.t, jacobians=True)
    dxi = problem.drive.settled_pose_jacobian(state.x_drive, state.R, state.t, state.inputs, problem.channels)
    n_params = problem.drive.n_params
    blocks = [H_X @ dxi[..., :n_params] @ basis]
    if np.any(fit_blocks):
        blocks.append(H_X @ dxi[..., n_params:][..., fit_blocks])
    blocks.append(H_u)
    scale = np.sqrt(weights)[:, None] / sigmas[None, :]
    A = np.concatenate(blocks, axis=-1) * scale[..., None]
    b = e * scale
    rows = np.isfinite(b)
    return A[rows], b[rows]


def _apply(problem: BatchProblem, state: _State, basis, step: np.ndarray, fit_blocks: np.ndarray) -> _State | None:
    n_free, n_params = basis.shape[1], problem.drive.n_params
    columns = n_params + np.flatnonzero(fit_blocks)
    n_blocks = len(columns)
    x_drive = state.x_drive.copy()
    x_drive[:n_params] += basis @ step[:n_free]
    x_drive[columns] += step[n_free : n_free + n_blocks]
    unknowns = state.unknowns.retract(step[n_free + n_blocks :])
    R, t, ok, inputs = _fk(problem, x_drive, (state.R, state.t))
    if not np.all(ok):
        return None
    return _State(x_drive, unknowns, R, t, inputs)


def _centred(state: _State, n_columns: int) -> np.ndarray:
    """``W (n_columns, n_columns)``: the columns of :func:`_system` (the instrument's tangent last) for
    the frame turned about the platform's mean place ``c`` (in {I}) instead of {I}'s origin: ``F Exp([ω, v])``
    with ``v = v' + c × ω``, so ``A W`` holds the columns of ``[ω, v']``.

    An instrument's origin is often metres from the robot (a laser tracker on its stand, motion capture's
    origin on the floor): a turn about it moves the readings by the lever arm, which its shift undoes,
    so the two columns nearly coincide, and conditioning measured so is that of where {I}'s origin is,
    not of what the poses show (the hobby log with {I} 2.7 m away: 13 462 against 2 847, its weakest
    direction frame_x against frame_yaw). About ``c`` the frame's turn and shift move the readings apart."""
    W = np.eye(n_columns)
    first = n_columns - state.unknowns.size  # the frame's tangent [ω, v] leads the instrument's
    centre = state.unknowns.R_frame.T @ (np.mean(state.t, axis=0) - state.unknowns.t_frame)
    W[first + 3 : first + 6, first : first + 3] = rotations.skew(centre)
    return W


def _cost(problem: BatchProblem, state: _State, sigmas, weights) -> float:
    e = problem.model.readings_residual(state.unknowns, problem.measured, state.R, state.t)[0] / sigmas
    return float(np.nansum(weights[:, None] * e**2))


def _levenberg_marquardt(problem, state, basis, sigmas, weights, fit_blocks, tolerance_mm) -> tuple[_State, int]:
    """Levenberg–Marquardt with Marquardt's scaling and Nielsen's damping update (Madsen, Nielsen &
    Tingleff 2004, §3.2): the damping follows the gain ratio ρ of the actual to the predicted decrease,
    falling by up to 10× after a good step and doubling its rise after each refused one. A fixed ×10 / ÷10
    cycles between a refused step and a short one where the optimum lies far along a weak direction (an
    instrument metres from the robot: its frame's turn and shift nearly one column; the hobby log with
    {I} 2.7 m away took 331 evaluations, more than :data:`MAX_EVALUATIONS`)."""
    cost = _cost(problem, state, sigmas, weights)
    damping, rise = 1e-3, 2.0
    evaluations = 0
    while evaluations < MAX_EVALUATIONS:
        A, b = _system(problem, state, basis, sigmas, weights, fit_blocks)
        normal = A.T @ A
        gradient = A.T @ b
        diag = np.maximum(np.diag(normal), 1e-12 * np.max(np.diag(normal)))
        while evaluations < MAX_EVALUATIONS:
            evaluations += 1
            step = np.linalg.solve(normal + damping * np.diag(diag), -gradient)
            trial = _apply(problem, state, basis, step, fit_blocks)
            trial_cost = np.inf if trial is None else _cost(problem, trial, sigmas, weights)
            # the decrease of Σ e² the linearised residual promises for this step
            predicted = float(step @ (damping * diag * step - gradient))
            if trial_cost <= cost:
                gain = (cost - trial_cost) / max(predicted, 1e-300)
                damping = max(damping * max(0.1, 1.0 - (2.0 * min(gain, 1.0) - 1.0) ** 3), 1e-12)
                rise = 2.0
                break
            damping *= rise
            rise *= 2.0
            if damping > 1e12:
                return state, evaluations  # no step lowers the cost: at the minimum to round-off
        else:
            break
        decrease = cost - trial_cost
        state, cost = trial, trial_cost
        moved_mm = max(
            np.max(np.abs(basis @ step[: basis.shape[1]])), np.max(np.abs(step)) if trial is not None else 0.0
        )
        if moved_mm < tolerance_mm or decrease <= 1e-14 * max(cost, 1.0):
            return _polished(problem, state, basis, sigmas, weights, fit_blocks, cost, evaluations)
    raise CalibError(_not_converged(problem, state, basis, sigmas, weights, fit_blocks))


def _polished(problem, state: _State, basis, sigmas, weights, fit_blocks, cost: float, evaluations: int):
    """``(state, evaluations)`` after Gauss–Newton steps from where Levenberg–Marquardt stopped, while
    each is shorter than the one before and than the poses' own precision (FK's tolerance), and the
    cost does not rise past round-off.

    LM stops on a step below ``tolerance_mm`` (or a decrease below 1e-14 of the cost); along the
    weakest directions (condition ~1e7) the iterate is then a few 1e-9 mm from the minimum, where
    the path left it: the hobby round trip's two logs, equal to 4e-14°, stop 5.3e-9 mm apart in
    δM. The undamped steps contract ~30× each (hobby: 5e-7, 2e-8, 5e-10 mm), so one or
    two of them put the result at the minimum itself: the same two logs then agree to 3e-12 mm.
    """
    last = math.inf
    for _ in range(MAX_POLISH_STEPS):
        A, b = _system(problem, state, basis, sigmas, weights, fit_blocks)
        q, r = np.linalg.qr(A)
        try:
            step = np.linalg.solve(r, -(q.T @ b))
        except np.linalg.LinAlgError:  # singular: the fit's covariance says so; LM's stop stands
            break
        size = float(np.max(np.abs(step)))
        if not size < last or size < kin.FK_TOLERANCE_MM:
            break
        trial = _apply(problem, state, basis, step, fit_blocks)
        evaluations += 1
        if trial is None:
            break
        trial_cost = _cost(problem, trial, sigmas, weights)
        if trial_cost > cost + 1e-8 * max(cost, 1.0):  # a rise, not the poses' round-off
            break
        state, cost, last = trial, trial_cost, size
    return state, evaluations


#: a whitened RMS residual beyond this many σ at the last iterate: the model cannot explain the readings
UNEXPLAINED_SIGMAS = 30.0
#: a stroke scale beyond this is no encoder's error (a few per cent) but the fit bending to a unit mistake
IMPLAUSIBLE_SCALE = 0.3
#: a condition number beyond this: the poses leave some direction of the fit nearly free
WEAK_CONDITION = 1e8


def _not_converged(problem: BatchProblem, state: _State, basis, sigmas, weights, fit_blocks: np.ndarray) -> str:
    """What a non-converging fit was fitting and its most likely cause, from its last iterate:
    residuals far beyond the noise (the model cannot explain the readings) or a nearly singular
    system (the poses leave directions free)."""
    mask = iter(
        np.split(fit_blocks, np.cumsum([b.size for b in problem.drive.blocks])[:-1]) if problem.drive.blocks else ()
    )
    blocks = "".join(f"{b.size} {b.key.replace('_', ' ')}s, " for b in problem.drive.blocks if np.all(next(mask)))
    fitted = (
        f"{basis.shape[1]} drive directions (the {problem.drive.n_params} parameters less the gauge), "
        f"{blocks}the {state.unknowns.size} instrument unknowns"
    )
    head = (
        f"ls: Levenberg–Marquardt did not converge in {MAX_EVALUATIONS} evaluations fitting {fitted} to "
        f"{len(problem.inputs)} samples"
    )
    # against the platform file's σ: the re-estimated ones grow with whatever the model cannot explain
    e = (
        problem.model.readings_residual(state.unknowns, problem.measured, state.R, state.t)[0]
        / problem.model.channel_sigma
    )
    whitened = float(np.sqrt(np.nanmean(e**2)))
    if whitened > UNEXPLAINED_SIGMAS:
        return (
            f"{head}; most likely the readings do not belong to this model: they stay {whitened:.3g} σ (RMS) from it "
            "(readings in another unit or frame convention, columns mixed up, or a log of another platform)"
        )
    scale = problem.drive.extension_per_stroke(state.x_drive) - 1.0  # the stroke scale k of each leg
    if np.any(fit_blocks) and np.max(np.abs(scale)) > IMPLAUSIBLE_SCALE:
        leg = int(np.argmax(np.abs(scale)))
        return (
            f"{head}; most likely the readings move the platform by another amount than the strokes say: the "
            f"fit took the stroke scale k{leg + 1} to {scale[leg]:+.3g} (a leg moving {1 + scale[leg]:.3g} mm per "
            "logged mm; readings or strokes in another unit?)"
        )
    A, _ = _system(problem, state, basis, sigmas, weights, fit_blocks)
    s = np.linalg.svd(A, compute_uv=False)
    condition = s[0] / s[-1] if s[-1] > 0 else math.inf
    if condition > WEAK_CONDITION:
        return (
            f"{head}; most likely the poses leave some directions nearly free (condition number {condition:.3g}): "
            f"expected poses that vary all six pose coordinates over the workspace, or --set "
            f"ls.{LSConfig.DRIVE_BLOCKS_KEY}=off"
        )
    return (
        f"{head}; the residuals ({whitened:.3g} σ RMS) and the conditioning ({condition:.3g}) look sound: "
        "most likely a few gross outliers pull it; try --set ls.robust_k=1.5"
    )


def _blocks_identifiable(problem: BatchProblem, state: _State, basis, sigmas) -> dict[str, bool]:
    """For each of the drive's blocks: whether adding its columns to δM's and the instrument's keeps
    the whitened Jacobian at ``state`` of full rank (true/false, by the block's key)."""
    A, _ = _system(problem, state, basis, sigmas, np.ones(len(problem.inputs)), True)
    n_free, out = basis.shape[1], {}
    start = n_free
    for block in problem.drive.blocks:
        others = np.r_[np.arange(n_free), np.arange(n_free + problem.drive.size - problem.drive.n_params, A.shape[1])]
        columns = np.sort(np.r_[others, np.arange(start, start + block.size)])
        s = np.linalg.svd(A[:, columns], compute_uv=False)
        out[block.key] = bool(s[-1] > 1e-8 * s[0])
        start += block.size
    return out


#: a reading whose RMS whitened residual exceeds this many times the Huber threshold is a gross
#: error (a swapped marker, a reflector seen twice) and gets no weight: Huber's bounded pull still
#: moves a fit of few readings by several of its σ, a gross error should move it by none
GROSS_ERROR_FACTOR = 4.0


def _robust_weights(whitened: np.ndarray, k: float) -> np.ndarray:
    """Per reading, with ``r`` the RMS of its finite whitened components: 1 up to ``k``, Huber's
    ``k / r`` beyond, 0 beyond ``GROSS_ERROR_FACTOR · k``."""
    if k <= 0:
        return np.ones(len(whitened))
    r = np.sqrt(np.nanmean(whitened**2, axis=1))
    return np.where(r > GROSS_ERROR_FACTOR * k, 0.0, np.where(r > k, k / np.maximum(r, 1e-300), 1.0))


def _absorbed(problem: BatchProblem, state: _State, basis, sigmas, weights, fit_blocks, e: np.ndarray) -> np.ndarray:
    """``(channels,)`` the degrees of freedom the fit takes from each noise channel's residuals: the
    trace over the channel's rows of the hat matrix ``H = A (AᵀA)⁻¹ Aᵀ`` of the whitened, weighted
    system at ``state`` (``e``: its readings residual there, NaN where a target was not seen). For a
    linear fit ``E Σ_c w e² = σ_c² (n_c − tr H_cc)`` (Förstner's variance components), and the
    traces sum to the unknowns. A channel that pins more of them gives up more than its share of
    the residuals: the pose instrument's orientation on the hobby hexapod (0.05° against 0.2 mm)
    takes 32 of 54 unknowns from half the rows, at 0.005° against 1 mm over 20 poses nearly all."""
    A, _ = _system(problem, state, basis, sigmas, weights, fit_blocks)
    channel = np.broadcast_to(problem.model.noise_channels, e.shape)[np.isfinite(e)]
    leverage = np.sum(np.linalg.qr(A)[0] ** 2, axis=1)  # diag H
    return np.bincount(channel, weights=leverage, minlength=len(problem.model.noise_channel_names))


def _channel_sigmas(
    problem: BatchProblem, e: np.ndarray, weights: np.ndarray, sigmas: np.ndarray, absorbed: np.ndarray
) -> np.ndarray:
    """Each channel's σ from its weighted residuals, ``σ_c² = Σ w e² / (n_c − tr H_cc)`` with the
    degrees of freedom the fit takes from the channel (:func:`_absorbed`)."""
    out = sigmas.copy()
    for c in range(len(problem.model.noise_channel_names)):
        cols = problem.model.noise_channels == c
        values = e[:, cols]
        seen = np.isfinite(values)
        dof = seen.sum() - absorbed[c]
        if dof > 0:
            out[cols] = np.sqrt(np.sum(np.where(seen, weights[:, None] * values**2, 0.0)) / dof)
    return out


def _robust_channel_scale(problem: BatchProblem, e: np.ndarray, absorbed: np.ndarray) -> np.ndarray:
    """Each channel's σ from the median absolute residual (1.4826 · MAD of a normal), corrected for
    the share of the channel's residual variance the fit absorbs (``1 − tr H_cc / n_c``,
    :func:`_absorbed`): blind to a few gross errors."""
    out = np.empty(e.shape[1])
    for c in range(len(problem.model.noise_channel_names)):
        cols = problem.model.noise_channels == c
        values = e[:, cols]
        kept = max(1.0 - absorbed[c] / np.isfinite(values).sum(), 1e-3)
        out[cols] = 1.4826 * np.nanmedian(np.abs(values)) / np.sqrt(kept)
    return out


def _channel_rms(problem: BatchProblem, e: np.ndarray) -> dict:
    """``{channel: RMS}`` of a residual, in file units (degrees for rotation channels)."""
    out = {}
    for c, name in enumerate(problem.model.noise_channel_names):
        values = e[:, problem.model.noise_channels == c]
        rms = float(np.sqrt(np.nanmean(values**2)))
        out[name.replace("_rad", "_deg")] = float(np.degrees(rms)) if name.endswith("_rad") else rms
    return out
