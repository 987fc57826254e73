"""The paper's semidefinite program for CL EDMD (cvxpy), a reference for small problems.

The closed form in :class:`~identify.ClEdmd` solves the same problem exactly
and thousands of times faster; this path exists as an independent
cross-check and as the place for constraints without a closed form.
cvxpy is imported only when a fit runs.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from identify._checks import check_choice
from identify.cl_edmd import REGULARIZE, _ClosedLoopKoopman
from sim.lti import DiscreteStateSpace

__all__ = ["ClEdmdSdp"]

CLARABEL_TIGHT = {"tol_gap_abs": 1e-10, "tol_gap_rel": 1e-10, "tol_feas": 1e-10, "max_iter": 500}


class ClEdmdSdp(_ClosedLoopKoopman):
    """Closed-loop EDMD as the paper's SDP: min tr(W) s.t. the Schur-complement LMI.

    The structural constraint is substituted (the plant rows are ``U^p S``)
    and the paper's ``W > 0`` is left out because the LMI implies it; stating
    it makes the problem degenerate on exact controller data.

    Parameters
    ----------
    controller : DiscreteStateSpace
        The known controller.
    lifting : Lifting or sequence of LiftingFunction, optional
        Lifting of the plant states.
    alpha : float
        Tikhonov coefficient.
    measured : sequence of int, optional
        Indices of the plant states fed back; all by default.
    regularize : {"closed_loop", "plant"}
        Penalize ``||U^f||_F^2`` (the paper) or ``||U^p||_F^2``.
    solver : str
        Any cvxpy solver that handles semidefinite cones (``"CLARABEL"``
        by default, ``"SCS"``, ...).
    solver_options : dict, optional
        Passed to ``cvxpy.Problem.solve``. By default Clarabel's gap and
        feasibility tolerances are tightened to 1e-10: this is a reference
        path, and the variables converge only like the square root of the
        objective's accuracy.

    Attributes
    ----------
    koopman_matrix_, plant_koopman_matrix_, closed_loop_model_, plant_model_
        As for :class:`~identify.ClEdmd`.
    solver_status_ : str
        The solver's final status.
    """

    def __init__(self, controller: DiscreteStateSpace, lifting=None, alpha: float = 0.0,
                 measured: Sequence[int] | None = None, regularize: str = "closed_loop",
                 solver: str = "CLARABEL", solver_options: dict | None = None) -> None:
        super().__init__(controller, lifting, alpha, measured)
        self.regularize = regularize
        self.solver = solver
        self.solver_options = solver_options

    def _solve(self, snapshots, S, alpha):
        import cvxpy as cp

        regularize = check_choice(self.regularize, "regularize", REGULARIZE)
        solver = str(self.solver).upper()
        if solver not in cp.installed_solvers():
            raise ValueError(f"solver {self.solver!r} is not installed; cvxpy has "
                             f"{', '.join(cp.installed_solvers())}")
        q = snapshots.q
        # The paper's 1/q scaling keeps the problem well conditioned; the minimizer is unchanged.
        F, G, H = snapshots.F / q, snapshots.G / q, snapshots.H / q
        n_theta, n_psi = G.shape
        n_c = self.controller.n_states
        n_pl = n_theta - n_c
        H_alpha = H + (alpha / q) * np.eye(n_psi) if regularize == "closed_loop" else H
        try:
            R = np.linalg.cholesky(H_alpha)
        except np.linalg.LinAlgError:
            # Unregularized collinear regressors: a jitter far below solver tolerance.
            R = np.linalg.cholesky(H_alpha + 1e-12 * np.trace(H_alpha) / n_psi * np.eye(n_psi))

        W = cp.Variable((n_theta, n_theta), symmetric=True)
        U_c = cp.Variable((n_c, n_psi))
        U_p = cp.Variable((n_pl, S.shape[0]))
        # The structural constraint U_f[plant rows] = U^p S, substituted (fewer variables, same problem).
        U_f = cp.vstack([U_c, U_p @ S])
        cross = U_f @ G.T
        lmi = cp.bmat([[-W + F - cross - cross.T, U_f @ R],
                       [R.T @ U_f.T, -np.eye(n_psi)]])
        # The LMI block is symmetric by construction; symmetrize the expression so the
        # cone constraint is imposed on the whole matrix, not only its symmetric part.
        # W >= 0 is implied by the LMI; stating it again makes the problem degenerate when a
        # block of rows fits with zero residual (exact controller data) and costs accuracy.
        constraints = [0.5 * (lmi + lmi.T) << 0]
        objective = cp.trace(W)
        if regularize == "plant":
            objective = objective + (alpha / q) * cp.sum_squares(U_p)
        problem = cp.Problem(cp.Minimize(objective), constraints)
        options = self.solver_options
        if options is None:
            options = CLARABEL_TIGHT if solver == "CLARABEL" else {}
        try:
            problem.solve(solver=solver, **options)
        except cp.error.SolverError as exc:
            raise ValueError(f"SDP solver {solver} failed: {exc}") from exc
        self.solver_status_ = problem.status
        if U_p.value is None or problem.status not in ("optimal", "optimal_inaccurate"):
            raise ValueError(f"SDP solver {solver} ended with status {problem.status!r}")
        return np.asarray(U_f.value), np.asarray(U_p.value)
