"""The controller's per-tick step in the acquisition loop, fast at any size.

Each tick the loop asks for the output ``u = C x + D e`` (before writing the command) and then
advances the state ``x <- A x + B e``, with ``e`` the two tracking errors, and the tick's
feedforward after them for a controller that takes it (core/CONTROLLER_FORMAT.md): the convention of
:class:`core.lti.DiscreteStateSpace` and of the log (``controller_state[k]`` is the state that
computed ``control_output[k]``), so :func:`core.lti.replay_controller` recomputes the logged
state from the log.

Two realizations of the same arithmetic, chosen by size:

- up to :data:`PLAIN_MAX_STATES` states (the QUBE's PD has 2), plain Python floats: numpy's
  per-call overhead would cost more than the arithmetic;
- above, numpy on preallocated arrays: one matrix-vector product ``[C D] [x; e]`` for the
  output and one ``[A B] [x; e]`` for the update, no allocation but the logged copy of the
  state (a 200-state step takes about 10-20 us; bench/bench_controller_size.py).
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from qube_koopman.core.lti import DiscreteStateSpace

__all__ = ["PLAIN_MAX_STATES", "Output", "Update", "controller_step"]

#: Largest controller run on plain floats; larger ones run on numpy.
PLAIN_MAX_STATES = 4

#: ``output(e_theta, e_alpha, feedforward) -> (u, x)``: the output and the state that computed it
#: (to log); a controller of the two errors only ignores the feedforward.
Output = Callable[[float, float, float], tuple[float, Sequence[float]]]
#: ``update(e_theta, e_alpha, feedforward)``: advance the state with this tick's inputs.
Update = Callable[[float, float, float], None]


def controller_step(system: DiscreteStateSpace) -> tuple[Output, Update]:
    """The per-tick output and state update of the loop's controller, from zero state.

    Parameters
    ----------
    system : DiscreteStateSpace
        The controller: the tracking errors (theta, alpha) in, and optionally the feedforward
        as a third input; one voltage out.

    Returns
    -------
    output : callable
        ``output(e0, e1, f) -> (u, x)``: ``u = C x + D e`` with ``e = (e0, e1)`` or
        ``(e0, e1, f)``, and the current state ``x`` (a tuple or list of floats the caller may
        keep: it is not changed by later ticks).
    update : callable
        ``update(e0, e1, f)``: ``x <- A x + B e``; call it after ``output`` with the same inputs.
    """
    if system.n_inputs not in (2, 3) or system.n_outputs != 1:
        raise ValueError(
            f"the loop's controller has 2 inputs (3 with the feedforward) and 1 output, got "
            f"{system.n_inputs} and {system.n_outputs}"
        )
    if system.n_states <= PLAIN_MAX_STATES:
        return _plain_step(system)
    return _numpy_step(system)


def _plain_step(system: DiscreteStateSpace) -> tuple[Output, Update]:
    """The step on plain floats (the arithmetic, in its order, of the loop before numpy steps).

    A controller of the two errors only gets a zero feedforward column: ``0.0 * f`` is a zero,
    and adding it changes no sum, so its samples are those of a two-input step.
    """
    B, D = system.B, system.D
    if system.n_inputs == 2:
        B, D = np.hstack([B, np.zeros((system.n_states, 1))]), np.hstack([D, [[0.0]]])
    rows = [(a, b[0], b[1], b[2]) for a, b in zip(system.A.tolist(), B.tolist())]
    C = system.C[0].tolist()
    D0, D1, D2 = D[0].tolist()
    xc = (0.0,) * len(rows)

    def output(e0: float, e1: float, f: float) -> tuple[float, tuple[float, ...]]:
        u = D0 * e0 + D1 * e1 + D2 * f
        for c, x in zip(C, xc):
            u += c * x
        return u, xc

    def update(e0: float, e1: float, f: float) -> None:
        nonlocal xc
        xc = tuple([sum([a * x for a, x in zip(row, xc)]) + b0 * e0 + b1 * e1 + b2 * f for row, b0, b1, b2 in rows])

    return output, update


def _numpy_step(system: DiscreteStateSpace) -> tuple[Output, Update]:
    """The step on preallocated numpy arrays: ``z = [x; e]``, ``u = [C D] z``, ``x <- [A B] z``."""
    n = system.n_states
    AB = np.ascontiguousarray(np.hstack([system.A, system.B]))
    CD = np.ascontiguousarray(np.hstack([system.C, system.D])[0])
    z = np.zeros(n + system.n_inputs)
    x = z[:n]
    nxt = np.empty(n)
    dot = np.dot
    sees_feedforward = system.n_inputs == 3

    def output(e0: float, e1: float, f: float) -> tuple[float, list[float]]:
        z[n] = e0
        z[n + 1] = e1
        if sees_feedforward:
            z[n + 2] = f
        return float(dot(CD, z)), x.tolist()

    def update(e0: float, e1: float, f: float) -> None:
        z[n] = e0
        z[n + 1] = e1
        if sees_feedforward:
            z[n + 2] = f
        dot(AB, z, out=nxt)
        x[:] = nxt

    return output, update
