"""The cables' relaxation in the closed-loop simulation: a torque the arm's motion drives, lagging it."""

from __future__ import annotations

import numpy as np
import pytest

from _episodes import QUBE_PD
from qube_koopman.sim.pendulum import CableRelaxation, PendulumParameters, SensorModel, simulate_closed_loop

DT = 1 / 500


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"fast": 0.1, "relaxing": -0.1, "time_constant": 1.0}, "at least 0"),
        ({"fast": 0.1, "relaxing": 0.1, "time_constant": 0.0}, "positive"),
        ({"fast": float("nan"), "relaxing": 0.1, "time_constant": 1.0}, "finite"),
        ({"fast": 0.1, "relaxing": 0.1, "time_constant": float("inf")}, "finite"),
        ({"fast": True, "relaxing": 0.1, "time_constant": 1.0}, "finite number"),
    ],
)
def test_bad_values_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        CableRelaxation(**kwargs)


def test_the_remembered_angle_is_the_element_stepped_sample_by_sample():
    # Two ways: the filter over a whole sequence, and the element's update one sample at a time.
    r = CableRelaxation(0.3, 0.4, 0.7)
    theta = np.cumsum(np.random.default_rng(0).normal(0, 0.01, 3000))
    stepped = [theta[0]]
    for value in theta[:-1]:
        stepped.append(r.then(stepped[-1], value, DT))
    np.testing.assert_allclose(r.remembered(theta, DT), stepped, rtol=0, atol=1e-12)
    both = r.remembered(np.column_stack([theta, -theta]), DT)  # along the first axis, column by column
    np.testing.assert_allclose(both[:, 1], -np.asarray(stepped), rtol=0, atol=1e-12)
    held = np.full(2000, 0.5)
    assert r.torque(held[-1], r.remembered(held, DT)[-1]) == pytest.approx(0.5 * (0.4 - 0.3))  # relaxed from the start


def _run(relaxation, n=2, steps=1000):
    rng = np.random.default_rng(3)
    ff = np.repeat(rng.choice([-0.4, 0.4], (steps // 100 + 1, n)), 100, axis=0)[:steps]
    x0 = np.column_stack([np.full(n, 0.1), np.zeros(n), np.zeros((n, 2))])
    return simulate_closed_loop(
        x0, QUBE_PD, np.zeros((steps, n, 2)), ff, PendulumParameters(), SensorModel(), relaxation=relaxation
    )


def test_a_relaxation_of_nothing_is_the_arithmetic_without_one():
    plain, nothing = _run(None), _run(CableRelaxation(0.0, 0.0, 1.0))
    assert np.array_equal(plain.states, nothing.states) and np.array_equal(plain.plant_input, nothing.plant_input)


def test_one_relaxation_per_episode_runs_each_episode_as_alone():
    r = CableRelaxation(0.3, 0.4, 1.0)
    mixed, with_it, without = _run([r, None]), _run(r), _run(None)
    np.testing.assert_allclose(mixed.states[:, 0], with_it.states[:, 0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(mixed.states[:, 1], without.states[:, 1], rtol=0, atol=1e-12)
    assert not np.allclose(with_it.states[:, 0, 0], without.states[:, 0, 0], atol=1e-4)  # it does act on the arm
    with pytest.raises(ValueError, match="one per episode"):
        _run([r, r, r])


def test_the_arm_settles_where_the_relaxed_stiffness_puts_it():
    # A constant push on the arm (feedforward 1 V): held still, the cables' extra stiffness is
    # fast - relaxing. Softer when relaxed (relaxing > fast), the arm sits further out than
    # without, stiffer (relaxing < fast) nearer; and the early excursion follows the fast stiffness.
    steps = 5000
    x0 = np.zeros((3, 4))
    runs = simulate_closed_loop(
        x0,
        QUBE_PD,
        np.zeros((steps, 3, 2)),
        np.ones((steps, 3)),
        PendulumParameters(),
        SensorModel(),
        relaxation=[None, CableRelaxation(0.1, 0.3, 1.0), CableRelaxation(0.3, 0.1, 1.0)],
    )
    final = runs.states[-500:, :, 0].mean(axis=0)
    assert final[1] > final[0] > final[2]


def test_the_per_tick_twin_steps_the_relaxation_as_the_batch_simulation_does():
    # qube-run's twin (one sample at a time, floats) against the closed-loop batch (arrays): the same
    # open-loop voltages, the same relaxation, the same states to rounding.
    from qube_koopman.sim.pendulum import PendulumSimulator

    r = CableRelaxation(0.3, 0.4, 0.5)
    u = np.repeat(np.random.default_rng(1).choice([-1.0, 1.0], 40), 25)
    twin = PendulumSimulator(PendulumParameters(), SensorModel(counts_per_rev=None), relaxation=r)
    twin.reset((0.05, 0.0, 0.0, 0.0))
    per_tick = [twin.state.copy()]
    for v in u:
        twin.step(v)
        per_tick.append(twin.state.copy())
    plain = PendulumSimulator(PendulumParameters(), SensorModel(counts_per_rev=None))
    plain.reset((0.05, 0.0, 0.0, 0.0))
    for v in u:
        plain.step(v)
    # The batch closed loop with a controller that passes the feedforward through (u = ff).
    from qube_koopman.core.lti import DiscreteStateSpace

    through = DiscreteStateSpace(np.zeros((1, 1)), np.zeros((1, 3)), np.zeros((1, 1)), np.array([[0.0, 0.0, 0.0]]), DT)
    batch = simulate_closed_loop(
        np.array([[0.05, 0.0, 0.0, 0.0]]),
        through,
        np.zeros((len(u), 1, 2)),
        u[:, None],
        PendulumParameters(),
        SensorModel(counts_per_rev=None),
        max_voltage=15.0,
        relaxation=r,
    )
    np.testing.assert_allclose(np.array(per_tick), batch.states[:, 0], rtol=0, atol=1e-9)
    assert abs(plain.state[0] - per_tick[-1][0]) > 1e-3  # and it acts
