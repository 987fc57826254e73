"""The ridge solves equal LAPACK's least squares on the stacked problem: from one SVD per factor (a sweep's
statistics, solved for many alphas) and by a QR of the regularized problem (statistics solved for one)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import linalg

from qube_koopman.identify.estimators.regression import (
    Snapshots,
    constrained_plant_solve,
    ridge_solve,
    solved_for_many_alphas,
)

PATHS = ["one-alpha", "many-alphas"]


def _statistics(theta, psi, path):
    snaps = Snapshots.from_snapshots(theta, psi)
    if path == "many-alphas":
        solved_for_many_alphas(snaps)
    return snaps


def _stacked(M, Y, alpha, penalty):
    """The reference: gelsd on [M; sqrt(alpha) P] against [Y; 0], built from the raw snapshots."""
    A = np.vstack([M, np.sqrt(alpha) * penalty])
    return linalg.lstsq(A, np.vstack([Y, np.zeros((penalty.shape[0], Y.shape[1]))]), lapack_driver="gelsd")[0].T


def _data(q, p, t, collinear, seed=0):
    rng = np.random.default_rng(seed)
    psi = rng.standard_normal((q, p)) * np.logspace(0, -3, p)
    if collinear:
        psi[:, -1] = psi[:, 0] - 2 * psi[:, 1]  # exactly dependent: the minimum-norm solution
    theta = psi @ rng.standard_normal((p, t)) + 0.01 * rng.standard_normal((q, t))
    return psi, theta


def _objective(U, psi, theta, alpha):
    return np.sum((theta - psi @ U.T) ** 2) + alpha * np.sum(U**2)


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("q, collinear", [(400, False), (400, True), (12, False)])  # tall, rank deficient, wide
@pytest.mark.parametrize("alpha", [0.0, 1e-9, 1e-3, 10.0])
def test_ridge_equals_least_squares_on_the_stacked_problem(q, collinear, alpha, path):
    psi, theta = _data(q, 20, 5, collinear)
    snaps = _statistics(theta, psi, path)
    expected = _stacked(psi, theta, alpha, np.eye(20))
    got = ridge_solve(snaps, alpha)
    assert _objective(got, psi, theta, alpha) == pytest.approx(_objective(expected, psi, theta, alpha), rel=1e-10)
    # A direction that is singular but for a 1e-9 ridge amplifies rounding (to ~1e-7 here) in both.
    rtol = 1e-5 if collinear and 0 < alpha < 1e-6 else 1e-8
    np.testing.assert_allclose(got, expected, rtol=rtol, atol=rtol * np.abs(expected).max())
    rows = slice(1, 3)
    np.testing.assert_allclose(ridge_solve(snaps, alpha, rows), got[rows], rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("regularize", ["closed_loop", "plant"])
@pytest.mark.parametrize("alpha", [0.0, 1e-6, 1e-1])
def test_constrained_solve_equals_least_squares_on_the_stacked_problem(regularize, alpha, path):
    psi, theta = _data(300, 12, 6, False, seed=1)
    S = np.random.default_rng(2).standard_normal((9, 12))  # full row rank
    snaps = _statistics(theta, psi, path)
    penalty = S.T if regularize == "closed_loop" else np.eye(9)
    expected = _stacked(psi @ S.T, theta[:, 2:], alpha, penalty)
    got = constrained_plant_solve(snaps, S, alpha, slice(2, None), regularize)
    np.testing.assert_allclose(got, expected, rtol=1e-7, atol=1e-10 * np.abs(expected).max())


def test_statistics_solved_for_one_alpha_take_the_qr_and_a_second_alpha_the_svd():
    """The first alpha is solved without the SVD (none is made); a second builds it, and both paths give the
    stacked least squares; a sweep's statistics build it at once."""
    psi, theta = _data(400, 20, 5, False, seed=5)
    snaps = Snapshots.from_snapshots(theta, psi)
    for alpha, without_svd in ((1e-3, True), (1e-3, True), (10.0, False), (1e-3, False)):
        np.testing.assert_allclose(ridge_solve(snaps, alpha), _stacked(psi, theta, alpha, np.eye(20)), rtol=1e-8)
        assert (snaps._paths[("ridge",)]._svd is None) == without_svd
    swept = _statistics(theta, psi, "many-alphas")
    ridge_solve(swept, 1e-3)
    assert swept._paths[("ridge",)]._svd is not None


