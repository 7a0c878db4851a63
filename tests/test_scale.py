"""Scale properties asserted without a clock: the identifiability report from the accumulated
42 × 42 information equals the SVD of the stacked N-sized Jacobian (to a bound derived from
the round-off of both), whatever the blocking."""

from __future__ import annotations

import numpy as np
import pytest

from stewart_calib import identifiability as ident
from stewart_calib.estimators.config import NoiseConfig
from tests.synthetic import nim_stewart, random_poses

NOISE = NoiseConfig()
UNIT_ROUNDOFF = np.finfo(float).eps / 2


@pytest.fixture(scope="module")
def platform():
    return nim_stewart()


def svd_of_stacked_rows(platform, poses):
    """What the report was computed from before: the full SVD of the (6N × 42) whitened rows."""
    A = ident.whitened_leg_jacobian(platform, poses, NOISE).reshape(-1, 42)
    _, s, Vt = np.linalg.svd(A, full_matrices=True)
    return A, np.r_[s, np.zeros(42 - len(s))], Vt


def roundoff_bound(A: np.ndarray, n_blocks: int) -> float:
    """|σ_i(computed) − σ_i(A)| for either path, by Weyl's theorem: Householder QR and the SVD are
    backward stable, ‖ΔA‖ ≤ m·n·u·‖A‖_F (Higham, Thm 19.4, c = 1), with m the rows factored —
    the N-sized stack, or all blocks plus the 42-row factor carried into each."""
    rows = A.shape[0] + 42 * n_blocks
    return rows * 42 * UNIT_ROUNDOFF * np.linalg.norm(A)


@pytest.mark.parametrize("block_poses", [7, 2048])
def test_accumulated_information_gives_the_stacked_svd(platform, monkeypatch, block_poses):
    monkeypatch.setattr(ident, "BLOCK_POSES", block_poses)
    poses = random_poses(platform, 40, np.random.default_rng(11))
    A, s, _ = svd_of_stacked_rows(platform, poses)
    report = ident.identifiability_report(platform, poses, NOISE)
    tol = 2 * roundoff_bound(A, n_blocks=-(-40 // block_poses))  # both paths' errors
    np.testing.assert_allclose(report.singular_values, s, rtol=0, atol=tol)
    # (AᵀA)⁻¹ moves by at most 2‖ΔA‖/σmin relative (first order); its square root by half that.
    np.testing.assert_allclose(report.predicted_stddev_mm, np.sqrt(np.diag(np.linalg.inv(A.T @ A))), rtol=2 * tol / s[-1])
    assert report.observability == ident.observability_indices(report.singular_values, A.shape[0])


def test_a_rank_deficient_stream_keeps_rank_and_null_space(platform, monkeypatch):
    # Translations only: the 18 directions d_i − j_i are unseen (tests/test_identifiability.py);
    # blocks of 4 poses hold fewer rows (24) than parameters, so the factor starts short.
    monkeypatch.setattr(ident, "BLOCK_POSES", 4)
    rng = np.random.default_rng(12)
    poses = platform.workspace.home + np.c_[rng.uniform(-200, 200, (30, 3)), np.zeros((30, 3))]
    A, s, Vt = svd_of_stacked_rows(platform, poses)
    report = ident.identifiability_report(platform, poses, NOISE)
    assert report.rank == int(np.sum(s > ident.RANK_RTOL * s[0])) == 24
    projector = Vt[24:].T @ Vt[24:]
    np.testing.assert_allclose(projector @ report.null_space, report.null_space, atol=1e-9)


def test_fewer_poses_than_parameters(platform):
    poses = random_poses(platform, 3, np.random.default_rng(13))
    A, s, _ = svd_of_stacked_rows(platform, poses)
    report = ident.identifiability_report(platform, poses, NOISE)
    assert report.rank == 18 and report.null_space_dimension == 24
    np.testing.assert_allclose(report.singular_values, s, rtol=0, atol=2 * roundoff_bound(A, 1))


def test_information_streams_in_pieces(platform):
    poses = random_poses(platform, 25, np.random.default_rng(14))
    whole = ident.identifiability_report(platform, poses, NOISE)
    information = ident.InformationAccumulator(platform, NOISE)
    for piece in np.array_split(poses, 6):
        information.add(piece)
    pieces = information.report()
    A, _, _ = svd_of_stacked_rows(platform, poses)
    assert pieces.n_poses == 25
    np.testing.assert_allclose(pieces.singular_values, whole.singular_values, rtol=0, atol=2 * roundoff_bound(A, 6))
    P = ident.scaled_paper_jacobian(platform, poses).reshape(-1, 42)
    np.testing.assert_allclose(pieces.paper_singular_values, whole.paper_singular_values, rtol=0, atol=2 * roundoff_bound(P, 6))
