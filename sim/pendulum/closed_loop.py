"""Batches of closed-loop episodes: the pendulum, its encoders and a linear controller.

Vectorized over episodes: every step advances the whole batch at once, so
replaying the dataset's 48 episodes costs one Python loop over time, not 48.
The loop does what the rig's did each tick: read the encoders, feed the
tracking error to the controller, add the feedforward, clip, hold the voltage.

Why it is not ``daq.loop``: that loop runs one episode through a backend tick by tick, as on
the rig (pacing, safety, logging, any controller kind); this one steps the twin's nonlinear
physics for many episodes at once with a linear controller, for calibration and replays where
nothing is logged and nothing waits. ``identify.models.simulate`` predicts with identified
linear models, not with this physics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from qube_koopman.core.lti import DiscreteStateSpace, spectral_radius, with_output_delay
from qube_koopman.sim.pendulum.physics import (
    DEFAULT_SUBSTEPS,
    PendulumParameters,
    advance,
    array_rk4,
    as_states,
    check_timing,
    coefficients_and_hold,
    linear_model,
)
from qube_koopman.sim.pendulum.relaxation import CableRelaxation, relaxation_torque, relaxed
from qube_koopman.sim.pendulum.sensor import SensorModel, measure

__all__ = ["ClosedLoopRun", "simulate_closed_loop", "linear_loop_radius"]


@dataclass(frozen=True, eq=False)
class ClosedLoopRun:
    """Result of :func:`simulate_closed_loop`; time is the first axis of every array.

    Parameters
    ----------
    states : ndarray of shape (n_steps + 1, ..., 4)
        True plant states, starting with the initial one.
    measurements : ndarray of shape (n_steps, ..., 2)
        Encoder readings (theta, alpha) the controller saw at each step.
    controller_states : ndarray of shape (n_steps, ..., n_c)
        Controller state at each step, before its update.
    control_output : ndarray of shape (n_steps, ...)
        Controller output ``C xc + D (r - y)`` (V), before feedforward.
    plant_input : ndarray of shape (n_steps, ...)
        ``clip(control_output + feedforward)`` (V), held over the step.
    """

    states: np.ndarray
    measurements: np.ndarray
    controller_states: np.ndarray
    control_output: np.ndarray
    plant_input: np.ndarray


def simulate_closed_loop(
    state0,
    controller: DiscreteStateSpace | Sequence[DiscreteStateSpace],
    references,
    feedforward,
    params: PendulumParameters | Sequence[PendulumParameters] = PendulumParameters(),
    sensor: SensorModel = SensorModel(),
    controller_state0=None,
    max_voltage: float = 10.0,
    n_substeps: int = DEFAULT_SUBSTEPS,
    rng: np.random.Generator | None = None,
    alpha_offsets=None,
    past_voltages=None,
    load=None,
    alpha_drift=None,
    relaxation: CableRelaxation | Sequence[CableRelaxation | None] | None = None,
) -> ClosedLoopRun:
    """Run the pendulum under a controller on the tracking error, for a batch of episodes.

    Parameters
    ----------
    state0 : array_like of shape (..., 4)
        Initial plant states; the leading shape is the batch.
    controller : DiscreteStateSpace, or a sequence of them
        Two inputs (errors of theta and alpha), or three with the feedforward last,
        one output (V); its ``dt`` is the sample period. A sequence gives one per
        episode of a one-dimensional batch, all of one order, inputs and sample period:
        the episodes of several controllers then run as one batch (each controller's
        episodes exactly as a batch of their own would run them).
    references : array_like of shape (n_steps, ..., 2)
        target_theta and target_alpha at each step.
    feedforward : array_like of shape (n_steps, ...)
        Voltage added to the controller output.
    params : PendulumParameters, or a sequence of them
        The pendulum, or one per episode of the batch (in its C order): the episodes'
        physics and delays may differ, and still run as one batch.
    sensor : SensorModel
        Encoder settings.
    controller_state0 : array_like of shape (..., n_c), optional
        Zero by default.
    max_voltage : float
        Output clamp (V); the rig used 10 V.
    n_substeps : int
        RK4 steps per sample.
    rng : numpy.random.Generator, optional
        For sensor noise.
    alpha_offsets : array_like broadcastable to the batch, optional
        Per-episode pendulum encoder zero offsets (rad), added to the sensor's own.
    past_voltages : array_like of shape (n_past, ...), optional
        Commands before the first step, oldest first, that a transport delay
        (``params.delay``) still applies; zero volts by default.
    load : array_like of shape (n_steps, ...), optional
        A torque on the arm over each step, in volts at the motor past the amplifier's dead zone
        (the torque ``km / Rm`` times it): a random load's samples
        (:meth:`~qube_koopman.sim.pendulum.load.RandomLoad.sample`). None: no load, exactly the
        arithmetic without one.
    alpha_drift : array_like of shape (n_steps, ...), optional
        A pendulum encoder zero that moves during the episode (rad), added to ``alpha_offsets`` at
        each step: the alternative to a load on the arm that the calibration's evidence weighs
        (``docs/calibration.md``). None: a constant zero.
    relaxation : CableRelaxation, or a sequence of them (or None), optional
        The cables' torque beyond the twin's spring that the arm's own motion drives
        (:class:`~qube_koopman.sim.pendulum.relaxation.CableRelaxation`), added to the load at each
        step, its element starting relaxed at the first state; a sequence gives one per episode of
        the batch (in its C order; None: none for that episode). None: none, exactly the arithmetic
        without it.
    """
    # The one controller, or the first of one per episode (all of its order, inputs and sample period).
    controllers: list[DiscreteStateSpace] | None = None
    if isinstance(controller, DiscreteStateSpace):
        system = controller
    else:
        controllers = list(controller)
        system = _check_per_episode(controllers)
    if system.n_inputs not in (2, 3) or system.n_outputs != 1:
        raise ValueError(
            "controller must map the two tracking errors (theta, alpha), and optionally the "
            f"feedforward, to one voltage; got {system.n_inputs} inputs and "
            f"{system.n_outputs} outputs"
        )
    check_timing(system.dt, n_substeps)
    if not max_voltage > 0:
        raise ValueError(f"max_voltage must be positive, got {max_voltage!r}")
    x = as_states(state0)
    r = np.asarray(references, dtype=float)
    f = np.asarray(feedforward, dtype=float)
    batch = x.shape[:-1]
    n_steps = r.shape[0] if r.ndim else 0
    if r.shape != (n_steps, *batch, 2) or f.shape != (n_steps, *batch):
        raise ValueError(
            f"for {n_steps} steps of a batch {batch}, references must have shape "
            f"{(n_steps, *batch, 2)} and feedforward {(n_steps, *batch)}; "
            f"got {r.shape} and {f.shape}"
        )
    if controllers is not None and (len(batch) != 1 or len(controllers) != batch[0]):
        raise ValueError(f"{len(controllers)} controllers for a batch of {batch}: give one per episode of a 1-D batch")
    n_c = system.n_states
    xc = np.zeros((*batch, n_c)) if controller_state0 is None else np.array(controller_state0, dtype=float)
    if xc.shape != (*batch, n_c):
        raise ValueError(f"controller_state0 must have shape {(*batch, n_c)}, got {xc.shape}")

    states = np.empty((n_steps + 1, *batch, 4))
    states[0] = x
    measurements = np.empty((n_steps, *batch, 2))
    xcs = np.empty((n_steps, *batch, n_c))
    control = np.empty((n_steps, *batch))
    plant_input = np.empty((n_steps, *batch))
    steps = _controller_steps([system] if controllers is None else controllers)
    Ac, Bc, Cc, Dc = steps[0][1]
    sees_feedforward = system.n_inputs == 3
    h = system.dt / n_substeps
    k, whole, weights, wholes = coefficients_and_hold(params, batch, system.dt, int(n_substeps))
    rk4 = array_rk4(k)
    past = np.zeros((whole + 1, *batch)) if past_voltages is None else np.asarray(past_voltages, dtype=float)
    if past.ndim != len(batch) + 1 or past.shape[0] < 1:
        raise ValueError(f"past_voltages must have shape (n_past, *{batch}), got {past.shape}")
    history = list(np.broadcast_to(past, (past.shape[0], *batch))[-(whole + 1) :])
    history = [history[0]] * (whole + 1 - len(history)) + history  # oldest first, whole + 1 commands
    if load is not None:
        load = np.asarray(load, dtype=float)
        if load.shape != (n_steps, *batch):
            raise ValueError(
                f"load must have shape {(n_steps, *batch)} (a torque per step and episode), got {load.shape}"
            )
    if alpha_drift is not None:
        alpha_drift = np.asarray(alpha_drift, dtype=float)
        if alpha_drift.shape != (n_steps, *batch):
            raise ValueError(f"alpha_drift must have shape {(n_steps, *batch)}, got {alpha_drift.shape}")
        base = 0.0 if alpha_offsets is None else np.broadcast_to(np.asarray(alpha_offsets, dtype=float), batch)
        drift_shift = np.stack(np.broadcast_arrays(0.0, base + alpha_drift), axis=-1)  # (n_steps, *batch, 2)
    comps = tuple(x[..., i] for i in range(4))
    relax = None if relaxation is None else _relaxation_arrays(relaxation, batch, system.dt)
    remembered = None if relax is None else np.array(comps[0], dtype=float, copy=True)
    shift = (
        None
        if alpha_offsets is None
        else np.stack(np.broadcast_arrays(0.0, np.broadcast_to(np.asarray(alpha_offsets, dtype=float), batch)), axis=-1)
    )
    for step in range(n_steps):
        if alpha_drift is not None:
            shift = drift_shift[step]
        y = measure(states[step] if shift is None else states[step][..., :2] + shift, sensor, rng)
        e = r[step] - y
        if sees_feedforward:  # the controller's third input (core/CONTROLLER_FORMAT.md)
            e = np.concatenate([e, f[step][..., None]], axis=-1)
        if len(steps) == 1:  # one controller: its products over the whole batch
            u = xc @ Cc + e @ Dc
            v = np.clip(u + f[step], -max_voltage, max_voltage)
            measurements[step], xcs[step], control[step], plant_input[step] = y, xc, u, v
            xc = xc @ Ac + e @ Bc
        else:  # each controller on its own episodes, with the products a batch of them alone would take
            xcs[step], nxt = xc, np.empty_like(xc)
            u = control[step]
            for rows, (A, B, C, D) in steps:
                u[rows] = xc[rows] @ C + e[rows] @ D
                nxt[rows] = xc[rows] @ A + e[rows] @ B
            v = np.clip(u + f[step], -max_voltage, max_voltage)
            measurements[step], plant_input[step] = y, v
            xc = nxt
        history.append(v)
        if wholes is None:
            previous, current = history[-whole - 2], history[-whole - 1]
        else:  # each episode's own whole samples of delay back
            held = np.stack(history)
            previous = np.take_along_axis(held, (len(history) - wholes - 2)[None], 0)[0]
            current = np.take_along_axis(held, (len(history) - wholes - 1)[None], 0)[0]
        torque = None if load is None else load[step]
        if relax is not None:  # the cables' relaxing torque, the arm's angle held over the step
            fast, relaxing, decay = relax
            theta = comps[0]
            extra = relaxation_torque(fast, relaxing, theta, remembered)
            torque = extra if torque is None else torque + extra
            remembered = relaxed(remembered, theta, decay)
        comps = advance(comps, previous, current, weights, h, k, np.sin, np.cos, rk4, torque)
        del history[0]
        states[step + 1] = np.stack(comps, axis=-1)
    return ClosedLoopRun(states, measurements, xcs, control, plant_input)


def _relaxation_arrays(relaxation, batch: tuple[int, ...], dt: float) -> tuple:
    """``(fast, relaxing, decay)`` of one relaxation, or arrays of shape ``batch`` of one per episode."""
    if isinstance(relaxation, CableRelaxation):
        return relaxation.fast, relaxation.relaxing, relaxation.decay(dt)
    each = list(relaxation)
    if len(each) != math.prod(batch) or not all(r is None or isinstance(r, CableRelaxation) for r in each):
        raise ValueError(
            f"relaxation must be a CableRelaxation or one per episode of the batch {batch} (None for none), "
            f"got {len(each)} items"
        )
    none = CableRelaxation(0.0, 0.0, 1.0)
    each = [none if r is None else r for r in each]
    columns = np.array([(r.fast, r.relaxing, r.decay(dt)) for r in each], dtype=float)
    return tuple(columns[:, j].reshape(batch) for j in range(3))


def _check_per_episode(controllers: list) -> DiscreteStateSpace:
    """The first of one controller per episode, once they are checked to run as one batch."""
    if not controllers or not all(isinstance(c, DiscreteStateSpace) for c in controllers):
        raise ValueError("controller must be a DiscreteStateSpace or a non-empty sequence of them, one per episode")
    first = controllers[0]
    for c in controllers[1:]:
        if (c.n_states, c.n_inputs, c.n_outputs, c.dt) != (first.n_states, first.n_inputs, first.n_outputs, first.dt):
            raise ValueError(
                "controllers of one batch must share their order, inputs, outputs and sample period; got "
                f"{first.n_states} states, {first.n_inputs} inputs, dt {first.dt} "
                f"and {c.n_states}, {c.n_inputs}, dt {c.dt}"
            )
    return first


def _controller_steps(controllers: list) -> list:
    """``[(rows, (A^T, B^T, C[0], D[0])), ...]``: each distinct controller's episodes (a slice where they are
    consecutive) and the matrices of its update and output."""
    groups: dict[int, list[int]] = {}
    for j, c in enumerate(controllers):
        groups.setdefault(id(c), []).append(j)
    steps = []
    for indices in groups.values():
        c = controllers[indices[0]]
        rows = slice(indices[0], indices[-1] + 1) if indices[-1] - indices[0] + 1 == len(indices) else np.array(indices)
        steps.append((rows, (c.A.T, c.B.T, c.C[0], c.D[0])))
    if len(steps) == 1:
        steps = [(slice(None), steps[0][1])]
    return steps


def linear_loop_radius(controller: DiscreteStateSpace, params: PendulumParameters | None = None) -> float:
    """The spectral radius of ``controller`` closed around the pendulum's linearization at upright.

    The loop is the one :func:`simulate_closed_loop` runs (the command from the tick's reading, held over the
    tick), with the plant's transport delay (``params.delay``) on the command. The arm's smoothed Coulomb
    friction is left out: its slope at rest, which :func:`~qube_koopman.sim.pendulum.physics.linearize_upright`
    takes as viscous damping, holds only within ``coulomb_speed`` of rest, where a moving loop spends little
    time, and with it the calibrated twin's linearization calls the rig's own PD unstable (1.0029) where the
    twin and the rig balance under it (0.9919 without).

    Parameters
    ----------
    controller : DiscreteStateSpace
        A controller of the tracking errors (theta, alpha) giving the voltage, ``u = C xc + D (r - y)``.
    params : PendulumParameters, optional
        The pendulum (the calibrated twin by default).

    Returns
    -------
    float
        Above 1: the loop diverges from upright.
    """
    import dataclasses

    params = PendulumParameters() if params is None else params
    plant = linear_model(dataclasses.replace(params, Cr=0.0), controller.dt)
    ctrl = with_output_delay(controller, params.delay / controller.dt) if params.delay else controller
    if ctrl.n_inputs != plant.n_outputs or ctrl.n_outputs != plant.n_inputs:
        raise ValueError(
            f"the controller takes {ctrl.n_inputs} inputs and gives {ctrl.n_outputs} outputs; the pendulum's loop "
            f"needs {plant.n_outputs} (theta, alpha) and {plant.n_inputs} (the voltage)"
        )
    loop = np.block(
        [
            [plant.A - plant.B @ ctrl.D @ plant.C, plant.B @ ctrl.C],
            [-ctrl.B @ plant.C, ctrl.A],
        ]
    )
    return float(spectral_radius(loop))
