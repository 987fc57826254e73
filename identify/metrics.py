"""Prediction scores, per episode and aggregated over episodes, and the search's scoring rule.

All take ``y_true`` and ``y_pred`` of shape (n_samples, n_states). The error
is ``y_true - y_pred``. A prediction with any non-finite value scores
``-inf`` for R^2 and ``+inf`` for the error measures: it never raises.

A channel whose true values are constant has no variance to explain: its
R^2 is undefined. It is left out of the average over states (with a
:class:`ConstantChannelWarning` from :func:`r2_score`); when every channel
is constant, R^2 is NaN.
"""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING, Callable, NamedTuple, Sequence

import numpy as np

from qube_koopman.identify.data.trajectory import Trajectory
from qube_koopman.identify.models.offsets import DEFAULT_BOUND, estimate_offsets_models, predict_with_offsets_models

if TYPE_CHECKING:
    from qube_koopman.identify.model_selection.transfer import ProbeSet

__all__ = [
    "ConstantChannelWarning",
    "r2_score",
    "r2_scores",
    "r2_scores_time_major",
    "r2_from_sums",
    "r2_from_residuals",
    "DivergedPrediction",
    "first_diverged_sample",
    "summarize_episodes",
    "EpisodeScore",
    "episode_score",
    "summarize_scores",
    "nrmse",
    "normalized_mean_error",
    "score_episodes",
    "SCORES",
    "scores_after_window",
    "scores_after_window_models",
    "probe_scores",
]


class ConstantChannelWarning(UserWarning):
    """A channel of the true values is constant: its R^2 is undefined and left out."""


def _pair(y_true, y_pred) -> tuple[np.ndarray, np.ndarray]:
    y_true = np.asarray(y_true, dtype=float)
    y_pred = np.asarray(y_pred, dtype=float)
    if y_true.ndim == 1:
        y_true, y_pred = y_true[:, None], y_pred.reshape(-1, 1)
    if y_true.shape != y_pred.shape:
        raise ValueError(f"true {y_true.shape} and predicted {y_pred.shape} shapes differ")
    if y_true.shape[0] < 2:
        raise ValueError("scores need at least two samples")
    return y_true, y_pred


def r2_scores(y_true, y_pred) -> np.ndarray:
    """R^2 averaged over states, vectorized over leading axes of ``y_pred``.

    ``y_true`` has shape (..., n_samples, n_states) and broadcasts against
    ``y_pred`` (e.g. one row of models per episode). Non-finite predictions
    give -inf; constant true channels are left out of the average (NaN when
    all are constant).
    """
    y_true = np.asarray(y_true, dtype=float)
    y_pred = np.asarray(y_pred, dtype=float)
    with np.errstate(all="ignore"):
        # Sums of squares by einsum: no squared temporary (sweeps score millions of samples).
        diff = y_pred - y_true
        ss_res = np.einsum("...tc,...tc->...c", diff, diff)
    return r2_from_sums(ss_res, *_true_sums(y_true, axis=-2))


