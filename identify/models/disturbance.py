"""A disturbance model, its Kalman filter, and predictions that use the measurements.

A Koopman model predicts what the excitation causes. What it leaves on the real rig is a slow
disturbance that no response to the references explains. This module models it as a state
driven by white noise (a random walk, or a first-order process when its pole is below 1) that
enters the model where the physics puts it, estimates it from the measurements with a
steady-state Kalman filter, and predicts K samples ahead from every sample with the
measurements up to it.

The model, in innovations form
------------------------------
The lifted state of a delay-embedding model is a function of the measured history, so the
one-step predictor from the measurements (the prediction-error method's predictor, as for an
ARX model) is ``y_{k+1} = C (A z_k + B v_k + E d_k) + e_{k+1}`` with ``z_k`` the lifting of the
measured ``y`` up to sample ``k`` (and the logged controller state), ``v_k`` the known inputs,
``e`` white noise of covariance ``R`` (the measurement noise and what the model misses in one
sample), and the disturbance

    d_{k+1} = pole d_k + w_k,   var(w) = q.

Its Kalman filter corrects the lifted state by lifting the new measurement (the innovations
form's gain on the history), and the disturbance by ``d_{k|k} = d_{k|k-1} + L (y_k - y_{k|k-1})``
with the steady-state gain ``L`` of the scalar system ``(pole, G = C E)`` (python-control's
``dlqe``). ``q`` and ``R`` are the Gaussian maximum-likelihood estimates on the training
episodes' one-step residuals (:func:`fit_disturbance`).

The entry points
----------------
- ``"input"``: a load at the plant input, in volts (``E`` the plant input's column of ``B``:
  the feedforward's of a closed loop, whose plant input is the controller's output plus the
  feedforward). On the QUBE-Servo, a torque on the arm (its cable, the motor's friction).
- ``"theta"``, ``"alpha"``: a rate added to that angle's equation (``E`` the unit vector of the
  angle's lifted coordinate): the angle creeps as an encoder that slips or an arm pulled by its
  cable at a random rate would.

:func:`compare_entries` fits each on the same residuals; their likelihoods say which the data
support (each has one disturbance state and the same number of parameters).

K-step predictions
------------------
:func:`predict_ahead` starts a prediction at every ``stride``-th sample from the measured
history, the logged controller state and the filtered disturbance, and runs the model (re-lifted
as its free-run prediction is) ``K`` samples under the known inputs with the disturbance's
forecast ``pole^j d_{k|k}``: the closed loop's prediction includes the controller's reaction to
the estimated disturbance. With ``K = 0`` it is the filtered estimate (the measurement itself in
innovations form); with a zero gain, its prediction from the first window is the free-run one.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from qube_koopman.identify.data.trajectory import Trajectory
from qube_koopman.identify.models.model import KoopmanModel

__all__ = [
    "ENTRIES",
    "POLES",
    "DisturbanceModel",
    "KStepData",
    "NotDetectable",
    "augmented_detectable",
    "disturbance_detectable",
    "compare_entries",
    "disturbance_direction",
    "filter_disturbance",
    "first_order_filter",
    "fit_disturbance",
    "load_response",
    "one_step_residuals",
    "prediction_errors",
    "predict_ahead",
    "predict_ahead_many",
    "simulate_with_rate",
    "starts_stride",
    "steady_state_gain",
    "steady_state_gains",
]

#: Where a disturbance may enter: a load at the plant input, or a rate on one angle's equation.
ENTRIES = ("input", "theta", "alpha")
#: The disturbance's poles a fit chooses among (:func:`~qube_koopman.identify.models.kstep.fit_training_disturbance`): a
#: random walk (1), then first-order processes whose time constants at 500 Hz are 2, 1, 0.4, 0.2, 0.1 and 0.04 s.
#: A random walk's forecast holds the last estimate for the whole horizon; a first-order one lets it fade as the
#: residuals' own correlation does.
POLES = (1.0, 0.999, 0.998, 0.995, 0.99, 0.98, 0.95)
#: Starts per episode and horizon of the K-step scores: an R^2 estimated from a few hundred predictions
#: differs from the every-sample one by far less than episodes differ.
N_STARTS = 200
#: The fewest starts per episode and horizon (a 1 s horizon of a 20 s episode: 25 starts, 1.25 free runs of steps).
MIN_STARTS = 25
#: Windows simulated together: their lifted states stay in the cache (a batch of 5600 windows of a 107-state
#: lifting stepped five times slower per window than batches of a few hundred).
_WINDOWS_PER_BATCH = 256
#: The measured channels' names, in the model's state order.
_CHANNELS = ("theta", "alpha")


class NotDetectable(ValueError):
    """The model augmented with the disturbance is not detectable: the filter could not estimate it."""


@dataclass(frozen=True)
class DisturbanceModel:
    """A disturbance state, where it enters, its statistics and its Kalman filter's gain.

    Parameters
    ----------
    entry : str
        Where it enters (one of :data:`ENTRIES`).
    pole : float
        ``d_{k+1} = pole d_k + w_k``: 1 for a random walk (integrated white noise).
    q : float
        Variance of ``w`` per sample (volts squared for ``"input"``, rad squared otherwise).
    R : ndarray of shape (n_outputs, n_outputs)
        Covariance of ``e``, the one-step noise besides the disturbance (the measurement noise and
        what the model misses in one sample), estimated as the training residuals' covariance; the
        filter's innovations have covariance ``R + P G G^T`` (``P`` the disturbance's steady-state
        prediction variance), ``R`` itself when ``q = 0``.
    gain : ndarray of shape (n_outputs,)
        The steady-state filter's gain: ``d_{k|k} = d_{k|k-1} + gain @ innovation``.
    log_likelihood : float
        Gaussian log-likelihood of the training residuals (per sample).
    n_samples : int
        Training residuals it was estimated from.
    """

    entry: str
    pole: float
    q: float
    R: np.ndarray
    gain: np.ndarray
    log_likelihood: float = float("nan")
    n_samples: int = 0

    def as_dict(self) -> dict:
        """The model file's ``disturbance`` entry (JSON values)."""
        return {
            "entry": self.entry,
            "kind": "random-walk" if self.pole == 1.0 else "first-order",
            "pole": float(self.pole),
            "q": float(self.q),
            "R": np.asarray(self.R, dtype=float).tolist(),
            "gain": np.asarray(self.gain, dtype=float).tolist(),
            "log_likelihood_per_sample": float(self.log_likelihood),
            "n_samples": int(self.n_samples),
        }

    @classmethod
    def from_dict(cls, data: dict) -> "DisturbanceModel":
        """The model back from :meth:`as_dict` (a ValueError naming what is wrong)."""
        try:
            entry, pole, q = str(data["entry"]), float(data["pole"]), float(data["q"])
            R = np.asarray(data["R"], dtype=float)
            gain = np.asarray(data["gain"], dtype=float)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"the disturbance model is incomplete or not numbers ({exc})") from None
        if entry not in ENTRIES:
            raise ValueError(f"unknown disturbance entry {entry!r} (one of {', '.join(ENTRIES)})")
        n = gain.shape[0] if gain.ndim == 1 else -1
        if R.shape != (n, n) or not (np.all(np.isfinite(R)) and np.all(np.isfinite(gain))):
            raise ValueError(f"the disturbance's R {R.shape} and gain {gain.shape} do not fit or are not finite")
        if not (0.0 <= pole <= 1.0 and np.isfinite(q) and q >= 0):
            raise ValueError(f"the disturbance's pole {pole} must be in [0, 1] and q {q} finite, 0 or more")
        return cls(
            entry,
            pole,
            q,
            R,
            gain,
            float(data.get("log_likelihood_per_sample", float("nan"))),
            int(data.get("n_samples", 0)),
        )

    def with_gain(self, gain: np.ndarray) -> "DisturbanceModel":
        """The same model with another filter gain (zero: the free-run prediction)."""
        return DisturbanceModel(self.entry, self.pole, self.q, self.R, np.asarray(gain, dtype=float))

    def integrated(self, G: np.ndarray) -> "DisturbanceModel":
        """The same disturbance as a random walk: its ``q`` and ``R``, pole 1, the steady-state gain for ``G = C E``.

        What offset-free control needs (a controller rejects a constant load only when its model
        integrates one: Pannocchia & Rawlings 2003, and MATLAB's MPC adds integrated white noise
        by default whatever the plant's noise model). Nothing is refitted: the gain is the Kalman
        filter's of the same covariances with the pole at 1. A random walk is returned as it is.
        """
        if self.pole == 1.0:
            return self
        gain, _ = steady_state_gain(G, 1.0, self.q, self.R)
        return DisturbanceModel(self.entry, 1.0, self.q, self.R, gain, self.log_likelihood, self.n_samples)


