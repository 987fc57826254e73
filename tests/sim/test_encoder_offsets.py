"""The pendulum encoder's zero offset: a sensor parameter drawn per episode and logged."""

import math

import numpy as np
import pytest

from qube_koopman.daq.backends.sim import SimBackend
from qube_koopman.sim.pendulum import PendulumSimulator, SensorModel, ZeroOffsetDistribution, measure

COUNT = 2 * math.pi / 2048


def test_offset_shifts_the_measured_alpha_by_whole_counts_when_it_is_whole_counts():
    state = np.array([[0.1, 0.0, 0.0, 0.0], [0.0, 0.02, 0.0, 0.0]])
    plain = measure(state, SensorModel())
    shifted = measure(state, SensorModel(alpha_offset=3 * COUNT))
    np.testing.assert_allclose(shifted[:, 1] - plain[:, 1], 3 * COUNT, atol=1e-12)
    np.testing.assert_array_equal(shifted[:, 0], plain[:, 0])  # theta untouched


def test_per_tick_simulator_and_batched_measurement_agree_on_the_offset():
    sensor = SensorModel(alpha_offset=0.004)
    sim = PendulumSimulator(sensor=sensor)
    y = sim.reset((0.0, 0.0, 0.0, 0.0))
    assert y[1] == pytest.approx(measure(np.zeros(4), sensor)[1])
    assert abs(y[1] - 0.004) <= COUNT / 2


def test_bad_offsets_are_refused():
    with pytest.raises(ValueError, match="alpha_offset"):
        SensorModel(alpha_offset=float("nan"))
    with pytest.raises(ValueError, match="std"):
        ZeroOffsetDistribution(std=-1.0)
    with pytest.raises(TypeError, match="SensorModel"):
        PendulumSimulator().sensor = "not a sensor"


def test_each_episode_draws_its_own_offset_and_describes_it():
    backend = SimBackend(seed=3)
    offsets = []
    for _ in range(200):
        backend.start()
        offsets.append(backend.describe()["sensor"]["alpha_offset"])
        backend.stop()
    offsets = np.array(offsets)
    assert len(set(offsets)) == len(offsets)
    # The dataset's distribution by default (its mean alpha per episode): mean 0.0025, spread 0.001.
    assert offsets.mean() == pytest.approx(0.0025, abs=3 * 0.001 / math.sqrt(200))
    assert offsets.std() == pytest.approx(0.001, rel=0.2)
    assert backend.describe()["zero_offsets"] == {"mean": 0.0025, "std": 0.001}


def test_the_controller_balances_the_true_upright_not_the_measured_zero():
    # Measured alpha settles at the offset (the true pendulum is upright on average).
    from qube_koopman.core.controller import PdGains, pd_controller
    from qube_koopman.sim.pendulum import simulate_closed_loop

    ctrl = pd_controller(PdGains(kp_theta=6, kd_theta=1.8, kp_alpha=30, kd_alpha=2.5, tau=50))
    n = 4000
    refs = np.zeros((n, 2))
    # Without dry friction and dead zone (PendulumParameters.previous()): the calibrated twin's
    # friction lets the arm rest anywhere in a small band, so its equilibrium is not this point.
    from qube_koopman.sim.pendulum import PendulumParameters

    run = simulate_closed_loop(
        np.zeros(4),
        ctrl,
        refs,
        np.zeros(n),
        PendulumParameters.previous(),
        sensor=SensorModel(counts_per_rev=None, alpha_offset=0.01),
    )
    tail = slice(n // 2, None)
    assert np.mean(run.states[1:][tail, 1]) == pytest.approx(0.0, abs=1e-4)
    assert np.mean(run.measurements[tail, 1]) == pytest.approx(0.01, abs=1e-4)
    # and the arm moves to balance it: kp_theta (theta - r) = -kp_alpha * offset.
    assert np.mean(run.measurements[tail, 0]) == pytest.approx(-30 / 6 * 0.01, rel=0.05)
