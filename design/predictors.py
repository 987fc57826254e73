"""The plant's multi-step predictors: the model's own, Korda & Mezić's lifted map, and the MPC's.

An MPC predicts the plant a horizon ahead from the measured history under the inputs it plans.
With an identified Koopman plant there are three ways to do it, started from the last ``d + 1``
measured samples ``x_{k-d} .. x_k`` and given the inputs ``u_k .. u_{k+K-1}``:

- ``"relifted"``: the model's own prediction (``qube-identify``'s free run,
  :meth:`~qube_koopman.identify.models.model.KoopmanModel.simulate`): each step lifts the last
  ``d + 1`` predicted samples again and advances the measured states with the rows of ``A``, ``B``
  that give them;
- ``"lifted"``: Korda & Mezić's (Automatica 2018): the history is lifted once, ``z_0 =
  lift(x_{k-d} .. x_k)``, then the lifted linear map ``z_{j+1} = A z_j + B u_{k+j}`` runs with no
  re-lifting, and theta, alpha are read from the lifted state's linear coordinates, ``x = C z``.
  Linear in ``z_0`` and the inputs, it is what a linear MPC can condense exactly, whatever the
  lifting; the predicted samples are ``C (A^j z_0 + sum_{i<j} A^(j-1-i) B u_{k+i})``;
- ``"upright"``: the MPC's (``qube-design --mpc``): the plant on its history
  (:func:`~qube_koopman.design.plant.linear_plant`), ``s_{j+1} = F s_j + G u_{k+j}``, with its
  affine term left out as the MPC leaves it. For a lifting of order-1 monomials and delays this is
  the model itself (its re-lifted prediction, but for the affine term of ``--const``); with
  nonlinear terms it is the model's linearization at upright.

For a lifting of order-1 monomials and delays whose delay rows shift exactly the first two agree
to rounding: re-lifting a linear lifting gives back the propagated state. With nonlinear features
they differ: ``A`` advances ``theta^2`` by its own fitted row where re-lifting squares the
predicted ``theta``.

:func:`score_predictors` scores them on episodes: from ``n_starts`` samples of each, the logged
plant input applied (the inputs the MPC would be choosing), each predictor's prediction ``K``
samples ahead against the measured sample, as ``qube-identify --horizon`` scores its K-step
predictions (R^2 per channel of the episode, averaged over episodes; the RMS error pooled).

Measured on the paper's held-out episodes (``bench/bench_mpc.py --only predictors``, docs/design.md):
at the MPC's 20 ticks the ``"upright"`` prediction of a ``--poly 1 --delays 35 --const`` plant is
1 % worse on the pendulum than its own; with ``--poly 3`` the linearization is 5 % worse and the
lifted map as good as re-lifting, so the MPC keeps the linear plant.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from qube_koopman.design.plant import DesignError, LinearPlant, linear_plant
from qube_koopman.identify.data.trajectory import Trajectory
from qube_koopman.identify.models.model import KoopmanModel

__all__ = ["PREDICTORS", "PredictorScores", "lifted_condensed", "predict_windows", "score_predictors"]

#: The predictors, in the order the bench prints them.
PREDICTORS = ("relifted", "lifted", "upright")
#: Windows predicted together (their lifted states stay in the cache).
_WINDOWS_PER_BATCH = 256


def predict_windows(
    model: KoopmanModel,
    histories: np.ndarray,
    inputs: np.ndarray,
    predictor: str,
    plant: LinearPlant | None = None,
) -> np.ndarray:
    """Each window's measured states predicted ``K`` samples ahead from its history under its inputs.

    Parameters
    ----------
    model : KoopmanModel
        A plant model (no passthrough states).
    histories : ndarray of shape (n_windows, n_delays + 1, n_states)
        The measured samples ``x_{k-d} .. x_k`` of each window, oldest first.
    inputs : ndarray of shape (n_windows, K, n_inputs)
        The inputs ``u_k .. u_{k+K-1}``.
    predictor : {"relifted", "lifted", "upright"}
        See the module's description.
    plant : LinearPlant, optional
        ``"upright"``'s plant (default: ``linear_plant(model)``, built here).

    Returns
    -------
    ndarray of shape (n_windows, K, n_states)
        ``x_{k+1} .. x_{k+K}``; non-finite where a prediction diverged.
    """
    if predictor not in PREDICTORS:
        raise ValueError(f"unknown predictor {predictor!r} (one of {', '.join(PREDICTORS)})")
    if model.n_passthrough:
        raise ValueError("the predictors run a plant model; this one has controller (passthrough) states")
    histories = np.asarray(histories, dtype=float)
    inputs = np.asarray(inputs, dtype=float)
    n, K = inputs.shape[:2]
    d, m = model.n_delays, model.n_states
    if histories.shape != (n, d + 1, m):
        raise ValueError(f"histories {histories.shape} must be ({n}, {d + 1}, {m}): one window of d + 1 samples each")
    if predictor == "upright":
        plant = linear_plant(model) if plant is None else plant
        s = histories[:, ::-1, :].reshape(n, -1)  # newest first
        out = np.empty((n, K, m))
        Ft, Gt = plant.F.T, plant.G.T
        with np.errstate(all="ignore"):
            for j in range(K):
                s = s @ Ft + inputs[:, j] @ Gt
                out[:, j] = s[:, :m]
        return out
    if predictor == "lifted":
        Phi, Gamma = lifted_condensed(model, K)
        z0 = model.lifting.transform(histories)[:, -1, :]
        return np.einsum("wz,jmz->wjm", z0, Phi) + np.einsum("wi,jmi->wjm", inputs.reshape(n, -1), Gamma)
    # identify's simulation: v holds a row per sample of the window, the first d unused
    v = np.concatenate([np.zeros((n, d, inputs.shape[2])), inputs, np.zeros((n, 1, inputs.shape[2]))], axis=1)
    out = np.empty((n, K, m))
    for c in range(0, n, _WINDOWS_PER_BATCH):
        part = slice(c, c + _WINDOWS_PER_BATCH)
        out[part] = model.simulate(histories[part], v[part])[0][:, d + 1 :]
    return out


def lifted_condensed(model: KoopmanModel, horizon: int) -> tuple[np.ndarray, np.ndarray]:
    """Korda & Mezić's predictor condensed: ``x_{k+j+1} = Phi_j z_0 + Gamma_j U``, ``j < horizon``.

    ``Phi_j = C A^(j+1)``, and ``Gamma_j``'s block on ``u_{k+i}`` is ``C A^(j-i) B`` for ``i <= j``
    (zero after): the matrices a linear MPC on the lifted map builds once.

    Parameters
    ----------
    model : KoopmanModel
        A plant model (``C`` picks the measured states out of its lifted state).
    horizon : int
        Predicted samples.

    Returns
    -------
    Phi : ndarray of shape (horizon, n_states, n_lifted)
    Gamma : ndarray of shape (horizon, n_states, horizon * n_inputs)
        ``U = [u_k; ...; u_{k+horizon-1}]`` flattened input by input.
    """
    A, B, C = model.A, model.B, model.C
    m, n_in = model.n_states, B.shape[1]
    Phi = np.empty((horizon, m, A.shape[0]))
    markov = np.empty((horizon, m, n_in))  # C A^j B
    P = C
    with np.errstate(all="ignore"):
        for j in range(horizon):
            markov[j] = P @ B
            P = P @ A
            Phi[j] = P
    Gamma = np.zeros((horizon, m, horizon, n_in))
    for j in range(horizon):
        Gamma[j, :, : j + 1] = np.moveaxis(markov[j::-1], 0, 1)
    return Phi, Gamma.reshape(horizon, m, horizon * n_in)


@dataclass(frozen=True)
class PredictorScores:
    """Each predictor's K-step scores on a set of episodes.

    Parameters
    ----------
    horizons : tuple of int
        ``K`` in samples.
    predictors : tuple of str
        The predictors scored (``"upright"`` left out for a plant the MPC refuses).
    r2 : ndarray of shape (n_predictors, n_horizons, n_states)
        R^2 per channel of the predictions ``K`` ahead, per episode (against the episode's variance of
        the channel), averaged over the episodes; ``-inf`` where a prediction diverged.
    rms : ndarray of shape (n_predictors, n_horizons, n_states)
        Their RMS error (rad), pooled over the episodes.
    n_windows : int
        Predictions per horizon and predictor.
    n_diverged : ndarray of shape (n_predictors, n_horizons)
        Of those, the predictions that diverged (non-finite).
    episode_rms : ndarray of shape (n_episodes, n_predictors, n_horizons, n_states)
        The RMS error per episode (to compare predictors episode by episode).
    refused : str
        Why ``"upright"`` is not among ``predictors`` ("" when it is).
    """

    horizons: tuple[int, ...]
    predictors: tuple[str, ...]
    r2: np.ndarray
    rms: np.ndarray
    n_windows: int
    n_diverged: np.ndarray
    episode_rms: np.ndarray
    refused: str = ""


def score_predictors(
    model: KoopmanModel,
    trajectories: Sequence[Trajectory],
    horizons: Sequence[int],
    n_starts: int = 100,
    predictors: Sequence[str] = PREDICTORS,
) -> PredictorScores:
    """The predictors' predictions ``K`` samples ahead on episodes, under the logged plant input, scored.

    Each episode's windows start at ``n_starts`` samples evenly spaced from its ``n_delays``-th to
    the last that leaves the longest horizon; one prediction per window gives every horizon
    (the ``K``-th predicted sample). The open-loop plant is unstable: at long horizons the errors
    grow with its unstable mode, whatever the predictor.

    Parameters
    ----------
    model : KoopmanModel
        A plant model with input ``u``.
    trajectories : sequence of Trajectory
        The episodes (measured states and plant input).
    horizons : sequence of int
        ``K`` in samples, 1 or more.
    n_starts : int
        Windows per episode.
    predictors : sequence of str
        Among :data:`PREDICTORS`; ``"upright"`` is left out (and :attr:`PredictorScores.refused`
        says why) when the design refuses the plant.

    Returns
    -------
    PredictorScores
    """
    horizons = tuple(int(K) for K in horizons)
    if not horizons or min(horizons) < 1:
        raise ValueError(f"horizons are samples, 1 or more, got {horizons}")
    plant, refused = None, ""
    predictors = tuple(predictors)
    if "upright" in predictors:
        try:
            plant = linear_plant(model)
        except DesignError as exc:
            refused = str(exc)
            predictors = tuple(p for p in predictors if p != "upright")
    d, K_max = model.n_delays, max(horizons)
    at = np.array(horizons) - 1
    sq = np.zeros((len(predictors), len(horizons), model.n_states))
    r2 = np.zeros_like(sq)
    diverged = np.zeros((len(predictors), len(horizons)), dtype=int)
    episode_rms = np.zeros((len(trajectories), len(predictors), len(horizons), model.n_states))
    n_windows = 0
    for i, t in enumerate(trajectories):
        x, u = np.asarray(t.x, dtype=float), model.inputs_of(t)
        if len(x) < d + K_max + 1:
            raise ValueError(f"episode {t.name!r} has {len(x)} samples; the longest horizon needs {d + K_max + 1}")
        starts = np.unique(np.linspace(d, len(x) - 1 - K_max, n_starts).round().astype(int))
        histories = x[starts[:, None] + np.arange(-d, 1)]
        inputs = u[starts[:, None] + np.arange(K_max)]
        truth = x[starts[:, None] + 1 + at]  # (windows, horizons, states)
        var = np.maximum(x[d:].var(axis=0), 1e-300)
        for p, name in enumerate(predictors):
            pred = predict_windows(model, histories, inputs, name, plant)[:, at]
            with np.errstate(all="ignore"):
                err2 = np.where(np.isfinite(pred), (pred - truth) ** 2, np.inf)
            sq[p] += err2.sum(axis=0)
            episode_rms[i, p] = np.sqrt(err2.mean(axis=0))
            diverged[p] += np.sum(~np.all(np.isfinite(pred), axis=2), axis=0)
            r2[p] += 1.0 - err2.mean(axis=0) / var
        n_windows += len(starts)
    n = max(len(trajectories), 1)
    rms = np.sqrt(sq / max(n_windows, 1))
    return PredictorScores(horizons, predictors, r2 / n, rms, n_windows, diverged, episode_rms, refused)
