"""Stability-constrained CL EDMD: inactive constraints change nothing, active ones hold."""

import numpy as np
import pytest

from qube_koopman.identify import ClEdmdKnownRows, Delay, Polynomial, r2_score
from qube_koopman.identify.stability import ClEdmdStable
from linear_loops import closed_loop_trajectories
from qube_koopman.sim.lti import DiscreteStateSpace
from test_sdp_cross_check import random_problem

LIFTING = [Polynomial(2), Delay(1)]


LINEAR = [Delay(1)]   # a linear lifting: prediction diverges exactly when the closed loop is unstable


def _closed_form(controller, trajs, alpha=1.0, lifting=LIFTING):
    return ClEdmdKnownRows(controller, lifting=lifting, alpha=alpha, measured=[0]).fit(trajs)


def _disc_radius(model, center):
    return float(np.max(np.abs(model.closed_loop_model_.eigenvalues() - center)))


@pytest.mark.parametrize("center", [0.0, 0.3])
def test_an_inactive_constraint_returns_the_closed_form(center):
    controller, trajs = random_problem(0)
    exact = _closed_form(controller, trajs)
    # A disc comfortably containing every eigenvalue of the unconstrained closed loop.
    radius = 1.5 * _disc_radius(exact, center)
    fit = ClEdmdStable(controller, lifting=LIFTING, alpha=1.0, measured=[0], max_radius=radius,
                       center=center).fit(trajs)
    assert fit.solver_status_ == "optimal"
    rel = np.linalg.norm(fit.koopman_matrix_ - exact.koopman_matrix_) / np.linalg.norm(exact.koopman_matrix_)
    assert rel < 1e-6


_PLANT = (np.array([[1.0, 0.01], [0.0, 0.999]]), np.array([[0.0], [0.01]]))


def _unstable_fit_problem():
    """A marginal loop (closed-loop eigenvalue 0.999) seen through short noisy episodes: the
    closed form's closed loop comes out unstable."""
    A_p, B_p = _PLANT
    controller = DiscreteStateSpace(A=[[0.5]], B=[[1.0]], C=[[0.0]], D=[[0.2]], dt=0.01)
    trajs = closed_loop_trajectories(A_p, B_p, controller, measured=[0], n_episodes=2, n=120, seed=1,
                                     process_noise=0.02)
    return controller, trajs


def test_the_constructed_case_is_unstable_unconstrained():
    controller, trajs = _unstable_fit_problem()
    assert _closed_form(controller, trajs, alpha=1e-3, lifting=LINEAR).closed_loop_model_.spectral_radius() > 1.0


@pytest.mark.parametrize("center, radius", [(0.0, 1.0), (0.2, 0.75)])
def test_an_active_constraint_holds_to_solver_tolerance(center, radius):
    controller, trajs = _unstable_fit_problem()
    exact = _closed_form(controller, trajs, alpha=1e-3, lifting=LINEAR)
    assert _disc_radius(exact, center) > radius
    fit = ClEdmdStable(controller, lifting=LINEAR, alpha=1e-3, measured=[0], max_radius=radius,
                       center=center).fit(trajs)
    assert _disc_radius(fit, center) <= radius + 1e-6
    assert fit.unconstrained_radius_ == pytest.approx(_disc_radius(exact, center))
    # Prediction error, reported: a held-out episode of the same loop.
    held_out = closed_loop_trajectories(*_PLANT, controller, measured=[0], n_episodes=1, n=400, seed=9)[0]
    r2_exact = r2_score(held_out.x[1:], exact.predict(held_out)[1:])
    r2_fit = r2_score(held_out.x[1:], fit.predict(held_out)[1:])
    print(f"disc ({center}, {radius}): radius {_disc_radius(exact, center):.5f} -> "
          f"{_disc_radius(fit, center):.5f}; held-out R^2 {r2_exact:.4f} -> {r2_fit:.4f}")
    assert np.isfinite(r2_fit) and fit.objective_ > 0


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

    assert qube_run(["--episodes", "3", "--duration", "6", "--seed", "4", "--out", str(tmp_path / "logs"),
                     "-q"]) == 0
    logs = sorted(str(p) for p in (tmp_path / "logs").glob("*.mcap"))
    out = tmp_path / "id"
    assert qube_identify(["--train", *logs[:2], "--test", logs[2], "--poly", "1", "--delays", "2",
                          "--max-radius", "0.999", "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["method"] == "cl-edmd-stable"
    assert report["spectral_radius"]["closed_loop"] <= 0.999 + 1e-6
    assert report["constraint"]["max_radius"] == 0.999 and report["constraint"]["center"] == 0.0
