"""The simulator's forward sensitivities (sim.pendulum.sensitivity) against differences of its simulation."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from qube_koopman.sim.pendulum import PendulumParameters, simulate
from qube_koopman.sim.pendulum.physics import Coefficients
from qube_koopman.sim.pendulum.sensitivity import FIELDS, Directions, simulate_tangents

DT = 1 / 500
#: Every optional term on: Coulomb friction and a static excess over it, a dead zone the voltage crosses, a
#: fractional delay (1.6 samples), the cables' levelling pull away from the encoder's zero, a tilted base.
PARAMS = replace(
    PendulumParameters(),
    Cr=4e-4,
    dead_zone=0.2,
    delay=0.0032,
    Kr=2e-3,
    cable_softening=4.0,
    theta_rest=0.05,
    Dp=3e-5,
    tilt_x=-5e-3,
    tilt_y=4e-3,
    Cs=8e-4,
    stribeck_speed=0.5,
)


def _case(n_seg: int = 6, n_steps: int = 80):
    rng = np.random.default_rng(3)
    state0 = np.column_stack([rng.normal(0, 0.3, n_seg), rng.normal(0, 0.05, n_seg), rng.normal(0, 1, (n_seg, 2))])
    voltages = rng.normal(0, 1.0, (n_steps, n_seg))
    past = rng.normal(0, 1.0, (6, n_seg))
    return state0, voltages, past


def _differences(state0, voltages, past, params_of, step=1e-6):
    """Forward difference of the angles of ``simulate`` as ``params_of(h)`` and the state move by ``h``."""
    (s0, p0), (s1, p1) = params_of(0.0), params_of(step)
    base = simulate(state0 + s0, voltages, p0, DT, past_voltages=past)[..., :2]
    return (simulate(state0 + s1, voltages, p1, DT, past_voltages=past)[..., :2] - base) / step


def _row(p: PendulumParameters) -> np.ndarray:
    k = Coefficients.of(p)._asdict()
    k["cable_softening"] = p.cable_softening
    return np.array([k[name] for name in FIELDS])


@pytest.mark.parametrize(
    "name",
    [
        "km",
        "Lp",
        "Jh",
        "Cr",
        "dead_zone",
        "Kr",
        "cable_softening",
        "coulomb_speed",
        "tilt_x",
        "tilt_y",
        "Cs",
        "stribeck_speed",
    ],
)
def test_each_parameters_tangent_is_the_simulations_difference(name):
    state0, voltages, past = _case()
    value = getattr(PARAMS, name)
    step = 1e-6 * value
    moved = replace(PARAMS, **{name: value + step})
    directions = Directions(np.zeros((1, 4)), ((_row(moved) - _row(PARAMS)) / step)[None], np.zeros(1))
    angles, tangents = simulate_tangents(state0, voltages, PARAMS, directions, DT, past_voltages=past)
    # The same trajectory (its own arithmetic, so to rounding)
    np.testing.assert_allclose(
        angles, simulate(state0, voltages, PARAMS, DT, past_voltages=past)[..., :2], rtol=0, atol=1e-12
    )
    expected = _differences(state0, voltages, past, lambda h: (0.0, replace(PARAMS, **{name: value + h * value})))
    expected /= value  # per unit of the parameter (the step was relative)
    assert np.abs(expected).max() > 0  # the parameter moves the angles
    np.testing.assert_allclose(tangents[:, 0], expected, rtol=0, atol=2e-5 * np.abs(expected).max())


def test_state_and_delay_tangents_and_a_mask_that_keeps_a_direction_to_some_segments():
    state0, voltages, past = _case()
    n_seg = state0.shape[0]
    mask = np.ones((6, n_seg))
    mask[5, ::2] = 0.0  # the delay's direction moves the odd segments only
    delay = np.zeros(6)
    delay[4] = delay[5] = 1.0
    directions = Directions(np.vstack([np.eye(4), np.zeros((2, 4))]), np.zeros((6, len(FIELDS))), delay, mask)
    _, tangents = simulate_tangents(state0, voltages, PARAMS, directions, DT, past_voltages=past)
    for j in range(4):
        unit = np.eye(4)[j]
        expected = _differences(state0, voltages, past, lambda h, unit=unit: (h * unit, PARAMS))
        np.testing.assert_allclose(tangents[:, j], expected, rtol=0, atol=2e-5 * np.abs(expected).max())
    expected = _differences(state0, voltages, past, lambda h: (0.0, replace(PARAMS, delay=PARAMS.delay + h)), 1e-9)
    np.testing.assert_allclose(tangents[:, 4], expected, rtol=0, atol=1e-4 * np.abs(expected).max())
    np.testing.assert_array_equal(tangents[:, 5, ::2], 0.0)
    np.testing.assert_array_equal(tangents[:, 5, 1::2], tangents[:, 4, 1::2])


def test_a_known_load_moves_the_trajectory_and_its_tangents_as_the_simulation_with_it():
    # A known torque on the arm (volts past the dead zone, not delayed): the tangents are the differences of
    # the simulation under the same load, for a parameter (km scales the load's torque too) and the state.
    state0, voltages, past = _case()
    loads = np.random.default_rng(4).normal(0, 0.5, voltages.shape)
    step = 1e-6 * PARAMS.km
    moved = replace(PARAMS, km=PARAMS.km + step)
    directions = Directions(
        np.vstack([np.zeros((1, 4)), np.eye(4)[:1]]),
        np.vstack([(_row(moved) - _row(PARAMS)) / step, np.zeros(len(FIELDS))]),
        np.zeros(2),
    )
    angles, tangents = simulate_tangents(state0, voltages, PARAMS, directions, DT, past_voltages=past, loads=loads)
    with_load = simulate(state0, voltages, PARAMS, DT, past_voltages=past, loads=loads)[..., :2]
    np.testing.assert_allclose(angles, with_load, rtol=0, atol=1e-12)
    assert np.abs(with_load - simulate(state0, voltages, PARAMS, DT, past_voltages=past)[..., :2]).max() > 1e-3

    def loaded(h, which):
        p = replace(PARAMS, km=PARAMS.km * (1 + h)) if which == "km" else PARAMS
        s = np.eye(4)[0] * h if which == "theta" else 0.0
        return simulate(state0 + s, voltages, p, DT, past_voltages=past, loads=loads)[..., :2]

    for j, which in enumerate(("km", "theta")):
        expected = (loaded(1e-6, which) - loaded(0.0, which)) / 1e-6
        if which == "km":
            expected /= PARAMS.km
        np.testing.assert_allclose(tangents[:, j], expected, rtol=0, atol=2e-5 * np.abs(expected).max())


def test_a_load_is_the_same_voltage_past_a_zero_dead_zone_without_delay():
    # With no dead zone and no delay, a load of d volts at the motor is the command raised by d.
    state0, voltages, _ = _case()
    plain = replace(PARAMS, dead_zone=0.0, delay=0.0)
    loads = np.random.default_rng(5).normal(0, 0.5, voltages.shape)
    np.testing.assert_allclose(
        simulate(state0, voltages, plain, DT, loads=loads),
        simulate(state0, voltages + loads, plain, DT),
        rtol=0,
        atol=1e-10,
    )
    with pytest.raises(ValueError, match="one row per sample"):
        simulate(state0, voltages, plain, DT, loads=loads[:-1])
