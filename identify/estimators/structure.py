"""The closed-loop structure: a plant in feedback with a known controller.

Notation (paper section 3, naming guide): the closed-loop lifted state is
``theta = [x^c; theta^p]``, its exogenous input ``upsilon = [r; f]``, the
controller input ``u^c = r - C^p theta^p``, the plant input
``u = C^c x^c + D^c u^c + f``. Then

    U^f = [[A^c,      -B^c C^p,             B^c,      0  ],
           [B^p C^c,  A^p - B^p D^c C^p,    B^p D^c,  B^p]]

and the plant block row is ``U^p S`` with ``U^p = [A^p B^p]``.

A controller may also take the feedforward as an input (core/CONTROLLER_FORMAT.md): its
``B^c = [B^c_e B^c_f]`` and ``D^c = [D^c_e D^c_f]`` split into the tracking errors' columns
and the feedforward's, and the feedforward still adds to its output. Then ``B^c`` and ``D^c``
above are the errors' columns, the last column of blocks is ``[B^c_f; B^p (I + D^c_f)]``
(:func:`feedforward_columns`), and with ``B^c_f = 0``, ``D^c_f = 0`` it is the paper's.
"""

from __future__ import annotations

from dataclasses import replace
from functools import partial
from typing import TYPE_CHECKING, Sequence

import numpy as np

from qube_koopman.core.lti import DiscreteStateSpace, controller_inputs, held_late, replay_controller, with_output_delay
from qube_koopman.core.qube import MEASURED

if TYPE_CHECKING:
    from qube_koopman.identify.data.logs import LoggedTrajectory, StoredLog
    from qube_koopman.identify.data.trajectory import Trajectory

__all__ = [
    "output_selection",
    "plant_input_map",
    "closed_loop_matrices",
    "extract_plant_lstsq",
    "controller_states",
    "feedforward_columns",
    "plant_input",
    "command_delayed",
    "with_command_delay",
    "close_loop",
]


def output_selection(n_lifted: int, measured: Sequence[int]) -> np.ndarray:
    """``C^p``: rows of the identity picking the measured states out of the lifted plant state.

    Parameters
    ----------
    n_lifted : int
        Size of the lifted plant state.
    measured : sequence of int
        The fed-back states' indices.

    Returns
    -------
    ndarray of shape (len(measured), n_lifted)
    """
    measured = list(measured)
    if any(not 0 <= i < n_lifted for i in measured):
        raise ValueError(f"measured state indices {measured} are outside 0..{n_lifted - 1}")
    return np.eye(n_lifted)[measured]


def _check_controller(controller: DiscreteStateSpace, C_p: np.ndarray, n_feedforward: int = 0) -> None:
    n_r = C_p.shape[0]
    if controller.n_inputs == n_r:
        return
    if controller.n_inputs == n_r + n_feedforward and n_feedforward:
        return
    if controller.n_inputs > n_r and not n_feedforward:
        raise ValueError(
            f"the controller takes {controller.n_inputs} inputs, the {n_r} tracking errors and the "
            "feedforward, but the data have no feedforward"
        )
    raise ValueError(
        f"the controller takes {controller.n_inputs} inputs but {n_r} states are fed back"
        + (f" and the feedforward has {n_feedforward} channels" if n_feedforward else "")
    )


def feedforward_columns(controller: DiscreteStateSpace, n_errors: int, n_feedforward: int) -> tuple[np.ndarray, ...]:
    """The controller's columns split: ``(B^c_e, D^c_e, B^c_f, D^c_f)``.

    Parameters
    ----------
    controller : DiscreteStateSpace
        The controller: ``n_errors`` tracking errors in, then the feedforward if it takes it.
    n_errors : int
        Fed-back states (tracking-error channels).
    n_feedforward : int
        The loop's feedforward channels (0 without feedforward).

    Returns
    -------
    B_e, D_e : ndarray
        The tracking errors' columns of ``B^c`` and ``D^c``.
    B_f, D_f : ndarray of shapes (n_c, n_feedforward), (n_u, n_feedforward)
        The feedforward's columns, zero for a controller that does not take it.
    """
    B, D = controller.B, controller.D
    if controller.n_inputs > n_errors:
        return B[:, :n_errors], D[:, :n_errors], B[:, n_errors:], D[:, n_errors:]
    return B, D, np.zeros((controller.n_states, n_feedforward)), np.zeros((controller.n_outputs, n_feedforward))