def disturbance_direction(model: KoopmanModel, entry: str) -> np.ndarray:
    """``E``: how a unit disturbance at ``entry`` moves the lifted state in one sample.

    ``"input"`` is the plant input's column of ``B`` (a plant model's ``u``; a closed loop's
    feedforward, which is added to the controller's output), ``"theta"`` and ``"alpha"`` the unit
    vector of that angle's lifted coordinate.
    """
    E = np.zeros(model.A.shape[0])
    if entry == "input":
        if model.input_signals == ("u",):
            E[:] = model.B[:, 0]
        elif model.input_signals and model.input_signals[-1] == "f":
            E[:] = model.B[:, -1]
        else:
            raise ValueError(f"a model with inputs {model.input_signals} has no plant input for a load to enter")
    elif entry in _CHANNELS:
        E[model.n_passthrough + _CHANNELS.index(entry)] = 1.0
    else:
        raise ValueError(f"unknown disturbance entry {entry!r} (one of {', '.join(ENTRIES)})")
    return E


def disturbance_detectable(model: KoopmanModel, E: np.ndarray, rtol: float = 1e-9) -> bool:
    """Whether the filter of this module can estimate disturbances entering along ``E``.

    In innovations form the lifted state is the lifting of the measured history (measured, not
    estimated), so the augmented model's only unknown state is the disturbance, and it is read
    from the next measurement through ``G = C E``: the augmented model is detectable exactly when
    ``C E`` has full column rank (at most as many disturbances as measured channels, each moving
    them). A lifting's own modes that the outputs do not see (a constant feature's eigenvalue at
    1) do not matter here, as they do for a filter that estimates the whole lifted state
    (:func:`augmented_detectable`).
    """
    G = model.C @ np.asarray(E, dtype=float).reshape(model.A.shape[0], -1)
    g = np.linalg.svd(G, compute_uv=False)
    return bool(g.size and G.shape[1] <= G.shape[0] and g[-1] > rtol * max(1.0, float(np.abs(G).max())))


