"""Stability-constrained CL EDMD: the closed loop's eigenvalues kept in a disc.

The paper's stated future work. With the controller rows of the
closed-loop Koopman matrix fixed to the known controller, its state matrix

    A^f = [[A^c, -B^c C^p], [B^p C^c, A^p - B^p D^c C^p]]

is affine in the plant (A^p, B^p), which stays free: the plant is unstable
and must be allowed to be. Eigenvalues of ``A^f`` in the disc of centre
``c`` and radius ``rho`` is ``M^T P M < rho^2 P`` for some ``P > 0``, with
``M = A^f - c I``: bilinear in (P, A^f). As in the iterative LMI methods for
Koopman approximation (Dahdah and Forbes, "Linear matrix inequality
approaches to Koopman operator approximation", arXiv:2102.03613, 2021), the
problem is solved for the plant with ``P`` fixed, which makes the constraint
the linear matrix inequality

    [[rho^2 P, M^T P], [P M, P]] >= 0

and ``P`` is updated between solves. Here each ``P`` is the solution of a
discrete Lyapunov equation of the current ``M`` (scaled into the disc if it
is outside), so a P-step costs a Lyapunov solve rather than a second SDP.
A ``P`` that certifies the unconstrained fit makes that fit feasible: when
the constraint is inactive the solve returns the closed form.

The least-squares objective is posed on the triangular factor of the
snapshot Gram matrix (size of the lifted state), never on the snapshots.

That fixed-``P`` LMI is kept as ``method="lmi"`` (the cross-check). Its
certificate is conservative: on the paper's QUBE split (10 delays, alpha
1e-3) it took the radius from 1.000016 to 0.9945 and the test R^2 from
0.897 to 0.770 in about 54 s. The default ``method="sqp"`` solves the same
problem, the least increase of the least-squares cost (a quadratic in the
plant rows, metric ``K = S (H + alpha I) S^T``) with every closed-loop
eigenvalue in the disc, directly on the eigenvalues by sequential quadratic
programming (:mod:`identify.estimators._spectral`): on the same data it moves the one
offending eigenvalue to ``rho (1 - 1e-6)`` in two linearizations, well under
a second, and leaves R^2 unchanged to 1e-6. It is a local method; when it
does not reach the disc the fit falls back to the LMI. Either way the result
is checked: its eigenvalues are in the disc and a Lyapunov matrix certifying
it is kept (``lyapunov_matrix_``).
"""

from __future__ import annotations

import warnings
from typing import Sequence

import numpy as np
from scipy import linalg

from qube_koopman.identify.estimators._spectral import DiscProblem, least_change_into_disc
from qube_koopman.identify._checks import check_choice
from qube_koopman.identify.estimators.cl_edmd import ClEdmdKnownRows
from qube_koopman.identify.estimators.regression import Snapshots, constrained_plant_solve
from qube_koopman.core.lti import DiscreteStateSpace, spectral_radius

__all__ = ["ClEdmdStable"]

# The LMI is imposed with this margin (relative to P's scale): solver tolerance, not slack.
_MARGIN = 1e-7
# Eigenvalues outside the disc are moved to this fraction of the radius to seed P: close to
# 1, so the certificate fits a matrix close to the fit (0.995 moved a unit eigenvalue so far
# that the paper data's R^2 fell from 0.66 to 0.34 at 5 delays; 0.9999 kept it).
_SEED_FRACTION = 0.9999
# The SQP steers eigenvalues to this fraction below the radius (eigenvalue rounding stays inside).
_SQP_MARGIN = 1e-6
METHODS = ("sqp", "lmi")