def plant_input_map(controller: DiscreteStateSpace, C_p: np.ndarray, n_feedforward: int) -> np.ndarray:
    """``S`` with ``S [x^c; theta^p; r; f] = [theta^p; u]``.

    ``n_feedforward`` is 0 when the loop has no feedforward input, else the
    number of plant inputs.

    Parameters
    ----------
    controller : DiscreteStateSpace
        The known controller.
    C_p : ndarray
        The fed-back states (:func:`output_selection`).
    n_feedforward : int
        Feedforward channels.

    Returns
    -------
    ndarray
    """
    _check_controller(controller, C_p, n_feedforward)
    n_c, n_p, n_r, n_u = controller.n_states, C_p.shape[1], C_p.shape[0], controller.n_outputs
    if n_feedforward not in (0, n_u):
        raise ValueError(f"feedforward has {n_feedforward} channels; the controller drives {n_u} plant inputs")
    _, D_e, _, D_f = feedforward_columns(controller, n_r, n_feedforward)
    top = np.hstack([np.zeros((n_p, n_c)), np.eye(n_p), np.zeros((n_p, n_r + n_feedforward))])
    bottom = np.hstack([controller.C, -D_e @ C_p, D_e, np.eye(n_u)[:, :n_feedforward] + D_f])
    return np.vstack([top, bottom])


def closed_loop_matrices(
    A_p: np.ndarray, B_p: np.ndarray, controller: DiscreteStateSpace, C_p: np.ndarray, n_feedforward: int
) -> tuple[np.ndarray, np.ndarray]:
    """Wrap a plant ``(A^p, B^p)`` with the controller: the closed-loop ``(A^f, B^f)``.

    Parameters
    ----------
    A_p, B_p : ndarray
        The plant on its lifted state.
    controller : DiscreteStateSpace
        The controller, from the tracking error (and, with more inputs, the feedforward).
    C_p : ndarray
        The fed-back states (:func:`output_selection`).
    n_feedforward : int
        Feedforward channels (0: none).

    Returns
    -------
    A_f, B_f : ndarray
        The closed loop on ``[x^c; theta^p]`` with inputs ``[r; f]``.
    """
    _check_controller(controller, C_p, n_feedforward)
    n_c = controller.n_states
    S = plant_input_map(controller, C_p, n_feedforward)
    B_e, _, B_f, _ = feedforward_columns(controller, C_p.shape[0], n_feedforward)
    controller_rows = np.hstack([controller.A, -B_e @ C_p, B_e, B_f])
    U_f = np.vstack([controller_rows, np.hstack([A_p, B_p]) @ S])
    n_theta = n_c + A_p.shape[0]
    return U_f[:, :n_theta], U_f[:, n_theta:]


def extract_plant_lstsq(
    U_f: np.ndarray, controller: DiscreteStateSpace, C_p: np.ndarray, n_feedforward: int
) -> tuple[np.ndarray, np.ndarray]:
    """The paper's least-squares plant extraction (eqs. lstsq_Bp, constr_Ap).

    ``B^p = [U21 U23 U24] [C^c D^c I]^+`` and ``A^p = U22 + B^p D^c C^p``.
    Re-wrapping the result with the controller does not in general give
    ``U^f`` back (paper appendix).

    Parameters
    ----------
    U_f : ndarray
        The closed-loop Koopman matrix, fitted freely.
    controller : DiscreteStateSpace
        The known controller.
    C_p : ndarray
        The fed-back states.
    n_feedforward : int
        Feedforward channels (0: none).

    Returns
    -------
    A_p, B_p : ndarray
    """
    _check_controller(controller, C_p, n_feedforward)
    n_c, n_p, n_r = controller.n_states, C_p.shape[1], C_p.shape[0]
    n_u = controller.n_outputs
    _, D_e, _, D_f = feedforward_columns(controller, n_r, n_feedforward)
    rows = U_f[n_c:]
    U21 = rows[:, :n_c]
    U22 = rows[:, n_c : n_c + n_p]
    U23 = rows[:, n_c + n_p : n_c + n_p + n_r]
    U24 = rows[:, n_c + n_p + n_r :]
    blocks = np.hstack([U21, U23, U24])
    known = np.hstack([controller.C, D_e, np.eye(n_u)[:, :n_feedforward] + D_f])
    B_p = blocks @ np.linalg.pinv(known)
    A_p = U22 + B_p @ D_e @ C_p
    return A_p, B_p


