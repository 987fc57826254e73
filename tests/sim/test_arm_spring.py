"""The arm's cable spring (PendulumParameters.Kr, theta_rest, cable_softening): analytic cases of the twin's physics."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from qube_koopman.sim.pendulum import PendulumParameters, PendulumSimulator, simulate
from qube_koopman.sim.pendulum.physics import dynamics, linearize_upright, total_energy

DT = 1 / 500
# No motor torque on the arm's motion (km = 0 removes the back-EMF), no friction, no dead zone, no delay;
# a linear spring (its softening is tested below).
FREE = replace(
    PendulumParameters(),
    km=0.0,
    Dr=0.0,
    Dp=0.0,
    Cr=0.0,
    dead_zone=0.0,
    delay=0.0,
    Kr=1e-3,
    theta_rest=0.05,
    cable_softening=0.0,
)


def test_the_arm_alone_oscillates_at_the_springs_natural_frequency():
    # A pendulum of negligible mass: the arm is a torsion oscillator, theta_rest + A cos(w t),
    # w = sqrt(Kr / J), J the arm's inertia about the motor axis.
    p = replace(FREE, mp=1e-12)
    J = p.Jr + p.Jh + p.mp * p.Lr**2
    w = math.sqrt(p.Kr / J)
    x = simulate([p.theta_rest + 0.1, 0.0, 0.0, 0.0], np.zeros(1000), p, DT)
    t = np.arange(1001) * DT
    np.testing.assert_allclose(x[:, 0], p.theta_rest + 0.1 * np.cos(w * t), atol=1e-7)


def test_a_constant_voltage_holds_the_arm_where_the_spring_balances_the_motor():
    # Pendulum hanging (alpha = pi, both joints damped so it settles within the 30 s, whatever the
    # calibrated defaults' damping): at rest the motor's torque km / Rm (V - dead_zone) equals the
    # spring's Kr (theta - theta_rest) (no dry friction, which would hold the arm anywhere within its
    # breakaway torque).
    p = replace(PendulumParameters(), Kr=8e-4, theta_rest=-0.1, Dr=1e-4, Dp=2e-4, Cr=0.0, cable_softening=0.0)
    volts = 0.4
    x = simulate([0.0, math.pi, 0.0, 0.0], np.full(15000, volts), p, DT)
    expected = p.theta_rest + p.km / p.Rm * (volts - p.dead_zone) / p.Kr
    assert x[-1, 0] == pytest.approx(expected, abs=1e-5)
    assert abs(x[-1, 2]) < 1e-5
    # A softening pull levels off at Kr / c: the motor holds the arm where Kr tanh(c x) / c is its torque,
    # x = atanh(c torque / Kr) / c, farther out than the linear spring's torque / Kr.
    # The voltage asks for 0.8 of the pull's limit (0.4 rad for a linear spring, 0.55 softened).
    soft, c = replace(p, cable_softening=4.0), 2.0
    torque = 0.8 * soft.Kr / c
    volts = soft.dead_zone + torque * soft.Rm / soft.km
    x = simulate([0.0, math.pi, 0.0, 0.0], np.full(15000, volts), soft, DT)
    assert x[-1, 0] - soft.theta_rest == pytest.approx(math.atanh(c * torque / soft.Kr) / c, abs=1e-5)
    assert x[-1, 0] - soft.theta_rest > 1.2 * torque / soft.Kr


@pytest.mark.parametrize("softening", [0.0, 6.0])
def test_energy_with_the_spring_is_conserved_without_losses(softening):
    p = replace(FREE, theta_rest=0.0, cable_softening=softening)
    x = simulate([0.2, 0.3, 0.5, -1.0], np.zeros(1000), p, DT)
    # The pendulum starts 0.3 rad off upright and falls: energy moves between arm, spring and pendulum.
    energy = total_energy(x, p)
    assert np.ptp(x[:, 1]) > 1.0
    assert np.max(np.abs(energy - energy[0])) < 1e-9 * 1e3 * abs(energy[0])


def test_the_per_tick_simulator_steps_as_the_batch_simulation():
    p = replace(PendulumParameters(), Kr=9e-4, theta_rest=0.02)
    volts = np.sin(np.arange(400) * 0.05)
    batch = simulate([0.1, 0.01, 0.0, 0.0], volts, p, DT)
    sim = PendulumSimulator(p, dt=DT)
    sim.reset((0.1, 0.01, 0.0, 0.0))
    for v in volts:
        sim.step(float(v))
    np.testing.assert_allclose(sim.state, batch[-1], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("softening", [0.0, 5.0])
def test_the_linearization_carries_the_springs_stiffness(softening):
    # The slope at rest is Kr whatever the softening.
    p = replace(PendulumParameters(), Kr=9e-4, theta_rest=0.3, cable_softening=softening)
    A, _ = linearize_upright(p)
    h = 1e-6
    # Finite differences of the dynamics in theta at the spring's rest angle, upright and at rest.
    column = (dynamics([p.theta_rest + h, 0, 0, 0], 0.0, p) - dynamics([p.theta_rest - h, 0, 0, 0], 0.0, p)) / (2 * h)
    np.testing.assert_allclose(A[:, 0], column, rtol=1e-6, atol=1e-9)
    assert A[2, 0] < 0 and A[3, 0] > 0  # the spring pulls the arm back and, through it, tips the pendulum
    no_spring, _ = linearize_upright(replace(p, Kr=0.0))
    np.testing.assert_array_equal(no_spring[:, 0], 0.0)


def test_a_negative_stiffness_or_softening_is_refused():
    with pytest.raises(ValueError, match="Kr"):
        PendulumParameters(Kr=-1e-4)
    with pytest.raises(ValueError, match="cable_softening"):
        PendulumParameters(cable_softening=-1.0)


@pytest.mark.parametrize(
    "gains, stiffness, softening",
    [((2.0, 2.0, 35.0, 3.0), 0.32, 0.0), ((6.0, 1.8, 30.0, 2.5), 0.14, 0.0), ((2.0, 2.0, 35.0, 3.0), 0.55, 5.2)],
)
def test_under_the_balancing_loop_the_spring_lowers_the_arms_stiffness(gains, stiffness, softening):
    # Balancing, the PD's arm channel pushes with kp_theta (theta - r) volts (its sign is the one that
    # tips the pendulum the right way); at rest, upright, the motor holds the spring's Kr theta, so the
    # arm settles at theta = kp_theta r / (kp_theta - K), K = Kr Rm / km in volts per radian: the spring
    # makes the arm overshoot its reference. With each recording day's cables, 19 % under the soft
    # controller (kp_theta 2, K 0.32 V/rad) against 2 % under the rig's (kp_theta 6, K 0.14 V/rad): why
    # the soft controller's arm wandered so much more than the twin's with one stiffness for both days.
    # A softening pull (c^2 = softening) balances kp_theta (theta - r) = K tanh(c theta) / c instead.
    from scipy.optimize import brentq

    from qube_koopman.core.controller import PdGains, pd_controller
    from qube_koopman.sim.pendulum import SensorModel, simulate_closed_loop

    kp_theta, kd_theta, kp_alpha, kd_alpha = gains
    base = replace(PendulumParameters(), Cr=0.0, dead_zone=0.0, delay=0.0, theta_rest=0.0, cable_softening=softening)
    p = replace(base, Kr=stiffness * base.km / base.Rm)
    controller = pd_controller(PdGains(kp_theta, kd_theta, kp_alpha, kd_alpha, 50.0))
    n, r = 8000, 0.2
    refs = np.zeros((n, 1, 2))
    refs[:, 0, 0] = r
    run = simulate_closed_loop(
        np.zeros((1, 4)), controller, refs, np.zeros((n, 1)), p, SensorModel(counts_per_rev=None)
    )
    settled = run.states[-1, 0]
    c = math.sqrt(softening)
    pull = (lambda x: stiffness * math.tanh(c * x) / c) if c else (lambda x: stiffness * x)
    expected = brentq(lambda x: kp_theta * (x - r) - pull(x), r, 2 * r)
    if not c:
        assert expected == pytest.approx(kp_theta * r / (kp_theta - stiffness), rel=1e-9)
    assert settled[0] == pytest.approx(expected, rel=1e-4)
    assert abs(settled[1]) < 1e-6 and abs(settled[2]) < 1e-6  # upright, at rest
