"""Stability-constrained CL EDMD: inactive constraints change nothing, active ones hold."""

import numpy as np
import pytest

from qube_koopman.identify import ClEdmdKnownRows, Delay, Polynomial, Trajectory, r2_score
from qube_koopman.identify.estimators import stability
from qube_koopman.identify.estimators._spectral import DiscResult
from qube_koopman.identify.estimators.stability import ClEdmdStable
from linear_loops import closed_loop_trajectories, prbs, simulate_loop
from qube_koopman.core.lti import DiscreteStateSpace
from test_sdp_cross_check import random_problem

LIFTING = [Polynomial(2), Delay(1)]


LINEAR = [Delay(1)]  # a linear lifting: prediction diverges exactly when the closed loop is unstable


def _closed_form(controller, trajs, alpha=1.0, lifting=LIFTING):
    return ClEdmdKnownRows(controller, lifting=lifting, alpha=alpha, measured=[0]).fit(trajs)


def _disc_radius(model, center):
    return float(np.max(np.abs(model.closed_loop_model_.eigenvalues() - center)))


@pytest.mark.parametrize("method", ["sqp", "lmi"])
@pytest.mark.parametrize("center", [0.0, 0.3])
def test_an_inactive_constraint_returns_the_closed_form(center, method):
    controller, trajs = random_problem(0)
    exact = _closed_form(controller, trajs)
    # A disc comfortably containing every eigenvalue of the unconstrained closed loop.
    radius = 1.5 * _disc_radius(exact, center)
    fit = ClEdmdStable(
        controller, lifting=LIFTING, alpha=1.0, measured=[0], max_radius=radius, center=center, method=method
    ).fit(trajs)
    assert fit.solver_status_ == "optimal" and fit.method_ == method
    rel = np.linalg.norm(fit.koopman_matrix_ - exact.koopman_matrix_) / np.linalg.norm(exact.koopman_matrix_)
    assert rel < 1e-6


_PLANT = (np.array([[1.0, 0.01], [0.0, 0.999]]), np.array([[0.0], [0.01]]))


def _unstable_fit_problem():
    """A marginal loop (closed-loop eigenvalue 0.999) seen through short noisy episodes: the
    closed form's closed loop comes out unstable."""
    A_p, B_p = _PLANT
    controller = DiscreteStateSpace(A=[[0.5]], B=[[1.0]], C=[[0.0]], D=[[0.2]], dt=0.01)
    trajs = closed_loop_trajectories(
        A_p, B_p, controller, measured=[0], n_episodes=2, n=120, seed=1, process_noise=0.02
    )
    return controller, trajs


def test_the_constructed_case_is_unstable_unconstrained():
    controller, trajs = _unstable_fit_problem()
    assert _closed_form(controller, trajs, alpha=1e-3, lifting=LINEAR).closed_loop_model_.spectral_radius() > 1.0


@pytest.mark.parametrize("method", ["sqp", "lmi"])
@pytest.mark.parametrize("center, radius", [(0.0, 1.0), (0.2, 0.75)])
def test_an_active_constraint_holds_to_solver_tolerance(center, radius, method):
    controller, trajs = _unstable_fit_problem()
    exact = _closed_form(controller, trajs, alpha=1e-3, lifting=LINEAR)
    assert _disc_radius(exact, center) > radius
    fit = ClEdmdStable(
        controller, lifting=LINEAR, alpha=1e-3, measured=[0], max_radius=radius, center=center, method=method
    ).fit(trajs)
    assert fit.method_ == method
    assert _disc_radius(fit, center) <= radius + 1e-6
    assert fit.unconstrained_radius_ == pytest.approx(_disc_radius(exact, center))
    # Prediction error, reported: a held-out episode of the same loop.
    held_out = closed_loop_trajectories(*_PLANT, controller, measured=[0], n_episodes=1, n=400, seed=9)[0]
    r2_exact = r2_score(held_out.x[1:], exact.predict(held_out)[1:])
    r2_fit = r2_score(held_out.x[1:], fit.predict(held_out)[1:])
    print(
        f"{method} disc ({center}, {radius}): radius {_disc_radius(exact, center):.5f} -> "
        f"{_disc_radius(fit, center):.5f}; held-out R^2 {r2_exact:.4f} -> {r2_fit:.4f}"
    )
    assert np.isfinite(r2_fit) and fit.objective_ > 0


@pytest.mark.parametrize("center, radius", [(0.0, 1.0), (0.0, 0.95), (0.2, 0.75)])
def test_the_sqp_costs_no_more_than_the_lmi_and_is_certified(center, radius):
    """The LMI's fixed Lyapunov matrix is a conservative certificate: the SQP's change is smaller."""
    controller, trajs = _unstable_fit_problem()
    fits = {
        m: ClEdmdStable(
            controller, lifting=LINEAR, alpha=1e-3, measured=[0], max_radius=radius, center=center, method=m
        ).fit(trajs)
        for m in ("sqp", "lmi")
    }
    sqp, lmi = fits["sqp"], fits["lmi"]
    assert sqp.method_ == "sqp" and _disc_radius(sqp, center) < radius
    assert sqp.objective_ <= lmi.objective_ * (1 + 1e-6)
    # The certificate: P > 0 with M^T P M - rho^2 P = -I, M the closed loop shifted by the centre.
    # In the pole region the least change puts a double eigenvalue just inside the disc, where P is
    # numerically out of reach (condition ~ margin^-3): the eigenvalue check above stands alone.
    M = sqp.closed_loop_model_.A - center * np.eye(sqp.closed_loop_model_.A.shape[0])
    P = sqp.lyapunov_matrix_
    if center != 0.0:
        assert P is None or np.linalg.eigvalsh(P)[0] > 0
        return
    assert np.linalg.eigvalsh(P)[0] > 0
    assert np.allclose(M.T @ P @ M - radius**2 * P, -np.eye(len(P)), atol=1e-6 * np.linalg.norm(P))