def controller_states(
    controller: DiscreteStateSpace, r: np.ndarray, y: np.ndarray, f: np.ndarray | None = None
) -> np.ndarray:
    """Controller state along an episode, run from zero on the tracking error ``r - y`` and, for a
    controller that takes it, the feedforward ``f`` (the states of :func:`core.lti.replay_controller`).

    Parameters
    ----------
    controller : DiscreteStateSpace
        The controller.
    r, y : ndarray of shape (n_samples, n_measured)
        References and measured states.
    f : ndarray of shape (n_samples, n_inputs), optional
        Feedforward.

    Returns
    -------
    ndarray of shape (n_samples, n_controller_states)
    """
    return replay_controller(controller, r, y, feedforward=f)[0]


def plant_input(
    controller: DiscreteStateSpace, xc: np.ndarray, r: np.ndarray, y: np.ndarray, f: np.ndarray | None = None
) -> np.ndarray:
    """The plant's input recovered from closed-loop data: ``C^c x^c + D^c (r - y) + f``
    (``D^c [r - y; f] + f`` for a controller that takes the feedforward).

    Saturation of the actuator is not modelled here.

    Parameters
    ----------
    controller, r, y, f
        As for :func:`controller_states`.
    xc : ndarray of shape (n_samples, n_controller_states)
        The controller's state.

    Returns
    -------
    ndarray of shape (n_samples, n_inputs)
    """
    inputs = controller_inputs(controller, r, y, f)  # r - y, then f for a controller that takes it
    u = np.asarray(xc, dtype=float) @ controller.C.T + inputs @ controller.D.T
    return u if f is None else u + np.asarray(f, dtype=float).reshape(u.shape)


def command_delayed(
    controller: DiscreteStateSpace,
    samples: float,
    xc: np.ndarray,
    r: np.ndarray,
    y: np.ndarray,
    f: np.ndarray | None = None,
) -> tuple[DiscreteStateSpace, np.ndarray, np.ndarray | None]:
    """A loop whose command reaches the plant ``samples`` periods later: the controller, its states and
    the feedforward that predict it.

    The command (the controller's output plus the feedforward) is held late as the simulated
    pendulum holds its transport delay: the controller is followed by
    :func:`~qube_koopman.core.lti.with_output_delay`, whose extra states are its past outputs along
    the episode, and the feedforward, which the loop adds after the controller, is held as late.
    :func:`close_loop` with the returned controller then predicts the loop with the extra delay.

    Parameters
    ----------
    controller : DiscreteStateSpace
        From the tracking errors to the plant input (not one that takes the feedforward itself).
    samples : float
        The extra delay in sample periods, 0 or more.
    xc : ndarray of shape (n_samples, n_controller_states)
        The controller's states along the episode.
    r, y, f
        As for :func:`controller_states`.

    Returns
    -------
    controller : DiscreteStateSpace
        The controller followed by the delay.
    xc : ndarray
        Its states along the episode: ``xc``, then its past outputs, newest first.
    f : ndarray or None
        The feedforward held ``samples`` later.
    """
    if controller.n_inputs != np.shape(r)[1]:
        raise ValueError(
            "a command delay needs a controller of the tracking errors alone; this one takes the feedforward too"
        )
    delayed = with_output_delay(controller, samples)
    output = plant_input(controller, xc, r, y)  # the controller's own output, before the feedforward
    n_past = (delayed.n_states - controller.n_states) // controller.n_outputs
    past = [held_late(output, j) for j in range(1, n_past + 1)]
    held = None if f is None else held_late(np.asarray(f, dtype=float), samples)
    return delayed, np.hstack([np.asarray(xc, dtype=float), *past]), held


