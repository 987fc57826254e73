"""The paper's semidefinite program for CL EDMD (cvxpy), a reference for small problems.

The closed form in :class:`~identify.ClEdmd` solves the same problem exactly
and thousands of times faster; this path exists as an independent
cross-check and as the place for constraints without a closed form.
To be independent it builds its own data: the snapshot matrices from the
trajectories (:func:`closed_loop_snapshots`), their Gram matrices from one
QR factorization, and the closed-loop matrix block by block from the
controller (:func:`closed_loop_blocks`), sharing none of the closed form's
set-up (``Snapshots``, ``plant_input_map``, ``closed_loop_matrices``).
cvxpy is imported only when a fit runs.
"""

from __future__ import annotations

from typing import Sequence, cast

import numpy as np

from dataclasses import dataclass

from qube_koopman.identify.estimators.base import resolve_lifting
from qube_koopman.identify._checks import check_alpha, check_choice, check_loop_controller
from qube_koopman.identify.estimators.cl_edmd import REGULARIZE, ClosedLoopKoopman
from qube_koopman.identify.data.trajectory import check_trajectories
from qube_koopman.core.lti import DiscreteStateSpace

__all__ = ["ClEdmdSdp", "SnapshotGram", "closed_loop_snapshots", "closed_loop_blocks"]

CLARABEL_TIGHT = {"tol_gap_abs": 1e-10, "tol_gap_rel": 1e-10, "tol_feas": 1e-10, "max_iter": 500}


@dataclass(frozen=True)
class SnapshotGram:
    """``F = Theta Theta^T``, ``G = Theta Psi^T``, ``H = Psi Psi^T`` over ``q`` snapshots, and a factor.

    ``R`` (upper triangular, from one QR factorization of the stacked
    snapshots ``[Psi^T Theta^T]``) satisfies ``R^T R = [[H, G^T], [G, F]]``:
    a fit can work on it (size of the lifted state) instead of the snapshots.
    """

    F: np.ndarray
    G: np.ndarray
    H: np.ndarray
    R: np.ndarray
    q: int


def closed_loop_snapshots(trajectories, lifting, n_feedforward: int) -> tuple[np.ndarray, np.ndarray]:
    """Snapshot matrices of the closed loop, one column per snapshot, episodes never joined.

    ``Psi`` stacks ``[x^c_k; theta^p_k; r_k; f_k]`` and ``Theta`` stacks
    ``[x^c_{k+1}; theta^p_{k+1}]``, where ``theta^p`` is the fitted
    ``lifting`` of the plant states (it consumes ``n_delays_`` samples).
    """
    psi, theta = [], []
    for t in trajectories:
        d = lifting.n_delays_
        lifted = lifting.transform(t.x)
        columns = [t.xc[d:].T, lifted.T, t.r[d:].T] + ([t.f[d:].T] if n_feedforward else [])
        stacked = np.vstack(columns)
        n_theta = t.xc.shape[1] + lifted.shape[1]
        psi.append(stacked[:, :-1])
        theta.append(stacked[:n_theta, 1:])
    return np.hstack(psi), np.hstack(theta)


def snapshot_gram(psi: np.ndarray, theta: np.ndarray) -> SnapshotGram:
    """Gram matrices of the snapshots from one QR factorization."""
    # numpy's stubs give every mode the (Q, R) result; mode "r" returns R alone.
    R = cast(np.ndarray, np.linalg.qr(np.vstack([psi, theta]).T, mode="r"))
    n_psi = psi.shape[0]
    R_psi, R_theta = R[:, :n_psi], R[:, n_psi:]
    return SnapshotGram(R_theta.T @ R_theta, R_theta.T @ R_psi, R_psi.T @ R_psi, R, psi.shape[1])


def closed_loop_blocks(controller: DiscreteStateSpace, A_p, B_p, measured, n_feedforward: int, rows_c=None):
    """``U^f`` assembled from its blocks (paper section 3), for numpy arrays or cvxpy expressions.

    ``[[A^c, -B^c C^p, B^c, 0], [B^p C^c, A^p - B^p D^c C^p, B^p D^c, B^p]]`` with
    ``C^p`` picking ``measured`` out of the lifted plant state; ``rows_c``
    replaces the controller rows when they are fitted (the paper's problem). A
    controller that also takes the feedforward (inputs beyond the tracking errors)
    puts its feedforward columns in the last block column: ``[B^c_f; B^p (I + D^c_f)]``.
    """
    import cvxpy as cp

    n_pl = A_p.shape[0]
    C_p = np.eye(n_pl)[list(measured)]
    n_r = len(measured)
    Ac, Cc = controller.A, controller.C
    Bc, Dc = controller.B[:, :n_r], controller.D[:, :n_r]  # the tracking errors' columns
    n_c, n_u = Ac.shape[0], Cc.shape[0]
    sees_f = controller.n_inputs > n_r
    Bf = controller.B[:, n_r:] if sees_f else np.zeros((n_c, n_feedforward))
    f_gain = np.eye(n_u) + (controller.D[:, n_r:] if sees_f else 0.0)  # u = ... + D^c_f f + f
    top = rows_c if rows_c is not None else np.hstack([Ac, -Bc @ C_p, Bc, Bf])
    bottom = [B_p @ Cc, A_p - B_p @ (Dc @ C_p), B_p @ Dc] + ([B_p @ f_gain] if n_feedforward else [])
    return cp.vstack([top if not isinstance(top, np.ndarray) else cp.Constant(top), cp.hstack(bottom)])


