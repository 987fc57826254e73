"""Analytic test systems: linear plants in closed loop with known controllers.

With identity lifting and noise-free data their Koopman matrices are known
exactly (the plant's own A and B), which makes them ground truth for EDMD
and CL EDMD.
"""

from __future__ import annotations

import numpy as np
from scipy import linalg

from qube_koopman.identify import Trajectory
from qube_koopman.core.lti import DiscreteStateSpace


def mass_spring_damper(dt: float = 0.01, m: float = 1.0, c: float = 0.4, k: float = 2.0):
    """ZOH-discretized mass-spring-damper, state (position, velocity), input force."""
    Ac = np.array([[0.0, 1.0], [-k / m, -c / m]])
    Bc = np.array([[0.0], [1.0 / m]])
    M = linalg.expm(np.block([[Ac, Bc], [np.zeros((1, 3))]]) * dt)
    return M[:2, :2], M[:2, 2:]


def pid_position_controller(dt: float = 0.01) -> DiscreteStateSpace:
    """PID with a filtered derivative on the position error (2 states), backward Euler.

    ``K(s) = 5 + 2/s + s 20/(s + 20)``; with :func:`mass_spring_damper` the
    loop is stable (checked in :func:`closed_loop_trajectories`).
    """
    import control

    from qube_koopman.core.controller import discretize_channels

    s = control.tf("s")
    return discretize_channels([5 + 2 / s + 20 * s / (s + 20)], dt, "backward-euler")


def simulate_loop(A_p, B_p, controller: DiscreteStateSpace, measured, r, f, w=None):
    """Run plant + controller; returns x, u, xc (x includes all plant states).

    ``w`` is optional process noise added to the plant state update.
    """
    n = r.shape[0]
    n_p = A_p.shape[0]
    x = np.zeros((n, n_p))
    xc = np.zeros((n, controller.n_states))
    u = np.zeros((n, B_p.shape[1]))
    state, cstate = np.zeros(n_p), np.zeros(controller.n_states)
    sees_f = controller.n_inputs > len(measured)  # a controller that also takes the feedforward
    for k in range(n):
        x[k], xc[k] = state, cstate
        e = r[k] - state[measured]
        if sees_f:
            e = np.concatenate([e, f[k]])
        u[k] = controller.C @ cstate + controller.D @ e + f[k]
        cstate = controller.A @ cstate + controller.B @ e
        state = A_p @ state + B_p @ u[k] + (0 if w is None else w[k])
    return x, u, xc


def prbs(rng, n, n_channels, amplitude, dwell=(20, 80)):
    """Random binary levels with random dwell, one column per channel."""
    cols = []
    for _ in range(n_channels):
        dwells = rng.integers(*dwell, size=n // dwell[0] + 1)
        levels = amplitude * np.where(np.arange(dwells.size) % 2 == 0, 1.0, -1.0) * rng.choice([-1, 1])
        cols.append(np.repeat(levels, dwells)[:n])
    return np.column_stack(cols)


def closed_loop_trajectories(
    A_p, B_p, controller, measured, n_episodes=4, n=400, seed=0, process_noise=0.0, feedforward=True
):
    """Episodes of the loop with PRBS references and feedforward."""
    from qube_koopman.identify import closed_loop_matrices, output_selection

    A_f, _ = closed_loop_matrices(A_p, B_p, controller, output_selection(A_p.shape[0], measured), controller.n_outputs)
    if max(abs(np.linalg.eigvals(A_f))) >= 1:
        raise ValueError("this test loop is unstable; pick other gains")
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_episodes):
        r = prbs(rng, n, len(measured), 1.0)
        f = 0.3 * rng.standard_normal((n, controller.n_outputs)) if feedforward else np.zeros((n, controller.n_outputs))
        w = process_noise * rng.standard_normal((n, A_p.shape[0])) if process_noise else None
        x, u, xc = simulate_loop(A_p, B_p, controller, measured, r, f, w)
        out.append(Trajectory(x=x, u=u, r=r, f=f if feedforward else None, xc=xc, name=f"ep{i}", dt=controller.dt))
    return out
