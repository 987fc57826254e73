"""The held-out episodes' prediction error as band spectra, kept for propagating it through another loop.

A training episode held out of a fit and predicted in closed loop under the controller it ran
differs from its log by ``r = x_measured - x_predicted`` (theta, alpha). The controller is known
and linear, so the logged voltage differs from the predicted one by ``-K r`` (``K``: the
controller from the tracking errors to the voltage), to rounding. Read as what the loop leaves of
an error ``d`` at the plant's output, ``r = (I + P K)^-1 d`` (``P``: the plant from the voltage to
the angles): ``d`` is the model's error on that episode, part of it following the voltage (a plant
error, ``dP u``), the rest not (sensor noise, disturbances the model does not know). Under another
controller ``K'`` the same ``d`` leaves ``(I + P K')^-1 d`` of angle error and ``-K' (I + P K')^-1 d``
of voltage: ``qube-design`` propagates it so (its ``error_transfer`` module), where
a ratio measured under the training controller would not transfer (a loop that feeds back harder
amplifies the sensors' noise more).

What a fit keeps of each held-out episode are the second moments that takes, summed over
frequency bands (a model file holds sums, not the episodes): of ``r``, of ``r`` with the predicted
voltage ``u``, of ``u``, and of the predicted tracking errors ``e = [theta - theta_ref, alpha]`` with
``u``, after the same ``skip`` samples as the cost, each band's sum normalized so that the sums
over the bands are the mean squares (Parseval). The controller's response is kept at each band's
centre. The bands are geometric from 0.04 Hz (the 0.05 Hz resolution of a 20 s episode) to the
Nyquist frequency, merged where too few of the episodes' frequencies fall in them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from qube_koopman.core.lti import DiscreteStateSpace

__all__ = ["ErrorSpectra", "band_sums", "error_spectra", "BANDS"]

#: Geometric band edges between 0.04 Hz and the Nyquist frequency (before merging sparse bands).
BANDS = 40


def _edges(dt: float) -> np.ndarray:
    return np.concatenate([[0.0], np.geomspace(0.04, 0.5 / dt, BANDS)])


def _frequencies(n: int, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """The one-sided DFT's frequencies and the weights that make its sums mean squares (Parseval)."""
    f = np.fft.rfftfreq(n, dt)
    w = np.full(len(f), 2.0)
    w[0] = 1.0
    if n % 2 == 0:
        w[-1] = 1.0
    return f, w / n**2


def _band_of(edges: np.ndarray, frequencies: np.ndarray) -> np.ndarray:
    """The band of each frequency (one at or past the last edge in the last band)."""
    return np.clip(np.searchsorted(edges, frequencies, side="right") - 1, 0, len(edges) - 2)


