"""Two independent solutions of the paper's constrained problem: closed form vs SDP."""

import numpy as np
import pytest

from qube_koopman.identify import ClEdmd, ClEdmdSdp, Delay, Polynomial
from linear_loops import closed_loop_trajectories
from qube_koopman.core.lti import DiscreteStateSpace


def random_problem(seed):
    """A random stable plant and controller, noisy data: a non-trivial constrained fit."""
    rng = np.random.default_rng(seed)
    n_p = 3
    A_p = rng.normal(size=(n_p, n_p))
    A_p *= 0.9 / max(abs(np.linalg.eigvals(A_p)))
    B_p = rng.normal(size=(n_p, 1))
    controller = DiscreteStateSpace(
        A=[[rng.uniform(0.3, 0.9)]], B=[[1.0]], C=[[rng.normal()]], D=[[rng.uniform(-0.3, 0.3)]], dt=0.01
    )
    trajs = closed_loop_trajectories(
        A_p, B_p, controller, measured=[0], n_episodes=3, n=150, seed=seed, process_noise=0.05
    )
    return controller, trajs


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:Solution may be inaccurate")
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("regularize,alpha", [("closed_loop", 0.0), ("closed_loop", 5.0), ("plant", 5.0)])
def test_closed_form_equals_sdp(seed, regularize, alpha):
    """Agreement to 1e-5 relative (measured: at most 4e-6)."""
    controller, trajs = random_problem(seed)
    # A nonlinear lifting (polynomial, then delays) makes the problem larger than the plant.
    lifting = [Polynomial(2), Delay(1)]
    # The paper's problem leaves the controller rows free, like the SDP.
    exact = ClEdmd(
        controller, lifting=lifting, alpha=alpha, measured=[0], regularize=regularize, known_controller_rows=False
    ).fit(trajs)
    sdp = ClEdmdSdp(controller, lifting=lifting, alpha=alpha, measured=[0], regularize=regularize).fit(trajs)
    assert sdp.solver_status_ in ("optimal", "optimal_inaccurate")
    rel = np.linalg.norm(sdp.koopman_matrix_ - exact.koopman_matrix_) / np.linalg.norm(exact.koopman_matrix_)
    assert rel < 1e-5
    rel_p = np.linalg.norm(sdp.plant_koopman_matrix_ - exact.plant_koopman_matrix_) / np.linalg.norm(
        exact.plant_koopman_matrix_
    )
    assert rel_p < 1e-5


def test_sdp_rejects_unknown_solver():
    controller, trajs = random_problem(0)
    with pytest.raises(ValueError, match="not installed"):
        ClEdmdSdp(controller, measured=[0], solver="NO_SUCH_SOLVER").fit(trajs)


def test_default_cl_edmd_is_the_papers_problem_and_the_variant_is_named():
    from qube_koopman.identify import ClEdmdKnownRows

    controller, trajs = random_problem(1)
    lifting = [Polynomial(2), Delay(1)]
    default = ClEdmd(controller, lifting=lifting, alpha=5.0, measured=[0]).fit(trajs)
    free = ClEdmd(controller, lifting=lifting, alpha=5.0, measured=[0], known_controller_rows=False).fit(trajs)
    known = ClEdmdKnownRows(controller, lifting=lifting, alpha=5.0, measured=[0]).fit(trajs)
    np.testing.assert_array_equal(default.koopman_matrix_, free.koopman_matrix_)
    np.testing.assert_array_equal(default.plant_koopman_matrix_, known.plant_koopman_matrix_)
    n_c = controller.n_states
    wrapped = known.wrap().koopman_matrix
    np.testing.assert_allclose(known.koopman_matrix_, wrapped, atol=1e-12)  # exactly the wrapped plant
    assert np.abs(default.koopman_matrix_[:n_c] - wrapped[:n_c]).max() > 1e-6  # the paper's rows drift
