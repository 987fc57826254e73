"""Least change of a regression that puts a matrix's eigenvalues in a disc (sequential QP).

The problem: the closed-loop state matrix ``A(U) = A_0 + E U S`` is affine
in the free rows ``U`` (``E`` places them, ``S`` maps the state onto the
regressors), and the least-squares cost is a quadratic
``(U - U_0) K (U - U_0)^T`` around its unconstrained minimizer ``U_0``.
Minimize that cost subject to ``|lambda_i(A(U)) - c| <= rho`` for every
eigenvalue.

The eigenvalue moduli are smooth where the eigenvalues are simple, with
first-order perturbation theory (left eigenvector ``w``, right ``v``)

    d lambda = w^H E dU S v / (w^H v).

Each step linearizes the moduli of the eigenvalues near or beyond the
boundary and solves the resulting least-distance problem in the metric of
``K`` exactly (Lawson and Hanson, *Solving Least Squares Problems*, 1974,
ch. 23: least distance programming through one NNLS), i.e. a sequential
quadratic programming method on the eigenvalue constraints (the spectral
abscissa/radius optimization literature, e.g. Overton and Womersley's
SQP for eigenvalue optimization). Usually one or two eigenvalues are
active; a step costs an eigendecomposition of ``A`` and an NNLS with one
column per active eigenvalue. Nothing here certifies optimality in
general (the feasible set is not convex); the caller checks the radius of
the result, which is the certificate, and keeps a Lyapunov matrix for it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import linalg, optimize

__all__ = ["DiscProblem", "DiscResult", "least_change_into_disc"]


@dataclass(frozen=True, eq=False)
class DiscProblem:
    """``A(U) = A_0 + E U S`` (``E`` = rows ``rows`` of the identity) and the cost metric ``K``.

    Attributes
    ----------
    A0 : ndarray of shape (n, n)
        The matrix with the free rows zeroed.
    rows : slice
        The free rows of ``A``.
    S : ndarray of shape (k, n)
        ``A[rows] = U @ S``.
    K : ndarray of shape (k, k)
        Symmetric positive semidefinite metric of the cost.
    """

    A0: np.ndarray
    rows: slice
    S: np.ndarray
    K: np.ndarray

    def matrix(self, U: np.ndarray) -> np.ndarray:
        """``A(U)``."""
        A = self.A0.copy()
        A[self.rows] += U @ self.S
        return A

    def cost(self, D: np.ndarray) -> float:
        """``trace(D K D^T)``, the cost increase of the change ``D``."""
        return float(np.sum((D @ self.K) * D))

    def distances(self, U: np.ndarray, center: float) -> np.ndarray:
        """``|lambda_i - center|`` of every eigenvalue of ``A(U)``."""
        return np.abs(np.linalg.eigvals(self.matrix(U)) - center)


@dataclass
class DiscResult:
    """Outcome of :func:`least_change_into_disc`.

    Attributes
    ----------
    U : ndarray
        The free rows found.
    radius : float
        Largest ``|lambda - center|`` of ``A(U)``.
    converged : bool
        Whether ``A(U)`` is in the disc.
    n_iter : int
        Linearizations taken.
    n_active : int
        Constraints active in the last step.
    """

    U: np.ndarray
    radius: float
    converged: bool
    n_iter: int
    n_active: int


def _whitening(K: np.ndarray) -> np.ndarray:
    """``W`` with ``W^T K W = I`` on the range of ``K`` (its null directions cost nothing: unused)."""
    d, Q = linalg.eigh(0.5 * (K + K.T))
    keep = d > 1e-13 * max(float(d[-1]), np.finfo(float).tiny)
    return Q[:, keep] / np.sqrt(d[keep])


def _groups(lam: np.ndarray, pick: np.ndarray, gap: float) -> list[list[int]]:
    """The picked eigenvalues in groups of one real eigenvalue or two (a conjugate pair, or two
    real eigenvalues closer than ``gap``: they may be about to meet and leave the real axis)."""
    groups: list[list[int]] = []
    used: set[int] = set()
    reals = sorted((i for i in pick if lam[i].imag == 0.0), key=lambda i: lam[i].real)
    for a, b in zip(reals, reals[1:]):
        if a not in used and b not in used and lam[b].real - lam[a].real < gap:
            groups.append([a, b])
            used.update((a, b))
    groups += [[i] for i in reals if i not in used]
    for i in pick:
        if lam[i].imag > 0.0:
            partner = int(np.argmin(np.abs(lam - np.conj(lam[i]))))
            groups.append([i, partner])
    return groups


def _group_constraints(problem: DiscProblem, A: np.ndarray, lam: np.ndarray, group: list[int], rho: float):
    """Linearized "the group's eigenvalues in the disc |z| <= rho": rows (value, gradient in U),
    each meaning ``value + <gradient, dU> <= 0``.

    The group's invariant subspace comes from a reordered real Schur form,
    ``A = Q [[T11, T12], [0, T22]] Q^T``; to first order its block changes by
    ``Y^T dA X`` (``X = Q[:, :k]``, ``Y^T = [I, R] Q^T`` with
    ``T11 R - R T22 = T12``). One real eigenvalue ``t``: ``|t| <= rho``. Two
    (trace ``s``, determinant ``p`` of ``T11``, smooth even where the two
    meet): the Schur-Cohn (Jury) conditions ``|p| <= rho^2`` and
    ``|s| <= rho + p / rho``, linear in ``(s, p)``.
    """
    chosen = lam[group]

    def select(re, im):
        return bool(
            np.argmin(np.abs(lam - complex(re, im))) in group
            or np.min(np.abs(chosen - complex(re, im))) < 1e-9 * (1.0 + abs(complex(re, im)))
        )

    T, Q, sdim = linalg.schur(A, output="real", sort=select)
    k = len(group)
    if sdim != k:
        return []
    R = linalg.solve_sylvester(T[:k, :k], -T[k:, k:], T[:k, k:]) if k < len(A) else np.zeros((k, 0))
    Yt = np.hstack([np.eye(k), R]) @ Q.T
    left, right = Yt[:, problem.rows].T, (problem.S @ Q[:, :k]).T

    def grad(C):  # gradient of trace(C^T T11) in U
        return left @ C @ right

    B = T[:k, :k]
    if k == 1:
        t = B[0, 0]
        return [(t - rho, grad(np.ones((1, 1)))), (-t - rho, -grad(np.ones((1, 1))))]
    s, p = np.trace(B), np.linalg.det(B)
    gs = grad(np.eye(2))
    gp = grad(np.array([[B[1, 1], -B[1, 0]], [-B[0, 1], B[0, 0]]]))  # adj(B)^T
    return [
        (p - rho**2, gp),
        (-p - rho**2, -gp),
        (s - rho - p / rho, gs - gp / rho),
        (-s - rho - p / rho, -gs - gp / rho),
    ]


def _constraints(problem: DiscProblem, U: np.ndarray, center: float, rho: float, floor: float):
    """Linearized disc constraints of every eigenvalue group above ``floor`` (the outermost at least)."""
    A = problem.matrix(U) - center * np.eye(problem.A0.shape[0])
    lam = np.linalg.eigvals(A)
    lam = np.where(np.abs(lam.imag) <= 1e-13 * (1.0 + np.abs(lam)), lam.real + 0j, lam)
    dist = np.abs(lam)
    floor = min(floor, dist.max() * (1.0 - 1e-12))
    pick = np.flatnonzero((dist > floor) & (lam.imag >= 0.0))
    rows = []
    for group in _groups(lam, pick, gap=0.1 * rho):
        rows += _group_constraints(problem, A, lam, group, rho)
    return np.array([r[0] for r in rows]), [r[1] for r in rows]


def _least_distance(G: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, float]:
    """``argmin ||z||`` subject to ``G z <= h`` (Lawson-Hanson LDP through NNLS), and the largest multiplier."""
    E = np.vstack([-G.T, -h[None, :]])
    f = np.zeros(E.shape[0])
    f[-1] = 1.0
    u, _ = optimize.nnls(E, f, maxiter=50 * E.shape[1] + 100)
    r = E @ u - f
    if abs(r[-1]) < 1e-14:
        raise ValueError("the linearized eigenvalue constraints are inconsistent")
    # z = -G^T nu with nu = u / |r_n|: the multipliers of 1/2 ||z||^2, doubled for ||z||^2.
    return -r[:-1] / r[-1], 2.0 * float(u.max(initial=0.0)) / abs(r[-1])


def least_change_into_disc(
    problem: DiscProblem,
    U0: np.ndarray,
    radius: float,
    center: float = 0.0,
    margin: float = 1e-9,
    band: float = 1e-2,
    max_iter: int = 100,
    rtol: float = 1e-4,
) -> DiscResult:
    """Smallest ``trace((U - U0) K (U - U0)^T)`` with every eigenvalue of ``A(U)`` in the disc.

    Parameters
    ----------
    problem : DiscProblem
        The affine matrix and the cost metric.
    U0 : ndarray
        The unconstrained minimizer (returned unchanged when it is feasible).
    radius, center : float
        The disc ``|lambda - center| <= radius``.
    margin : float
        Eigenvalues are steered to ``radius * (1 - margin)``, strictly inside.
    band : float
        Eigenvalues within ``band * radius`` of the boundary are constrained
        in each step (so that none crosses it unnoticed).
    max_iter : int
        Most linearizations.
    rtol : float
        Stop at a feasible point once a step changes ``U - U0`` by less
        than this fraction (the SQP converges linearly: it ignores the
        constraints' curvature).

    Returns
    -------
    DiscResult
        The cheapest iterate in the disc, or the last one if none is, the
        largest ``|lambda - center|`` of it, and whether it is in the disc.
    """
    W = _whitening(problem.K)
    target = radius * (1.0 - margin)

    def violation(U):
        return float(np.sum(np.maximum(problem.distances(U, center) - target, 0.0)))

    U, viol, mu = U0, violation(U0), 0.0
    if viol == 0.0:
        return DiscResult(U0, float(problem.distances(U0, center).max()), True, 0, 0)
    best, n_active = None, 0
    for it in range(1, max_iter + 1):  # noqa: B007 - read after the loop: the iterations taken
        values, grads = _constraints(problem, U, center, target, target - band * radius)
        if not grads:
            break
        step, nu_max, n_active = _sqp_step(W, U, U0, values, grads)
        # Backtracking on the exact-penalty merit cost + mu * violation (Han's SQP globalization).
        mu = max(mu, 2.0 * nu_max)
        merit = problem.cost(U - U0) + mu * viol
        t = 1.0
        while True:
            U_try = U + t * step
            viol_try = violation(U_try)
            if problem.cost(U_try - U0) + mu * viol_try < merit or t < 1e-3:
                break
            t *= 0.5
        U, viol = U_try, viol_try
        if viol == 0.0:
            if best is None or problem.cost(U - U0) < problem.cost(best - U0):
                best = U
            if t * np.linalg.norm(step) <= rtol * np.linalg.norm(U - U0) + 1e-14 * np.linalg.norm(U0):
                break
    found = U if best is None else best
    return DiscResult(found, float(problem.distances(found, center).max()), best is not None, it, n_active)


def _sqp_step(W: np.ndarray, U: np.ndarray, U0: np.ndarray, values: np.ndarray, grads: list):
    """The step to the least change obeying the linearized constraints, the largest multiplier,
    and the number of active constraints."""
    Gw = np.stack([(g @ W).ravel() for g in grads])
    # Constraint value_i + <g_i, U_new - U> <= 0, in the whitened change Z (U_new = U0 + Z W^T).
    h = -values + np.array([np.sum(g * (U - U0)) for g in grads])
    z, nu_max = _least_distance(Gw, h)
    n_active = int(np.sum(Gw @ z > h - 1e-9 * np.abs(h).max()))
    return U0 + z.reshape(U0.shape[0], W.shape[1]) @ W.T - U, nu_max, n_active
