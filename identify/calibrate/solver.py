"""A bounded Levenberg-Marquardt for sparse, arrow-shaped least squares (multiple shooting).

scipy's ``least_squares`` (trf with an LSMR trust-region solver) handles the
same sparse problem but needed over 10 s per iteration on the 28 training
episodes (measured); here each iteration factors the sparse normal matrix
``J^T J`` (block diagonal in the node states, bordered by the shared
parameters) directly with SuperLU, which costs milliseconds.

The Jacobian is what costs: a simulation of every segment with its tangents, about eight times a
residual. After a step the linear model predicted well (the cost fell by at least
:data:`CHORD_RATIO` of the predicted decrease), the next step reuses that Jacobian with the new
residual (a chord step, as in Shamanskii's variant of Newton's method) and the one after takes a
fresh one: a Jacobian serves at most two steps. A chord step that does not lower the cost is
dropped for a fresh Jacobian at the same point (the damping unchanged); the fit converges only on
a step of a fresh Jacobian, and when a chord step's gain falls below ``ftol`` one fresh step
decides (if it cannot lower the cost either, the chord step's point is the minimum).

Where a fit crawls along a valley, this is what it saves (the torque constant against the hub's
inertia, correlated +0.99, on the rig's logs): on the paper's 28 training episodes the same
minimum (the cost equal to nine digits) with 11 Jacobians in 17 steps instead of 27 in 26 (the
last Jacobian at the minimum counted; 16 against 45 s in the solver); on the 38 logs of both
controllers with each session's delay and each day's cables, a cost lower by 4e-7 with 17
Jacobians in 21 steps instead of 27 in 26 (49 against 78 s). A fit that converges in a few steps
takes as many Jacobians as before (the 38 logs with each day's cables: 12 either way, in 18 steps
instead of 11, with 4 more residual evaluations), and lands on a lower cost (by 4e-8).
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from scipy.sparse import diags
from scipy.sparse.linalg import splu

__all__ = ["levenberg_marquardt", "LmResult", "CHORD_RATIO"]

#: A step whose cost fell by at least this share of the linear model's predicted decrease lets the
#: next step reuse its Jacobian (a chord step; see the module docstring).
CHORD_RATIO = 0.75


class LmResult:
    """``x``, ``fun`` (residuals), ``jac`` (sparse, at ``x``), ``cost`` (half the sum of squares), ``nfev``, ``nit``
    (steps tried, chord steps included), ``njev`` (Jacobians computed, the final one at ``x`` included)."""

    def __init__(self, x, fun, jac, cost, nfev, nit, converged, njev=0):
        self.x, self.fun, self.jac, self.cost = x, fun, jac, cost
        self.nfev, self.nit, self.converged, self.njev = nfev, nit, converged, njev


def levenberg_marquardt(
    fun: Callable,
    jac: Callable,
    x0: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    max_iter: int = 40,
    ftol: float = 1e-7,
    callback: Callable | None = None,
    normal: Callable | None = None,
) -> LmResult:
    """Minimize ``0.5 ||fun(x)||^2`` within bounds.

    A variable at a bound that the gradient pushes out of the box stays out of the step (:func:`_free`);
    the step of the others is projected onto the bounds.

    ``jac(x, r)`` returns the sparse Jacobian at ``x`` (``r = fun(x)``); ``normal(J)``, when given, its
    normal matrix ``J^T J`` in CSC (a problem's structure may compute it faster than a general product).
    Stops when an accepted step of a fresh Jacobian lowers the cost by less than ``ftol`` relatively. A
    step the linear model predicted well lets the next one reuse its Jacobian (a chord step: see the
    module docstring); ``max_iter`` counts steps, chord steps included.
    """
    x = np.clip(x0, lower, upper)
    r = fun(x)
    cost = 0.5 * float(r @ r)
    nfev, njev, lam, converged, it = 1, 0, 1e-3, False, 0
    J, reuse = None, False  # the Jacobian in use; whether the next step may take it again (a chord step)
    confirming = False  # a chord step changed the cost by less than ftol: one fresh step says whether that is all
    for it in range(1, max_iter + 1):
        chord = reuse
        if not chord:
            J = jac(x, r)
            njev += 1
            JtJ_full = (J.T @ J).tocsc() if normal is None else normal(J)
        assert J is not None  # the first step is never a chord step
        g = J.T @ r  # a chord step: the previous point's Jacobian and normal matrix, this point's residual
        JtJ = JtJ_full
        d = np.maximum(JtJ.diagonal(), 1e-12 * max(1.0, JtJ.diagonal().max()))
        free = _free(x, g, lower, upper)
        if not free.all():  # the variables a bound holds: out of the step (see _free)
            JtJ, g, d = JtJ[free][:, free], g[free], d[free]
        while True:
            step = np.zeros_like(x)
            step[free] = -splu((JtJ + diags(lam * d)).tocsc()).solve(g)
            x_new = np.clip(x + step, lower, upper)
            r_new = fun(x_new)
            nfev += 1
            cost_new = 0.5 * float(r_new @ r_new)
            lowered = np.isfinite(cost_new) and cost_new < cost
            if lowered or chord:  # a chord step that fails is dropped for a fresh Jacobian, the damping kept
                break
            if confirming:  # the fresh step cannot lower the cost either: the chord step's point is the minimum
                return LmResult(x, r, J, cost, nfev, it, True, njev)  # (J is this point's)
            lam *= 5.0
            if lam > 1e12:
                return LmResult(x, r, J, cost, nfev, it, True, njev)
        if not lowered:
            reuse = False
            continue
        # The linear model's predicted decrease, 0.5 h^T (lam D h - g) for the LM step h (free variables).
        h = step[free]
        predicted = 0.5 * float(h @ (lam * d * h - g))
        gain = (cost - cost_new) / cost
        reuse = not chord and predicted > 0 and cost - cost_new >= CHORD_RATIO * predicted
        x, r, cost, lam = x_new, r_new, cost_new, max(lam / 3.0, 1e-9)
        if callback is not None:
            callback(it, cost)
        if gain < ftol:
            if not chord:
                converged = True
                break
            reuse = False  # converged on a chord step: confirmed by a step of a fresh Jacobian
        confirming = chord and gain < ftol
    return LmResult(x, r, jac(x, r), cost, nfev, it, converged, njev + 1)


def _free(x: np.ndarray, g: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """The variables a step may move: all but those at a bound that the descent direction ``-g`` pushes out.

    Projecting the full step onto the bounds instead leaves such a variable where it is but lets its
    wanted move bend the steps of every variable it is correlated with: a fit with one parameter at
    a bound then crawled along its valley at 1e-5 of the cost per iteration to the end of its budget
    (the arm's viscous friction Dp at 0 on the paper's logs). Fixing the active set is the textbook
    cure (projected Gauss-Newton); the set is chosen anew at every iteration, so a variable leaves
    its bound as soon as the gradient pulls it back in.
    """
    return ~(((x <= lower) & (g > 0)) | ((x >= upper) & (g < 0)))
