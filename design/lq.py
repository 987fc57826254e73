"""LQ state feedback on the plant's history, with integral action, realized on the tracking errors.

The design (on :class:`~design.plant.LinearPlant`, the plant as a shift register of its last
``d + 1`` measurements ``s_k = [x_k; ...; x_{k-d}]``):

- augmented state ``a_k = [s_k; w_k]`` with ``w_{k+1} = w_k + dt e_theta,k`` the integral of the
  arm's tracking error (``e = r - x``; in regulation ``w_{k+1} = w_k - dt theta_k``), when
  :attr:`Weights.integral`;
- the discrete LQ cost ``sum_k q_theta theta_k^2 + q_alpha alpha_k^2 + q_integral w_k^2 +
  r_voltage u_k^2``, solved by python-control's ``dlqr``: ``u_k = -K a_k = -K_s s_k - K_w w_k``.

Realization: a state feedback on the history of the measurements is, on the history of the
tracking errors ``E_k = [e_k; ...; e_{k-d}]`` (``E = -s`` in regulation, ``E = s_ref - s`` with
a reference), ``u_k = K_s E_k - K_w w_k``. The controller's state holds the past errors and the
integral, ``x^c_k = [e_{k-1}; ...; e_{k-d}; w_k]``, so that ``u_k = C x^c_k + D e_k`` and
``x^c_{k+1} = A x^c_k + B e_k`` is exactly the controller file's tick (core/CONTROLLER_FORMAT.md):
``D`` = the gains on the newest errors, ``C`` = the gains on the older ones and ``-K_w``, ``A``
shifts the errors and accumulates the integral.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from qube_koopman.design.plant import DesignError, LinearPlant
from qube_koopman.core.lti import DiscreteStateSpace

__all__ = ["Weights", "LqDesign", "augment", "design_lq", "realize"]

#: Smallest singular value of ``[lambda I - F, G]`` (relative to the matrices' norm) below which
#: a mode at or outside the unit circle counts as uncontrollable.
_PBH_TOLERANCE = 1e-9


@dataclass(frozen=True)
class Weights:
    """Weights of the LQ cost per sample; the defaults are ``qube-design``'s.

    The defaults were tuned on the twin with a plant identified on the paper's 28 training
    episodes (``--poly 1 --delays 35 --const``): they cut the PD's cost J by about 60 % at about 1.1
    times its voltage RMS (README, ``qube-design``).

    Parameters
    ----------
    q_theta : float
        On the arm angle's tracking error (rad^-2).
    q_alpha : float
        On the pendulum angle (rad^-2).
    r_voltage : float
        On the voltage (V^-2); positive.
    q_integral : float
        On the integral of the arm's tracking error ((rad s)^-2); used with ``integral``.
    integral : bool
        Integral action on the arm's tracking error.
    """

    q_theta: float = 10.0
    q_alpha: float = 0.1
    r_voltage: float = 0.01
    q_integral: float = 10.0
    integral: bool = True

    def __post_init__(self) -> None:
        for name in ("q_theta", "q_alpha", "q_integral"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise DesignError(f"--{name.replace('_', '-')} must be a finite number >= 0, got {value!r}")
        if not (isinstance(self.r_voltage, (int, float)) and math.isfinite(self.r_voltage) and self.r_voltage > 0):
            raise DesignError(f"--r-voltage must be a finite number > 0, got {self.r_voltage!r}")
        if self.q_theta == 0 and self.q_alpha == 0:
            raise DesignError("--q-theta and --q-alpha are both 0: the cost would not see the pendulum or the arm")

    def as_dict(self) -> dict:
        """Plain data, for the controller file's provenance."""
        return asdict(self)


@dataclass(frozen=True, eq=False)
class LqDesign:
    """An LQ design and its realization.

    Parameters
    ----------
    plant : LinearPlant
        The plant designed on.
    weights : Weights
        The LQ cost's weights.
    gain : ndarray of shape (1, n_plant + integral)
        ``K`` of ``u = -K [s; w]``.
    controller : DiscreteStateSpace
        The realization on the tracking errors (2 inputs, 1 output).
    """

    plant: LinearPlant
    weights: Weights
    gain: np.ndarray
    controller: DiscreteStateSpace