def _true_sums(y_true: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """Total sum of squares about the mean along the time ``axis``, and which channels are constant."""
    with np.errstate(all="ignore"):
        centered = y_true - y_true.mean(axis=axis, keepdims=True)
        ss_tot = np.sum(centered * centered, axis=axis)
    # Constant means every value equals the first (the mean's rounding leaves ss_tot ~1e-31).
    first = np.take(y_true, [0], axis=axis)
    return ss_tot, np.all(y_true == first, axis=axis)


def r2_from_sums(ss_res: np.ndarray, ss_tot: np.ndarray, constant: np.ndarray) -> np.ndarray:
    """R^2 averaged over the last (state) axis from residual and total sums of squares.

    ``ss_res`` broadcasts against ``ss_tot`` and ``constant`` (which channels of the
    truth are constant: left out). A non-finite residual (a non-finite prediction
    anywhere, constant channels included) gives -inf; all channels constant gives NaN.
    """
    with np.errstate(all="ignore"):
        per_state = 1.0 - ss_res / ss_tot
    per_state = np.where(np.isfinite(per_state) | constant, per_state, -np.inf)
    per_state, constant = np.broadcast_arrays(per_state, constant)
    valid = ~constant
    n_valid = valid.sum(axis=-1)
    diverged = np.any(np.isinf(np.where(valid, per_state, 0.0)), axis=-1) | ~np.all(np.isfinite(ss_res), axis=-1)
    with np.errstate(all="ignore"):
        mean = np.where(valid, per_state, 0.0).sum(axis=-1) / n_valid
    return np.where(diverged, -np.inf, np.where(n_valid > 0, mean, np.nan))


def r2_scores_time_major(y_true: np.ndarray, *y_pred: np.ndarray) -> np.ndarray:
    """:func:`r2_scores` for arrays with time first.

    Parameters
    ----------
    y_true : ndarray of shape (n_samples, n_episodes, n_states)
    *y_pred : ndarray of shape (n_samples, n_models, n_episodes, n_i)
        The predicted states, in one array or in parts whose channels follow each
        other (``sum(n_i) == n_states``; e.g. controller states, then plant states).

    Returns
    -------
    ndarray of shape (n_models, n_episodes)

    Notes
    -----
    The batched simulator stores its predictions time-major: scoring them in that
    layout, part by part, reads memory in order with no transposed or joined copy.
    """
    y_true = np.asarray(y_true, dtype=float)
    sums, lo = [], 0
    with np.errstate(all="ignore"):
        for part in y_pred:
            diff = part - y_true[:, None, :, lo : lo + part.shape[-1]]
            sums.append(np.einsum("tmec,tmec->mec", diff, diff))
            lo += part.shape[-1]
    if lo != y_true.shape[-1]:
        raise ValueError(f"predicted parts have {lo} channels, the truth {y_true.shape[-1]}")
    return r2_from_residuals(np.concatenate(sums, axis=-1), y_true)


def r2_from_residuals(ss_res: np.ndarray, y_true: np.ndarray) -> np.ndarray:
    """R^2 averaged over states from residual sums of squares accumulated elsewhere.

    Parameters
    ----------
    ss_res : ndarray of shape (..., n_episodes, n_states)
        Sums of squared prediction errors over the scored samples (e.g. summed
        chunk by chunk as a simulation runs).
    y_true : ndarray of shape (n_samples, n_episodes, n_states)
        The true values of those samples, time first.

    Returns
    -------
    ndarray of shape (..., n_episodes)
    """
    return r2_from_sums(ss_res, *_true_sums(np.asarray(y_true, dtype=float), axis=0))


def r2_score(y_true, y_pred) -> float:
    """Coefficient of determination, averaged over states (1 is perfect).

    Constant true channels are left out with a :class:`ConstantChannelWarning`
    (NaN when every channel is constant).

    Parameters
    ----------
    y_true, y_pred : array_like of shape (n_samples, n_states)
        Measured and predicted states (error = true - predicted).
    """
    y_true, y_pred = _pair(y_true, y_pred)
    constant = np.flatnonzero(np.all(y_true == y_true[0], axis=0))
    if constant.size:
        warnings.warn(
            f"true channel(s) {constant.tolist()} are constant: R^2 is undefined there and left out of the average",
            ConstantChannelWarning,
            stacklevel=2,
        )
    return float(r2_scores(y_true, y_pred))


def _peak(y_true: np.ndarray) -> np.ndarray:
    peak = np.max(np.abs(y_true), axis=0)
    return np.where(peak > 0, peak, 1.0)


def nrmse(y_true, y_pred) -> float:
    """RMS error as a percentage of each state's peak amplitude, averaged over states.

    Parameters
    ----------
    y_true, y_pred : array_like of shape (n_samples, n_states)
        Measured and predicted states (error = true - predicted).
    """
    y_true, y_pred = _pair(y_true, y_pred)
    if not np.all(np.isfinite(y_pred)):
        return np.inf
    rmse = np.sqrt(np.mean((y_true - y_pred) ** 2, axis=0))
    return float(np.mean(100.0 * rmse / _peak(y_true)))


def normalized_mean_error(y_true, y_pred) -> float:
    """Mean error as a percentage of each state's peak amplitude, averaged over states.

    Parameters
    ----------
    y_true, y_pred : array_like of shape (n_samples, n_states)
        Measured and predicted states (error = true - predicted).
    """
    y_true, y_pred = _pair(y_true, y_pred)
    if not np.all(np.isfinite(y_pred)):
        return np.inf
    return float(np.mean(100.0 * np.mean(y_true - y_pred, axis=0) / _peak(y_true)))


SCORES: dict[str, Callable] = {"r2": r2_score, "nrmse": nrmse, "nme": normalized_mean_error}


def score_episodes(
    y_true: Sequence[np.ndarray], y_pred: Sequence[np.ndarray], score: str = "r2"
) -> tuple[float, float]:
    """Mean and standard deviation of a score over episodes.

    A diverged episode makes the mean (and standard deviation) infinite.

    Parameters
    ----------
    y_true, y_pred : sequence of ndarray of shape (n_samples, n_states)
        Each episode's measured and predicted states.
    score : {"r2", "nrmse", "nme"}
        The score.

    Returns
    -------
    mean, std : float
    """
    if score not in SCORES:
        raise ValueError(f"unknown score {score!r}; expected one of {', '.join(SCORES)}")
    if len(y_true) != len(y_pred) or not y_true:
        raise ValueError(f"need matching, non-empty episode lists, got {len(y_true)} and {len(y_pred)}")
    values = np.array([SCORES[score](t, p) for t, p in zip(y_true, y_pred)])
    if not np.all(np.isfinite(values)):
        bad = values[~np.isfinite(values)][0]
        return float(bad), float("nan")
    return float(values.mean()), float(values.std())


class DivergedPrediction(UserWarning):
    """A predicted episode diverged: its score is -inf and the means leave it out, saying so."""


def first_diverged_sample(y_pred: np.ndarray) -> int | None:
    """Index of the first sample with a non-finite prediction, or None."""
    bad = ~np.all(np.isfinite(np.asarray(y_pred, dtype=float).reshape(len(y_pred), -1)), axis=1)
    return int(np.argmax(bad)) if bad.any() else None


class EpisodeScore(NamedTuple):
    """One test episode's scores (:func:`episode_score`): what a summary keeps of its prediction."""

    r2: float
    nrmse: float
    #: First non-finite predicted sample (from the scored start on) when it diverged, else None.
    diverged_at: int | None


#: A prediction that leaves this many times the measured signals' range (at least 1) has diverged,
#: finite or not: an unstable model's prediction can stay finite for seconds while it grows to
#: 1e15 rad, and an R^2 of -1e30 says less than "diverged at sample k".
DIVERGED_FACTOR = 1e3


def episode_score(y_true: np.ndarray, y_pred: np.ndarray, start: int = 1) -> EpisodeScore:
    """R^2 and NRMSE of one episode from sample ``start`` on, and where it diverged (see :func:`summarize_episodes`).

    A prediction diverged where it is first non-finite or beyond :data:`DIVERGED_FACTOR` times the
    largest measured magnitude (at least 1): its R^2 is then -inf and its NRMSE inf.
    """
    y_true, y_pred = np.asarray(y_true, dtype=float), np.asarray(y_pred, dtype=float)
    bound = DIVERGED_FACTOR * max(1.0, float(np.nanmax(np.abs(y_true[start:]), initial=0.0)))
    with np.errstate(invalid="ignore"):
        beyond = ~(np.abs(y_pred[start:].reshape(len(y_pred) - start, -1)) <= bound).all(axis=1)
    if beyond.any():
        return EpisodeScore(-np.inf, np.inf, int(np.argmax(beyond)) + start)
    r2, err = r2_score(y_true[start:], y_pred[start:]), nrmse(y_true[start:], y_pred[start:])
    if np.isfinite(r2) and np.isfinite(err):
        return EpisodeScore(r2, err, None)
    k = first_diverged_sample(y_pred[start:])
    return EpisodeScore(r2, err, None if k is None else k + start)


def summarize_episodes(
    y_true: Sequence[np.ndarray], y_pred: Sequence[np.ndarray], start: int = 1, names: Sequence[str] | None = None
) -> dict:
    """Test-set summary: R^2 and NRMSE per episode, their means and standard deviations.

    Samples before ``start`` are left out (by default the first, which is the
    initial condition itself; the reference code keeps the other
    initial-condition samples). A diverged episode (a non-finite prediction
    from ``start`` on) makes the means infinite (R^2 -inf, NRMSE +inf, the
    reference's convention) and the deviations None; it is listed under
    ``"diverged"`` (episode index, name, first non-finite sample), and
    ``"r2_mean_converged"`` is the mean over the other episodes (None when
    all diverged), so nothing is averaged silently.
    """
    if len(y_true) != len(y_pred) or not y_true:
        raise ValueError(f"need matching, non-empty episode lists, got {len(y_true)} and {len(y_pred)}")
    return summarize_scores([episode_score(t, p, start) for t, p in zip(y_true, y_pred)], names)


def summarize_scores(scores: Sequence[EpisodeScore], names: Sequence[str] | None = None) -> dict:
    """:func:`summarize_episodes` from each episode's :func:`episode_score`, computed as the episodes streamed by."""
    if not scores:
        raise ValueError("need a non-empty list of episode scores")
    names = [str(i) for i in range(len(scores))] if names is None else [str(n) for n in names]
    r2 = np.array([s.r2 for s in scores])
    err = np.array([s.nrmse for s in scores])
    ok = np.isfinite(r2) & np.isfinite(err)
    diverged = [
        {"episode": i, "name": names[i], "sample": scores[i].diverged_at} for i in map(int, np.flatnonzero(~ok))
    ]
    finite = bool(ok.all())
    with np.errstate(over="ignore"):  # a finite but huge R^2 (a model that all but diverged): its spread is inf
        r2_std, err_std = (float(r2.std()), float(err.std())) if finite else (None, None)
    return {
        "r2_mean": float(r2.mean()) if finite else -np.inf,
        "r2_std": r2_std,
        "nrmse_mean": float(err.mean()) if finite else np.inf,
        "nrmse_std": err_std,
        "n_episodes": int(r2.size),
        "n_diverged": len(diverged),
        "diverged": diverged,
        "r2_mean_converged": float(r2[ok].mean()) if ok.any() else None,
        "r2_per_episode": r2.tolist(),
    }


def scores_after_window(
    model, trajectories: Sequence[Trajectory], window: int, offsets: bool, bound: float = DEFAULT_BOUND
) -> np.ndarray:
    """R^2 of each episode's prediction from sample ``window`` on, its alpha offset estimated first or not.

    The protocol candidates and probes are scored by: the whole episode predicted from its start
    (with the offset estimated from the first ``window`` samples when ``offsets``), R^2 averaged
    over the measured states, -inf for a diverged prediction.

    Parameters
    ----------
    model : KoopmanModel
        Closed-loop model (inputs r, f).
    trajectories : sequence of Trajectory
        The episodes.
    window : int
        Samples of the estimation window; scored from the next one on.
    offsets : bool
        Estimate each episode's alpha offset from the window first.
    bound : float
        Plausibility bound of the estimate (:func:`estimate_offsets`).

    Returns
    -------
    ndarray of shape (n_episodes,)
    """
    if offsets:
        return scores_after_window_models([model], trajectories, window, bound)[0]
    trajectories = list(trajectories)
    return _scores_from(trajectories, model.predict_many(trajectories), window)


def _scores_from(trajectories: list[Trajectory], predictions, window: int) -> np.ndarray:
    """Each episode's R^2 of its prediction from sample ``window`` on."""
    return np.array([float(r2_scores(t.x[window:], p[window:])) for t, p in zip(trajectories, predictions)])


def scores_after_window_models(
    models: Sequence, trajectories: Sequence[Trajectory], window: int, bound: float = DEFAULT_BOUND
) -> np.ndarray:
    """:func:`scores_after_window` with offsets of several closed-loop models (one lifting and structure) on
    the same episodes, their estimates and predictions batched over the models: shape (n_models, n_episodes)."""
    trajectories = list(trajectories)
    estimates = estimate_offsets_models(models, trajectories, ["alpha"], window, bound)
    predictions = predict_with_offsets_models(models, trajectories, estimates)
    return np.array([_scores_from(trajectories, each, window) for each in predictions]).reshape(
        len(models), len(trajectories)
    )


def probe_scores(
    plant, probes: ProbeSet, window: int, offsets: bool, bound: float, measured: Sequence[int] = (0, 1)
) -> np.ndarray:
    """R^2 of every probe episode predicted by ``plant`` wrapped with its probe controller.

    Parameters
    ----------
    plant : KoopmanModel
        An identified plant (input ``u``).
    probes : ProbeSet
    window : int
        Scores cover the samples from this one on (the offset estimation window's end).
    offsets : bool
        Estimate each probe episode's alpha offset from the window first.
    bound : float
        Plausibility bound of the offsets (larger estimates are not used).
    measured : sequence of int
        Fed-back states.

    Returns
    -------
    ndarray of shape (n_episodes,)
        Mean R^2 of theta and alpha per probe episode (-inf: diverged).
    """
    from qube_koopman.identify.metrics import scores_after_window
    from qube_koopman.identify.estimators.structure import close_loop

    return np.concatenate(
        [
            scores_after_window(close_loop(plant, controller, list(measured)), episodes, window, offsets, bound)
            for controller, episodes in zip(probes.controllers, probes.episodes)
        ]
    )