def augmented_detectable(model: KoopmanModel, E: np.ndarray, pole: float = 1.0, rtol: float = 1e-9) -> bool:
    """The rank condition of offset-free estimation, for a filter of the whole lifted state from the outputs.

    Pannocchia & Rawlings: with ``(A, C)`` detectable, the augmented
    ``([[A, E], [0, pole I]], [C, 0])`` is detectable exactly when ``[[A - pole I, E], [C, 0]]`` has
    full column rank (at ``pole = 1`` it needs no more disturbances than measured outputs). A
    controller that estimates the lifted state from the two angles alone (rather than lifting
    their measured history) needs this.
    """
    E = np.asarray(E, dtype=float).reshape(model.A.shape[0], -1)
    n_z, n_d = E.shape
    C = model.C
    M = np.block([[model.A - pole * np.eye(n_z), E], [C, np.zeros((C.shape[0], n_d))]])
    s = np.linalg.svd(M, compute_uv=False)
    scale = max(1.0, float(np.max(np.abs(M))))
    return bool(s[-1] > rtol * scale * max(M.shape)) and disturbance_detectable(model, E, rtol)


def steady_state_gain(G: np.ndarray, pole: float, q: float, R: np.ndarray) -> tuple[np.ndarray, float]:
    """The steady-state Kalman filter of ``d_{k+1} = pole d_k + w``, ``r_k = G d_k + e_k``.

    Returns the filtered gain ``L`` (``d_{k|k} = d_{k|k-1} + L (r_k - G d_{k|k-1})``) and the
    predicted variance ``P`` (``var(d_k - d_{k|k-1})``), the positive root of the scalar Riccati
    equation ``P = pole^2 P - pole^2 P^2 G' S^-1 G + q``, ``S = G P G' + R``. Python-control's
    ``dlqe`` gives the same gain (solve_discrete_are); this closed form avoids its cost inside the
    likelihood's search.
    """
    G = np.asarray(G, dtype=float).reshape(-1)
    R = np.asarray(R, dtype=float)
    gamma = float(G @ np.linalg.solve(R, G))  # G' R^-1 G
    a2 = pole * pole
    if q <= 0 or gamma <= 0:
        return np.zeros_like(G), 0.0
    # With S^-1 by the matrix inversion lemma, G'S^-1G = gamma / (1 + gamma P): the Riccati equation is
    # gamma P^2 + (1 - a2 - q gamma) P - q = 0.
    b = 1.0 - a2 - q * gamma
    P = (-b + np.sqrt(b * b + 4.0 * gamma * q)) / (2.0 * gamma)
    L = P * np.linalg.solve(R, G) / (1.0 + gamma * P)
    return L, float(P)


