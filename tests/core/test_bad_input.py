"""Bad input gives a ValueError that names the problem, never a silent wrong answer."""

import numpy as np
import pytest

from qube_koopman.identify import Arx, ClEdmd, Delay, Edmd, Polynomial, Trajectory
from qube_koopman.core.lti import DiscreteStateSpace
from linear_loops import closed_loop_trajectories, mass_spring_damper, pid_position_controller


@pytest.fixture(scope="module")
def loop():
    A_p, B_p = mass_spring_damper()
    controller = pid_position_controller()
    return controller, closed_loop_trajectories(A_p, B_p, controller, [0], n_episodes=2, n=100, seed=0)


def test_mismatched_signal_lengths():
    with pytest.raises(ValueError, match="trajectory 'ep': u has 9 samples, expected 10"):
        Trajectory(x=np.zeros((10, 2)), u=np.zeros((9, 1)), name="ep")


def test_non_finite_data_is_located():
    x = np.zeros((10, 2))
    x[4, 1] = np.nan
    with pytest.raises(ValueError, match="non-finite value at sample 4, channel 1"):
        Trajectory(x=x, name="ep")


def test_wrong_dimensions():
    with pytest.raises(ValueError, match="1-D or 2-D"):
        Trajectory(x=np.zeros((3, 2, 2)))


def test_episode_too_short_for_the_delays(loop):
    controller, trajs = loop
    short = Trajectory(x=trajs[0].x[:5], u=trajs[0].u[:5], name="short", dt=trajs[0].dt)
    with pytest.raises(ValueError, match="trajectory short has 5 samples; EDMD needs at least 12"):
        Edmd(lifting=[Delay(10)]).fit([trajs[0], short])


def test_episodes_with_different_widths(loop):
    controller, trajs = loop
    other = Trajectory(x=trajs[0].x[:, :1], u=trajs[0].u, name="narrow")
    with pytest.raises(ValueError, match="narrow: x has 1 channels, the first trajectory has 2"):
        Edmd().fit([trajs[0], other])


def test_missing_signal(loop):
    controller, trajs = loop
    with pytest.raises(ValueError, match="needs signal 'xc', missing in trajectory plain"):
        ClEdmd(controller, measured=[0]).fit([Trajectory(x=trajs[0].x, r=trajs[0].r, name="plain")])


def test_controller_dimensions_must_match_the_data(loop):
    controller, trajs = loop
    one_state = DiscreteStateSpace([[1.0]], [[1.0]], [[1.0]], [[1.0]], controller.dt)
    with pytest.raises(ValueError, match="controller has 1 states but the data's controller state has 2"):
        ClEdmd(one_state, measured=[0]).fit(trajs)
    with pytest.raises(ValueError, match="takes 1 tracking errors; the data has 1 references and 2 fed-back"):
        ClEdmd(controller).fit(trajs)  # default: both states fed back, the controller takes one error
    with pytest.raises(ValueError, match="outside"):
        ClEdmd(controller, measured=[5]).fit(trajs)


def test_sample_period_must_match_the_controller(loop):
    controller, trajs = loop
    slow = [Trajectory(x=t.x, r=t.r, f=t.f, xc=t.xc, dt=0.02) for t in trajs]
    with pytest.raises(ValueError, match="sample period 0.02 s differs from the controller's 0.01 s"):
        ClEdmd(controller, measured=[0]).fit(slow)


def test_feedforward_in_some_episodes_only(loop):
    controller, trajs = loop
    without = Trajectory(x=trajs[1].x, r=trajs[1].r, xc=trajs[1].xc, dt=trajs[1].dt)
    with pytest.raises(ValueError, match="feedforward f is present in some episodes"):
        ClEdmd(controller, measured=[0]).fit([trajs[0], without])


@pytest.mark.parametrize("alpha", [-1.0, float("nan"), "big"])
def test_bad_alpha(loop, alpha):
    controller, trajs = loop
    with pytest.raises(ValueError, match="alpha must be a non-negative number"):
        Edmd(alpha=alpha).fit(trajs)


def test_unknown_options(loop):
    controller, trajs = loop
    with pytest.raises(ValueError, match="unknown regularize 'both'"):
        ClEdmd(controller, measured=[0], regularize="both").fit(trajs)
    with pytest.raises(ValueError, match="unknown parameter 'alhpa'"):
        Edmd().set_params(alhpa=1.0)
    with pytest.raises(ValueError, match="not a LiftingFunction"):
        Edmd(lifting=["poly"]).fit(trajs)


def test_predict_before_fit_and_with_wrong_data(loop):
    controller, trajs = loop
    with pytest.raises(ValueError, match="not fitted"):
        Edmd().predict(trajs[0])
    model = Edmd(lifting=[Polynomial(2)]).fit(trajs)
    with pytest.raises(ValueError, match="has 1 states, the model 2"):
        model.predict(Trajectory(x=trajs[0].x[:, :1], u=trajs[0].u))
    with pytest.raises(ValueError, match="lacks signal 'u'"):
        model.predict(Trajectory(x=trajs[0].x))


def test_bad_state_space():
    with pytest.raises(ValueError, match="D must have shape"):
        DiscreteStateSpace([[1.0]], [[1.0]], [[1.0]], [[1.0, 2.0]], 0.1)
    with pytest.raises(ValueError, match="dt must be a positive"):
        DiscreteStateSpace([[1.0]], [[1.0]], [[1.0]], [[1.0]], 0.0)
    with pytest.raises(ValueError, match="A has non-finite"):
        DiscreteStateSpace([[np.inf]], [[1.0]], [[1.0]], [[1.0]], 0.1)


def test_arx_needs_its_input_signals(loop):
    controller, trajs = loop
    with pytest.raises(ValueError, match="needs signal 'f'"):
        Arx(inputs=("r", "f")).fit([Trajectory(x=trajs[0].x, r=trajs[0].r)])