def band_sums(edges: np.ndarray, dt: float, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``sum over each band of A(f) B(f)^H``, weighted so that the bands add up to ``mean(a b^T)``.

    Parameters
    ----------
    edges : ndarray of shape (n_bands + 1,)
        Band edges (Hz), the first 0; a frequency at or past the last edge counts in the last band.
    dt : float
        Sample period (s).
    a, b : ndarray of shape (n_samples, p) and (n_samples, q)
        Two signals of one episode.

    Returns
    -------
    ndarray of complex, shape (n_bands, p, q)
    """
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    f, w = _frequencies(len(a), dt)
    A, B = np.fft.rfft(a, axis=0), np.fft.rfft(b, axis=0)
    band = _band_of(edges, f)
    out = np.zeros((len(edges) - 1, a.shape[1], b.shape[1]), dtype=complex)
    np.add.at(out, band, w[:, None, None] * A[:, :, None] * np.conj(B)[:, None, :])
    return out


@dataclass(frozen=True)
class ErrorSpectra:
    """Band sums of held-out episodes' prediction errors (module docstring), and their controllers' responses.

    Parameters
    ----------
    edges : ndarray of shape (n_bands + 1,)
        Band edges (Hz).
    centres : ndarray of shape (n_bands,)
        Where each band's responses are evaluated (Hz).
    controller : ndarray of complex, shape (n, n_bands, 2)
        Each episode's controller from the tracking errors (theta, alpha) to the voltage.
    error : ndarray of complex, shape (n, n_bands, 2, 2)
        ``r r^H``.
    error_input : ndarray of complex, shape (n, n_bands, 2)
        ``r u^H``.
    input : ndarray of shape (n, n_bands)
        ``|u|^2``.
    tracking_input : ndarray of complex, shape (n, n_bands, 2)
        ``e u^H``.
    dt : float
        Sample period (s).
    """

    edges: np.ndarray
    centres: np.ndarray
    controller: np.ndarray
    error: np.ndarray
    error_input: np.ndarray
    input: np.ndarray
    tracking_input: np.ndarray
    dt: float

    def as_dict(self) -> dict:
        """Plain data for the model file: complex arrays as ``{"re": ..., "im": ...}`` (7 significant digits),
        ``error`` by its three distinct entries (it is Hermitian), each controller's response once."""
        distinct: list[np.ndarray] = []
        index = []
        for response in self.controller:
            same = [i for i, known in enumerate(distinct) if np.array_equal(known, response)]
            if not same:
                distinct.append(response)
            index.append(same[0] if same else len(distinct) - 1)
        error = np.stack([self.error[..., 0, 0], self.error[..., 1, 1], self.error[..., 0, 1]], axis=-1)
        arrays = {
            "controllers": np.array(distinct),
            "error": error,
            "error_input": self.error_input,
            "tracking_input": self.tracking_input,
        }
        out: dict = {"dt": self.dt, "edges_hz": _plain(self.edges), "centres_hz": _plain(self.centres)}
        out.update({name: {"re": _plain(value.real), "im": _plain(value.imag)} for name, value in arrays.items()})
        out["controller_of_episode"] = index
        out["input"] = _plain(self.input)
        return out

    @classmethod
    def from_dict(cls, data: dict) -> ErrorSpectra:
        """Inverse of :meth:`as_dict`.

        Raises
        ------
        ValueError
            Naming the entry, when one is missing, non-finite or of a shape that does not fit the others.
        """

        def real(name: str) -> np.ndarray:
            if name not in data:
                raise ValueError(f"{name} is missing")
            try:
                value = np.asarray(data[name], dtype=float)
            except (TypeError, ValueError):
                raise ValueError(f"{name} is not an array of numbers") from None
            if not np.all(np.isfinite(value)):
                raise ValueError(f"{name} has a non-finite entry")
            return value

        def complex_array(name: str, shape: tuple) -> np.ndarray:
            if not isinstance(data.get(name), dict):
                raise ValueError(f"{name} is missing (an object of re and im)")
            parts = data[name]
            try:
                re, im = np.asarray(parts["re"], dtype=float), np.asarray(parts["im"], dtype=float)
            except (KeyError, TypeError, ValueError):
                raise ValueError(f"{name} must hold re and im of shape {shape}") from None
            if re.shape != shape or im.shape != shape:
                raise ValueError(f"{name} must hold re and im of shape {shape}, not {re.shape} and {im.shape}")
            if not (np.all(np.isfinite(re)) and np.all(np.isfinite(im))):
                raise ValueError(f"{name} has a non-finite entry")
            return re + 1j * im

        try:
            dt = float(data.get("dt", np.nan))
            edges, centres, power = real("edges_hz"), real("centres_hz"), real("input")
            if not dt > 0:
                raise ValueError("dt must be a positive sample period")
            n_b = len(centres)
            if edges.shape != (n_b + 1,) or power.ndim != 2 or power.shape[1] != n_b:
                raise ValueError(
                    f"edges_hz {edges.shape}, centres_hz ({n_b},) and input {power.shape} disagree on the bands"
                )
            n = power.shape[0]
            index = np.asarray(data.get("controller_of_episode", []))
            responses = data.get("controllers", {}).get("re") if isinstance(data.get("controllers"), dict) else None
            k = len(responses) if isinstance(responses, list) else 0
            if index.shape != (n,) or index.dtype.kind not in "iu" or np.any(index < 0) or np.any(index >= k):
                raise ValueError(f"controller_of_episode must give each of the {n} episodes one of {k} controllers")
            packed = complex_array("error", (n, n_b, 3))
        except (TypeError, AttributeError) as exc:
            raise ValueError(f"malformed ({exc})") from None
        error = np.empty(packed.shape[:-1] + (2, 2), dtype=complex)
        error[..., 0, 0], error[..., 1, 1] = packed[..., 0], packed[..., 1]
        error[..., 0, 1], error[..., 1, 0] = packed[..., 2], np.conj(packed[..., 2])
        return cls(
            edges=edges,
            centres=centres,
            controller=complex_array("controllers", (k, n_b, 2))[index],
            error=error,
            error_input=complex_array("error_input", (n, n_b, 2)),
            input=power,
            tracking_input=complex_array("tracking_input", (n, n_b, 2)),
            dt=dt,
        )

    @property
    def n_episodes(self) -> int:
        """Held-out episodes."""
        return len(self.input)


def _plain(a: np.ndarray) -> list:
    """``a`` as nested lists of floats of 7 significant digits (the model file's size; sums known to far less)."""
    return np.vectorize(lambda v: float(f"{v:.7g}"), otypes=[float])(a).tolist() if a.size else a.tolist()


def _merged_edges(lengths: Sequence[int], dt: float) -> np.ndarray:
    """The geometric edges with each band holding, over the episodes, at least as many frequencies as episodes."""
    edges = _edges(dt)
    counts = np.zeros(len(edges) - 1, dtype=int)
    for n in lengths:
        f, _ = _frequencies(n, dt)
        counts += np.bincount(_band_of(edges, f), minlength=len(counts))
    kept, held = [0.0], 0
    for i, count in enumerate(counts):
        held += count
        if held >= len(lengths) and i < len(counts) - 1:
            kept.append(edges[i + 1])
            held = 0
    kept.append(edges[-1])
    if held < len(lengths) and len(kept) > 2:  # the last band too sparse: merged into the one before
        kept.pop(-2)
    return np.array(kept)


def _centres(edges: np.ndarray) -> np.ndarray:
    """Geometric centres; the first band (which holds 0 Hz) at half its width, off an integrator's pole."""
    centres = np.sqrt(edges[:-1] * edges[1:])
    centres[0] = edges[1] / 2
    return centres


def error_spectra(
    measured: Sequence[np.ndarray],
    predicted: Sequence[np.ndarray],
    voltage: Sequence[np.ndarray],
    target_theta: Sequence[np.ndarray],
    controllers: Sequence[DiscreteStateSpace],
    dt: float,
    skip: int,
) -> ErrorSpectra:
    """The band sums of held-out episodes (module docstring).

    Parameters
    ----------
    measured, predicted : sequence of ndarray of shape (n_samples, 2)
        Each episode's logged and predicted theta, alpha (rad).
    voltage : sequence of ndarray of shape (n_samples,)
        The predicted voltage: the controller on the predicted angles, feedforward included (V).
    target_theta : sequence of ndarray of shape (n_samples,)
        The arm's reference (rad).
    controllers : sequence of DiscreteStateSpace
        The controller each episode ran (its first two inputs: the tracking errors).
    dt : float
        Sample period (s).
    skip : int
        Samples left out at each episode's start (those of the cost).

    Returns
    -------
    ErrorSpectra

    Raises
    ------
    ValueError
        When an episode has fewer than 2 samples past ``skip``, or its prediction diverged.
    """
    lengths = [len(x) - skip for x in measured]
    if min(lengths, default=0) < 2:
        raise ValueError(f"held-out error spectra need 2 samples or more past the first {skip} of each episode")
    for i, (x, p, u) in enumerate(zip(measured, predicted, voltage)):
        if not (np.all(np.isfinite(x[skip:])) and np.all(np.isfinite(p[skip:])) and np.all(np.isfinite(u[skip:]))):
            raise ValueError(f"held-out episode {i}: its prediction diverged (non-finite), no spectrum to take")
    edges = _merged_edges(lengths, dt)
    centres = _centres(edges)
    parts: dict[str, list] = {name: [] for name in ("controller", "error", "error_input", "input", "tracking_input")}
    responses: dict[int, np.ndarray] = {}
    for x, p, u, target, controller in zip(measured, predicted, voltage, target_theta, controllers):
        r = (np.asarray(x, dtype=float) - np.asarray(p, dtype=float))[skip:, :2]
        v = np.asarray(u, dtype=float)[skip:, None]
        e = np.column_stack([p[skip:, 0] - np.asarray(target, dtype=float)[skip:], p[skip:, 1]])
        if id(controller) not in responses:
            responses[id(controller)] = controller.frequency_response(centres)[:, 0, :2]
        parts["controller"].append(responses[id(controller)])
        parts["error"].append(band_sums(edges, dt, r, r))
        parts["error_input"].append(band_sums(edges, dt, r, v)[:, :, 0])
        parts["input"].append(band_sums(edges, dt, v, v)[:, 0, 0].real)
        parts["tracking_input"].append(band_sums(edges, dt, e, v)[:, :, 0])
    arrays = {name: np.array(values) for name, values in parts.items()}
    return ErrorSpectra(edges=edges, centres=centres, dt=float(dt), **arrays)
