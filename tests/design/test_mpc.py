"""The condensed linear MPC: its QP against cvxpy, the unconstrained MPC against the LQ gain, the fallback."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from qube_koopman.daq.controller_step import controller_step
from qube_koopman.design import Weights, design_lq, linear_plant
from qube_koopman.design.mpc import MpcRuntime, MpcSettings, OsqpSolver, build_problem, solve_newton

sys.path.insert(0, str(Path(__file__).parent))
from test_design import _pendulum_like  # noqa: E402


def _random_qp(rng, N):
    A = rng.standard_normal((N, N))
    H = A @ A.T + 0.1 * np.eye(N)
    g = 3 * rng.standard_normal(N)
    lo, hi = -rng.uniform(0.1, 1, N), rng.uniform(0.1, 1, N)
    M = rng.standard_normal((N, N))
    m_hi, m_lo = rng.uniform(0, 0.5, N), -rng.uniform(0, 0.5, N)
    return H, g, lo, hi, M, m_lo, m_hi


def _cvxpy(H, g, lo, hi, M, m_lo, m_hi, rho):
    cp = pytest.importorskip("cvxpy")
    N = len(g)
    U, e = cp.Variable(N), cp.Variable(N)
    cost = 0.5 * cp.quad_form(U, cp.psd_wrap(H)) + g @ U + 0.5 * rho * cp.sum_squares(e)
    cons = [U >= lo, U <= hi, M @ U <= m_hi + e, M @ U >= m_lo - e, e >= 0]
    cp.Problem(cp.Minimize(cost), cons).solve(solver=cp.CLARABEL)
    return U.value


@pytest.mark.parametrize("seed", range(8))
def test_the_projected_newton_solver_matches_cvxpy_on_random_problems(seed):
    rng = np.random.default_rng(seed)
    N = int(rng.integers(3, 25))
    H, g, lo, hi, M, m_lo, m_hi = _random_qp(rng, N)
    rho = 50.0
    res = solve_newton(H, g, lo, hi, M, m_lo, m_hi, rho, np.zeros(N), max_iterations=100, tolerance=1e-10)
    assert res.status == "solved"
    np.testing.assert_allclose(res.U, _cvxpy(H, g, lo, hi, M, m_lo, m_hi, rho), atol=1e-5)
    assert np.all(res.U >= lo - 1e-12) and np.all(res.U <= hi + 1e-12)


def _plant_problem(settings=MpcSettings()):
    plant = linear_plant(_pendulum_like(3, False))
    return plant, build_problem(plant, Weights(), settings)


@pytest.mark.parametrize("seed", range(4))
def test_osqp_on_the_mpc_problem_matches_cvxpy(seed):
    rng = np.random.default_rng(seed)
    _, p = _plant_problem(MpcSettings(solver="osqp", tolerance=1e-9, time_budget=1.0))
    z = 0.05 * rng.standard_normal(p.G_z.shape[1])
    g, mz = p.G_z @ z, p.theta_z @ z
    lo, hi = -np.full(p.horizon, 2.0), np.full(p.horizon, 2.0)
    m_hi, m_lo = 0.01 - mz, -0.01 - mz
    res = OsqpSolver(p).solve(g, lo, hi, m_lo, m_hi, np.zeros(p.horizon))
    ref = _cvxpy(p.H, g, lo, hi, p.theta_U, m_lo, m_hi, p.settings.theta_penalty)
    new = solve_newton(p.H, g, lo, hi, p.theta_U, m_lo, m_hi, p.settings.theta_penalty, np.zeros(p.horizon))
    np.testing.assert_allclose(res.U, ref, atol=1e-4)
    np.testing.assert_allclose(new.U, ref, atol=1e-4)


@pytest.mark.parametrize("solver", ["newton", "osqp"])
def test_the_unconstrained_mpc_is_the_lq_gain_of_the_same_weights(solver):
    plant, p = _plant_problem(MpcSettings(solver=solver, tolerance=1e-10, time_budget=10.0))
    lq = design_lq(plant, Weights())
    np.testing.assert_allclose(p.gain, lq.gain, rtol=1e-8)
    runtime = MpcRuntime(p, plant.n_delays, True, plant.dt)
    out, upd = runtime.step()
    lq_out, lq_upd = controller_step(lq.controller)
    rng = np.random.default_rng(1)
    for _ in range(100):
        e0, e1 = 1e-5 * rng.standard_normal(2)
        u, x = out(e0, e1, 0.0, 0.0)
        u_lq, x_lq = lq_out(e0, e1, 0.0)
        assert abs(u) < 9  # no constraint active
        assert u == pytest.approx(u_lq, abs=1e-6 * max(1.0, abs(u_lq)))
        np.testing.assert_allclose(x, x_lq, atol=1e-15)
        upd(e0, e1, 0.0)
        lq_upd(e0, e1, 0.0)
    assert runtime.n_fallbacks == 0


class _SlowClock:
    """A clock that advances ``step`` seconds per reading: the solver's budget runs out on it."""

    def __init__(self, step):
        self.t, self.step = 0.0, step

    def __call__(self):
        self.t += self.step
        return self.t


