"""Ground truth: a linear plant in closed loop, identity lifting, noise-free data."""

import numpy as np
import pytest

from qube_koopman.identify import ClEdmd, ClEdmdLstsq, Edmd, close_loop
from linear_loops import closed_loop_trajectories, mass_spring_damper, pid_position_controller


@pytest.fixture(scope="module")
def loop():
    A_p, B_p = mass_spring_damper()
    controller = pid_position_controller()
    trajs = closed_loop_trajectories(A_p, B_p, controller, measured=[0], n_episodes=4, seed=3)
    return A_p, B_p, controller, trajs


@pytest.mark.parametrize("regularize", ["closed_loop", "plant"])
def test_cl_edmd_recovers_plant_exactly(loop, regularize):
    A_p, B_p, controller, trajs = loop
    model = ClEdmd(controller, measured=[0], regularize=regularize).fit(trajs)
    np.testing.assert_allclose(model.plant_model_.A, A_p, atol=1e-8)
    np.testing.assert_allclose(model.plant_model_.B, B_p, atol=1e-8)


def test_cl_edmd_closed_loop_matrix_is_the_wrapped_plant(loop):
    A_p, B_p, controller, trajs = loop
    model = ClEdmd(controller, measured=[0]).fit(trajs)
    from qube_koopman.identify import closed_loop_matrices, output_selection

    A_f, B_f = closed_loop_matrices(A_p, B_p, controller, output_selection(2, [0]), 1)
    np.testing.assert_allclose(model.koopman_matrix_, np.hstack([A_f, B_f]), atol=1e-8)


def test_edmd_on_plant_data_agrees(loop):
    A_p, B_p, controller, trajs = loop
    edmd = Edmd().fit(trajs)
    cl = ClEdmd(controller, measured=[0]).fit(trajs)
    np.testing.assert_allclose(edmd.model_.A, A_p, atol=1e-8)
    np.testing.assert_allclose(edmd.model_.B, B_p, atol=1e-8)
    np.testing.assert_allclose(edmd.koopman_matrix_, cl.plant_koopman_matrix_, atol=1e-8)


def test_least_squares_variant_is_exact_on_exact_data(loop):
    A_p, B_p, controller, trajs = loop
    model = ClEdmdLstsq(controller, measured=[0]).fit(trajs)
    np.testing.assert_allclose(model.plant_model_.A, A_p, atol=1e-7)
    np.testing.assert_allclose(model.plant_model_.B, B_p, atol=1e-7)


def test_prediction_reproduces_noise_free_episodes(loop):
    A_p, B_p, controller, trajs = loop
    model = ClEdmd(controller, measured=[0]).fit(trajs[:3])
    test = trajs[3]
    np.testing.assert_allclose(model.predict(test), test.x, atol=1e-8)
    np.testing.assert_allclose(model.predict_plant(test), test.x, atol=1e-8)
    wrapped = close_loop(Edmd().fit(trajs[:3]).model_, controller, measured=[0])
    np.testing.assert_allclose(wrapped.predict(test), test.x, atol=1e-8)


def test_state_space_export(loop):
    A_p, B_p, controller, trajs = loop
    model = ClEdmd(controller, measured=[0]).fit(trajs)
    sys = model.plant_model_.to_state_space()
    assert sys.dt == pytest.approx(controller.dt)
    np.testing.assert_allclose(sys.A, A_p, atol=1e-8)
    cl = model.closed_loop_model_.to_state_space()
    assert cl.ninputs == 2 and cl.noutputs == 2 and cl.nstates == 4
    # closed-loop DC gain from the reference to the position is 1 (integral action)
    assert cl.dcgain()[0, 0] == pytest.approx(1.0, abs=1e-6)