def steady_state_gains(G: np.ndarray, pole: float, Q: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`steady_state_gain` for several disturbances: ``d_{k+1} = pole d_k + w``, ``r_k = G d_k + e_k``.

    Parameters
    ----------
    G : ndarray of shape (n_outputs, n_d)
        One column per disturbance, ``C E``; full column rank (:func:`disturbance_detectable`).
    pole : float
        The disturbances' common pole.
    Q : ndarray of shape (n_d, n_d)
        ``cov(w)``.
    R : ndarray of shape (n_outputs, n_outputs)
        ``cov(e)``.

    Returns
    -------
    L : ndarray of shape (n_d, n_outputs)
        The filtered gain, ``d_{k|k} = d_{k|k-1} + L (r_k - G d_{k|k-1})``.
    P : ndarray of shape (n_d, n_d)
        The predicted covariance, ``cov(d_k - d_{k|k-1})``: the filter's Riccati equation, solved
        by scipy's ``solve_discrete_are`` (python-control's ``dlqe`` gives the same gain).
    """
    from scipy.linalg import solve_discrete_are

    G = np.asarray(G, dtype=float)
    Q, R = np.atleast_2d(np.asarray(Q, dtype=float)), np.asarray(R, dtype=float)
    n_d = G.shape[1]
    P = solve_discrete_are(pole * np.eye(n_d), G.T, Q, R)
    L = np.linalg.solve(G @ P @ G.T + R, G @ P).T  # P G' S^-1, S symmetric
    return L, P


def one_step_residuals(model: KoopmanModel, trajectory: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """The one-step residuals from the measurements, and the one-step predictions.

    ``r_{k+1} = y_{k+1} - C (A z_k + B v_k)`` with ``z_k`` the lifting of the measured history
    up to ``k`` (and the logged controller state), for ``k`` from the first lifted sample on.

    Returns
    -------
    residuals, predictions : ndarray of shape (n_samples, n_states)
        Row ``k`` holds sample ``k``'s residual and prediction; NaN up to sample ``n_delays``.
    """
    model.check_trajectory(trajectory)
    d, n_p, m = model.n_delays, model.n_passthrough, model.n_states
    z = model.lifting.transform(np.asarray(trajectory.x, dtype=float))  # sample k = d + j
    if n_p:
        z = np.hstack([np.asarray(trajectory.xc, dtype=float)[d:], z])
    v = model.inputs_of(trajectory)[d:]
    rows = slice(n_p, n_p + m)
    predicted = z[:-1] @ model.A[rows].T + v[:-1] @ model.B[rows].T
    out_p = np.full((trajectory.n_samples, m), np.nan)
    out_p[d + 1 :] = predicted
    return np.asarray(trajectory.x, dtype=float) - out_p, out_p


def filter_disturbance(residuals: np.ndarray, G: np.ndarray, pole: float, gain: np.ndarray) -> tuple:
    """The steady-state filter run on one episode's one-step residuals.

    Parameters
    ----------
    residuals : ndarray of shape (n_samples, n_outputs)
        :func:`one_step_residuals` (NaN before the first).
    G : ndarray of shape (n_outputs,)
        ``C E``.
    pole : float
    gain : ndarray of shape (n_outputs,)

    Returns
    -------
    filtered : ndarray of shape (n_samples,)
        ``d_{k|k}`` (the disturbance in the step from ``k`` to ``k+1``; 0 before the first residual).
    innovations : ndarray of shape (n_samples, n_outputs)
        ``r_k - G d_{k|k-1}`` (NaN where there is no residual).
    """

    r = np.asarray(residuals, dtype=float)
    n = r.shape[0]
    ok = np.flatnonzero(np.all(np.isfinite(r), axis=1))
    filtered = np.zeros(n)
    innovations = np.full_like(r, np.nan)
    if not ok.size:
        return filtered, innovations
    first = int(ok[0])
    rr = np.nan_to_num(r[first:])
    G = np.asarray(G, dtype=float).reshape(-1)
    gain = np.asarray(gain, dtype=float).reshape(-1)
    # The residual r_k carries d_{k-1} (the step from k-1 to k): predicted d_{k-1|k-1}-based value
    # p_k = pole * f_{k-1}, filtered f_k = p_k + L (r_k - G p_k) = pole (1 - L G) f_{k-1} + L r_k, f_{first-1} = 0.
    f = _filter_recursion(rr, G, pole, gain)
    predicted = np.concatenate([[0.0], pole * f[:-1]])
    innovations[first:] = rr - predicted[:, None] * G[None, :]
    filtered[first:] = pole * f  # d_{k|k}: the step from k to k+1
    return filtered, innovations


def _filter_recursion(rr: np.ndarray, G: np.ndarray, pole: float, gain: np.ndarray) -> np.ndarray:
    """``f_k``, the filtered estimate of the disturbance each residual row of ``rr`` carries (rows from the first
    residual on, NaN-free): ``f_k = pole (1 - L G) f_{k-1} + L r_k``, ``f_{-1} = 0``, a first-order recursion run
    in C."""
    beta = pole * (1.0 - float(gain @ G))
    return first_order_filter(beta, rr @ gain)


def first_order_filter(beta: float, u: np.ndarray) -> np.ndarray:
    """``y_k = beta y_{k-1} + u_k`` from ``y_{-1} = 0``: the disturbance filter's recursion.

    A unit lower-bidiagonal triangular solve, BLAS's ``dtbsv`` (in C, through scipy.linalg,
    which the fit imports anyway). ``scipy.signal.lfilter([1], [1, -beta], u)`` gives the same to
    within an ulp or two and a little faster, but importing scipy.signal took 0.4-0.8 s of every
    ``qube-identify --horizon`` run, which needs nothing else from it.
    """
    from scipy.linalg.blas import dtbsv

    u = np.ascontiguousarray(u, dtype=float)
    if not u.size:
        return u.copy()
    band = np.empty((2, u.size))
    band[0] = 1.0
    band[1] = -beta
    return dtbsv(1, band, u, lower=1, diag=1)


def _neg_log_likelihood(params, residuals, G, pole):
    """Minus the Gaussian log-likelihood per sample of the steady-state filter's innovations."""
    log_q, log_r1, log_r2, rho = params[:4]
    s1, s2 = np.exp(0.5 * log_r1), np.exp(0.5 * log_r2)
    c = 0.999 * np.tanh(rho)  # a correlation, kept off +-1 (a singular R)
    R = np.array([[s1 * s1, c * s1 * s2], [c * s1 * s2, s2 * s2]])
    if not np.all(np.isfinite(R)) or abs(log_q) > 700:
        return np.inf
    L, P = steady_state_gain(G, pole, float(np.exp(log_q)), R)
    S = np.outer(G, G) * P + R
    S_inv = np.linalg.inv(S)
    _, logdet = np.linalg.slogdet(S)
    total, count = 0.0, 0
    for r in residuals:
        _, e = filter_disturbance(r, G, pole, L)
        e = e[np.all(np.isfinite(e), axis=1)]
        total += float(np.einsum("ij,jk,ik->", e, S_inv, e))
        count += len(e)
    return 0.5 * (total / count + logdet + 2 * np.log(2 * np.pi))


def load_response(model: KoopmanModel, E: np.ndarray, pole: float, horizons: Sequence[int]) -> np.ndarray:
    """``S_K``: the measured states ``K`` samples after a unit disturbance (decaying as ``pole^j``) starts.

    From the lifted linear map (the disturbance's effect is small beside the state's, so its
    propagation is linear). Returns an array of shape ``(len(horizons), n_states)``.
    """
    K_max = max(int(K) for K in horizons)
    A, C = model.A, model.C  # C is built by its property: once, not per step
    z = np.zeros(A.shape[0])
    out = np.zeros((K_max + 1, model.n_states))
    for j in range(K_max):
        z = A @ z + E * pole**j
        out[j + 1] = C @ z
    return out[[int(K) for K in horizons]]