def augment(plant: LinearPlant, weights: Weights) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The design system and its weights: ``(F_a, G_a, Q, R)`` on ``a = [s; w]`` (``w`` with integral action).

    Parameters
    ----------
    plant : LinearPlant
        The plant on its history.
    weights : Weights
        The LQ cost per sample.

    Returns
    -------
    F_a, G_a, Q, R : ndarray
        ``a_{k+1} = F_a a_k + G_a u_k`` and the cost ``a^T Q a + u^T R u``.
    """
    n = plant.n_states
    q = np.zeros(n)
    q[0], q[1] = weights.q_theta, weights.q_alpha
    if not weights.integral:
        return plant.F, plant.G, np.diag(q), np.array([[weights.r_voltage]])
    F = np.zeros((n + 1, n + 1))
    F[:n, :n] = plant.F
    F[n, 0] = -plant.dt
    F[n, n] = 1.0
    G = np.vstack([plant.G, np.zeros((1, 1))])
    return F, G, np.diag(np.append(q, weights.q_integral)), np.array([[weights.r_voltage]])


def _check_stabilizable(F: np.ndarray, G: np.ndarray) -> None:
    """PBH test on every mode at or outside the unit circle; a :class:`DesignError` naming the first that fails."""
    n = F.shape[0]
    scale = max(float(np.linalg.norm(F, 2)), float(np.linalg.norm(G, 2)), 1.0)
    for lam in np.linalg.eigvals(F):
        if abs(lam) < 1 - 1e-9:
            continue
        sigma = np.linalg.svd(np.hstack([lam * np.eye(n) - F, G]), compute_uv=False)[-1]
        if sigma < _PBH_TOLERANCE * scale:
            raise DesignError(
                f"the plant model is not stabilizable: its mode at {_complex(lam)} (|lambda| = "
                f"{abs(lam):.4g}) does not respond to the voltage, so no feedback can move it"
            )


def _complex(value: complex) -> str:
    value = complex(value)
    return f"{value.real:.4g}" if abs(value.imag) < 1e-12 else f"{value.real:.4g}{value.imag:+.4g}j"


def design_lq(plant: LinearPlant, weights: Weights = Weights()) -> LqDesign:
    """The LQ state feedback on the plant's history (and the arm's integral), realized on the tracking errors.

    Parameters
    ----------
    plant : LinearPlant
    weights : Weights

    Returns
    -------
    LqDesign

    Raises
    ------
    DesignError
        When the plant (with the integrator) is not stabilizable, or the Riccati equation has
        no stabilizing solution.
    """
    import control  # lazily: python-control imports matplotlib

    F, G, Q, R = augment(plant, weights)
    _check_stabilizable(F, G)
    try:
        K, _, _ = control.dlqr(F, G, Q, R)
    except (ValueError, np.linalg.LinAlgError, control.ControlArgument) as exc:
        raise DesignError(
            f"the LQ design has no stabilizing solution ({exc}); is the plant model "
            "stabilizable and are the weights sensible?"
        ) from None
    K = np.atleast_2d(np.asarray(K, dtype=float))
    return LqDesign(plant, weights, K, realize(K, plant, weights.integral))


def realize(gain: np.ndarray, plant: LinearPlant, integral: bool) -> DiscreteStateSpace:
    """The controller on the tracking errors whose output equals ``u = -K [s; w]`` sample for sample.

    Parameters
    ----------
    gain : ndarray of shape (1, n_plant + integral)
        ``K`` on the history ``s`` (newest sample first) and, with ``integral``, on ``w``.
    plant : LinearPlant
        The plant whose history ``s`` is.
    integral : bool
        Whether the last entry of ``gain`` is the integral's.

    Returns
    -------
    DiscreteStateSpace
        State ``[e_{k-1}; ...; e_{k-d}; w_k]`` (one inert state when there is none: a controller
        file holds at least one), inputs ``e_theta, e_alpha``, output the voltage.
    """
    m, n = plant.n_measured, plant.n_states
    gain = np.asarray(gain, dtype=float).reshape(1, n + int(integral))
    K_s = gain[:, :n]
    n_c = (n - m) + int(integral)
    if n_c == 0:  # a static gain: one inert state
        return DiscreteStateSpace(np.zeros((1, 1)), np.zeros((1, m)), np.zeros((1, 1)), K_s, plant.dt)
    held = n - m  # past errors held: e_{k-1} ... e_{k-d}
    A = np.zeros((n_c, n_c))
    B = np.zeros((n_c, m))
    if held:
        B[:m] = np.eye(m)  # e_k becomes e_{k-1}
        A[m:held, : held - m] = np.eye(held - m)  # the older ones move down
    C = np.zeros((1, n_c))
    C[:, :held] = K_s[:, m:]
    if integral:
        A[-1, -1] = 1.0
        B[-1, 0] = plant.dt
        C[0, -1] = -gain[0, -1]
    return DiscreteStateSpace(A, B, C, K_s[:, :m], plant.dt)