def _delayed_trajectory(t: Trajectory, controller: DiscreteStateSpace, samples: float) -> Trajectory:
    """A log's trajectory as :func:`with_command_delay`'s loop sees it (its plant input held as late)."""
    if t.xc is None or t.r is None:
        raise ValueError(f"{t.name}: a command delay needs the loop's references and controller states")
    _, xc, f = command_delayed(controller, samples, t.xc, t.r, t.x[:, MEASURED], t.f)
    return replace(t, xc=xc, f=f, u=held_late(np.asarray(t.u, dtype=float), samples))


def with_command_delay(log: LoggedTrajectory | StoredLog, samples: float) -> LoggedTrajectory | StoredLog:
    """The loop a log ran, when its commands reached the motor ``samples`` periods later than logged.

    A host's latency between computing a command and the motor receiving it differs between
    recording sessions (a slower USB write); a plant identified from logs of several sessions
    (or predicting another session's loop) sees each log's loop as it ran: its controller
    followed by the delay (:func:`command_delayed`, whose extra states are the controller's
    past outputs along the episode), the feedforward held as late, and the plant input the
    command as it reached the motor. A log with no extra delay comes back as it is.

    Parameters
    ----------
    log : LoggedTrajectory or StoredLog
        As :func:`~qube_koopman.identify.data.logs.load_logs` returns it (a stored log's delay is
        applied at every read).
    samples : float
        The extra delay in sample periods, 0 or more.

    Returns
    -------
    LoggedTrajectory or StoredLog
        The same kind of log, with the delayed controller and its trajectory.
    """
    from qube_koopman.identify.data.logs import StoredLog

    samples = float(samples)
    if not (np.isfinite(samples) and samples >= 0):
        raise ValueError(f"{log.path}: the command delay must be 0 or more sample periods, got {samples}")
    if samples == 0:
        return log
    delayed = with_output_delay(log.controller, samples)
    adjust = partial(_delayed_trajectory, controller=log.controller, samples=samples)
    if log.recorded_controller is not None:
        raise ValueError(f"{log.path}: its loop is already delayed; delay it once, by the whole delay")
    if isinstance(log, StoredLog):
        shape = log.shape
        if shape is not None:
            shape = replace(shape, widths={**shape.widths, "xc": delayed.n_states})
        return replace(log, controller=delayed, shape=shape, adjust=adjust, recorded_controller=log.controller)
    return replace(log, controller=delayed, trajectory=adjust(log.trajectory), recorded_controller=log.controller)


def close_loop(plant, controller: DiscreteStateSpace, measured: Sequence[int] | None = None, feedforward: bool = True):
    """Wrap an identified plant model with a known controller.

    Parameters
    ----------
    plant : KoopmanModel
        Plant model with input ``u`` (from :class:`~identify.Edmd` or the
        ``plant_model_`` of a closed-loop fit).
    controller : DiscreteStateSpace
        The controller, from tracking error ``r - C^p theta^p`` to the plant input.
    measured : sequence of int, optional
        Indices of the fed-back plant states; all original states by default.
    feedforward : bool
        Whether the loop has a feedforward input ``f`` added to the controller output.

    Returns
    -------
    KoopmanModel
        Closed-loop model with state ``[x^c; theta^p]`` and input ``[r; f]``.
    """
    from qube_koopman.identify.models.model import KoopmanModel

    if plant.n_passthrough or plant.input_signals != ("u",) or plant.input_lifting is not None:
        raise ValueError("close_loop needs a plant model whose input is the unlifted plant input u")
    if plant.B.shape[1] != controller.n_outputs:
        raise ValueError(f"the plant takes {plant.B.shape[1]} inputs, the controller drives {controller.n_outputs}")
    measured = list(range(plant.n_states)) if measured is None else list(measured)
    C_p = output_selection(plant.A.shape[0], measured)
    n_f = controller.n_outputs if feedforward else 0
    A_f, B_f = closed_loop_matrices(plant.A, plant.B, controller, C_p, n_f)
    return KoopmanModel(
        A_f,
        B_f,
        plant.lifting,
        ("r", "f") if feedforward else ("r",),
        n_passthrough=controller.n_states,
        dt=plant.dt if plant.dt is not None else controller.dt,
        feedback=tuple(measured),
    )
