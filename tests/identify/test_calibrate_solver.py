"""The calibration's bounded Levenberg-Marquardt against scipy's bounded least squares (independent code).

The case that matters is a variable held at a bound while variables correlated with it are free:
the calibration's arm viscous friction sits at 0 on the rig's logs. Projecting the full step onto
the bounds made such a fit crawl along its valley to the end of its iteration budget; with the
active variables out of the step it reaches the bounded minimum in a few iterations.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares, lsq_linear
from scipy.sparse import csr_matrix

from qube_koopman.identify.calibrate.solver import levenberg_marquardt


def _correlated_problem(seed: int):
    """A tall linear least squares whose first two columns are nearly the same: correlated variables."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(200, 5))
    A[:, 1] = A[:, 0] + 0.05 * rng.normal(size=200)
    x_true = np.array([-1.0, 2.0, 0.5, -0.3, 1.5])
    b = A @ x_true + 0.01 * rng.normal(size=200)
    return A, b


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_bound_held_variable_correlated_with_free_ones_gives_the_bounded_minimum(seed):
    A, b = _correlated_problem(seed)
    # x0 >= 0 binds (the data want -1), and x1, nearly the same column, must make up for it.
    lower = np.array([0.0, -10, -10, -10, -10])
    upper = np.full(5, 10.0)
    result = levenberg_marquardt(
        lambda x: A @ x - b, lambda x, r: csr_matrix(A), np.full(5, 0.5), lower, upper, max_iter=40, ftol=1e-12
    )
    reference = lsq_linear(A, b, bounds=(lower, upper), method="bvls", tol=1e-14)
    assert reference.active_mask[0] == -1  # the case: the bound is active at the minimum
    np.testing.assert_allclose(result.x, reference.x, atol=1e-7)
    assert result.x[0] == 0.0
    # Linear: a few iterations while the damping falls, not the whole budget.
    assert result.converged and result.nit <= 15, result.nit


def test_a_nonlinear_fit_with_an_active_bound_matches_scipys_trust_region_fit():
    # Exponential decay with an offset, the decay rate bounded below the data's: the bound binds.
    t = np.linspace(0, 4, 120)
    rng = np.random.default_rng(3)
    y = 2.0 * np.exp(-1.3 * t) + 0.4 + 0.002 * rng.normal(size=t.size)

    def fun(x):
        return x[0] * np.exp(-x[1] * t) + x[2] - y

    def jac(x, r):
        e = np.exp(-x[1] * t)
        return csr_matrix(np.column_stack([e, -x[0] * t * e, np.ones_like(t)]))

    lower, upper = np.array([0.0, 0.0, -5.0]), np.array([10.0, 1.0, 5.0])
    result = levenberg_marquardt(fun, jac, np.array([1.0, 0.5, 0.0]), lower, upper, max_iter=60, ftol=1e-14)
    reference = least_squares(
        fun, [1.0, 0.5, 0.0], jac=lambda x: jac(x, None).toarray(), bounds=(lower, upper), xtol=1e-14, ftol=1e-14
    )
    assert reference.active_mask[1] == 1
    np.testing.assert_allclose(result.x, reference.x, atol=1e-6)
    assert result.cost <= reference.cost * (1 + 1e-9)
    assert result.nit <= 25, result.nit


def test_a_variable_leaves_its_bound_when_the_gradient_pulls_it_in():
    # Started at a bound the minimum lies away from: the active set is chosen anew each iteration.
    A, b = _correlated_problem(4)
    lower, upper = np.full(5, -10.0), np.full(5, 10.0)
    x0 = np.array([10.0, -10.0, 0.0, 0.0, 0.0])  # two variables at bounds, both pulled inwards
    result = levenberg_marquardt(lambda x: A @ x - b, lambda x, r: csr_matrix(A), x0, lower, upper, ftol=1e-14)
    np.testing.assert_allclose(result.x, np.linalg.lstsq(A, b, rcond=None)[0], atol=1e-7)


def test_chord_steps_reuse_well_predicted_jacobians_and_reach_the_known_minimum():
    # Rosenbrock's curved valley as least squares (minimum (1, 1), cost 0): the steps the linear model
    # predicts well let the next step reuse their Jacobian, so fewer Jacobians than steps are computed
    # (the returned one at the minimum included), and the fit still ends on the analytic minimum.
    calls = []

    def fun(x):
        return np.array([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]])

    def jac(x, r):
        calls.append(x.copy())
        return csr_matrix(np.array([[-20.0 * x[0], 10.0], [-1.0, 0.0]]))

    bounds = np.full(2, -5.0), np.full(2, 5.0)
    result = levenberg_marquardt(fun, jac, np.array([-1.2, 1.0]), *bounds, max_iter=200, ftol=1e-15)
    np.testing.assert_allclose(result.x, [1.0, 1.0], atol=1e-6)
    assert result.converged and result.cost < 1e-12
    assert result.njev == len(calls) < result.nit + 1, (result.njev, result.nit)
    np.testing.assert_array_equal(calls[-1], result.x)  # the Jacobian returned is the minimum's
