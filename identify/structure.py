"""The closed-loop structure: a plant in feedback with a known controller.

Notation (paper section 3, naming guide): the closed-loop lifted state is
``theta = [x^c; theta^p]``, its exogenous input ``upsilon = [r; f]``, the
controller input ``u^c = r - C^p theta^p``, the plant input
``u = C^c x^c + D^c u^c + f``. Then

    U^f = [[A^c,      -B^c C^p,             B^c,      0  ],
           [B^p C^c,  A^p - B^p D^c C^p,    B^p D^c,  B^p]]

and the plant block row is ``U^p S`` with ``U^p = [A^p B^p]``.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from qube_koopman.sim.lti import DiscreteStateSpace, replay_controller

__all__ = [
    "output_selection",
    "plant_input_map",
    "closed_loop_matrices",
    "extract_plant_lstsq",
    "controller_states",
    "plant_input",
    "close_loop",
]


def output_selection(n_lifted: int, measured: Sequence[int]) -> np.ndarray:
    """``C^p``: rows of the identity picking the measured states out of the lifted plant state."""
    measured = list(measured)
    if any(not 0 <= i < n_lifted for i in measured):
        raise ValueError(f"measured state indices {measured} are outside 0..{n_lifted - 1}")
    return np.eye(n_lifted)[measured]


def _check_controller(controller: DiscreteStateSpace, C_p: np.ndarray) -> None:
    if controller.n_inputs != C_p.shape[0]:
        raise ValueError(f"the controller takes {controller.n_inputs} tracking errors but "
                         f"{C_p.shape[0]} states are fed back")


def plant_input_map(controller: DiscreteStateSpace, C_p: np.ndarray, n_feedforward: int) -> np.ndarray:
    """``S`` with ``S [x^c; theta^p; r; f] = [theta^p; u]``.

    ``n_feedforward`` is 0 when the loop has no feedforward input, else the
    number of plant inputs.
    """
    _check_controller(controller, C_p)
    n_c, n_p, n_r, n_u = controller.n_states, C_p.shape[1], C_p.shape[0], controller.n_outputs
    if n_feedforward not in (0, n_u):
        raise ValueError(f"feedforward has {n_feedforward} channels; the controller drives {n_u} plant inputs")
    top = np.hstack([np.zeros((n_p, n_c)), np.eye(n_p), np.zeros((n_p, n_r + n_feedforward))])
    bottom = np.hstack([controller.C, -controller.D @ C_p, controller.D, np.eye(n_u)[:, :n_feedforward]])
    return np.vstack([top, bottom])


def closed_loop_matrices(A_p: np.ndarray, B_p: np.ndarray, controller: DiscreteStateSpace,
                         C_p: np.ndarray, n_feedforward: int) -> tuple[np.ndarray, np.ndarray]:
    """Wrap a plant ``(A^p, B^p)`` with the controller: the closed-loop ``(A^f, B^f)``."""
    _check_controller(controller, C_p)
    n_c = controller.n_states
    S = plant_input_map(controller, C_p, n_feedforward)
    Ac, Bc = controller.A, controller.B
    controller_rows = np.hstack([Ac, -Bc @ C_p, Bc, np.zeros((n_c, n_feedforward))])
    U_f = np.vstack([controller_rows, np.hstack([A_p, B_p]) @ S])
    n_theta = n_c + A_p.shape[0]
    return U_f[:, :n_theta], U_f[:, n_theta:]


def extract_plant_lstsq(U_f: np.ndarray, controller: DiscreteStateSpace, C_p: np.ndarray,
                        n_feedforward: int) -> tuple[np.ndarray, np.ndarray]:
    """The paper's least-squares plant extraction (eqs. lstsq_Bp, constr_Ap).

    ``B^p = [U21 U23 U24] [C^c D^c I]^+`` and ``A^p = U22 + B^p D^c C^p``.
    Re-wrapping the result with the controller does not in general give
    ``U^f`` back (paper appendix).
    """
    _check_controller(controller, C_p)
    n_c, n_p, n_r = controller.n_states, C_p.shape[1], C_p.shape[0]
    n_u = controller.n_outputs
    rows = U_f[n_c:]
    U21 = rows[:, :n_c]
    U22 = rows[:, n_c:n_c + n_p]
    U23 = rows[:, n_c + n_p:n_c + n_p + n_r]
    U24 = rows[:, n_c + n_p + n_r:]
    blocks = np.hstack([U21, U23, U24])
    known = np.hstack([controller.C, controller.D, np.eye(n_u)[:, :n_feedforward]])
    B_p = blocks @ np.linalg.pinv(known)
    A_p = U22 + B_p @ controller.D @ C_p
    return A_p, B_p


def controller_states(controller: DiscreteStateSpace, r: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Controller state along an episode, run from zero on the tracking error ``r - y``
    (the states of :func:`sim.lti.replay_controller`)."""
    return replay_controller(controller, r, y)[0]


def plant_input(controller: DiscreteStateSpace, xc: np.ndarray, r: np.ndarray, y: np.ndarray,
                f: np.ndarray | None = None) -> np.ndarray:
    """The plant's input recovered from closed-loop data: ``C^c x^c + D^c (r - y) + f``.

    Saturation of the actuator is not modelled here.
    """
    e = np.atleast_2d(np.asarray(r, dtype=float) - np.asarray(y, dtype=float))
    if e.shape[0] == 1 and np.ndim(r) == 1:
        e = e.T
    u = np.asarray(xc, dtype=float) @ controller.C.T + e @ controller.D.T
    return u if f is None else u + np.asarray(f, dtype=float).reshape(u.shape)


def close_loop(plant, controller: DiscreteStateSpace, measured: Sequence[int] | None = None,
               feedforward: bool = True):
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
    from qube_koopman.identify.model import KoopmanModel

    if plant.n_passthrough or plant.input_signals != ("u",) or plant.input_lifting is not None:
        raise ValueError("close_loop needs a plant model whose input is the unlifted plant input u")
    if plant.B.shape[1] != controller.n_outputs:
        raise ValueError(f"the plant takes {plant.B.shape[1]} inputs, the controller drives "
                         f"{controller.n_outputs}")
    measured = list(range(plant.n_states)) if measured is None else list(measured)
    C_p = output_selection(plant.A.shape[0], measured)
    n_f = controller.n_outputs if feedforward else 0
    A_f, B_f = closed_loop_matrices(plant.A, plant.B, controller, C_p, n_f)
    return KoopmanModel(A_f, B_f, plant.lifting, ("r", "f") if feedforward else ("r",),
                        n_passthrough=controller.n_states, dt=plant.dt if plant.dt is not None else controller.dt,
                        feedback=tuple(measured))