def test_one_decomposition_serves_every_alpha_and_a_rank_deficient_map_still_solves():
    psi, theta = _data(300, 12, 6, False, seed=3)
    snaps = Snapshots.from_snapshots(theta, psi)
    S = np.random.default_rng(4).standard_normal((9, 12))
    for alpha in np.logspace(-6, 2, 9):
        constrained_plant_solve(snaps, S, alpha, slice(0, None))
        ridge_solve(snaps, alpha)
    assert len(snaps._paths) == 2
    S[-1] = S[0]  # a repeated row: no triangular change of variables, the stacked problem instead
    expected = _stacked(psi @ S.T, theta, 1e-2, S.T)
    np.testing.assert_allclose(
        constrained_plant_solve(snaps, S, 1e-2, slice(0, None)),
        expected,
        rtol=1e-7,
        atol=1e-10 * np.abs(expected).max(),
    )


def test_an_episodes_statistics_hold_only_their_small_factor():
    # The factor is copied out of the QR's full-height R: a view would keep every episode's
    # (snapshots x columns) array alive, and memory would grow with the data (issue 29).
    rng = np.random.default_rng(0)
    psi = rng.normal(size=(2000, 12))
    stats = Snapshots.from_snapshots(rng.normal(size=(2000, 3)), psi)
    assert stats.R.shape == (15, 15) and stats.R.base is None


@pytest.mark.parametrize("q", [400, 12])  # more snapshots than columns (square factors), and fewer
def test_folded_factors_give_the_stacked_snapshots_gram_matrix(q):
    # Square factors are merged two triangles at a time (LAPACK tpqrt); a short episode's factor has
    # fewer rows and takes the stacked QR. Either way R^T R is that of all the snapshots stacked.
    rng = np.random.default_rng(3)
    parts = [(rng.standard_normal((n, 2)), rng.standard_normal((n, 20))) for n in (q, 300, 250, 500, 350, 320)]
    total = Snapshots.total(Snapshots.from_snapshots(y, x) for y, x in parts)
    M = np.vstack([np.hstack([x, y]) for y, x in parts])
    np.testing.assert_allclose(total.R.T @ total.R, M.T @ M, rtol=1e-11, atol=1e-9)
    assert np.allclose(total.R, np.triu(total.R)) and total.q == sum(len(y) for y, _ in parts)


@pytest.mark.parametrize("q", [400, 20])  # square factors, and fewer snapshots than columns (factored whole)
def test_targets_that_copy_regressors_take_their_factor_columns(q):
    # With delays most of the next lifted state is the current one's slots moved along: those target
    # columns equal regressor columns and are not factored again. The factor still gives the stacked
    # snapshots' Gram matrix, its leading blocks too, and the same solves as a factor of everything.
    rng = np.random.default_rng(5)
    psi = rng.standard_normal((q, 30))
    near = psi[:, 7].copy()
    near[q // 2] += 1e-12  # one sample off: not a copy
    theta = np.hstack(
        [rng.standard_normal((q, 2)), psi[:, 3:15], near[:, None], rng.standard_normal((q, 1)), psi[:, :1]]
    )
    snaps = Snapshots.from_snapshots(theta, psi)
    M = np.hstack([psi, theta])
    np.testing.assert_allclose(snaps.R.T @ snaps.R, M.T @ M, rtol=1e-11, atol=1e-9)
    assert np.allclose(snaps.R, np.triu(snaps.R))
    lead = snaps.leading(3)
    np.testing.assert_allclose(lead.R.T @ lead.R, M[:, :33].T @ M[:, :33], rtol=1e-11, atol=1e-9)
    full = Snapshots(linalg.qr(M, mode="economic")[1], 30, q)
    for alpha in (0.0, 1e-3, 1.0):
        np.testing.assert_allclose(ridge_solve(snaps, alpha), ridge_solve(full, alpha), rtol=1e-8, atol=1e-10)
    # The 13 copies' rows of the factor are zero when it is square (factored without them).
    zero_rows = int(np.sum(~snaps.R.any(axis=1)))
    assert zero_rows == (13 if q > 50 else 0)
