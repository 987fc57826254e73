"""The scores of one lifting search candidate's models: its folds' scores with per-episode offsets
estimated (:func:`offset_scores`), the plants fitted on all the training episodes at its best
alphas (:func:`probe_plants`) and their transfer scores on the probes (:func:`transfer_scores`).
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np

from qube_koopman.core.qube import MEASURED
from qube_koopman.identify.metrics import scores_after_window_models
from qube_koopman.identify.model_selection.lifting_space import LiftingSpec
from qube_koopman.identify.model_selection.ranking import CandidateResult
from qube_koopman.identify.model_selection.transfer import ProbeSet

if TYPE_CHECKING:
    from qube_koopman.identify.model_selection.evaluation import SearchData

__all__ = ["fold_scores", "best_alphas", "offset_scores", "probe_plants", "transfer_scores"]


def fold_scores(plain) -> np.ndarray:
    """The plain fold scores, given as an array or a :class:`~.CandidateResult`."""
    return np.asarray(plain.cv_r2 if isinstance(plain, CandidateResult) else plain, dtype=float)


def probe_plants(estimator, data: SearchData, cv: np.ndarray, statistics, timing: dict) -> dict:
    """The plants fitted on all training episodes at the best CV alphas ({alpha index: plant}).

    They fit only the rows re-lifted predictions use, from the statistics of all the
    episodes the sweep folded with its folds' when it had them. ``timing["probe_fits"]``
    gets their time.
    """
    from qube_koopman.core.blas import limited_blas_threads
    from qube_koopman.identify.model_selection.sweep import fit_alphas, fitted_models

    started = time.perf_counter()
    top = np.sort(best_alphas(cv, data.n_transfer_alphas))
    if statistics is not None:
        setup, snapshots = statistics
        with limited_blas_threads(1):
            _, plants = fitted_models(estimator, setup, snapshots, data.alphas[top], None, None)
    else:
        _, plants = fit_alphas(
            estimator, data.trajectories, data.alphas[top], relift_rows_only=True, controllers=data.controllers
        )
    timing["probe_fits"] = time.perf_counter() - started
    return {int(j): plant for j, plant in zip(top, plants)}


def transfer_scores(
    spec: LiftingSpec, data: SearchData, cv: np.ndarray, plants: dict, timing: dict, known: np.ndarray | None = None
) -> np.ndarray:
    """Probe scores (episodes x alphas) of ``plants`` ({alpha index: plant}) at the best CV alphas.

    ``known``: scores already computed at some alphas (NaN elsewhere), kept. Without offsets, the
    plants' closed loops with each probe controller are simulated together.
    ``timing["probe_scoring"]`` gets their time.
    """
    from qube_koopman.core.blas import limited_blas_threads

    probes = data.probes
    if probes is None:
        raise ValueError("transfer scores need the search's probes (SearchData.probes)")
    started = time.perf_counter()
    # The alphas with a plant: an offsets candidate predicting with its plain twin's has them at its scored alphas.
    top = [int(j) for j in np.sort(best_alphas(cv, data.n_transfer_alphas)) if int(j) in plants]
    out = np.full((probes.n_episodes, data.alphas.size), np.nan)
    if known is not None:  # the columns a screen scored already (the same plants: the same numbers)
        done = [j for j in top if not np.all(np.isnan(known[:, j]))]
        out[:, done] = known[:, done]
        top = [j for j in top if j not in done]
    with limited_blas_threads(1):
        if spec.offsets and top:
            out[:, top] = _offset_probe_scores([plants[j] for j in top], probes, data.window, data.bound)
        elif top:
            out[:, top] = _plain_probe_scores([plants[j] for j in top], probes, data.window)
    timing["probe_scoring"] = time.perf_counter() - started
    return out


def _plain_probe_scores(plants: list, probes: ProbeSet, window: int) -> np.ndarray:
    """:func:`~qube_koopman.identify.metrics.probe_scores` without offsets of several plants (one lifting),
    every probe controller's closed loops of all of them simulated together: shape (n_episodes, n_plants)."""
    from qube_koopman.identify.model_selection.sweep import grouped_episode_scores

    return np.concatenate(grouped_episode_scores(_probe_loops(plants, probes), "cl", window, True), axis=1).T


def _offset_probe_scores(plants: list, probes: ProbeSet, window: int, bound: float) -> np.ndarray:
    """:func:`~qube_koopman.identify.metrics.probe_scores` with offsets of several plants (one lifting), each
    probe controller's closed loops of all of them estimated and predicted together: shape (n_episodes, n_plants)."""
    return np.concatenate(
        [scores_after_window_models(loops, held, window, bound) for loops, held in _probe_loops(plants, probes)],
        axis=1,
    ).T


def _probe_loops(plants: list, probes: ProbeSet) -> list[tuple[list, list]]:
    """Per probe controller: the plants' closed loops with it, and its probe episodes."""
    from qube_koopman.identify.estimators.structure import close_loop

    return [
        ([close_loop(p, controller, list(MEASURED)) for p in plants], episodes)
        for controller, episodes in zip(probes.controllers, probes.episodes)
    ]


def best_alphas(cv: np.ndarray, k: int) -> np.ndarray:
    """Indices of the ``k`` best alphas by mean fold score (-inf where a fold diverged), best first."""
    mean = cv.mean(axis=0)
    mean = np.where(np.isfinite(mean), mean, -np.inf)
    return np.argsort(-mean, kind="stable")[: min(k, mean.size)]


def offset_scores(folds: list, lifting, data: SearchData, top: np.ndarray, timing: dict) -> np.ndarray:
    """Fold scores with an alpha offset estimated on each validation episode, at the alphas ``top``.

    ``folds``: per fold, {alpha index: closed loop} and the validation episodes; the closed loops
    are FittedRows rebuilt with ``lifting``, or models themselves when ``lifting`` is None.
    """
    from qube_koopman.core.blas import limited_blas_threads
    from qube_koopman.identify.model_selection.sweep import EPISODES_PER_BATCH

    started = time.perf_counter()
    out = np.full((len(folds), data.alphas.size), np.nan)
    with limited_blas_threads(1):
        for i, (closed, validation) in enumerate(folds):
            models = {int(j): closed[int(j)] if lifting is None else closed[int(j)].model(lifting) for j in top}
            scores = []
            for lo in range(0, len(validation), EPISODES_PER_BATCH):  # a few episodes read at a time
                held_out = [data.trajectories[k] for k in validation[lo : lo + EPISODES_PER_BATCH]]
                scores.append(scores_after_window_models(list(models.values()), held_out, data.window, data.bound))
            out[i, list(models)] = np.concatenate(scores, axis=1).mean(axis=1)
    timing["offsets"] = time.perf_counter() - started
    return out