class ClEdmdStable(ClEdmdKnownRows):
    """CL EDMD with the closed loop's eigenvalues in a disc (SQP on the eigenvalues, or an LMI).

    Parameters
    ----------
    controller : DiscreteStateSpace
        The known controller.
    lifting : Lifting or sequence of LiftingFunction, optional
        Lifting of the plant states.
    alpha : float
        Tikhonov coefficient on ``||U^f||_F^2`` (closed-loop regularization).
    measured : sequence of int, optional
        Indices of the plant states fed back; all by default.
    max_radius : float
        Radius ``rho`` of the disc (the spectral radius bound when
        ``center`` is 0).
    center : float
        Centre ``c`` of the disc on the real axis (a pole-region constraint).
    n_iter : int
        ``method="lmi"``: Lyapunov-matrix updates after the first solve (each one more SDP).
    solver : str
        ``method="lmi"``: a cvxpy solver for semidefinite cones.
    method : {"sqp", "lmi"}
        ``"sqp"`` (default): least cost increase by sequential QP on the
        eigenvalues, falling back to the LMI if it does not reach the disc.
        ``"lmi"``: the fixed-Lyapunov-matrix LMI solved with cvxpy.

    Attributes
    ----------
    koopman_matrix_, plant_koopman_matrix_, closed_loop_model_, plant_model_
        As for :class:`~identify.ClEdmd`.
    unconstrained_radius_ : float
        ``max |lambda - c|`` of the closed form's closed loop.
    solver_status_ : str
        ``"optimal"`` when the SQP reached the disc, else the SDP solver's status.
    method_ : str
        The method that produced the result (``"lmi"`` after a fallback).
    n_sqp_iter_ : int
        Linearizations the SQP took (0 when the constraint is inactive).
    objective_ : float
        Regularized least-squares cost of the result (divided by the snapshot count).
    lyapunov_matrix_ : ndarray or None
        ``P > 0`` with ``M^T P M - rho^2 P = -I`` (``M = A^f - c I``), a
        certificate of the disc checked positive definite; None where it is
        numerically out of reach (see :func:`_certificate`). The SQP's result
        is accepted on its eigenvalues: ``max |lambda - c| <= rho``.
    """

    _mixed_controllers = False  # its cost and metric are written for one controller's statistics

    def __init__(
        self,
        controller: DiscreteStateSpace,
        lifting=None,
        alpha: float = 0.0,
        measured: Sequence[int] | None = None,
        max_radius: float = 1.0,
        center: float = 0.0,
        n_iter: int = 2,
        solver: str = "CLARABEL",
        method: str = "sqp",
    ) -> None:
        super().__init__(controller, lifting, alpha, measured)
        self.max_radius = max_radius
        self.center = center
        self.n_iter = n_iter
        self.solver = solver
        self.method = method

    def relift_rows(self, setup) -> None:
        # The disc constrains the eigenvalues of the whole closed loop: no row can be left out of the fit.
        return None

    def _closed_loop_state(self, U_p: np.ndarray, S: np.ndarray) -> np.ndarray:
        n_theta = self.controller.n_states + U_p.shape[0]
        return np.vstack([self._known_controller_rows()[:, :n_theta], (U_p @ S)[:, :n_theta]])

    def _solve(self, snapshots: Snapshots, S: np.ndarray, alpha: float):
        if not (np.isfinite(self.max_radius) and self.max_radius > 0 and np.isfinite(self.center)):
            raise ValueError(
                f"the disc needs a positive radius and a finite centre, got {self.max_radius!r}, {self.center!r}"
            )
        method = check_choice(self.method, "method", METHODS)
        n_c = self.controller.n_states
        U0 = constrained_plant_solve(snapshots, S, alpha, slice(n_c, None), "closed_loop")
        shift = self.center * np.eye(n_c + U0.shape[0])
        M0 = self._closed_loop_state(U0, S) - shift
        self.unconstrained_radius_ = spectral_radius(M0)
        self.n_sqp_iter_ = 0
        U_p, seed = self._solve_sqp(snapshots, S, alpha, U0) if method == "sqp" else (None, U0)
        if U_p is None:  # the LMI asked for, or the SQP did not reach the disc: seed P from its last step
            U_p = self._solve_lmi(snapshots, S, alpha, self._closed_loop_state(seed, S) - shift, shift)
            self.method_ = "lmi"
        else:
            self.method_, self.solver_status_ = "sqp", "optimal"
            self.objective_ = _plant_cost(snapshots, S, alpha, U_p, n_c)
        self.lyapunov_matrix_ = _certificate(self._closed_loop_state(U_p, S) - shift, self.max_radius)
        return np.vstack([self._known_controller_rows(), U_p @ S]), U_p

    def _solve_sqp(self, snapshots: Snapshots, S: np.ndarray, alpha: float, U0: np.ndarray):
        """The plant rows by :func:`least_change_into_disc` (None if it did not reach the disc), and its last
        iterate."""
        n_c = self.controller.n_states
        n_theta = n_c + U0.shape[0]
        # The cost is (||R_psi S^T U^T - Y||^2 + alpha ||U S||^2) / q: metric K = F^T F / q.
        F = np.vstack([snapshots.R[:, : snapshots.n_regressors] @ S.T, np.sqrt(alpha) * S.T])
        A0 = np.vstack([self._known_controller_rows()[:, :n_theta], np.zeros((U0.shape[0], n_theta))])
        problem = DiscProblem(
            A0 - self.center * np.eye(n_theta), slice(n_c, None), S[:, :n_theta], F.T @ F / snapshots.q
        )
        result = least_change_into_disc(problem, U0, self.max_radius, 0.0, margin=_SQP_MARGIN)
        self.n_sqp_iter_ = result.n_iter
        return (result.U if result.converged and result.radius <= self.max_radius else None), result.U

    def _solve_lmi(self, snapshots: Snapshots, S: np.ndarray, alpha: float, M: np.ndarray, shift):
        """The plant rows by the fixed-``P`` LMI, ``P`` seeded from ``M`` and updated ``n_iter`` times."""
        best, best_cost = None, np.inf
        for _ in range(int(self.n_iter) + 1):
            P = _lyapunov_certificate(M, self.max_radius)
            U_p, cost = self._solve_fixed_p(snapshots, S, alpha, P, shift)
            if cost < best_cost:
                best, best_cost = U_p, cost
            M = self._closed_loop_state(U_p, S) - shift
        self.objective_ = best_cost
        return best

    def _solve_fixed_p(self, snapshots: Snapshots, S: np.ndarray, alpha: float, P: np.ndarray, shift):
        import cvxpy as cp

        n_c = self.controller.n_states
        R_psi = snapshots.R[:, : snapshots.n_regressors]
        Y = snapshots.R[:, snapshots.n_regressors + n_c :]  # plant rows of the targets
        n_pl, n_s = Y.shape[1], S.shape[0]
        U_p = cp.Variable((n_pl, n_s))
        rows = U_p @ S
        residual = R_psi @ rows.T - Y
        # Scaled by the snapshot count like the paper's SDP: same minimizer, better conditioning.
        q = snapshots.q
        cost = (cp.sum_squares(residual) + alpha * cp.sum_squares(rows)) / q
        n_theta = n_c + n_pl
        ctrl_rows = self._known_controller_rows()[:, :n_theta]
        # P M = P M_c + (P E) U_p S_theta, with E placing the plant rows. Written with
        # W = (P E) U_p as a variable of its own, every entry of the LMI depends on one row of
        # W (sparse); P times the variable directly would make each entry depend on all of
        # U_p, and the solver's matrices dense (minutes instead of seconds at QUBE size).
        M_c = np.vstack([ctrl_rows, np.zeros((n_pl, n_theta))]) - shift
        PE = P[:, n_c:]
        W = cp.Variable((n_theta, n_s))
        PM = P @ M_c + W @ S[:, :n_theta]
        rho2 = self.max_radius**2
        lmi = cp.bmat([[rho2 * P, PM.T], [PM, P]])
        constraints = [W == PE @ U_p, 0.5 * (lmi + lmi.T) >> _MARGIN * np.eye(2 * n_theta)]
        problem = cp.Problem(cp.Minimize(cost), constraints)
        try:
            problem.solve(solver=str(self.solver).upper())
        except cp.error.SolverError as exc:
            raise ValueError(f"SDP solver {self.solver} failed: {exc}") from exc
        self.solver_status_ = problem.status
        if U_p.value is None or problem.status not in ("optimal", "optimal_inaccurate"):
            raise ValueError(f"SDP solver {self.solver} ended with status {problem.status!r}")
        return np.asarray(U_p.value), float(problem.value)