def _q_grid(G: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Candidate ``q``, a decade apart: from a disturbance whose one-step effect is 1e-8 of the innovations' to
    1e2 of it (a finer grid changed the K-step scores by less than episodes differ)."""
    scale = float(np.min(np.diag(R) / np.maximum(G**2, 1e-300)))
    return scale * np.logspace(-8, 2, 11)


def fit_disturbance(
    model: KoopmanModel,
    trajectories: Sequence[Trajectory],
    entry: str = "input",
    *,
    horizons: Sequence[int] = (50, 500),
    pole: float = 1.0,
    skip: int = 0,
    stride: int | None = None,
    q: float | None = None,
    method: str = "prediction",
    data: KStepData | None = None,
) -> DisturbanceModel:
    """Estimate a disturbance's statistics and its filter's gain from training episodes.

    ``R`` is the covariance of the training episodes' one-step residuals
    (:func:`one_step_residuals`). ``q`` is chosen by one of two criteria:

    - ``"prediction"`` (default): the ``q`` whose filter predicts the training episodes best
      ``horizons`` samples ahead (the sum over horizons and channels of the squared errors, each
      channel's divided by its variance, as R^2 weighs it), over a grid of 12 values from
      ``q = 0`` up. The prediction-error method's criterion at the horizons that are scored: a
      slow load moves the next sample by far less than the encoders' quantization, so a one-step
      criterion hardly sees it.
    - ``"likelihood"``: Gaussian maximum likelihood of the steady-state filter's one-step
      innovations, in ``log q``, ``log R`` and the innovations' correlation: consistent when the
      model is exact and its one-step residuals white.

    Parameters
    ----------
    model : KoopmanModel
        The model predicting the episodes (a closed loop with its controller state logged, or a
        plant with its input).
    trajectories : sequence of Trajectory
        Training episodes.
    entry : str
        Where the disturbance enters (:data:`ENTRIES`).
    horizons : sequence of int
        The prediction criterion's horizons (samples).
    pole : float
        ``d_{k+1} = pole d_k + w``: 1 for a random walk.
    skip : int
        Samples left out at each episode's start (a transient).
    stride : int, optional
        The prediction criterion starts a prediction every ``stride`` samples (default: a tenth
        of the longest horizon).
    q : float, optional
        Use this ``q`` (``R`` still estimated): the choice made by hand.
    method : {"prediction", "likelihood"}
    data : KStepData, optional
        The episodes' predictions without a disturbance, when already simulated (their
        ``horizons``, ``skip`` and stride are then used).

    Returns
    -------
    DisturbanceModel

    Raises
    ------
    NotDetectable
        When the model augmented with the disturbance is not detectable.
    """
    if model.n_states != 2:
        raise ValueError(f"a disturbance model needs the two measured angles, the model has {model.n_states} states")
    if method not in ("prediction", "likelihood"):
        raise ValueError(f"unknown criterion {method!r}: 'prediction' or 'likelihood'")
    E = disturbance_direction(model, entry)
    if not disturbance_detectable(model, E):
        raise NotDetectable(
            f"the model augmented with a disturbance at {entry!r} is not detectable: it does not move the "
            "measured angles (C E, its effect on the next measurement, has rank 0)"
        )
    G = model.C @ E
    trajectories = list(trajectories)
    if data is None:
        residuals, n_residuals, R = _residual_statistics([one_step_residuals(model, t)[0] for t in trajectories], skip)
    else:
        residuals, n_residuals, R = data.residual_statistics(skip)
    if method == "likelihood":
        return _maximum_likelihood(entry, residuals, G, pole, R, n_residuals)
    if q is None:
        if data is None:
            data = KStepData.of(model, trajectories, horizons, skip, stride)
        q = _best_prediction_q(model, data, entry, G, pole, R)
    L, _ = steady_state_gain(G, pole, q, R)
    return DisturbanceModel(entry, float(pole), float(q), R, L, float("nan"), int(n_residuals))


def _residual_statistics(residuals: list[np.ndarray], skip: int) -> tuple[list[np.ndarray], int, np.ndarray]:
    """The episodes' one-step residuals with their first ``skip`` samples left out (NaN), how many are finite, and
    their covariance ``R`` (a ValueError when fewer than 10)."""
    kept = []
    for r in residuals:
        r = r.copy()
        r[: max(skip, 0)] = np.nan
        kept.append(r)
    stacked = np.concatenate([r[np.all(np.isfinite(r), axis=1)] for r in kept])
    if len(stacked) < 10:
        raise ValueError("too few one-step residuals to estimate a disturbance model")
    return kept, len(stacked), np.cov(stacked.T)


@dataclass
class KStepData:
    """Training episodes' K-step predictions without a disturbance, and their one-step residuals.

    Simulated once (:meth:`of`), then shared by every candidate disturbance model a fit or a
    comparison of entry points scores (:func:`prediction_errors`).
    """

    horizons: list[int]
    skip: int
    truths: list[np.ndarray]
    bases: list[dict[int, np.ndarray]]
    residuals: list[np.ndarray]
    #: What every candidate's errors share, per episode and per (entry, pole): computed on first use.
    _terms: list | None = field(default=None, repr=False, compare=False)
    _responses: dict = field(default_factory=dict, repr=False, compare=False)
    _statistics: dict = field(default_factory=dict, repr=False, compare=False)

    def residual_statistics(self, skip: int) -> tuple[list[np.ndarray], int, np.ndarray]:
        """The one-step residuals from ``skip`` on, how many, and their covariance: what every candidate disturbance
        model fitted on these episodes shares (computed once per ``skip``)."""
        if skip not in self._statistics:
            self._statistics[skip] = _residual_statistics(self.residuals, skip)
        return self._statistics[skip]

    def episode_terms(self) -> list[tuple[np.ndarray, int, np.ndarray, dict[int, np.ndarray], dict[int, np.ndarray]]]:
        """Per episode: each channel's variance from ``skip`` on, the first residual's row, the residuals from it
        (NaN-free), and per horizon the scored end samples and the misses without a disturbance there."""
        if self._terms is None:
            terms = []
            for x, base, residuals in zip(self.truths, self.bases, self.residuals):
                var = np.maximum(x[self.skip :].var(axis=0), 1e-300)
                ok = np.flatnonzero(np.all(np.isfinite(residuals), axis=1))
                first = int(ok[0]) if ok.size else len(x)
                ends_of, misses = {}, {}
                for h, K in enumerate(self.horizons):
                    ends = np.flatnonzero(np.all(np.isfinite(base[K]), axis=1))
                    ends_of[h] = ends[ends - K >= self.skip]
                    misses[h] = x[ends_of[h]] - base[K][ends_of[h]]
                terms.append((var, first, np.nan_to_num(residuals[first:]), ends_of, misses))
            self._terms = terms
        return self._terms

    def response(self, model: KoopmanModel, entry: str, pole: float) -> tuple[np.ndarray, np.ndarray]:
        """``G = C E`` and :func:`load_response` at the horizons of a disturbance at ``entry`` with ``pole``."""
        key = (entry, float(pole))
        if key not in self._responses:
            E = disturbance_direction(model, entry)
            self._responses[key] = (model.C @ E, load_response(model, E, pole, self.horizons))
        return self._responses[key]

    @classmethod
    def of(
        cls,
        model: KoopmanModel,
        trajectories: Sequence[Trajectory],
        horizons: Sequence[int],
        skip: int = 0,
        stride: int | None = None,
    ) -> "KStepData":
        """Predict every episode ``horizons`` ahead every ``stride`` samples (default: about
        :data:`N_STARTS` starts per episode and horizon)."""
        horizons = [int(K) for K in horizons]
        trajectories = list(trajectories)
        strides = [
            [
                starts_stride(t.n_samples, model.n_delays, K, N_STARTS) if stride is None else int(stride)
                for K in horizons
            ]
            for t in trajectories
        ]
        bases = predict_ahead_many(model, None, trajectories, horizons, strides)
        truths = [np.asarray(t.x, dtype=float) for t in trajectories]
        residuals = [one_step_residuals(model, t)[0] for t in trajectories]
        return cls(horizons, skip, truths, bases, residuals)


def prediction_errors(
    model: KoopmanModel, data: KStepData, candidates: Sequence[DisturbanceModel], per_episode: bool = False
) -> np.ndarray:
    """Each candidate's K-step errors on ``data``'s episodes: ``1 - R^2`` per horizon and channel.

    The mean squared error of the predictions ``K`` ahead divided by the episode's variance of the
    channel (from ``data.skip`` on), averaged over the episodes. A candidate's filtered disturbance
    adds its response ``S_K d_{k|k}`` (:func:`load_response`, linear in the disturbance) to the
    predictions without one, so that many candidates cost little more than one.

    Returns
    -------
    ndarray of shape (n_candidates, n_horizons, n_states), or (n_candidates, n_episodes, n_horizons,
    n_states) with ``per_episode``
    """
    horizons = data.horizons
    out = np.zeros((len(candidates), len(data.truths), len(horizons), model.n_states))
    # Candidates of one entry and pole (a grid of q) share the response: their errors are one array per horizon
    groups: dict[tuple[str, float], list[int]] = {}
    for c, cand in enumerate(candidates):
        groups.setdefault((cand.entry, float(cand.pole)), []).append(c)
    for i, (var, first, rr, ends_of, misses) in enumerate(data.episode_terms()):
        for (entry, pole), members in groups.items():
            G, response = data.response(model, entry, pole)
            # filter_disturbance's recursion, its filtered estimate alone (the innovations are not needed here)
            dhat = np.zeros((len(members), len(data.truths[i])))
            for row, c in enumerate(members):
                if rr.size and np.any(candidates[c].gain):
                    dhat[row, first:] = pole * _filter_recursion(rr, G, pole, candidates[c].gain)
            for h, K in enumerate(horizons):
                if not ends_of[h].size:
                    continue
                err = misses[h][None] - dhat[:, ends_of[h] - K, None] * response[h][None, None, :]
                out[members, i, h] = np.mean(err**2, axis=1) / var
    return out if per_episode else out.mean(axis=1)


def _best_prediction_q(model, data: KStepData, entry, G, pole, R) -> float:
    """The grid's ``q`` (0 included) whose filter predicts ``data``'s episodes best at its horizons."""
    grid = np.concatenate([[0.0], _q_grid(G, R)])
    candidates = [DisturbanceModel(entry, pole, q, R, steady_state_gain(G, pole, q, R)[0]) for q in grid]
    cost = prediction_errors(model, data, candidates).sum(axis=(1, 2))
    return float(grid[int(np.argmin(cost))])


def _maximum_likelihood(entry, residuals, G, pole, R0, n_samples) -> DisturbanceModel:
    """One-step Gaussian maximum likelihood in log q, log R and the innovations' correlation."""
    from scipy.optimize import minimize

    s1, s2 = np.sqrt(np.diag(R0))
    rho0 = np.arctanh(np.clip(R0[0, 1] / (s1 * s2), -0.99, 0.99))
    q0 = float(np.min(np.diag(R0) / np.maximum(G**2, 1e-300))) * 1e-4
    rest = [np.log(R0[0, 0]), np.log(R0[1, 1]), rho0]
    # A start from a coarse grid in log q (R at the residuals' covariance), then every parameter.
    starts = [np.log(q0) + shift for shift in np.arange(-12.0, 13.0, 3.0)]
    log_q0 = min(starts, key=lambda lq: _neg_log_likelihood([lq, *rest], residuals, G, pole))
    best = minimize(
        _neg_log_likelihood,
        np.array([log_q0, *rest]),
        args=(residuals, G, pole),
        method="L-BFGS-B",  # smooth in these coordinates: quasi-Newton steps converge in tens of evaluations
    )
    assert best is not None
    log_q, log_r1, log_r2, rho = best.x
    s1, s2, c = np.exp(0.5 * log_r1), np.exp(0.5 * log_r2), 0.999 * np.tanh(rho)
    R = np.array([[s1 * s1, c * s1 * s2], [c * s1 * s2, s2 * s2]])
    q = float(np.exp(log_q))
    L, _ = steady_state_gain(G, pole, q, R)
    return DisturbanceModel(entry, float(pole), q, R, L, float(-best.fun), int(n_samples))


def compare_entries(
    model: KoopmanModel,
    trajectories: Sequence[Trajectory],
    entries: Sequence[str] = ENTRIES,
    *,
    horizons: Sequence[int] = (50, 500),
    skip: int = 0,
    stride: int | None = None,
) -> dict[str, tuple[DisturbanceModel, float]]:
    """Each entry point's disturbance model fitted on the same episodes, with its K-step cost.

    The cost is :func:`prediction_errors` summed over horizons and channels (without a
    disturbance: ``entry "none"``'s); the entry with the lowest is the one the data support.
    A non-detectable entry is left out.
    """
    data = KStepData.of(model, trajectories, horizons, skip, stride)
    out: dict[str, tuple[DisturbanceModel, float]] = {}
    for entry in entries:
        try:
            fitted = fit_disturbance(model, trajectories, entry, skip=skip, data=data)
        except NotDetectable:
            continue
        out[entry] = (fitted, float(prediction_errors(model, data, [fitted]).sum()))
    return out


def predict_ahead(
    model: KoopmanModel,
    disturbance: DisturbanceModel | None,
    trajectory: Trajectory,
    horizons: Sequence[int],
    stride: int | Sequence[int] = 1,
    relift: bool = True,
) -> dict[int, np.ndarray]:
    """Predict every ``stride``-th sample ``K`` samples ahead from the measurements up to it.

    Parameters
    ----------
    model : KoopmanModel
        The loop (or plant) predicting the episode.
    disturbance : DisturbanceModel or None
        Its disturbance model; None predicts from the measured history alone (no disturbance).
    trajectory : Trajectory
        The episode: its measurements, inputs and (closed loop) logged controller state.
    horizons : sequence of int
        ``K`` in samples (0: the filtered estimate).
    stride : int or sequence of int
        Start a prediction at every ``stride``-th sample from ``n_delays`` on (per horizon).
    relift : bool
        Re-lift the predicted states at every step (as :meth:`KoopmanModel.predict` does).

    Returns
    -------
    dict of int to ndarray of shape (n_samples, n_states)
        For each horizon, sample ``k + K`` holds the prediction started at ``k``; NaN where no
        prediction ends (before ``n_delays + K``, or between strided starts).
    """
    strides = [int(stride)] * len(horizons) if isinstance(stride, (int, np.integer)) else list(stride)
    return predict_ahead_many(model, disturbance, [trajectory], horizons, [strides], relift)[0]


def starts_stride(n_samples: int, n_delays: int, horizon: int, n_starts: int) -> int:
    """The stride of the predictions ``horizon`` ahead in an episode: about ``n_starts`` of them, fewer for a long
    horizon so that they step no more samples than the episode has (one free run), never fewer than
    :data:`MIN_STARTS`."""
    n = max(MIN_STARTS, min(n_starts, n_samples // max(1, horizon)))
    return max(1, (n_samples - n_delays - horizon) // n)


def predict_ahead_many(
    model: KoopmanModel,
    disturbance: DisturbanceModel | None,
    trajectories: Sequence[Trajectory],
    horizons: Sequence[int],
    strides: Sequence[Sequence[int]],
    relift: bool = True,
) -> list[dict[int, np.ndarray]]:
    """:func:`predict_ahead` for several episodes, every start of a horizon simulated in one batch.

    ``strides[i][h]`` is episode ``i``'s stride at horizon ``h``; the batch makes a long horizon
    cost its ``K`` steps once, whatever the number of episodes and starts.
    """
    d = model.n_delays
    trajectories = list(trajectories)
    xs = [np.asarray(t.x, dtype=float) for t in trajectories]
    vs = [model.inputs_of(t) for t in trajectories]
    dhats: list[np.ndarray | None] = [None] * len(trajectories)
    if disturbance is not None:
        G = model.C @ disturbance_direction(model, disturbance.entry)
        for i, t in enumerate(trajectories):
            dhats[i] = filter_disturbance(one_step_residuals(model, t)[0], G, disturbance.pole, disturbance.gain)[0]
    out: list[dict[int, np.ndarray]] = [{} for _ in trajectories]
    for h, K_given in enumerate(horizons):
        K = int(K_given)
        starts = [np.arange(d, len(x) - K, max(1, int(strides[i][h]))) for i, x in enumerate(xs)]
        for i, x in enumerate(xs):
            out[i][K] = np.full(x.shape, np.nan)
            if K == 0:
                out[i][K][starts[i]] = x[starts[i]]
        if K == 0 or not sum(len(s) for s in starts):
            continue
        window = np.arange(-d, K + 1)[None, :]  # each window: history, then K steps
        x_init = np.concatenate([x[s[:, None] + window[:, : d + 1]] for x, s in zip(xs, starts)])
        vv = np.concatenate([v[s[:, None] + window] for v, s in zip(vs, starts)])
        p0 = (
            None
            if not model.n_passthrough
            else np.concatenate([np.asarray(t.xc, dtype=float)[s] for t, s in zip(trajectories, starts)])
        )
        d0 = None if disturbance is None else np.concatenate([dh[s] for dh, s in zip(dhats, starts) if dh is not None])
        forecast = None
        if d0 is not None and disturbance is not None and np.any(d0):
            forecast = d0[:, None] * disturbance.pole ** np.arange(K + 1)[None, :]
            if disturbance.entry == "input":
                vv[:, d:, -1] += forecast  # the load adds to the plant input (a closed loop's feedforward)
                forecast = None
        loop, windows = model, vv
        if forecast is not None:  # a rate disturbance: the model with one more input, the forecast its signal
            assert disturbance is not None
            loop, windows = _with_rate_input(model, disturbance), _rate_windows(vv, forecast)
        ahead = _affine_ahead(loop, x_init, windows, p0, K, relift)
        if ahead is None:
            ahead = np.empty((len(x_init), model.n_states))
            for c in range(0, len(x_init), _WINDOWS_PER_BATCH):
                part = slice(c, c + _WINDOWS_PER_BATCH)
                p0_part = None if p0 is None else p0[part]
                ahead[part] = loop.simulate(x_init[part], windows[part], p0_part, relift=relift)[0][:, d + K]
        at = 0
        for i, s in enumerate(starts):
            out[i][K][s + K] = ahead[at : at + len(s)]
            at += len(s)
    return out


#: Windows simulated directly to check the affine predictor against (a nonlinear step is caught, whatever
#: the lifting claims).
_AFFINE_CHECKS = 4


def _affine_ahead(model: KoopmanModel, x_init, v, p0, K: int, relift: bool) -> np.ndarray | None:
    """Each window's state ``K`` samples after its start, as a filter of its history and inputs: None unless the
    model's lifting is affine and the filter reproduces a direct simulation of the first windows.

    A model on an affine lifting predicts an affine function of its window, re-lifted or not: the
    state ``K`` ahead is ``y_0 + H x_init + P p0 + sum_j M_j v_j`` (each sample's input ``v_j``
    weighed by the loop's response to it). The weights come from one batch of probe windows (a unit
    change of each history sample, of each passthrough state, and of each input at the first step:
    the loop is time-invariant, so that impulse's response gives every later input's), ``K`` steps
    each, whatever the number of windows: a few thousand windows cost their gathered inputs' product
    with the weights, not a simulation each (the prediction-error method's and the scores' K-step
    predictions, at horizons of hundreds of samples).
    """
    if not model.lifting.affine or len(x_init) <= _AFFINE_CHECKS:
        return None
    d, n = model.n_delays, model.n_states
    m, n_p = v.shape[2], model.n_passthrough
    n_hist = (d + 1) * n
    # The probes: none moved (the affine part), each history sample, each input at the first step, each
    # passthrough state. The inputs before the first step are not used (KoopmanModel.simulate).
    n_probe = 1 + n_hist + m + n_p
    X = np.zeros((n_probe, d + 1, n))
    V = np.zeros((n_probe, d + K + 1, m))
    P = np.zeros((n_probe, n_p)) if n_p else None
    rows = np.arange(n_probe)
    X.reshape(n_probe, -1)[rows[1 : 1 + n_hist], np.arange(n_hist)] = 1.0
    V[rows[1 + n_hist : 1 + n_hist + m], d, np.arange(m)] = 1.0  # an impulse at the first step
    if P is not None:
        P[rows[1 + n_hist + m :], np.arange(n_p)] = 1.0
    with np.errstate(all="ignore"):
        Y = model.simulate(X, V, P, relift=relift)[0]  # (n_probe, d + K + 1, n)
        response = Y[1:] - Y[0]
        at_k = response[:, d + K]  # each probe's change of the state K ahead
        impulse = response[n_hist : n_hist + m]  # (m, d + K + 1, n)
        # the input at sample d + j moves the state K ahead as the first step's impulse moves the state K - j ahead
        weights = impulse[:, d + K - np.arange(K + 1)].transpose(1, 0, 2)  # (K + 1, m, n)
        ahead = Y[0, d + K] + x_init.reshape(len(x_init), -1) @ at_k[:n_hist]
        ahead += np.einsum("wji,jin->wn", v[:, d:], weights)
        if p0 is not None and n_p:
            ahead += p0 @ at_k[n_hist + m :]
    if not np.all(np.isfinite(ahead)):
        return None
    check = slice(0, _AFFINE_CHECKS)
    direct = model.simulate(x_init[check], v[check], None if p0 is None else p0[check], relift=relift)[0][:, d + K]
    scale = 1.0 + float(np.max(np.abs(direct)))
    return ahead if np.max(np.abs(direct - ahead[check])) <= 1e-9 * scale else None


def _with_rate_input(model: KoopmanModel, disturbance: DisturbanceModel) -> KoopmanModel:
    """The model with a rate disturbance on one angle's equation as one more input."""
    E = disturbance_direction(model, disturbance.entry)
    return replace(model, B=np.hstack([model.B, E[:, None]]))


def simulate_with_rate(
    model: KoopmanModel,
    disturbance: DisturbanceModel,
    x_init: np.ndarray,
    v: np.ndarray,
    p0: np.ndarray | None,
    forecast: np.ndarray,
    relift: bool = True,
) -> np.ndarray:
    """Windows simulated with a rate disturbance (entry ``theta`` or ``alpha``) following ``forecast``.

    Parameters
    ----------
    model : KoopmanModel
    disturbance : DisturbanceModel
        Its entry says which angle's equation the disturbance moves.
    x_init, v, p0, relift
        As for :meth:`KoopmanModel.simulate` (batched: one window per row).
    forecast : ndarray of shape (n_windows, n_steps)
        The disturbance over each window's last ``n_steps`` samples.

    Returns
    -------
    ndarray of shape (n_windows, n_samples, n_states)
    """
    return _with_rate_input(model, disturbance).simulate(x_init, _rate_windows(v, forecast), p0, relift=relift)[0]


def _rate_windows(v: np.ndarray, forecast: np.ndarray) -> np.ndarray:
    """The windows' inputs with the rate disturbance's forecast as the last input (from the windows' start on)."""
    extra = np.zeros(v.shape[:2] + (1,))
    extra[:, -forecast.shape[1] :, 0] = forecast
    return np.concatenate([v, extra], axis=2)
