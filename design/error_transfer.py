"""The model's held-out error propagated through a designed loop: the J and voltage a design will carry.

The held-out training episodes ran the training controller ``K0``; what their logs differ by from
the prediction, ``r`` (theta, alpha), is what that loop leaves of the model's error ``d`` at the
plant's output: ``r = (I + P K0)^-1 d``, ``P`` the design plant from the voltage to the angles
(:meth:`~design.plant.LinearPlant.frequency_response`), ``K0`` the controller from the tracking
errors to the voltage (the model file keeps both sides' band spectra:
:mod:`~qube_koopman.identify.uncertainty.spectra`). So ``d = (I + P K0) r``, per frequency band, and

- the part of ``d`` that follows the predicted voltage ``u`` is a plant error ``dP = <d u^H> / <|u|^2>``
  (pooled over the held-out episodes: too few frequencies per band in one episode);
- the rest, ``n = d - dP u``, is noise to the loop (the encoders' quantization, disturbances the
  model does not know): its spectrum is kept per episode.

Under a designed controller ``K`` the same error leaves ``S (dP u + n)`` of angle error, with
``S = (I + P K)^-1``, and ``-T (dP u + n)`` of voltage, ``T = K S = K / (1 + K P)``. Added to the
design's predicted episodes (their own band spectra of ``u`` and of the tracking errors ``e``), the
mean squares grow by, per band::

    voltage:  |T dP|^2 <|u|^2> - 2 Re(T dP) <|u|^2> + T <n n^H> T^H
    J:        |S dP|^2 <|u|^2> + 2 Re((S dP)^T <e u^H>^*) + tr(S <n n^H> S^H)

(the noise uncorrelated with the excitation). With ``K = K0`` this gives back each held-out
episode's measured mean squares, to the bands' resolution; with a design that feeds back harder,
the larger share of the sensors' noise it turns into voltage, which a ratio measured under ``K0``
misses (on the twin, a design predicted at 1.47 V RMS drew 1.65 V; the held-out ratio said 1.55, the
propagation 1.64).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from qube_koopman.core.lti import DiscreteStateSpace
from qube_koopman.design.plant import LinearPlant
from qube_koopman.identify.uncertainty.spectra import ErrorSpectra, band_sums

__all__ = ["PropagatedError", "propagate_error", "loop_spectra"]


def _h(a: np.ndarray) -> np.ndarray:
    """Conjugate transpose of the last two axes."""
    return np.conj(np.swapaxes(a, -1, -2))


@dataclass(frozen=True)
class PropagatedError:
    """The held-out error under a designed loop.

    Parameters
    ----------
    shift : ndarray of shape (2,)
        ``log(F_expected / F_predicted)`` of the design's J and voltage RMS.
    residuals : ndarray of shape (n, 2)
        ``log(F_measured / F_expected)`` of each held-out episode's J and voltage RMS under its own
        controller: what the propagation does not account for, episode by episode.
    """

    shift: np.ndarray
    residuals: np.ndarray


def loop_spectra(theta, target_theta, alpha, voltage, edges: np.ndarray, dt: float, skip: int):
    """Band sums of predicted episodes, pooled (their mean): ``<|u|^2>`` (n_bands,) and ``<e u^H>`` (n_bands, 2).

    Parameters
    ----------
    theta, target_theta, alpha, voltage : ndarray of shape (n_episodes, n_samples)
        The predicted loop (:class:`~design.predict.LoopTrajectories`' arrays).
    edges : ndarray
        The bands (Hz) of the model file's spectra.
    dt : float
        Sample period (s).
    skip : int
        Samples left out at each episode's start.
    """
    uu, eu = [], []
    for th, ref, al, u in zip(theta, target_theta, alpha, voltage):
        v = np.asarray(u, dtype=float)[skip:, None]
        e = np.column_stack([np.asarray(th)[skip:] - np.asarray(ref)[skip:], np.asarray(al)[skip:]])
        uu.append(band_sums(edges, dt, v, v)[:, 0, 0].real)
        eu.append(band_sums(edges, dt, e, v)[:, :, 0])
    return np.mean(uu, axis=0), np.mean(eu, axis=0)


def _additions(P, K, dP, noise, uu, eu) -> tuple[float, float]:
    """Mean squares added to J and to the voltage (module docstring) by the error under controller ``K``."""
    T = K / (1.0 + K @ P)  # (bands, 1, 2)
    S = np.eye(2) - P @ T  # (bands, 2, 2)
    g = (T @ dP)[:, 0, 0]
    voltage = np.sum(np.abs(g) ** 2 * uu - 2 * g.real * uu + (T @ noise @ _h(T))[:, 0, 0].real)
    SdP = (S @ dP)[:, :, 0]
    J = np.sum(
        np.sum(np.abs(SdP) ** 2, axis=1) * uu
        + 2 * np.sum(SdP * np.conj(eu), axis=1).real
        + np.trace(S @ noise @ _h(S), axis1=1, axis2=2).real
    )
    return float(J), float(voltage)


def propagate_error(
    spectra: ErrorSpectra,
    held_out: np.ndarray,
    plant: LinearPlant,
    controller: DiscreteStateSpace,
    uu: np.ndarray,
    eu: np.ndarray,
    predicted: tuple[float, float],
) -> PropagatedError:
    """The held-out error propagated through ``controller`` (module docstring).

    Parameters
    ----------
    spectra : ErrorSpectra
        The model file's held-out error spectra.
    held_out : ndarray of shape (n, 2, 3)
        The same episodes' measured and predicted ``[J, voltage RMS, voltage peak]``.
    plant : LinearPlant
        The design plant.
    controller : DiscreteStateSpace
        The designed controller (tracking errors in, voltage out).
    uu, eu : ndarray
        The design's predicted episodes' pooled band sums (:func:`loop_spectra`).
    predicted : (float, float)
        The design's predicted J and voltage RMS on those episodes.

    Returns
    -------
    PropagatedError
    """
    P = plant.frequency_response(spectra.centres)  # (bands, 2, 1)
    M = np.eye(2) + P @ spectra.controller[:, :, None, :]  # (n, bands, 2, 2): I + P K0 of each episode
    DU = M @ spectra.error_input[..., None]  # (n, bands, 2, 1)
    DD = M @ spectra.error @ _h(M)
    UU = spectra.input[..., None, None]
    dP = DU.sum(axis=0) / np.maximum(UU.sum(axis=0), np.finfo(float).tiny)  # (bands, 2, 1)
    noise = DD - dP @ _h(DU) - DU @ _h(dP) + dP @ _h(dP) * UU
    mean_noise = noise.mean(axis=0)
    K = controller.frequency_response(spectra.centres)[:, :, :2]  # (bands, 1, 2)
    J_add, v_add = _additions(P, K, dP, mean_noise, uu, eu)
    J, V = predicted
    shift = np.array([np.log((J + J_add) / J), 0.5 * np.log((V**2 + v_add) / V**2)])
    residuals = []
    for j in range(spectra.n_episodes):
        J_j, v_j = _additions(
            P, spectra.controller[j][:, None, :], dP, mean_noise, spectra.input[j], spectra.tracking_input[j]
        )
        (J_m, V_m, _), (J_p, V_p, _) = held_out[j]
        residuals.append([np.log(J_m / (J_p + J_j)), 0.5 * np.log(V_m**2 / (V_p**2 + v_j))])
    with np.errstate(invalid="ignore"):
        return PropagatedError(shift, np.array(residuals, dtype=float))
