"""Replaying the 48 real episodes through the simulated pendulum and the paper's controller.

Choice of start: each episode starts at sample 500 (after the hand-raising
second the paper drops) from the real state there: the measured angles,
rates from a Savitzky-Golay derivative of the measured angles, and the
controller state the rig had (controller run from zero at t = 0 on the real
tracking errors). Starting at t = 0 instead would need the
velocities the hand left the pendulum with, which the data does not show,
and would replay the saturated derivative kick. From sample 500 on, the
loop is closed on the simulated encoders only: the real data contributes the
references and feedforward.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from _qube_csv import load_episode
from scipy.signal import savgol_filter

from qube_koopman.core.controller import load_pd_gains, pd_controller
from qube_koopman.daq.episode import REFERENCE_SIGNALS, STATE_SIGNALS, stack_signals
from qube_koopman.core.lti import replay_controller
from qube_koopman.sim.pendulum import PendulumParameters, simulate_closed_loop

START = 500
DT = 1.0 / 500.0
COUNT = 2 * math.pi / 2048

pytestmark = [pytest.mark.dataset]


@pytest.fixture(scope="module")
def real(qube_csv_files):
    """All episodes stacked, time first: (10000, 48[, 2])."""
    episodes = [load_episode(path) for path in qube_csv_files]
    stack = {name: np.stack([e[name] for e in episodes], axis=1) for name in episodes[0]}
    stack["r"] = stack_signals(stack, REFERENCE_SIGNALS)
    stack["y"] = stack_signals(stack, STATE_SIGNALS)
    return stack


@pytest.fixture(scope="module")
def controller(qube_dataset):
    return pd_controller(load_pd_gains(qube_dataset / "controller.toml"))


def replay(real, controller, params):
    r, y = real["r"][: START + 1], real["y"][: START + 1]
    controller_state = np.stack([replay_controller(controller, r[:, i], y[:, i])[0][START] for i in range(r.shape[1])])
    rates = savgol_filter(real["y"][START - 10 : START + 11], 21, 2, deriv=1, delta=DT, axis=0)[10]
    state0 = np.concatenate([real["y"][START], rates], axis=-1)
    return simulate_closed_loop(
        state0, controller, real["r"][START:], real["feedforward"][START:], params, controller_state0=controller_state
    )


def balanced(run):
    """Per episode: within the rig's safety limits (|theta| < pi/2, |alpha| < pi/4) throughout."""
    peak = np.max(np.abs(run.measurements), axis=0)
    return (peak[..., 0] < math.pi / 2) & (peak[..., 1] < math.pi / 4)


def test_real_measurements_are_on_the_encoder_grid(real):
    # The sensor model's premise: 2048 counts per revolution on both angles.
    counts = real["y"] / COUNT
    np.testing.assert_allclose(counts, np.round(counts), rtol=0, atol=1e-6)


def test_controller_state_reproduces_the_logged_output(real, controller):
    # The starting controller state is only right if it reproduces the rig's output.
    _, u = replay_controller(controller, real["r"][:, 0], real["y"][:, 0])
    np.testing.assert_allclose(u[:, 0], real["control_output"][:, 0], rtol=0, atol=1e-9)


@pytest.mark.slow
def test_replay_keeps_all_48_balanced_with_realistic_spread(real, controller):
    run = replay(real, controller, PendulumParameters())
    assert balanced(run).all(), f"fell: episodes {np.flatnonzero(~balanced(run)).tolist()}"
    ratio = run.measurements.std(axis=0) / real["y"][START:].std(axis=0)  # (48, 2)
    print(
        f"replay std ratio sim/real: theta {ratio[:, 0].min():.3f}..{ratio[:, 0].max():.3f}, "
        f"alpha {ratio[:, 1].min():.3f}..{ratio[:, 1].max():.3f}"
    )
    assert np.all((ratio > 0.5) & (ratio < 2.0)), ratio
    # The simulated loop applies what the controller asked for, clipped like the rig.
    np.testing.assert_array_equal(run.plant_input, np.clip(run.control_output + real["feedforward"][START:], -10, 10))


@pytest.mark.slow
def test_replay_tells_damping_values_apart(real, controller):
    # With the workbook's damping (Dr 0.0015, Dp 0.0005) the replayed episodes fall; the test
    # above would catch a model as wrong as that.
    run = replay(real, controller, PendulumParameters.workbook())
    assert not balanced(run).all()