def _lyapunov_certificate(M: np.ndarray, radius: float) -> np.ndarray:
    """``P > 0`` with ``M'^T P M' < radius^2 P`` for ``M'`` = ``M`` with its eigenvalues moved into the disc.

    Only the eigenvalues at or beyond the radius are moved (radially, to just
    inside it); the rest of the spectrum and the eigenvectors are kept, so the
    certificate fits a matrix as close to ``M`` as possible and the
    constrained solve moves the fit no further than it must.
    """
    lam, V = np.linalg.eig(M)
    outside = np.abs(lam) >= _SEED_FRACTION * radius
    if np.any(outside):
        lam = np.where(outside, _SEED_FRACTION * radius * lam / np.maximum(np.abs(lam), 1e-300), lam)
        moved = np.real(V @ np.diag(lam) @ np.linalg.inv(V))
        # A defective or badly conditioned eigenbasis: scale the whole matrix instead.
        if not spectral_radius(moved) < radius:
            moved = M * (_SEED_FRACTION * radius / spectral_radius(M))
        M = moved
    a = M / radius
    # a^T P a - P + I = 0  <=>  (a^T) P (a^T)^T - P + I = 0: scipy's form with a^T.
    P = linalg.solve_discrete_lyapunov(a.T, np.eye(M.shape[0]))
    P = 0.5 * (P + P.T)
    return P / np.linalg.norm(P, 2)