class ClEdmdSdp(ClosedLoopKoopman):
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

    def __init__(
        self,
        controller: DiscreteStateSpace,
        lifting=None,
        alpha: float = 0.0,
        measured: Sequence[int] | None = None,
        regularize: str = "closed_loop",
        solver: str = "CLARABEL",
        solver_options: dict | None = None,
    ) -> None:
        super().__init__(controller, lifting, alpha, measured)
        self.regularize = regularize
        self.solver = solver
        self.solver_options = solver_options

    # No controllers argument, unlike ClosedLoopKoopman.fit: the SDP fits its own controller's episodes only.
    def fit(self, trajectories) -> "ClEdmdSdp":  # type: ignore[override]
        """Fit on closed-loop trajectories (signals x, r, xc, optional f), from data built here.

        Returns
        -------
        self
        """
        alpha = check_alpha(self.alpha)
        regularize = check_choice(self.regularize, "regularize", REGULARIZE)
        lifting = resolve_lifting(self.lifting)
        trajs = check_trajectories(trajectories, ("x", "r", "xc"), lifting.n_delays + 2, type(self).__name__)
        with_f = [t.f is not None for t in trajs]
        if any(with_f) and not all(with_f):
            raise ValueError("feedforward f is present in some episodes and missing in others")
        f0 = trajs[0].f  # given in every episode or in none
        n_f = f0.shape[1] if f0 is not None else 0
        m = trajs[0].x.shape[1]
        measured = list(range(m)) if self.measured is None else [int(i) for i in self.measured]
        check_loop_controller(self.controller, measured, n_f, trajs[0].dt, trajs[0])
        lifting.fit([t.x for t in trajs], trajs[0].state_names)
        gram = snapshot_gram(*closed_loop_snapshots(trajs, lifting, n_f))
        U_f, U_p = self._solve_sdp(gram, lifting.n_features_out_, measured, n_f, alpha, regularize)
        self.snapshots_ = gram
        self.output_matrix_ = np.eye(lifting.n_features_out_)[measured]
        self.n_feedforward_ = n_f
        self._set_models(U_f, U_p, lifting, n_f, trajs[0].dt if trajs[0].dt is not None else self.controller.dt)
        return self

    def _solve(self, snapshots, S: np.ndarray, alpha: float):
        raise NotImplementedError(
            "ClEdmdSdp solves its SDP on the snapshots' Gram matrix, which fit builds: it fits with fit only, "
            "not from per-episode statistics (finish_fit)"
        )

    def _solve_sdp(self, gram: SnapshotGram, n_pl: int, measured, n_f: int, alpha: float, regularize: str):
        import cvxpy as cp

        solver = str(self.solver).upper()
        if solver not in cp.installed_solvers():
            raise ValueError(f"solver {self.solver!r} is not installed; cvxpy has {', '.join(cp.installed_solvers())}")
        q = gram.q
        # The paper's 1/q scaling keeps the problem well conditioned; the minimizer is unchanged.
        F, G, H = gram.F / q, gram.G / q, gram.H / q
        n_theta, n_psi = G.shape
        n_c, n_u = self.controller.n_states, self.controller.n_outputs
        H_alpha = H + (alpha / q) * np.eye(n_psi) if regularize == "closed_loop" else H
        try:
            R = np.linalg.cholesky(H_alpha)
        except np.linalg.LinAlgError:
            # Unregularized collinear regressors: a jitter far below solver tolerance.
            R = np.linalg.cholesky(H_alpha + 1e-12 * np.trace(H_alpha) / n_psi * np.eye(n_psi))

        W = cp.Variable((n_theta, n_theta), symmetric=True)
        U_c = cp.Variable((n_c, n_psi))  # the paper leaves the controller rows free
        A_p, B_p = cp.Variable((n_pl, n_pl)), cp.Variable((n_pl, n_u))
        U_f = closed_loop_blocks(self.controller, A_p, B_p, measured, n_f, rows_c=U_c)
        cross = U_f @ G.T
        lmi = cp.bmat([[-W + F - cross - cross.T, U_f @ R], [R.T @ U_f.T, -np.eye(n_psi)]])
        # The LMI block is symmetric by construction; symmetrize the expression so the
        # cone constraint is imposed on the whole matrix, not only its symmetric part.
        # W >= 0 is implied by the LMI; stating it again makes the problem degenerate when a
        # block of rows fits with zero residual (exact controller data) and costs accuracy.
        constraints = [0.5 * (lmi + lmi.T) << 0]
        objective = cp.trace(W)
        if regularize == "plant":
            objective = objective + (alpha / q) * (cp.sum_squares(A_p) + cp.sum_squares(B_p))
        problem = cp.Problem(cp.Minimize(objective), constraints)
        options = self.solver_options
        if options is None:
            options = CLARABEL_TIGHT if solver == "CLARABEL" else {}
        try:
            problem.solve(solver=solver, **options)
        except cp.error.SolverError as exc:
            raise ValueError(f"SDP solver {solver} failed: {exc}") from exc
        self.solver_status_ = problem.status
        if A_p.value is None or B_p.value is None or problem.status not in ("optimal", "optimal_inaccurate"):
            raise ValueError(f"SDP solver {solver} ended with status {problem.status!r}")
        return np.asarray(U_f.value), np.hstack([A_p.value, B_p.value])
