"""The rotary-pendulum model, encoders and per-tick simulator (sim.pendulum) against the QUBE-Servo 2's
encoders and the Quanser workbook's model."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from qube_koopman.core.controller import PdGains, pd_controller
from qube_koopman.sim.pendulum import (
    PendulumParameters,
    PendulumSimulator,
    SensorModel,
    dynamics,
    linear_model,
    linearize_upright,
    measure,
    rk4_step,
    simulate,
    total_energy,
)

#: The workbook's model with hardware-fitted damping (the defaults before calibration): no dry
#: friction, dead zone, hub inertia or delay, so the analytic checks below hold exactly.
P = PendulumParameters.previous()
COUNT = 2 * math.pi / 2048  # encoder resolution: 2048 counts per revolution


def test_previous_is_the_workbook_with_hardware_fitted_damping():
    assert (P.Rm, P.km, P.mr, P.Lr, P.mp, P.Lp, P.g) == (8.4, 0.042, 0.095, 0.085, 0.024, 0.129, 9.81)
    assert (P.Dr, P.Dp) == (2.7e-4, 5e-5)
    assert (P.Cr, P.dead_zone, P.Jh, P.delay) == (0.0, 0.0, 0.0, 0.0)
    assert P.Jr == pytest.approx(0.095 * 0.085**2 / 12) and P.Jp == pytest.approx(0.024 * 0.129**2 / 12)
    wb = PendulumParameters.workbook()
    assert (wb.Dr, wb.Dp) == (0.0015, 0.0005)
    assert dataclasses.replace(wb, Dr=P.Dr, Dp=P.Dp) == P


def test_defaults_are_the_calibrated_twin_with_the_workbook_masses():
    from qube_koopman.sim.pendulum.params_file import PLANTS, load_plant

    cal = PendulumParameters()
    assert cal == load_plant(PLANTS / "qube_20230828_20230915.toml").params  # digit for digit
    assert (cal.Rm, cal.mr, cal.Lr, cal.mp, cal.g) == (P.Rm, P.mr, P.Lr, P.mp, P.g)
    assert cal.Jh > 0 and cal.delay > 0 and cal.Cr > 0 and cal.dead_zone > 0 and cal.Kr > 0


def test_hub_inertia_adds_to_the_arm_rod():
    # Jh enters only the arm's inertia: Jh = Jr is the same plant as an arm rod twice as heavy,
    # and it slows the arm's response to a voltage (B[2] smaller), not the pendulum's gravity term.
    assert P.Jh == 0.0
    hub = dataclasses.replace(P, Jh=P.Jr)
    heavy = dataclasses.replace(P, mr=2 * P.mr)
    x = np.array([[0.1, 0.2, -1.0, 3.0], [0.0, -0.4, 2.0, -1.0]])
    np.testing.assert_allclose(dynamics(x, 1.5, hub), dynamics(x, 1.5, heavy), rtol=1e-12)
    assert np.all(np.abs(dynamics(x, 1.5, hub)[:, 2:] - dynamics(x, 1.5, P)[:, 2:]) > 1.0)
    with pytest.raises(ValueError, match="Jh"):
        dataclasses.replace(P, Jh=-1e-6)


@pytest.mark.parametrize(
    "changes, match",
    [
        (dict(Rm=0.0), "Rm"),
        (dict(Dr=-1e-4), "Dr"),
        (dict(mp=float("nan")), "mp"),
        (dict(km="0.04"), "km"),
        (dict(tilt_x=0.2), "tilt_x"),
        (dict(Cs=-1e-4), "Cs"),
        (dict(stribeck_speed=0.0), "stribeck_speed"),
    ],
)
def test_parameters_reject_bad_values(changes, match):
    with pytest.raises(ValueError, match=match):
        dataclasses.replace(P, **changes)


# --- linearization -----------------------------------------------------------------------------


def test_linearization_has_the_familiar_magnitudes():
    A, B = linearize_upright(P)
    # The Quanser workbook's linearization at upright: |A32| 149, |A42| 262, |B3| 50, |B4| 49 (1-based, rounded).
    assert abs(A[2, 1]) == pytest.approx(149, rel=0.01)
    assert abs(A[3, 1]) == pytest.approx(262, rel=0.01)
    assert abs(B[2, 0]) == pytest.approx(50, rel=0.01)
    assert abs(B[3, 0]) == pytest.approx(49, rel=0.01)
    # Signs of this frame: gravity tips the pendulum further (unstable) and
    # pushes the arm the other way; a positive voltage swings it back.
    assert A[3, 1] > 0 > A[2, 1] and B[2, 0] > 0 > B[3, 0]
    np.testing.assert_array_equal(A[:2], [[0, 0, 1, 0], [0, 0, 0, 1]])


#: A base tilted by a few mrad, as the rig's was on its recording days.
TILTED = dataclasses.replace(P, tilt_x=-5e-3, tilt_y=4e-3)
#: The calibrated twin with static friction beyond its Coulomb torque (and no dead zone, which the
#: linearization leaves out).
STICKY = dataclasses.replace(PendulumParameters(), dead_zone=0.0, Cs=8e-4, stribeck_speed=0.1)


@pytest.mark.parametrize("params", [P, TILTED, STICKY], ids=["level", "tilted", "static-friction"])
def test_linearization_is_the_jacobian_of_the_dynamics(params):
    # On a tilted base about its equilibrium: the arm at rest, the pendulum at its balance angle there.
    A, B = linearize_upright(params)
    rest = np.array([0.0, params.tilt_y, 0.0, 0.0])
    eps = 1e-6
    jac = np.empty((4, 5))
    for i in range(5):
        step = np.zeros(5)
        step[i] = eps
        plus, minus = rest + step[:4], rest - step[:4]
        jac[:, i] = (dynamics(plus, step[4], params) - dynamics(minus, -step[4], params)) / (2 * eps)
    # level: exact; tilted: to first order in the tilt (the terms left out are of the tilt's relative size, 4e-3)
    tolerance = 5e-3 if params.tilt_x or params.tilt_y else 1e-6
    np.testing.assert_allclose(jac, np.hstack([A, B]), rtol=tolerance, atol=1e-6)
    if params.tilt_x:
        assert A[3, 0] != 0.0 and A[2, 0] != 0.0  # the arm's angle moves the pendulum's balance


def test_on_a_tilted_base_gravity_pulls_the_pendulum_to_its_balance_angle_and_the_arm_downhill():
    from qube_koopman.sim.pendulum.physics import Coefficients

    free = dataclasses.replace(TILTED, Kr=0.0, Cr=0.0)
    k = Coefficients.of(free)
    for theta in (-1.0, 0.0, 0.4, 2.0):
        # at its balance angle gravity leaves the pendulum no torque: only the arm's motion moves it
        balance = free.tilt_x * math.sin(theta) + free.tilt_y * math.cos(theta)
        arm, pendulum = dynamics([theta, balance, 0.0, 0.0], 0.0, free)[2:]
        # (to first order in the tilt: what is left is of third order in the balance angle)
        assert abs(k.m12 * math.cos(balance) * arm + k.m22 * pendulum) < k.gravity * abs(balance) ** 3
        # ... and the arm's tip, on the slope, is pulled towards the low side
        assert abs(arm) > 1e-3 and np.sign(arm) == -np.sign(balance)
        level = dynamics([theta, balance, 0.0, 0.0], 0.0, dataclasses.replace(free, tilt_x=0.0, tilt_y=0.0))
        assert abs(k.m12 * math.cos(balance) * level[2] + k.m22 * level[3]) > 0.9 * k.gravity * abs(balance)
    # upright where the balance angle is zero (the arm across the slope) is an equilibrium of both
    across = math.atan2(-free.tilt_y, free.tilt_x)
    np.testing.assert_allclose(dynamics([across, 0.0, 0.0, 0.0], 0.0, free), 0.0, atol=1e-14)


def test_paper_controller_stabilizes_the_linear_model():
    # The rig's controller (its PD, backward Euler) on the ZOH-discretized linearization: closed
    # loop x+ = Ap x + Bp u, xc+ = Ac xc + Bc e, u = Cc xc + Dc e, e = -Cp x.
    plant = linear_model(P)
    ctrl = pd_controller(PdGains(6.0, 1.8, 30.0, 2.5, 50.0))
    top = np.hstack([plant.A - plant.B @ ctrl.D @ plant.C, plant.B @ ctrl.C])
    bottom = np.hstack([-ctrl.B @ plant.C, ctrl.A])
    radius = np.max(np.abs(np.linalg.eigvals(np.vstack([top, bottom]))))
    assert radius < 1.0
    # ... and the open-loop plant is unstable (an inverted pendulum).
    assert np.max(np.abs(np.linalg.eigvals(plant.A))) > 1.0


def test_linear_model_matches_small_nonlinear_motions():
    plant = linear_model(P)
    x0 = np.array([0.0, 1e-4, 0.0, 0.0])
    u = 1e-3 * np.sin(np.arange(50) / 5.0)
    nonlinear = simulate(x0, u, P)
    xl, yl = x0, []
    for uk in u:
        yl.append(plant.C @ xl)
        xl = plant.A @ xl + plant.B[:, 0] * uk
    np.testing.assert_allclose(nonlinear[:-1, :2], np.array(yl), atol=1e-9)


# --- behaviour of the nonlinear model ----------------------------------------------------------


def test_constant_1v_settles_at_the_back_emf_limited_speed():
    # Hanging down at rest, 1 V: steady state km V / Rm = (km^2 / Rm + Dr) w.
    x = simulate([0.0, math.pi, 0.0, 0.0], np.ones(2500), P)  # 5 s, ~10 time constants
    expected = (P.km / P.Rm) / (P.km**2 / P.Rm + P.Dr)
    assert expected == pytest.approx(10.4, abs=0.1)  # near 10 rad/s, not 35 (a reversed back-EMF sign gives 35)
    assert x[-1, 2] == pytest.approx(expected, rel=1e-3)
    assert np.ptp(x[-250:, 2]) < 1e-3
    assert abs(x[-1, 1] - math.pi) < 1e-3 and abs(x[-1, 3]) < 1e-3


def test_static_friction_holds_the_arm_against_a_torque_coulomb_friction_alone_would_yield_to():
    # Hanging down at rest, a voltage whose torque (km V / Rm = 1.3 Cr) is above the Coulomb torque but
    # below the breakaway one (Cr + Cs = 2 Cr). Without the static excess the arm runs off (0.30 rad/s
    # after a second, 0.18 rad); with it the arm only creeps, as far as tanh's smoothing of the friction's
    # sign over 0.05 rad/s lets it (measured 0.046 rad/s, 0.041 rad).
    twin = PendulumParameters()  # the calibrated twin's Coulomb torque
    free = dataclasses.replace(twin, dead_zone=0.0, Kr=0.0)  # the motor's torque alone against the friction
    sticky = dataclasses.replace(free, Cs=twin.Cr, stribeck_speed=0.1)
    volts = 1.3 * twin.Cr * twin.Rm / twin.km
    hanging = [0.0, math.pi, 0.0, 0.0]
    held = simulate(hanging, np.full(500, volts), sticky)
    slid = simulate(hanging, np.full(500, volts), free)
    assert abs(held[-1, 0]) < 0.05 and abs(held[-1, 2]) < 0.06
    assert abs(slid[-1, 0]) > 3 * abs(held[-1, 0]) and abs(slid[-1, 2]) > 5 * abs(held[-1, 2])
    # Once the torque is above the breakaway, the arm moves whether or not the excess is there.
    assert abs(simulate(hanging, np.full(500, 2.5 * volts), sticky)[-1, 2]) > 0.1


@pytest.mark.parametrize("params", [P, TILTED], ids=["level", "tilted"])
def test_energy_is_conserved_without_damping_or_input(params):
    # An amplifier at 0 V still brakes the arm through the back-EMF (km^2/Rm),
    # so the undamped case also takes the motor out (km = 0). On a tilted base the
    # pendulum's potential depends on the arm's angle: energy moves between them.
    free = dataclasses.replace(params, Dr=0.0, Dp=0.0, km=0.0, Cr=0.0)
    x = simulate([0.0, 0.3, 5.0, 0.0], np.zeros(5000), free)  # 10 s at 500 Hz
    # Large swings: through hanging down and back to near upright, fast.
    assert np.ptp(x[:, 1]) > 5.0 and np.max(np.abs(x[:, 3])) > 20.0
    energy = total_energy(x, free)
    scale = free.mp * free.g * free.Lp  # twice the pendulum's potential swing
    assert np.max(np.abs(energy - energy[0])) < 1e-6 * scale


def test_energy_balance_with_damping_and_input():
    # dE/dt = (km/Rm) V theta_dot - (km^2/Rm + Dr) theta_dot^2 - Dp alpha_dot^2:
    # checks the torque law, the back-EMF sign and both damping terms at once.
    p = PendulumParameters.workbook()
    dt = 1e-4
    t = np.arange(20_000) * dt
    volts = 3.0 * np.sin(2 * math.pi * 1.5 * t)
    x = simulate([0.0, 2.5, 0.0, 0.0], volts, p, dt=dt, n_substeps=1)

    def power(td, ad):
        return p.km / p.Rm * volts * td - (p.km**2 / p.Rm + p.Dr) * td**2 - p.Dp * ad**2

    trapezoids = 0.5 * (power(x[:-1, 2], x[:-1, 3]) + power(x[1:, 2], x[1:, 3])) * dt
    work = np.concatenate([[0.0], np.cumsum(trapezoids)])
    energy = total_energy(x, p)
    assert np.ptp(energy) > 1e-3
    np.testing.assert_allclose(energy - energy[0], work, rtol=0, atol=1e-7)


def test_more_substeps_converge():
    x0, volts = [0.0, 0.5, 0.0, 0.0], np.full(500, 2.0)
    fine = simulate(x0, volts, P, n_substeps=16)
    errors = [np.max(np.abs(simulate(x0, volts, P, n_substeps=n) - fine)) for n in (1, 2, 4)]
    assert errors[1] < errors[0] / 8 and errors[2] < errors[1] / 8  # fourth order: ~1/16 per halving
    assert errors[1] < 1e-5


@pytest.mark.parametrize(
    "changes",
    [
        {},
        dict(Cr=0.0),
        dict(Kr=0.0),
        dict(cable_softening=0.0),
        dict(dead_zone=0.3),
        dict(Cr=0.0, Kr=0.0, dead_zone=0.0),
        dict(tilt_x=-5e-3, tilt_y=4e-3),
        dict(tilt_y=4e-3),
        dict(Cs=8e-4, stribeck_speed=0.2),
        dict(Cr=0.0, Cs=8e-4),
    ],
)
def test_the_per_tick_integrator_is_the_general_one_bit_for_bit(changes):
    """The simulator's float integrator (its coefficients bound once) against the general one that
    batches and the calibration use: the same floats for every combination of the optional terms."""
    from qube_koopman.sim.pendulum.physics import Coefficients, _rk4, advance, scalar_rk4

    k = Coefficients.of(dataclasses.replace(PendulumParameters(), **changes))
    rk4 = scalar_rk4(k)
    rng = np.random.default_rng(7)
    for _ in range(300):
        x = tuple(float(v) for v in rng.normal(size=4) * [0.5, 0.3, 3.0, 5.0])
        volts = float(rng.normal() * 5.0)
        assert rk4(*x, volts, 1e-3, 2) == _rk4(*x, volts, 1e-3, 2, k, math.sin, math.cos)
        weights = (1.0, 0.4)  # a fractional delay: the previous command held into the second substep
        assert advance(x, -volts, volts, weights, 1e-3, k, math.sin, math.cos, rk4) == advance(
            x, -volts, volts, weights, 1e-3, k, math.sin, math.cos
        )


def test_batches_match_single_states():
    rng = np.random.default_rng(0)
    states = rng.normal(size=(3, 5, 4))
    volts = rng.normal(size=(3, 5))
    batch = rk4_step(states, volts, P)
    assert batch.shape == (3, 5, 4)
    single = rk4_step(states[1, 2], volts[1, 2], P)
    np.testing.assert_array_equal(batch[1, 2], single)
    assert dynamics(states, 0.0).shape == (3, 5, 4)
    trajectory = simulate(states[0], np.broadcast_to(volts[0], (3, 5)), P)
    np.testing.assert_array_equal(trajectory[1], rk4_step(states[0], volts[0], P))


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: dynamics(np.zeros(3), 0.0), "shape"),
        (lambda: rk4_step(np.zeros(4), 0.0, n_substeps=0), "n_substeps"),
        (lambda: rk4_step(np.zeros(4), 0.0, dt=-1.0), "dt"),
        (lambda: simulate(np.zeros(4), 1.0), "time axis"),
    ],
)
def test_model_functions_reject_bad_arguments(call, match):
    with pytest.raises(ValueError, match=match):
        call()


# --- encoders ----------------------------------------------------------------------------------


def test_encoder_quantizes_to_2048_counts_and_wraps_alpha():
    rng = np.random.default_rng(1)
    states = np.zeros((1000, 4))
    states[:, 0] = rng.uniform(-3, 3, 1000)
    states[:, 1] = rng.uniform(-12, 12, 1000)
    y = measure(states)
    counts = y / COUNT
    np.testing.assert_allclose(counts, np.round(counts), atol=1e-9)
    assert np.max(np.abs(y[:, 0] - states[:, 0])) <= COUNT / 2 + 1e-12
    assert np.all((y[:, 1] >= -math.pi) & (y[:, 1] < math.pi))
    wrapped_error = np.angle(np.exp(1j * (y[:, 1] - states[:, 1])))
    assert np.max(np.abs(wrapped_error)) <= COUNT / 2 + 1e-12
    # The upside-down pendulum reads -pi, like the rig's wrap to [-pi, pi).
    assert measure([0.0, math.pi, 0.0, 0.0])[1] == pytest.approx(-math.pi)


def test_exact_sensor_only_wraps():
    y = measure([[0.1234, 2 * math.pi + 0.5, 0.0, 0.0]], SensorModel(counts_per_rev=None))
    np.testing.assert_allclose(y, [[0.1234, 0.5]], atol=1e-15)


def test_noise_is_seeded_and_has_the_given_size():
    sensor = SensorModel(counts_per_rev=None, noise_std=0.01)
    states = np.zeros((20_000, 4))
    a = measure(states, sensor, np.random.default_rng(5))
    b = measure(states, sensor, np.random.default_rng(5))
    np.testing.assert_array_equal(a, b)
    assert a.std(axis=0) == pytest.approx([0.01, 0.01], rel=0.03)
    with pytest.raises(ValueError, match="rng"):
        measure(states, sensor)


@pytest.mark.parametrize("kwargs", [dict(counts_per_rev=2047), dict(counts_per_rev=0), dict(noise_std=-1.0)])
def test_sensor_rejects_bad_settings(kwargs):
    with pytest.raises(ValueError):
        SensorModel(**kwargs)


# --- the per-tick simulator --------------------------------------------------------------------


def test_simulator_follows_the_batch_integrator():
    sim = PendulumSimulator()
    x0 = [0.01, 0.05, -0.2, 0.3]
    assert sim.reset(x0) == tuple(measure(x0))
    volts = np.sin(np.arange(200) / 10.0)
    expected = simulate(x0, volts)
    measured = [sim.step(v) for v in volts]
    np.testing.assert_allclose(sim.state, expected[-1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(measured, measure(expected[1:]), atol=1e-12)
    assert sim.time == pytest.approx(200 * 0.002)
    assert sim.measurement == measured[-1]


def test_transport_delay_shifts_whole_samples_and_splits_fractions():
    dt = 0.002
    x0 = [0.0, 0.05, 0.0, 0.0]
    volts = 2.0 * np.sin(np.arange(300) * 0.07)
    plain = simulate(x0, volts, P)
    # Two whole samples: the commands arrive two samples late, zero volts before the first.
    late = simulate(x0, volts, dataclasses.replace(P, delay=2 * dt))
    np.testing.assert_allclose(late, simulate(x0, np.r_[0.0, 0.0, volts[:-2]], P), rtol=0, atol=1e-12)
    # 0.3 of a sample: each sample holds the previous command for its first 0.3 (fine reference integration).
    part = simulate(x0, volts, dataclasses.replace(P, delay=0.3 * dt), n_substeps=10)
    fine = np.repeat(volts, 10)
    fine[3:] = fine[:-3].copy()
    fine[:3] = 0.0
    np.testing.assert_allclose(part, simulate(x0, fine, P, dt=dt / 10, n_substeps=1)[::10], rtol=0, atol=1e-9)
    assert np.max(np.abs(part - plain)) > 1e-3
    # Continuous in the delay at zero, and the per-tick simulator and the closed loop agree with the batch.
    tiny = simulate(x0, volts, dataclasses.replace(P, delay=1e-9))
    assert np.max(np.abs(tiny - plain)) < 1e-5
    lagging = dataclasses.replace(P, delay=1.4 * dt)
    sim = PendulumSimulator(lagging, SensorModel(counts_per_rev=None))
    sim.reset(x0)
    for v in volts:
        sim.step(v)
    np.testing.assert_allclose(sim.state, simulate(x0, volts, lagging)[-1], rtol=0, atol=1e-12)
    from qube_koopman.core.lti import DiscreteStateSpace
    from qube_koopman.sim.pendulum import simulate_closed_loop

    silent = DiscreteStateSpace(np.zeros((1, 1)), np.zeros((1, 2)), np.zeros((1, 1)), np.zeros((1, 2)), dt)
    run = simulate_closed_loop(x0, silent, np.zeros((300, 2)), volts, lagging)  # plant input = feedforward
    np.testing.assert_allclose(run.states, simulate(x0, volts, lagging), rtol=0, atol=1e-12)


def test_simulator_saturates_at_the_amplifier_limit():
    a, b = PendulumSimulator(), PendulumSimulator(max_voltage=None)
    a.step(100.0)
    b.step(15.0)
    np.testing.assert_array_equal(a.state, b.state)


def test_simulator_noise_is_reproducible():
    runs = []
    for _ in range(2):
        sim = PendulumSimulator(sensor=SensorModel(noise_std=0.01), seed=3)
        sim.reset()
        runs.append([sim.step(0.0) for _ in range(5000)])  # spans several noise blocks
    assert runs[0] == runs[1]
    assert np.std(np.array(runs[0])[:, 0]) == pytest.approx(0.01, rel=0.1)


def test_simulator_balances_under_the_paper_controller():
    ctrl = pd_controller(PdGains(6.0, 1.8, 30.0, 2.5, 50.0))
    sim = PendulumSimulator()
    y = np.array(sim.reset([0.0, 0.05, 0.0, 0.0]))
    xc = np.zeros(2)
    for _ in range(1500):
        e = -y
        u = float(ctrl.C[0] @ xc + ctrl.D[0] @ e)
        xc = ctrl.A @ xc + ctrl.B @ e
        y = np.array(sim.step(np.clip(u, -10, 10)))
    assert abs(sim.state[1]) < 0.02 and abs(sim.state[0]) < 0.1


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: PendulumSimulator().reset([0, 0, 0]), "4 finite"),
        (lambda: PendulumSimulator().reset([0, 0, np.nan, 0]), "4 finite"),
        (lambda: PendulumSimulator().step(float("nan")), "voltage"),
        (lambda: PendulumSimulator(max_voltage=0.0), "max_voltage"),
        (lambda: PendulumSimulator(n_substeps=0), "n_substeps"),
    ],
)
def test_simulator_rejects_bad_arguments(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_a_new_period_keeps_the_commands_in_flight():
    # The emulated bridge steps the plant at its ticks' pace (periods a few cycles apart):
    # a period change must not drop the delayed commands (it did: the pendulum fell on the
    # emulated Uno once the calibrated twin's 1 ms delay became the default).
    dt = 0.002
    lagging = dataclasses.replace(P, delay=1.4 * dt)
    volts = 2.0 * np.sin(np.arange(400) * 0.07)
    steady, jittery = (PendulumSimulator(lagging, SensorModel(counts_per_rev=None)) for _ in range(2))
    for x in (steady, jittery):
        x.reset([0.0, 0.05, 0.0, 0.0])
    for k, v in enumerate(volts):
        jittery.set_period(dt * (1 + (1e-6 if k % 2 else -1e-6)))
        steady.step(v)
        jittery.step(v)
    np.testing.assert_allclose(jittery.state, steady.state, rtol=0, atol=1e-4)
    assert jittery.time == pytest.approx(steady.time, rel=1e-5)
    jittery.set_period(3 * dt)  # a longer period: fewer whole samples in flight, the newest kept
    assert jittery._commands == [float(volts[-1])]
    with pytest.raises(ValueError, match="dt"):
        jittery.set_period(-1.0)


def test_a_batch_of_pendulums_each_with_its_own_physics_and_delay_runs_as_each_alone():
    """simulate_closed_loop with one parameter set per episode (delays of whole and fractional samples,
    cable stiffness and damping differing): each episode as the batch of that pendulum alone gives it (exact
    angles: the encoders' rounding would turn a last-bit difference of the batch's arithmetic into counts)."""
    from dataclasses import replace

    from qube_koopman.core.controller import PdGains, pd_controller
    from qube_koopman.sim.pendulum import PendulumParameters, SensorModel, simulate_closed_loop

    controller = pd_controller(PdGains(2.0, 2.0, 35.0, 3.0, 50.0), 0.002, "backward-euler")
    base = PendulumParameters()
    params = [
        replace(base, delay=d, Kr=base.Kr * s, Dr=base.Dr * s)
        for d, s in ((1.0e-3, 0.5), (4.9e-3, 2.0), (2.0e-3, 1.0), (0.0, 1.5))
    ]
    n, rng = 800, np.random.default_rng(3)
    refs = np.zeros((n, 4, 2))
    refs[:, :, 0] = np.repeat(rng.uniform(-0.2, 0.2, (n // 200, 4)), 200, axis=0)
    ff = 0.1 * rng.standard_normal((n, 4))
    x0 = np.zeros((4, 4))
    x0[:, 1] = rng.normal(0, 0.005, 4)
    past = rng.normal(0, 0.5, (3, 4))
    exact = SensorModel(counts_per_rev=None)
    batch = simulate_closed_loop(x0, controller, refs, ff, params, exact, past_voltages=past)
    assert np.abs(batch.states[..., 1]).max() < 0.3  # every episode stays balanced
    for j, p in enumerate(params):
        alone = simulate_closed_loop(
            x0[j : j + 1], controller, refs[:, j : j + 1], ff[:, j : j + 1], p, exact, past_voltages=past[:, j : j + 1]
        )
        np.testing.assert_allclose(batch.states[:, j], alone.states[:, 0], rtol=0, atol=1e-11)
        np.testing.assert_allclose(batch.plant_input[:, j], alone.plant_input[:, 0], rtol=0, atol=1e-11)
    # The delay matters: the 4.9 ms pendulum's run is not the 1 ms one's.
    assert (
        np.abs(
            batch.states[:, 1]
            - simulate_closed_loop(
                x0[1:2],
                controller,
                refs[:, 1:2],
                ff[:, 1:2],
                replace(params[1], delay=1.0e-3),
                exact,
                past_voltages=past[:, 1:2],
            ).states[:, 0]
        ).max()
        > 1e-4
    )


def test_several_controllers_episodes_in_one_batch_run_as_each_controllers_batch_alone():
    """simulate_closed_loop with one controller per episode (three PD controllers, a filtered derivative
    each, their episodes interleaved and on session twins of their own): every controller's episodes
    are, bit for bit, what a batch of that controller's episodes alone gives (the probe sets rely on it:
    their cache holds what either way simulated)."""
    from dataclasses import replace

    from qube_koopman.core.controller import PdGains, pd_controller
    from qube_koopman.sim.pendulum import PendulumParameters, SensorModel, simulate_closed_loop

    gains = [(6.0, 1.8, 30.0, 2.5, 50.0), (2.0, 2.0, 35.0, 3.0, 50.0), (4.0, 1.0, 35.0, 3.0, 40.0)]
    controllers = [pd_controller(PdGains(*g), 0.002, "backward-euler") for g in gains]
    base = PendulumParameters()
    twins = [replace(base, delay=1.0e-3), replace(base, delay=2.9e-3, Kr=1.5 * base.Kr)]
    n, rng = 600, np.random.default_rng(5)
    order = [0, 1, 2, 0, 1, 2]  # controller of each episode, not consecutive
    refs = np.zeros((n, 6, 2))
    refs[:, :, 0] = np.repeat(rng.uniform(-0.1, 0.1, (n // 150, 6)), 150, axis=0)
    ff = 0.02 * rng.standard_normal((n, 6))
    x0 = np.zeros((6, 4))
    x0[:, 1] = rng.normal(0, 0.005, 6)
    zeros = rng.normal(0, 0.003, 6)
    params = [twins[j % 2] for j in range(6)]
    batch = simulate_closed_loop(
        x0, [controllers[i] for i in order], refs, ff, params, SensorModel(), alpha_offsets=zeros
    )
    assert np.abs(batch.states[..., 1]).max() < 0.3  # every episode stays balanced
    for i, controller in enumerate(controllers):
        mine = [j for j, c in enumerate(order) if c == i]
        alone = simulate_closed_loop(
            x0[mine],
            controller,
            refs[:, mine],
            ff[:, mine],
            [params[j] for j in mine],
            SensorModel(),
            alpha_offsets=zeros[mine],
        )
        for name in ("states", "measurements", "controller_states", "control_output", "plant_input"):
            np.testing.assert_array_equal(getattr(batch, name)[:, mine], getattr(alone, name), err_msg=name)
    # The controllers matter: the same episodes under the first controller alone differ.
    under_first = simulate_closed_loop(x0, controllers[0], refs, ff, params, SensorModel(), alpha_offsets=zeros)
    assert np.abs(under_first.plant_input[:, 1] - batch.plant_input[:, 1]).max() > 0.01
    with pytest.raises(ValueError, match="one per episode"):
        simulate_closed_loop(x0, controllers, refs, ff, params)
    with pytest.raises(ValueError, match="share their order"):
        simulate_closed_loop(
            x0[:2], [controllers[0], pd_controller(PdGains(*gains[0]), 0.004, "backward-euler")], refs[:, :2], ff[:, :2]
        )


def test_one_pendulum_per_batch_element_is_each_simulated_alone():
    # What a multiple-shooting fit with setups runs: segments of different cables and delays (whole
    # and fractional samples apart) in one batch, each as if simulated on its own.
    from dataclasses import replace

    pendulums = [
        replace(PendulumParameters(), Kr=kr, delay=d) for kr, d in ((7e-4, 1e-3), (1.8e-3, 4.3e-3), (1e-3, 0.0))
    ]
    rng = np.random.default_rng(3)
    state0 = np.column_stack([rng.normal(0, 0.05, 3), rng.normal(0, 0.02, 3), np.zeros((3, 2))])
    volts = rng.normal(0, 1.0, (200, 3))
    past = rng.normal(0, 1.0, (4, 3))
    batch = simulate(state0, volts, pendulums, past_voltages=past)
    for i, p in enumerate(pendulums):
        alone = simulate(state0[i], volts[:, i], p, past_voltages=past[:, i])
        np.testing.assert_allclose(batch[:, i], alone, rtol=1e-12, atol=1e-14)
    with pytest.raises(ValueError, match="3 parameter sets for a batch of \\(2,\\)"):
        simulate(state0[:2], volts[:, :2], pendulums)
