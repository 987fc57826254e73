"""The swing-up (daq.swing_up): the energy controller, the supervisor's swing-up limits, the phase."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from qube_koopman.daq.swing_up import EnergyController
from qube_koopman.sim.pendulum import PendulumParameters, dynamics, total_energy

PARAMS = PendulumParameters()


def test_energy_is_the_models_pendulum_energy():
    """Upright at rest E0 = mp Lp g / 2, hanging at rest -E0; and at any (alpha, alpha_dot) with the arm
    at rest at its zero, the model's total energy (kinetic with the full inertia matrix, the spring
    unstretched)."""
    ctrl = EnergyController(PARAMS)
    e0 = PARAMS.mp * PARAMS.Lp * PARAMS.g / 2.0
    assert ctrl.reference_energy == pytest.approx(e0, rel=1e-15)
    assert ctrl.energy(0.0, 0.0) == pytest.approx(e0, rel=1e-15)
    assert ctrl.energy(math.pi, 0.0) == pytest.approx(-e0, rel=1e-15)
    # The workbook's pendulum: 0.024 kg, 0.129 m -> 0.0151850 J (worked by hand: 0.024 * 0.129 * 9.81 / 2).
    assert EnergyController(PendulumParameters.workbook()).reference_energy == pytest.approx(0.01518588, rel=1e-6)
    rng = np.random.default_rng(0)
    for alpha, alpha_dot in zip(rng.uniform(-math.pi, math.pi, 50), rng.uniform(-20, 20, 50)):
        state = [PARAMS.theta_rest, alpha, 0.0, alpha_dot]
        assert ctrl.energy(alpha, alpha_dot) == pytest.approx(float(total_energy(state, PARAMS)), rel=1e-12, abs=1e-15)


def _pendulum_energy_rate(state, volts, params=PARAMS) -> float:
    """dE/dt of the pendulum's energy along the model's own equations under ``volts``."""
    _, alpha, _, alpha_dot = state
    alpha_ddot = dynamics(state, volts, params)[3]
    inertia = params.Jp + params.mp * params.Lp**2 / 4.0
    return inertia * alpha_dot * alpha_ddot - params.mp * params.Lp * params.g / 2.0 * math.sin(alpha) * alpha_dot


@pytest.mark.parametrize("params", [PARAMS, PendulumParameters.workbook()], ids=["twin", "workbook"])
def test_energy_controller_pumps_energy_towards_the_upright(params):
    """With the arm at rest at its zero (the centering term then asks nothing), the voltage the
    controller gives makes the model's pendulum energy rise while it is below E0 and fall above,
    at the rate the acceleration it asks for predicts: -(mp Lp Lr / 2) a alpha_dot cos(alpha), less
    what the pendulum's own friction takes (Dp alpha_dot^2: none in the twin)."""
    ctrl = EnergyController(params, energy_margin=0.0)
    rng = np.random.default_rng(1)
    below = above = 0
    for alpha, alpha_dot in zip(rng.uniform(-math.pi, math.pi, 400), rng.uniform(-15, 15, 400)):
        state = np.array([params.theta_rest, alpha, 0.0, alpha_dot])
        volts = ctrl.voltage(*state)
        assert abs(volts) <= 10.0  # inside the clamp at this saturation: the rate is the one asked for
        rate = _pendulum_energy_rate(state, volts, params)
        a = ctrl.acceleration(*state)
        friction = params.Dp * alpha_dot**2
        pumped = -(params.mp * params.Lp * params.Lr / 2.0) * a * alpha_dot * math.cos(alpha)
        assert rate == pytest.approx(pumped - friction, rel=1e-6, abs=1e-12)
        if ctrl.energy(alpha, alpha_dot) < ctrl.reference_energy:
            below += 1
            assert rate + friction >= 0.0
        else:
            above += 1
            assert rate + friction <= 0.0
    assert below > 100 and above > 50


def test_energy_controller_centers_the_arm_and_kicks_a_pendulum_at_rest():
    """Hanging at rest (sign(0) taken as +1) it pushes; with the pendulum upright at rest it only
    centres the arm: the acceleration is -kp theta - kd theta_dot."""
    ctrl = EnergyController(PARAMS)
    assert ctrl.acceleration(0.0, math.pi, 0.0, 0.0) != 0.0
    still = replace(ctrl, energy_margin=0.0)
    assert still.acceleration(0.3, 0.0, -0.5, 0.0) == pytest.approx(
        -still.centering_kp * 0.3 + still.centering_kd * 0.5
    )
