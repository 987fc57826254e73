"""The linear plant a design works on: the identified plant as a shift register of past measurements.

An identified plant model (``identify``) predicts by re-lifting: each step it lifts the last
``n_delays + 1`` measured samples ``x_k, x_{k-1}, ..., x_{k-d}`` and advances the measured
states only, ``x_{k+1} = A_x lift(history) + B_x u_k`` (``A_x``, ``B_x``: the rows of ``A`` and
``B`` that give the measured states). Its true state is therefore that history,

    s_k = [x_k; x_{k-1}; ...; x_{k-d}]          (2 (d + 1) states for theta, alpha)
    s_{k+1} = F s_k + G u_k + c

with ``F``'s first rows the one-step map's Jacobian, the rest an exact shift, and ``c`` the
affine term (a ``Constant`` lifting step). For a lifting of order-1 monomials, delays and a
constant this *is* the plant model, exactly (the re-lifted prediction and this system agree
sample for sample). For liftings with nonlinear terms (monomials of higher order, sin/cos,
radial basis functions) it is the model's linearization at upright (zero history, zero
voltage), and :attr:`LinearPlant.note` says so. A lifting with the arm's Coulomb friction shape
is refused: its linearization at zero speed is the steepest part of a dry friction (slope
1 / width), not a model of the arm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from qube_koopman.identify.lifting import Constant, CoulombFriction, Delay, Polynomial
from qube_koopman.identify.models.model import KoopmanModel

__all__ = ["DesignError", "LinearPlant", "linear_plant", "IDENTIFY_FLAGS"]

#: The identification that gives a plant a design uses exactly (no linearization).
IDENTIFY_FLAGS = "qube-identify ... --poly 1 --delays N [--const] (no --trig, --rbf, --friction)"

#: Step of the central differences that linearize a nonlinear lifting at upright (rad).
_STEP = 1e-4


class DesignError(ValueError):
    """A model or weights a design cannot use, or a design that failed; the message says why."""


@dataclass(frozen=True)
class LinearPlant:
    """``s_{k+1} = F s_k + G u_k + c`` on the history ``s_k = [x_k; ...; x_{k-d}]`` of the measured states.

    Parameters
    ----------
    F : ndarray of shape (n, n)
        ``n = n_measured * (n_delays + 1)``; rows past the first ``n_measured`` shift the history.
    G : ndarray of shape (n, 1)
        Input column (zero past the first ``n_measured`` rows).
    c : ndarray of shape (n,)
        Affine term (zero past the first ``n_measured`` rows).
    n_measured : int
        Measured states (2: theta, alpha).
    n_delays : int
        Past samples in the history.
    dt : float
        Sample period (s).
    exact : bool
        True when this system is the plant model itself (a linear lifting), False when it is
        the model's linearization at upright.
    note : str
        What this system is, for the report.
    state_names : tuple of str
        The measured states' names.
    """

    F: np.ndarray
    G: np.ndarray
    c: np.ndarray
    n_measured: int
    n_delays: int
    dt: float
    exact: bool
    note: str
    state_names: tuple[str, ...] = ("theta", "alpha")

    @property
    def n_states(self) -> int:
        """States of the history, ``n_measured * (n_delays + 1)``."""
        return self.F.shape[0]

    def frequency_response(self, frequencies: np.ndarray) -> np.ndarray:
        """The plant from the voltage to the measured states at ``z = exp(2 pi j f dt)``, per frequency ``f`` (Hz).

        From its one-step rows, ``P(z) = (z I - sum_j A_j z^-j)^-1 b`` (``A_j``: the block of ``F`` on
        ``x_{k-j}``): a solve of the measured states' size per frequency, where the history's state
        space would need one of its full size. The same response as python-control's.

        Returns
        -------
        ndarray of complex, shape (n_f, n_measured, 1)
        """
        z = np.exp(2j * np.pi * np.asarray(frequencies, dtype=float).ravel() * self.dt)
        m, d = self.n_measured, self.n_delays
        blocks = self.F[:m].reshape(m, d + 1, m)  # [out, j, state]: the block on x_{k-j}
        lagged = np.einsum("wj,ojs->wos", z[:, None] ** -np.arange(d + 1), blocks)
        return np.linalg.solve(z[:, None, None] * np.eye(m) - lagged, np.broadcast_to(self.G[:m], (len(z), m, 1)))

    def to_control(self):
        """The plant from the voltage to the measured states, a discrete ``control.StateSpace``."""
        import control  # lazily: python-control imports matplotlib

        C = np.eye(self.n_measured, self.n_states)
        return control.ss(self.F, self.G, C, np.zeros((self.n_measured, 1)), self.dt)


def linear_plant(model: KoopmanModel) -> LinearPlant:
    """The shift-register plant of an identified plant model (exact, or linearized at upright).

    Parameters
    ----------
    model : KoopmanModel
        A plant model: input ``u`` (one voltage), no passthrough states.

    Returns
    -------
    LinearPlant

    Raises
    ------
    DesignError
        When the model is not a plant with one voltage input, or its lifting holds the arm's
        Coulomb friction shape; the message says which ``qube-identify`` flags to use.
    """
    if model.n_passthrough or tuple(model.input_signals) != ("u",) or model.input_lifting is not None:
        raise DesignError("the model is not a plant model with the voltage u as its input")
    if model.B.shape[1] != 1:
        raise DesignError(f"the plant model has {model.B.shape[1]} inputs; a design drives one voltage")
    steps = model.lifting.steps_
    if any(isinstance(step, CoulombFriction) for step in steps):
        raise DesignError(
            "its lifting holds the arm's Coulomb friction shape (--friction), whose linearization "
            f"at rest is no model of the arm; identify the plant for a design with {IDENTIFY_FLAGS}"
        )
    if model.dt is None:
        raise DesignError("the plant model has no sample period (dt): a design needs the discrete plant's")
    m, d = model.n_states, model.n_delays
    n = m * (d + 1)
    one_step = _one_step(model)
    exact = all(isinstance(s, (Delay, Constant)) or (isinstance(s, Polynomial) and s.order == 1) for s in steps)
    zero = np.zeros(n)
    c_x = one_step(zero)
    if exact:  # affine in the history: each column is exact
        J = np.column_stack([one_step(unit) - c_x for unit in np.eye(n)])
    else:  # central differences at upright
        J = np.column_stack([(one_step(_STEP * unit) - one_step(-_STEP * unit)) / (2 * _STEP) for unit in np.eye(n)])
    F = np.zeros((n, n))
    F[:m] = J
    F[m:, :-m] = np.eye(n - m)
    G = np.zeros((n, 1))
    G[:m, 0] = model.B[:m, 0]
    c = np.zeros(n)
    c[:m] = c_x
    note = (
        f"the identified plant itself: {d} delays of {', '.join(model.lifting.feature_names_in_)}"
        + (" and a constant" if np.any(c_x) else "")
        if exact
        else f"the identified plant's linearization at upright (zero history, zero voltage) over {d} delays: its "
        "lifting has nonlinear terms; for a plant a design uses exactly, identify with " + IDENTIFY_FLAGS
    )
    return LinearPlant(F, G, c, m, d, float(model.dt), exact, note, tuple(model.lifting.feature_names_in_))


def _one_step(model: KoopmanModel):
    """``s -> x_{k+1}`` at zero voltage: the model's re-lifted step from the history ``s`` (newest first)."""
    m, d = model.n_states, model.n_delays
    A_x = model.A[:m]

    def step(s: np.ndarray) -> np.ndarray:
        window = np.asarray(s, dtype=float).reshape(d + 1, m)[::-1]  # oldest first, as lifted
        return A_x @ model.lifting.transform(window)[-1]

    return step