def test_a_solve_over_budget_applies_the_previous_plans_next_input_or_the_clipped_lq_gain():
    plant, p = _plant_problem(MpcSettings(time_budget=1e-3, voltage_limit=3.0))
    clock = _SlowClock(0.0)
    runtime = MpcRuntime(p, plant.n_delays, True, plant.dt, clock=clock)
    out, upd = runtime.step()
    # first tick over budget: no plan yet, the LQ gain clipped at the limit
    clock.step = 1.0
    u, _ = out(0.3, 0.0, 0.0, 0.0)
    z = np.zeros(p.G_z.shape[1])
    z[0] = -0.3
    assert runtime.tick_record[4] == 1.0 and runtime.n_fallbacks == 1
    assert u == pytest.approx(float(np.clip(-p.gain[0] @ z, -3, 3)))
    assert abs(u) == 3.0
    # a new episode: a tick in budget plans; the next one over budget applies that plan's next input
    out, upd = runtime.step()
    clock.step = 0.0
    u1, _ = out(1e-4, 0.0, 0.0, 0.0)
    assert runtime.tick_record[4] == 0.0 and u1 == runtime.plan[0]
    planned = runtime.plan.copy()
    upd(1e-4, 0.0, 0.0)
    clock.step = 1.0
    u2, _ = out(2e-4, 0.0, 0.0, 0.0)
    assert runtime.tick_record[4] == 1.0 and runtime.n_fallbacks == 1
    assert u2 == pytest.approx(planned[1]) and u2 == pytest.approx(runtime.plan[0])
    assert planned[1] != planned[0] and abs(u2) < 3.0


def test_a_solver_failure_applies_the_fallback_not_the_last_voltage(monkeypatch):
    import qube_koopman.design.mpc as mpc

    # a budget no host misses: the first tick must plan, whatever the machine's load
    plant, p = _plant_problem(MpcSettings(voltage_limit=5.0, time_budget=10.0))
    runtime = MpcRuntime(p, plant.n_delays, True, plant.dt)
    out, upd = runtime.step()
    out(0.05, 0.0, 0.0, 0.0)
    planned = runtime.plan.copy()
    upd(0.05, 0.0, 0.0)

    def broken(*args, **kwargs):
        raise FloatingPointError("solver blew up")

    monkeypatch.setattr(mpc, "solve_newton", broken)
    for k in range(3):
        u, _ = out(0.05, 0.0, 0.0, 0.0)
        assert runtime.tick_record[0] == mpc.SOLVER_STATUS["failed"] and runtime.tick_record[4] == 1.0
        assert u == pytest.approx(planned[k + 1]) and abs(u) <= 5.0  # the plan's next inputs, not the last voltage
        upd(0.05, 0.0, 0.0)
    assert runtime.n_fallbacks == 3