def _scalar_unstable_plant(a=1.01, b=0.1):
    """x+ = a x + b u, u = feedforward only (a controller with zero gains): the closed loop's only
    free eigenvalue is ``a``, so the constrained least squares has a closed form."""
    controller = DiscreteStateSpace(A=[[0.0]], B=[[0.0]], C=[[0.0]], D=[[0.0]], dt=0.01)
    rng = np.random.default_rng(3)
    trajs = []
    for i in range(2):
        n = 150
        r, f = np.zeros((n, 1)), prbs(rng, n, 1, 1.0, dwell=(3, 12))
        w = 0.01 * rng.standard_normal((n, 1))
        x, u, xc = simulate_loop(np.array([[a]]), np.array([[b]]), controller, [0], r, f, w)
        trajs.append(Trajectory(x=x, u=u, r=r, f=f, xc=xc, name=f"ep{i}", dt=0.01))
    return controller, trajs


@pytest.mark.parametrize("method, tol", [("sqp", 1e-5), ("lmi", 1e-3)])
def test_the_constrained_fit_of_a_scalar_plant_is_the_analytic_one(method, tol):
    """Minimize ||x+ - a x - b u||^2 subject to |a| <= rho: a = rho and b the conditional least squares."""
    controller, trajs = _scalar_unstable_plant()
    z = np.vstack([np.hstack([t.x[:-1], t.u[:-1]]) for t in trajs])
    y = np.concatenate([t.x[1:, 0] for t in trajs])
    (a_ls, b_ls), *_ = np.linalg.lstsq(z, y, rcond=None)
    rho = 1.0
    assert a_ls > rho
    K = z.T @ z
    b_star = b_ls - K[1, 0] / K[1, 1] * (rho - a_ls)
    fit = ClEdmdStable(controller, alpha=0.0, measured=[0], max_radius=rho, method=method).fit(trajs)
    assert fit.method_ == method
    a_fit, b_fit = fit.plant_koopman_matrix_[0]
    assert a_fit == pytest.approx(rho, abs=tol) and a_fit <= rho
    assert b_fit == pytest.approx(b_star, rel=tol)
    assert fit.unconstrained_radius_ == pytest.approx(a_ls)


def test_an_sqp_that_does_not_reach_the_disc_falls_back_to_the_lmi(monkeypatch):
    controller, trajs = _unstable_fit_problem()

    def stuck(problem, U0, radius, center=0.0, **kwargs):
        return DiscResult(U0, 2.0, False, 100, 1)

    monkeypatch.setattr(stability, "least_change_into_disc", stuck)
    fit = ClEdmdStable(controller, lifting=LINEAR, alpha=1e-3, measured=[0], max_radius=1.0).fit(trajs)
    assert fit.method_ == "lmi" and _disc_radius(fit, 0.0) <= 1.0 + 1e-6


def test_unknown_method_is_refused():
    controller, trajs = random_problem(0)
    with pytest.raises(ValueError, match="unknown method"):
        ClEdmdStable(controller, lifting=LIFTING, measured=[0], method="newton").fit(trajs)


def test_bad_disc_is_refused():
    controller, trajs = random_problem(0)
    with pytest.raises(ValueError, match="positive radius"):
        ClEdmdStable(controller, lifting=LIFTING, measured=[0], max_radius=0.0).fit(trajs)


@pytest.mark.slow
def test_qube_identify_max_radius_on_simulated_logs(tmp_path):
    """The command's path: a small lifting keeps the LMI small; the report records the constraint."""
    import json

    from qube_koopman.daq.cli.run import main as qube_run
    from qube_koopman.identify.cli.identify import main as qube_identify

    assert qube_run(["--episodes", "3", "--duration", "6", "--seed", "4", "--out", str(tmp_path / "logs"), "-q"]) == 0
    logs = sorted(str(p) for p in (tmp_path / "logs").glob("*.mcap"))
    out = tmp_path / "id"
    assert (
        qube_identify(
            [
                "--train",
                *logs[:2],
                "--test",
                logs[2],
                "--poly",
                "1",
                "--delays",
                "2",
                "--max-radius",
                "0.999",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    report = json.loads((out / "report.json").read_text())
    assert report["method"] == "cl-edmd-stable"
    assert report["spectral_radius"]["closed_loop"] <= 0.999 + 1e-6
    assert report["constraint"]["max_radius"] == 0.999 and report["constraint"]["center"] == 0.0