def _plant_cost(snapshots: Snapshots, S: np.ndarray, alpha: float, U_p: np.ndarray, n_c: int) -> float:
    """``(||Theta_2 - U^p S Psi||^2 + alpha ||U^p S||^2) / q`` from the triangular factor."""
    rows = U_p @ S
    residual = snapshots.R[:, : snapshots.n_regressors] @ rows.T - snapshots.R[:, snapshots.n_regressors + n_c :]
    return float((np.sum(residual**2) + alpha * np.sum(rows**2)) / snapshots.q)


def _certificate(M: np.ndarray, radius: float) -> np.ndarray | None:
    """``P > 0`` with ``M^T P M - radius^2 P = -I``, or None where it is not numerically available.

    For ``max |lambda(M)| < radius`` the solution is positive definite, and a
    positive definite solution proves it (discrete Lyapunov theorem). It is
    returned only if it is positive definite and solves the equation to 1e-8
    relative. None: the LMI's result sits on the disc to solver tolerance, or
    a multiple eigenvalue sits just inside it (where a minimal change tends to
    put them), which makes ``P`` too ill-conditioned to compute; the
    eigenvalue check of the result stands alone then.
    """
    a = M / radius
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", linalg.LinAlgWarning)
        P = linalg.solve_discrete_lyapunov(a.T, np.eye(M.shape[0]) / radius**2)
    P = 0.5 * (P + P.T)
    if not np.all(np.isfinite(P)):
        return None
    residual = np.linalg.norm(M.T @ P @ M - radius**2 * P + np.eye(M.shape[0]))
    if residual > 1e-8 * radius**2 * np.linalg.norm(P) or np.linalg.eigvalsh(P)[0] <= 0:
        return None
    return P
