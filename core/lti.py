"""Discrete-time linear state-space systems.

The one container for a discrete LTI system (A, B, C, D, dt) in the project:
controllers run with it in the loop and in simulations, logs store its
matrices, and identification reads them back as the known controller.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

__all__ = [
    "DiscreteStateSpace",
    "controller_inputs",
    "replay_controller",
    "padded_realization",
    "spectral_radius",
    "same_system",
    "with_output_delay",
    "held_late",
]


def spectral_radius(matrix) -> float:
    """The largest magnitude of the eigenvalues of a square matrix: ``x[k+1] = A x[k]`` is asymptotically
    stable when it is below 1. The one way every package computes it (models, controllers, designs).

    Parameters
    ----------
    matrix : array_like of shape (n, n)
        The state matrix; with n = 0 (a system without states) the radius is 0.

    Returns
    -------
    float

    Examples
    --------
    >>> spectral_radius([[0.5, 1.0], [0.0, -0.8]])
    0.8
    """
    matrix = np.asarray(matrix)
    return float(np.max(np.abs(np.linalg.eigvals(matrix)))) if matrix.size else 0.0


def _as_matrix(value, name: str) -> np.ndarray:
    arr = np.atleast_2d(np.asarray(value, dtype=float))
    if arr.ndim != 2:
        raise ValueError(f"{name} must be a 2-D matrix, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} has non-finite entries")
    return arr


@dataclass(frozen=True, eq=False)
class DiscreteStateSpace:
    """A discrete-time LTI system ``x[k+1] = A x[k] + B u[k]``, ``y[k] = C x[k] + D u[k]``.

    Parameters
    ----------
    A, B, C, D : array_like
        State-space matrices of shapes (n, n), (n, p), (q, n) and (q, p).
    dt : float
        Sample period in seconds (positive).

    Raises
    ------
    ValueError
        If the shapes are inconsistent, an entry is non-finite or ``dt`` is
        not positive.

    Examples
    --------
    A discrete integrator (the state sums the inputs) at the loop's 500 Hz:

    >>> integrator = DiscreteStateSpace(A=[[1.0]], B=[[1.0]], C=[[1.0]], D=[[0.0]], dt=0.002)
    >>> x, y = integrator.simulate([[1.0], [2.0], [3.0]])
    >>> y.ravel().tolist()
    [0.0, 1.0, 3.0]
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    dt: float

    def __post_init__(self) -> None:
        A = _as_matrix(self.A, "A")
        B = _as_matrix(self.B, "B")
        C = _as_matrix(self.C, "C")
        D = _as_matrix(self.D, "D")
        n = A.shape[0]
        if A.shape != (n, n):
            raise ValueError(f"A must be square, got shape {A.shape}")
        if B.shape[0] != n:
            raise ValueError(f"B has {B.shape[0]} rows but A has {n} states")
        if C.shape[1] != n:
            raise ValueError(f"C has {C.shape[1]} columns but A has {n} states")
        if D.shape != (C.shape[0], B.shape[1]):
            raise ValueError(f"D must have shape {(C.shape[0], B.shape[1])} (outputs x inputs), got {D.shape}")
        if not (np.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"dt must be a positive number of seconds, got {self.dt!r}")
        for name, value in zip("ABCD", (A, B, C, D)):
            value.setflags(write=False)
            object.__setattr__(self, name, value)
        object.__setattr__(self, "dt", float(self.dt))

    @property
    def n_states(self) -> int:
        """Number of states."""
        return self.A.shape[0]

    @property
    def n_inputs(self) -> int:
        """Number of inputs."""
        return self.B.shape[1]

    @property
    def n_outputs(self) -> int:
        """Number of outputs."""
        return self.C.shape[0]

    def simulate(self, u: np.ndarray, x0: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Run the system over an input sequence, or over a batch of them at once.

        Parameters
        ----------
        u : ndarray of shape (..., n_samples, n_inputs)
            Input at each sample; leading axes run as a batch of independent sequences
            (one pass over the samples for all of them).
        x0 : ndarray of shape (n_states,) or (..., n_states), optional
            Initial state (one for all sequences, or one each); zero by default.

        Returns
        -------
        x : ndarray of shape (..., n_samples, n_states)
            State at each sample (``x[..., 0, :] = x0``), before that sample's update.
        y : ndarray of shape (..., n_samples, n_outputs)
            Output at each sample.
        """
        u = np.asarray(u, dtype=float)
        if u.ndim == 1 and self.n_inputs == 1:
            u = u[:, None]
        if u.ndim < 2 or u.shape[-1] != self.n_inputs:
            raise ValueError(f"u must have shape (..., n_samples, {self.n_inputs}), got {u.shape}")
        batch = u.shape[:-2]
        x = np.empty(u.shape[:-1] + (self.n_states,))
        if x0 is None:
            state = np.zeros(batch + (self.n_states,))
        else:
            x0 = np.asarray(x0, dtype=float)
            x0 = x0.reshape(self.n_states) if x0.size == self.n_states else x0.reshape(x0.shape[:-1] + (self.n_states,))
            state = np.array(np.broadcast_to(x0, batch + (self.n_states,)))
        # B u for all samples at once; the recursion itself is inherently sequential.
        bu = u @ self.B.T
        A = self.A
        if not batch:  # one sequence: the product as it always ran (a batch's may round a last bit apart)
            for k in range(u.shape[0]):
                x[k] = state
                state = A @ state + bu[k]
        else:  # every sequence in one step: the per-sample cost is Python's, not the arithmetic's
            At = np.ascontiguousarray(A.T)
            for k in range(u.shape[-2]):
                x[..., k, :] = state
                state = state @ At + bu[..., k, :]
        y = x @ self.C.T + u @ self.D.T
        return x, y

    def frequency_response(self, frequencies: np.ndarray) -> np.ndarray:
        """``C (z I - A)^-1 B + D`` at ``z = exp(2 pi j f dt)`` for each frequency ``f``.

        python-control's ``frequency_response`` gives the same; this one solves all the
        frequencies in a few batched solves, without importing python-control (and matplotlib).

        Parameters
        ----------
        frequencies : array_like of shape (n_f,)
            Frequencies (Hz).

        Returns
        -------
        ndarray of complex, shape (n_f, n_outputs, n_inputs)
            Infinite where ``z`` is a pole (an integrator at 0 Hz).
        """
        z = np.exp(2j * np.pi * np.asarray(frequencies, dtype=float).ravel() * self.dt)
        n, B = self.n_states, self.B
        out = np.empty((len(z), self.n_outputs, self.n_inputs), dtype=complex)
        for start in range(0, len(z), 256):  # bounded memory: 256 systems of this size at a time
            w = z[start : start + 256]
            try:
                resolvent = np.linalg.solve(
                    w[:, None, None] * np.eye(n) - self.A, np.broadcast_to(B, (len(w), *B.shape))
                )
            except np.linalg.LinAlgError:  # a pole on the grid: those frequencies one at a time
                resolvent = np.array([self._resolvent(one) for one in w])
            with np.errstate(invalid="ignore"):  # inf times a zero entry at a pole
                out[start : start + 256] = self.C @ resolvent + self.D
        return out

    def _resolvent(self, z: complex) -> np.ndarray:
        """``(z I - A)^-1 B``, infinite at a pole."""
        try:
            return np.linalg.solve(z * np.eye(self.n_states) - self.A, self.B)
        except np.linalg.LinAlgError:
            return np.full(self.B.shape, np.inf, dtype=complex)

    def as_dict(self) -> dict:
        """Plain-data form (lists of lists), for logs and model files."""
        return {"A": self.A.tolist(), "B": self.B.tolist(), "C": self.C.tolist(), "D": self.D.tolist(), "dt": self.dt}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "DiscreteStateSpace":
        """Inverse of :meth:`as_dict`."""
        missing = {"A", "B", "C", "D", "dt"} - set(data)
        if missing:
            raise ValueError(f"state-space data misses {sorted(missing)}")
        return cls(data["A"], data["B"], data["C"], data["D"], data["dt"])

    def to_control(self):
        """The same system as a ``control.StateSpace`` (discrete, with ``dt``)."""
        import control  # imported lazily: python-control pulls in matplotlib

        return control.ss(self.A, self.B, self.C, self.D, self.dt)


def replay_controller(
    controller: DiscreteStateSpace, references, measured, x0: np.ndarray | None = None, feedforward=None
) -> tuple[np.ndarray, np.ndarray]:
    """Re-run a controller over logged samples: its state and output along the tracking error.

    Every controller of the project maps the tracking error ``e = references - measured``
    (one channel per fed-back state), and optionally the feedforward, to the plant input; this
    is the one place that replays it offline, from ``x0`` (zero, as on the rig, by default).

    Parameters
    ----------
    controller : DiscreteStateSpace
        The controller: ``n_errors`` tracking-error channels in, then, if it has more inputs,
        the feedforward's channels (:func:`controller_inputs`).
    references, measured : array_like of shape (..., n_samples, n_errors) or (n_samples,)
        Logged references and measured outputs; 1-D for a one-channel controller. Leading
        axes replay a batch of episodes of equal length in one pass.
    x0 : ndarray of shape (n_states,), optional
        Initial controller state.
    feedforward : array_like of shape (..., n_samples, n_f) or (n_samples,), optional
        Logged feedforward; needed only by a controller that takes it as an input.

    Returns
    -------
    states : ndarray of shape (..., n_samples, n_states)
        State before each sample's update.
    outputs : ndarray of shape (..., n_samples, n_outputs)
        Controller output ``C x + D [e; f]`` at each sample (before the feedforward is added
        to it).
    """
    return controller.simulate(controller_inputs(controller, references, measured, feedforward), x0)


def controller_inputs(controller: DiscreteStateSpace, references, measured, feedforward=None) -> np.ndarray:
    """A controller's input sequence: the tracking errors, then the feedforward if it takes it.

    The loop always adds the feedforward to the controller's output; a controller whose inputs
    outnumber the tracking errors also sees the feedforward itself (its last inputs), e.g. to
    shape or cancel it (core/CONTROLLER_FORMAT.md).

    Parameters
    ----------
    controller : DiscreteStateSpace
        The controller whose inputs these are.
    references, measured : array_like of shape (..., n_samples, n_errors) or (n_samples,)
        References and measured outputs (any leading batch axes).
    feedforward : array_like of shape (..., n_samples, n_f) or (..., n_samples), optional
        The feedforward; ignored by a controller of the tracking errors only.

    Returns
    -------
    ndarray of shape (..., n_samples, controller.n_inputs)
        ``r - y``, then ``f`` when the controller takes it.

    Raises
    ------
    ValueError
        When the controller takes the feedforward and none (or one of another width) is given.
    """
    error = np.asarray(references, dtype=float) - np.asarray(measured, dtype=float)
    if error.ndim == 1:
        error = error[:, None]
    n_e = error.shape[-1]
    if controller.n_inputs == n_e:
        return error
    if feedforward is None:
        raise ValueError(
            f"the controller takes {controller.n_inputs} inputs; the tracking errors have shape "
            f"{error.shape} and no feedforward is given"
        )
    f = np.asarray(feedforward, dtype=float).reshape(*error.shape[:-1], -1)
    if controller.n_inputs != n_e + f.shape[-1]:
        raise ValueError(
            f"the controller takes {controller.n_inputs} inputs, not the {n_e} tracking errors and "
            f"{f.shape[-1]} feedforward channel{'s' if f.shape[-1] != 1 else ''} of the data"
        )
    return np.concatenate([error, f], axis=-1)


def padded_realization(system: DiscreteStateSpace, n_states: int, seed: int = 0) -> DiscreteStateSpace:
    """The same transfer function in ``n_states`` states, every state coupled to every other.

    The extra states are stable (eigenvalues drawn in (-0.95, 0.95)), driven by the inputs and
    absent from the output; then a random orthogonal change of coordinates mixes them with the
    system's own. For tests and benchmarks of large controllers that must behave like a known one.

    Parameters
    ----------
    system : DiscreteStateSpace
        The system to realize again.
    n_states : int
        States of the result, at least ``system.n_states``.
    seed : int
        Seed of the extra states' dynamics and of the change of coordinates.

    Returns
    -------
    DiscreteStateSpace
    """
    extra = n_states - system.n_states
    if extra < 0:
        raise ValueError(f"n_states must be at least {system.n_states}, got {n_states}")
    rng = np.random.default_rng(seed)
    A = np.zeros((n_states, n_states))
    A[: system.n_states, : system.n_states] = system.A
    A[system.n_states :, system.n_states :] = np.diag(rng.uniform(-0.95, 0.95, extra))
    B = np.vstack([system.B, rng.standard_normal((extra, system.n_inputs))])
    C = np.hstack([system.C, np.zeros((system.n_outputs, extra))])
    Q, _ = np.linalg.qr(rng.standard_normal((n_states, n_states)))
    return DiscreteStateSpace(Q @ A @ Q.T, Q @ B, C @ Q.T, system.D, system.dt)


def same_system(a: DiscreteStateSpace, b: DiscreteStateSpace) -> bool:
    """Whether two discrete systems have the same matrices and period (to 1e-12)."""
    return a.dt == b.dt and all(
        x.shape == y.shape and np.allclose(x, y, rtol=1e-12, atol=1e-12)
        for x, y in zip((a.A, a.B, a.C, a.D), (b.A, b.B, b.C, b.D))
    )


def with_output_delay(system: DiscreteStateSpace, samples: float) -> DiscreteStateSpace:
    """``system`` followed by a delay of ``samples`` sample periods (a fraction interpolates).

    The output is ``(1 - w) y(k - n) + w y(k - n - 1)`` with ``n`` the whole samples and ``w`` the
    fraction: the average over a sample of a command held ``samples`` periods late, as the
    simulated pendulum applies its transport delay (``PendulumParameters.delay``). The states
    are ``system``'s, then its past outputs ``y(k - 1), ..., y(k - n - 1)`` (none past ``y(k - n)``
    when ``w`` is 0), newest first: a loop's controller wrapped so models the host's latency
    between computing a command and the motor receiving it.

    Parameters
    ----------
    system : DiscreteStateSpace
        The system whose output is delayed.
    samples : float
        The delay in sample periods, 0 or more.

    Returns
    -------
    DiscreteStateSpace
        With ``system.n_states + n_past * system.n_outputs`` states.

    Examples
    --------
    A gain of 2 delayed by one and a half samples:

    >>> gain = DiscreteStateSpace(A=np.zeros((0, 0)), B=np.zeros((0, 1)), C=np.zeros((1, 0)), D=[[2.0]], dt=0.002)
    >>> _, y = with_output_delay(gain, 1.5).simulate([[1.0], [0.0], [0.0], [0.0]])
    >>> y.ravel().tolist()
    [0.0, 1.0, 1.0, 0.0]
    """
    samples = float(samples)
    if not (np.isfinite(samples) and samples >= 0):
        raise ValueError(f"the delay must be a finite number of samples, 0 or more, got {samples}")
    whole = int(np.floor(samples))
    fraction = samples - whole
    n_past = whole + (fraction > 0)
    n, q, p = system.n_states, system.n_outputs, system.n_inputs
    A = np.zeros((n + n_past * q, n + n_past * q))
    B = np.zeros((n + n_past * q, p))
    A[:n, :n], B[:n] = system.A, system.B
    if n_past:
        A[n : n + q, :n], B[n : n + q] = system.C, system.D  # the newest past output: y(k)
        for j in range(1, n_past):  # older ones shift down
            A[n + j * q : n + (j + 1) * q, n + (j - 1) * q : n + j * q] = np.eye(q)
    C, D = np.zeros((q, A.shape[0])), np.zeros((q, p))
    for age, weight in ((whole, 1.0 - fraction), (whole + 1, fraction)):
        if weight == 0:
            continue
        if age == 0:
            C[:, :n] += weight * system.C
            D += weight * system.D
        else:
            C[:, n + (age - 1) * q : n + age * q] += weight * np.eye(q)
    return DiscreteStateSpace(A, B, C, D, system.dt)


def held_late(signal: np.ndarray, samples: float) -> np.ndarray:
    """A signal held ``samples`` periods late: ``(1 - w) s(k - n) + w s(k - n - 1)``, as
    :func:`with_output_delay` delays an output (``n`` whole samples, ``w`` the fraction), the first
    value standing in before the start.

    Parameters
    ----------
    signal : ndarray of shape (n_samples, ...)
        Sampled along its first axis.
    samples : float
        The delay in sample periods, 0 or more.

    Returns
    -------
    ndarray
        The same shape.

    Examples
    --------
    >>> held_late(np.array([1.0, 2.0, 3.0, 4.0]), 1.5).tolist()
    [1.0, 1.0, 1.5, 2.5]
    """
    whole, w = int(np.floor(samples)), samples - np.floor(samples)
    index = np.arange(len(signal))
    return (1 - w) * signal[np.maximum(index - whole, 0)] + w * signal[np.maximum(index - whole - 1, 0)]
