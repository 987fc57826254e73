"""Regularization sweeps with episode-grouped cross-validation.

Snapshot statistics are computed once per episode, in one pass over the episodes
that folds each into the running totals of the folds training on it (memory
grows with the folds, not the episodes; the episodes may be a lazy sequence
read one at a time); each
alpha is then one small least-squares solve, and every alpha's model
predicts every validation episode in one batched simulation. A lifting that
learns from data (RBF centres) is refitted on each fold's training episodes.
Episodes of several controllers (``controllers``) are grouped per controller
in the statistics; each fold's closed loops are those of the controller its
validation episodes ran (a per-controller fold that holds out a whole
controller: one the fold's plant was not fitted to).
"""

from __future__ import annotations

import copy
import dataclasses
import time
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from qube_koopman.core.blas import limited_blas_threads
from qube_koopman.identify._checks import check_choice
from qube_koopman.identify.estimators.cl_edmd import ClosedLoopKoopman
from qube_koopman.core.lti import same_system
from qube_koopman.identify.estimators.edmd import Edmd
from qube_koopman.identify.estimators.mixed import distinct_controllers
from qube_koopman.identify.models.model import FittedRows, KoopmanModel
from qube_koopman.identify.estimators.regression import GroupedSnapshots, Snapshots, solved_for_many_alphas
from qube_koopman.identify.metrics import r2_from_residuals
from qube_koopman.identify.models.simulate import simulate_chunks
from qube_koopman.identify.estimators.structure import close_loop
from qube_koopman.identify.data.trajectory import Trajectory, as_episodes, select_episodes
from qube_koopman.core.lti import DiscreteStateSpace

__all__ = [
    "AlphaAtGridEdge",
    "FLAT_R2",
    "warn_at_grid_edge",
    "SweepResult",
    "regularization_sweep",
    "SweepOptions",
    "fitted_models",
    "fit_alphas",
    "episode_scores",
    "SCORINGS",
]

SCORINGS = ("cl", "plant")
# Models simulated together: bounds their rings of permuted Koopman rows to ~64 MB (predictions
# are scored as they come, never held whole).
_MAX_BATCH_VALUES = 8_000_000
# Validation episodes scored together: a fold's held-out episodes are read and simulated this many
# at a time, so scoring memory does not grow with the data (a batch of 32 episodes of 20 s holds about
# 25 MB). Each batch is one pass over the samples, whose per-step cost does not grow with the batch:
# the paper's 20 test episodes are one pass, not 16 then 4.
EPISODES_PER_BATCH = 32


@dataclass
class SweepResult:
    """Cross-validated scores and spectral radii against the regularization coefficient.

    Attributes
    ----------
    alphas : ndarray of shape (n_alphas,)
    cv_r2 : dict of str to ndarray of shape (n_folds, n_alphas)
        Mean R^2 over each fold's validation episodes, per scoring
        (``"cl"``: closed-loop prediction, controller states included;
        ``"plant"``: plant prediction from the plant input).
    spectral_radius_closed_loop, spectral_radius_plant : ndarray of shape (n_alphas,)
        Of the models fitted on all training episodes.
    closed_loop_models, plant_models : list of KoopmanModel
        The models fitted on all training episodes, one per alpha
        (closed-loop entries are None for EDMD without a controller).
    fold_models : list of (closed-loop models, plant models, validation indices), optional
        Every fold's models, with ``keep_fold_models``. Without ``fit_all`` (and
        with ``relift``) only the rows a re-lifted prediction uses are fitted;
        the others are NaN. With ``keep_fold_models="rows"`` the models are
        :class:`~qube_koopman.identify.models.model.FittedRows` (their fitted rows only,
        rebuilt with the setup's lifting ``statistics[0].lifting``).
    seconds : dict of str to float
        Where the time went: ``statistics`` (lifting the episodes and folding their
        factors), ``fits`` (the solves for every alpha) and ``predictions`` (the folds'
        validation episodes predicted and scored).
    statistics : (setup, Snapshots or GroupedSnapshots), optional
        Without ``fit_all``: the setup every fold shared and the statistics of
        all the episodes, folded in the same pass as the folds' (None when the
        lifting learns from data and each fold computed its own, and with
        ``fit_all``, which fits the final models itself): models on all the
        episodes at any alpha are then one small solve each (:func:`fitted_models`).
    """

    alphas: np.ndarray
    cv_r2: dict[str, np.ndarray] = field(default_factory=dict)
    spectral_radius_closed_loop: np.ndarray | None = None
    spectral_radius_plant: np.ndarray | None = None
    closed_loop_models: list | None = None
    plant_models: list | None = None
    fold_models: list | None = None
    statistics: tuple | None = None
    seconds: dict = field(default_factory=lambda: {"statistics": 0.0, "fits": 0.0, "predictions": 0.0})

    def cv_r2_mean(self, scoring: str) -> np.ndarray:
        """Mean over folds (-inf where any fold diverged)."""
        return self.cv_r2[scoring].mean(axis=0)

    def best_alpha(self, scoring: str) -> float:
        """The alpha with the highest mean cross-validated R^2 (the smallest among ties)."""
        return float(self.alphas[int(np.argmax(self.cv_r2_mean(scoring)))])


class AlphaAtGridEdge(UserWarning):
    """The sweep's best alpha is the first or last of its grid: the best may lie beyond it."""


#: A cross-validated R^2 that changes by less than this between a grid's edge and its neighbour is flat there: a
#: wider grid would gain about as little, so the edge is no reason to warn.
FLAT_R2 = 1e-4


def warn_at_grid_edge(alphas: Sequence[float] | np.ndarray, best: float, scores=None) -> None:
    """Warn (:class:`AlphaAtGridEdge`) when ``best`` is the smallest or largest of ``alphas``.

    Parameters
    ----------
    alphas : sequence of float
        The sweep's grid.
    best : float
        The alpha the sweep chose.
    scores : sequence of float, optional
        The cross-validated score of each alpha (in the order of ``alphas``): no warning when the edge's beats
        its neighbour's by less than :data:`FLAT_R2` (the score is flat there).
    """
    order = np.argsort(np.asarray(alphas, dtype=float))
    grid = np.asarray(alphas, dtype=float)[order]
    if len(grid) < 2 or grid[0] < best < grid[-1]:
        return
    lower = best <= grid[0]
    if scores is not None:
        ranked = np.asarray(scores, dtype=float)[order]
        edge, neighbour = (ranked[0], ranked[1]) if lower else (ranked[-1], ranked[-2])
        if np.isfinite(neighbour) and edge - neighbour < FLAT_R2:
            return
    warnings.warn(
        f"the sweep's best alpha {best:g} is the {'smallest' if lower else 'largest'} of its grid ({grid[0]:g} to "
        f"{grid[-1]:g}) and its score still rises there: the best may lie beyond it; widen the sweep "
        "(--alpha-sweep MIN MAX N)",
        AlphaAtGridEdge,
        stacklevel=2,
    )


def fitted_models(
    template,
    setup,
    snapshots: Snapshots,
    alphas: Sequence[float] | np.ndarray,
    controller: DiscreteStateSpace | None,
    measured,
) -> tuple[list[KoopmanModel | None], list[KoopmanModel]]:
    """Closed-loop and plant models of ``template`` for each alpha from shared statistics.

    EDMD plants are wrapped with ``controller`` for their closed loop (None each without one).
    """
    closed, plants = [], []
    if len(alphas) > 1:
        solved_for_many_alphas(snapshots)
    for alpha in alphas:
        est = copy.copy(template)
        est.alpha = float(alpha)
        est.finish_fit(setup, snapshots)
        if isinstance(est, Edmd):
            plants.append(est.model_)
            closed.append(close_loop(est.model_, controller, measured) if controller is not None else None)
        else:
            plants.append(est.plant_model_)
            closed.append(est.closed_loop_model_)
    return closed, plants


def fit_alphas(
    estimator,
    trajectories: Sequence[Trajectory],
    alphas: Sequence[float] | np.ndarray,
    controller: DiscreteStateSpace | None = None,
    measured=None,
    relift_rows_only: bool = False,
    controllers: Sequence[DiscreteStateSpace] | None = None,
) -> tuple[list, list[KoopmanModel]]:
    """Closed-loop and plant models of ``estimator`` fitted on all ``trajectories``, one per alpha.

    The statistics are computed once and shared by every alpha (as in a sweep).
    With ``relift_rows_only`` only the Koopman rows a re-lifted prediction uses
    are fitted (the others NaN, as in a sweep's folds): several times faster
    for long liftings, for models that only predict. ``controllers``: each
    episode's, for a closed-loop estimator's episodes under several controllers.
    """
    if isinstance(estimator, ClosedLoopKoopman):
        controller, measured = estimator.controller, estimator.measured
    with limited_blas_threads(1):
        setup, (snapshots,) = _statistics(estimator, as_episodes(trajectories), [None], relift_rows_only, controllers)
        return fitted_models(estimator, setup, snapshots, alphas, controller, measured)


def _batches(n_models: int, n_values_per_model: int) -> list[slice]:
    size = max(1, _MAX_BATCH_VALUES // max(1, n_values_per_model))
    return [slice(i, min(i + size, n_models)) for i in range(0, n_models, size)]


class _ResidualSums:
    """Squared prediction errors from sample ``start`` on, summed chunk by chunk as the simulation runs.

    ``truth`` is time-major (samples, episodes, channels); the chunk's channels ``channels``
    (passthrough then plant states, or the plant states alone) are compared with it.
    Samples before the first prediction are the initial condition itself: no error.
    """

    def __init__(self, truth: np.ndarray, start: int, n_models: int, channels: slice, groups: int = 0) -> None:
        """``groups``: paired groups of models (see :func:`grouped_episode_scores`); ``truth`` is then
        (samples, groups, episodes, channels), each group's ``n_models // groups`` models on its own."""
        self.truth, self.start, self.channels, self.groups = truth, start, channels, groups
        self.sums = np.zeros((n_models,) + truth.shape[-2:])

    def __call__(self, k0: int, chunk: np.ndarray, models: np.ndarray) -> None:
        lo, hi = max(k0, self.start), k0 + len(chunk)
        if lo < hi and self.groups:  # every model stays to the end: each group's against its own truth
            part = chunk[lo - k0 :, ..., self.channels]
            part = part.reshape((part.shape[0], self.groups, -1) + part.shape[2:])
            diff = part - self.truth[lo:hi, :, None]
            self.sums += np.einsum("tgmec,tgmec->gmec", diff, diff).reshape(self.sums.shape)
        elif lo < hi:
            diff = chunk[lo - k0 :, ..., self.channels] - self.truth[lo:hi, None]
            self.sums[models] += np.einsum("tmec,tmec->mec", diff, diff)
        else:
            # Not scored yet, but a prediction diverged here stays diverged (its model may leave
            # the chunks before the scored samples): its sums become infinite now.
            diverged = ~np.isfinite(chunk[-1, ..., self.channels])
            self.sums[models] += np.where(diverged, np.inf, 0.0)


def _score(
    models: list[KoopmanModel],
    episodes: Sequence[Trajectory],
    scoring: str,
    relift: bool,
    start: int = 1,
    measured_only: bool = False,
) -> np.ndarray:
    """Mean R^2 over episodes for every model, from sample ``start`` on: shape (n_models,).

    The episodes are taken ``EPISODES_PER_BATCH`` at a time (a lazy sequence is read so): memory stays
    that of one batch however many a fold holds out.
    """
    totals = np.zeros(len(models))
    for lo in range(0, len(episodes), EPISODES_PER_BATCH):
        batch = [episodes[j] for j in range(lo, min(lo + EPISODES_PER_BATCH, len(episodes)))]
        totals += _score_sums(models, batch, scoring, relift, start, measured_only)
    return totals / len(episodes)


def _score_sums(
    models: list[KoopmanModel], episodes: list[Trajectory], scoring: str, relift: bool, start: int, measured_only: bool
) -> np.ndarray:
    """Sum of R^2 over ``episodes`` for every model (batched by length): shape (n_models,)."""
    return episode_scores(models, episodes, scoring, relift, start, measured_only).sum(axis=1)


def episode_scores(
    models: Sequence[KoopmanModel],
    episodes: Sequence[Trajectory],
    scoring: str = "cl",
    relift: bool = True,
    start: int = 1,
    measured_only: bool = True,
) -> np.ndarray:
    """R^2 of every episode predicted by every model, simulated together (one batch per episode length).

    Parameters
    ----------
    models : sequence of KoopmanModel
        Models sharing one lifting and structure (a sweep's alphas, or their closed loops with
        one controller).
    episodes : sequence of Trajectory
    scoring : {"cl", "plant"}
        Closed-loop prediction (inputs r, f) or plant prediction (input u).
    relift : bool
        Re-lift the predicted states at every step.
    start : int
        First scored sample of each episode.
    measured_only : bool
        Closed-loop scores of the measured states only, not the controller states too.

    Returns
    -------
    ndarray of shape (n_models, n_episodes)
        Mean R^2 over the scored channels (-inf: the prediction diverged), as
        :func:`~qube_koopman.identify.metrics.scores_after_window` gives one model's without offsets.
    """
    ref = models[0]
    d, n_p = ref.n_delays, ref.n_passthrough
    by_length: dict[int, list[int]] = {}
    for i, t in enumerate(episodes):
        by_length.setdefault(t.n_samples, []).append(i)
    out = np.zeros((len(models), len(episodes)))
    A = np.stack([m.A for m in models])
    B = np.stack([m.B for m in models])
    with_p = scoring == "cl" and not measured_only
    channels = slice(0, None) if with_p else slice(n_p, None)
    # The memory a model's simulation holds: its ring of permuted rows (see identify.models.simulate).
    per_model = (n_p + ref.n_states) * A.shape[1] * (d + 1)
    for indices in by_length.values():
        group = [episodes[i] for i in indices]
        x_init = np.stack([t.x[: d + 1] for t in group])
        v = np.stack([ref.inputs_of(t) for t in group])
        # Time-major truth (samples, episodes, channels), as the simulator hands its predictions.
        truth = np.stack([np.hstack([_controller_states(t), t.x]) if with_p else t.x for t in group], axis=1)
        p0 = np.stack([_controller_states(t)[d] for t in group]) if scoring == "cl" else None
        for sl in _batches(len(models), per_model):
            sums = _ResidualSums(truth, start, sl.stop - sl.start, channels)
            simulate_chunks(A[sl], B[sl], ref.lifting, n_p, x_init, v, p0, relift, sums)
            out[sl, indices] = r2_from_residuals(sums.sums, truth[start:])
    return out


def grouped_episode_scores(
    groups: Sequence[tuple[Sequence[KoopmanModel], Sequence[Trajectory]]],
    scoring: str = "cl",
    start: int = 1,
    measured_only: bool = True,
) -> list[np.ndarray]:
    """:func:`episode_scores` (re-lifted) of several groups of models, each on its own episodes.

    The probe controllers' closed loops are such groups: each controller's loops of a few plants
    predict that controller's episodes. Scored one group at a time, a group of one or two models
    costs the simulator's per-sample overhead, not arithmetic; groups step together instead
    (:func:`~qube_koopman.identify.models.simulate.simulate_chunks` with ``paired``), one batch per
    episode length, a group with fewer episodes of that length padded by repeating its last one
    (the padding's scores dropped). The scores are each group's own, as :func:`episode_scores` gives them.

    Parameters
    ----------
    groups : sequence of (models, episodes)
        Every group has as many models, all of one lifting and structure (controllers of one order).
    scoring, start, measured_only
        As for :func:`episode_scores`.

    Returns
    -------
    list of ndarray of shape (n_models, n_episodes)
        Per group.
    """
    n_models = {len(models) for models, _ in groups}
    if len(n_models) != 1:
        raise ValueError(f"groups of {sorted(n_models)} models: grouped scores need as many models in each")
    out = [np.zeros((len(models), len(episodes))) for models, episodes in groups]
    ref = groups[0][0][0]
    d, n_p, M = ref.n_delays, ref.n_passthrough, n_models.pop()
    with_p = scoring == "cl" and not measured_only
    channels = slice(0, None) if with_p else slice(n_p, None)
    by_length: dict[int, dict[int, list[int]]] = {}  # length -> group -> its episodes of that length
    for g, (_, episodes) in enumerate(groups):
        for i, t in enumerate(episodes):
            by_length.setdefault(t.n_samples, {}).setdefault(g, []).append(i)
    per_model = (n_p + ref.n_states) * ref.A.shape[0] * (d + 1)
    for members in by_length.values():
        for sl in _batches(len(members), per_model * M):
            chosen = list(members.items())[sl]
            E = max(len(indices) for _, indices in chosen)
            padded = [[groups[g][1][indices[min(e, len(indices) - 1)]] for e in range(E)] for g, indices in chosen]
            inputs = [groups[g][0][0] for g, _ in chosen]  # each group's models share their inputs' shape
            x_init = np.stack([[t.x[: d + 1] for t in ts] for ts in padded])
            v = np.stack([[model.inputs_of(t) for t in ts] for model, ts in zip(inputs, padded)])
            truth = np.stack(
                [
                    np.stack([np.hstack([_controller_states(t), t.x]) if with_p else t.x for t in ts], axis=1)
                    for ts in padded
                ],
                axis=1,
            )
            p0 = np.stack([[_controller_states(t)[d] for t in ts] for ts in padded]) if scoring == "cl" else None
            A = np.stack([m.A for g, _ in chosen for m in groups[g][0]])
            B = np.stack([m.B for g, _ in chosen for m in groups[g][0]])
            sums = _ResidualSums(truth, start, len(A), channels, groups=len(chosen))
            simulate_chunks(A, B, ref.lifting, n_p, x_init, v, p0, True, sums, paired=True)
            for k, (g, indices) in enumerate(chosen):
                scores = r2_from_residuals(sums.sums[k * M : (k + 1) * M], truth[start:, k])
                out[g][:, indices] = scores[:, : len(indices)]
    return out


def _controller_states(t: Trajectory) -> np.ndarray:
    """``t``'s controller states, which a closed-loop score predicts from (a ValueError when it has none)."""
    if t.xc is None:
        raise ValueError(f"episode {t.name or '(unnamed)'}: a closed-loop score needs the controller state 'xc'")
    return t.xc


@dataclass(frozen=True)
class SweepOptions:
    """How :func:`regularization_sweep` scores, what it keeps and fits, and where its statistics come from.

    Parameters
    ----------
    measured : sequence of int, optional
        Fed-back states for wrapping EDMD plants.
    relift : bool
        Re-lift predictions at every step (as the reference code).
    progress : callable(done, total), optional
        Called after each fold and after the final fits.
    score_from : int
        First scored sample of each validation episode (1: all but the
        initial condition, the reference's convention).
    measured_only : bool
        Closed-loop scoring of the measured states only (the test scores'
        measure), not of the controller states too.
    keep_fold_models : bool or "rows"
        Keep every fold's models in :attr:`SweepResult.fold_models`; ``"rows"``:
        only their fitted rows (kilobytes where a partial model holds megabytes).
    fit_all : bool
        Also fit every alpha on all the episodes (models and spectral radii
        in the result); a search that only ranks liftings can skip it, and
        then (with ``relift``) the folds fit only the Koopman rows that
        re-lifted predictions use.
    episode_statistics : callable(estimator, setup, indices), optional
        Computes the per-episode statistics of the episodes at ``indices`` (of
        ``trajectories``), in order, elsewhere: on a dask cluster,
        :class:`~qube_koopman.identify.model_selection.distributed.ClusterStatistics`. Default: here.
    shared : (setup, per-fold statistics, all-episode statistics[, episode heads]), optional
        The folds' statistics already computed, on these ``splits`` without ``fit_all``, for
        a lifting whose features include this one's (:func:`fold_statistics` of it): this
        lifting's are taken from them (:func:`sub_statistics`) instead of lifting the
        episodes again, when it can (a single controller; fewer delays with the episodes'
        heads, :func:`episode_heads`). As :class:`OwnStatistics`, this very lifting's (with
        ``controllers`` too): used as they are.
    """

    measured: Sequence[int] | None = None
    relift: bool = True
    progress: Callable[[int, int], None] | None = None
    score_from: int = 1
    measured_only: bool = False
    keep_fold_models: bool | str = False
    fit_all: bool = True
    episode_statistics: Callable | None = None
    shared: tuple | None = None


def regularization_sweep(
    estimator,
    trajectories: Sequence[Trajectory],
    alphas: Sequence[float] | np.ndarray,
    splits: Sequence[tuple[np.ndarray, np.ndarray]],
    scorings: Sequence[str] = SCORINGS,
    controller: DiscreteStateSpace | None = None,
    controllers: Sequence[DiscreteStateSpace] | None = None,
    options: SweepOptions = SweepOptions(),
) -> SweepResult:
    """Cross-validate ``estimator`` over ``alphas`` on episode-grouped ``splits``.

    Parameters
    ----------
    estimator : Edmd or ClEdmd (or ClEdmdLstsq)
        Unfitted template; its ``alpha`` is ignored.
    trajectories : sequence of Trajectory
        Training episodes (signals x, u, r, f, xc as the scorings need).
    alphas : sequence of float (or ndarray)
    splits : sequence of (train_indices, validation_indices)
        For example :func:`identify.model_selection.split.group_shuffle_splits`, or with
        several controllers :func:`identify.model_selection.split.leave_one_controller_out`.
    scorings : sequence of {"cl", "plant"}
    controller : DiscreteStateSpace, optional
        Wraps EDMD plants for closed-loop scoring (a closed-loop estimator
        uses its own).
    controllers : sequence of DiscreteStateSpace, optional
        The controller each episode was recorded under (None: all ran the
        estimator's, or ``controller`` for EDMD). Each fold's validation
        episodes must share one controller: the fold's closed loops are that
        controller's (a closed-loop estimator's plant fitted to the fold's
        training episodes, whatever their controllers).
    options : SweepOptions
        How it scores, what it keeps and fits, where the statistics come from.

    Returns
    -------
    SweepResult
    """
    with limited_blas_threads(1):
        return _sweep(estimator, trajectories, alphas, splits, scorings, controller, controllers, options)


def _sweep(estimator, trajectories, alphas, splits, scorings, controller, controllers, options):
    start, measured_only, keep, relift = (
        options.score_from,
        options.measured_only,
        options.keep_fold_models,
        options.relift,
    )
    for s in scorings:
        check_choice(s, "scoring", SCORINGS)
    alphas = np.asarray(alphas, dtype=float)
    if alphas.ndim != 1 or alphas.size == 0 or not np.all(np.isfinite(alphas)) or np.any(alphas < 0):
        raise ValueError("alphas must be a non-empty list of non-negative numbers")
    measured = options.measured
    if isinstance(estimator, ClosedLoopKoopman):
        controller, measured = estimator.controller, estimator.measured
    elif "cl" in scorings and controller is None:
        raise ValueError("closed-loop scoring of EDMD needs the controller to wrap its plant")
    trajectories = as_episodes(trajectories)
    if controllers is not None and len(controllers) != len(trajectories):
        raise ValueError(f"{len(controllers)} controllers for {len(trajectories)} episodes: give one per episode")
    total = len(splits) + 1
    # Without the final fits only re-lifted predictions are made: the rows they recompute from
    # the predicted states need no fit (on a 40-delay search lifting, 4 rows of 370).
    partial = relift and not options.fit_all
    result = SweepResult(
        alphas, {s: np.zeros((len(splits), alphas.size)) for s in scorings}, fold_models=[] if keep else None
    )
    timed = seconds_timer(result.seconds)
    shared, per_fold = _sweep_statistics(estimator, trajectories, splits, controllers, options, timed)
    result.statistics = None if options.fit_all else shared
    for i, (train, validation) in enumerate(splits):
        held_out_by = _fold_controller(controllers, validation, controller, i)
        fold = _for_controller(estimator, held_out_by)
        if shared is None:
            with timed("statistics"):
                setup, (snapshots,) = _statistics(
                    fold,
                    select_episodes(trajectories, train),
                    [None],
                    partial,
                    None if controllers is None else [controllers[j] for j in train],
                    options.episode_statistics,
                    train,
                )
        else:
            setup, snapshots = shared[0], per_fold[i]
        with timed("fits"):
            closed, plants = fitted_models(fold, setup, snapshots, alphas, held_out_by, measured)
        held_out = select_episodes(trajectories, validation)
        with timed("predictions"):
            for s in scorings:
                result.cv_r2[s][i] = _score(closed if s == "cl" else plants, held_out, s, relift, start, measured_only)
        if keep:
            if keep == "rows":
                closed, plants = [FittedRows.of(m) for m in closed], [FittedRows.of(m) for m in plants]
            result.fold_models.append((closed, plants, np.asarray(validation)))
        if options.progress:
            options.progress(i + 1, total)
    if not options.fit_all:
        return result
    _final_fits(
        estimator, trajectories, controllers, shared, (controller, measured), options.episode_statistics, result
    )
    if options.progress:
        options.progress(total, total)
    return result


def _sweep_statistics(estimator, trajectories, splits, controllers, options: SweepOptions, timed) -> tuple:
    """The statistics the sweep's folds share, ``((setup, all-episode statistics), per-fold statistics)``:
    taken from ``options.shared``, or from one pass over the episodes; ``(None, None)`` for a lifting
    that learns from each fold's episodes."""
    given = options.shared
    if given is None or options.fit_all or not options.relift:
        derived = None
    elif isinstance(given, OwnStatistics):
        derived = tuple(given)[:3]
    else:
        derived = sub_statistics(estimator, given, controllers, splits)
    if derived is not None:
        with timed("statistics"):
            setup, per_fold, everything = derived
        return (setup, everything), per_fold
    if _learns_from_data(estimator):
        return None, None
    # One pass over the episodes folds each into the running totals of the folds training on it
    # (and of all of them): memory O(folds x p^2), not O(episodes x p^2).
    partial = options.relift and not options.fit_all
    with timed("statistics"):
        setup, (*per_fold, everything) = _statistics(
            estimator,
            trajectories,
            [t for t, _ in splits] + [None],
            partial,
            controllers,
            options.episode_statistics,
        )
    return (setup, everything), per_fold


def _final_fits(estimator, trajectories, controllers, shared, loop, elsewhere, result):
    """Every alpha fitted on all the episodes (``loop``: the controller and measured states wrapping a plant),
    its models and spectral radii set in ``result``."""
    controller, measured = loop
    if shared is None:
        setup, (snapshots,) = _statistics(estimator, trajectories, [None], controllers=controllers, elsewhere=elsewhere)
    else:
        setup, snapshots = shared
    closed, plants = fitted_models(estimator, setup, snapshots, result.alphas, controller, measured)
    result.closed_loop_models, result.plant_models = closed, plants
    result.spectral_radius_plant = np.array([m.spectral_radius() for m in plants])
    if closed[0] is not None:
        result.spectral_radius_closed_loop = np.array([m.spectral_radius() for m in closed])


def fold_statistics(
    estimator,
    trajectories: Sequence[Trajectory],
    splits: Sequence[tuple[np.ndarray, np.ndarray]],
    controllers: Sequence[DiscreteStateSpace] | None = None,
    episodes=None,
) -> tuple:
    """What a sweep without final fits (``fit_all=False``, re-lifted) computes before it solves.

    Returns ``(setup, [statistics of each fold's training episodes], statistics of all
    episodes)``: the ``shared`` argument of :func:`regularization_sweep` for any lifting whose
    features are some of this one's. ``episodes`` (indices): of those episodes only, a part
    that :func:`merge_fold_statistics` joins with the others' (None where a fold trains on none
    of them); the other episodes are not read.
    """
    selections: list[np.ndarray | list[int] | None] = [t for t, _ in splits] + [None]
    if episodes is not None:
        part = {int(j) for j in episodes}
        selections = [sorted(part if s is None else part.intersection(int(j) for j in s)) for s in selections]
    setup, totals = _statistics(
        estimator, as_episodes(trajectories), [s for s in selections if s is None or len(s)], True, controllers
    )
    totals = iter(totals)
    *per_fold, everything = [next(totals) if s is None or len(s) else None for s in selections]
    return setup, per_fold, everything


class OwnStatistics(tuple):
    """:func:`fold_statistics` of the very lifting (and controllers) a sweep is given them for
    (its ``shared``): used as they are, with no columns taken."""


def merge_fold_statistics(parts: Sequence[tuple]) -> tuple:
    """The :func:`fold_statistics` of all the episodes from those of parts of them (per controller when several).

    Exact up to rounding: each total is the factor of the parts' factors stacked.
    """

    setup = parts[0][0]

    def total(stats):
        stats = [s for s in stats if s is not None]
        if not isinstance(stats[0], GroupedSnapshots):
            return Snapshots.total(stats)
        # Per controller, in the setup's order (that of a pass over all the episodes); a part may lack some.
        order = [
            c
            for c in setup.controller_groups.controllers
            if any(same_system(c, k) for s in stats for k in s.controllers)
        ]
        merged = []
        for ctrl in order:
            mine = [
                (p, m, r, k)
                for s in stats
                for p, m, r, k in zip(s.parts, s.maps, s.plant_rows, s.controllers)
                if same_system(k, ctrl)
            ]
            merged.append((Snapshots.total([p for p, _, _, _ in mine]), *mine[0][1:]))
        return GroupedSnapshots(*(tuple(column) for column in zip(*merged)))

    per_fold = [total([p[1][i] for p in parts]) for i in range(len(parts[0][1]))]
    return setup, per_fold, total([p[2] for p in parts])


def episode_heads(trajectories: Sequence[Trajectory], n_delays: int) -> list[Trajectory]:
    """Each episode's first ``n_delays + 1`` samples: what :func:`sub_statistics` needs to take the
    statistics of a lifting with fewer delays from those of one with ``n_delays``."""
    return [_first_samples(t, n_delays + 1) for t in as_episodes(trajectories)]


def _first_samples(t: Trajectory, n: int) -> Trajectory:
    """``t``'s first ``n`` samples."""

    def head(signal: np.ndarray | None) -> np.ndarray | None:
        return None if signal is None else signal[:n]

    return dataclasses.replace(t, x=t.x[:n], u=head(t.u), r=head(t.r), f=head(t.f), xc=head(t.xc))


def sub_statistics(
    estimator, statistics: tuple, controllers=None, splits=None, columns: Sequence[int] | None = None
) -> tuple | None:
    """``estimator``'s fold statistics taken from those of a lifting whose features include its own.

    ``statistics`` is :func:`fold_statistics` of the larger lifting. Exact (a factor of the
    selected columns, :meth:`~qube_koopman.identify.estimators.regression.Snapshots.columns`, of each
    controller's part when ``controllers`` are given); None when it cannot be done so: a feature the
    larger lifting lacks, or other leading (re-lifted) rows.
    A lifting with fewer delays has more snapshots (from an earlier sample of each episode): when
    ``statistics`` has a fourth element, :func:`episode_heads` of the episodes at the larger
    lifting's delays, its extra snapshots are factored from those and folded in (into each fold's
    by its training episodes, ``splits``, and into its controller's part); without, None.
    ``columns``: the column of each of this lifting's features among the larger lifting's, where
    their names do not say (the RBF stage's candidates, all of whose centres one basis holds, name
    them alike); by default found by name.
    """
    big_setup, per_fold, everything = statistics[:3]
    heads = statistics[3] if len(statistics) > 3 else None
    grouped = isinstance(everything, GroupedSnapshots)  # per controller: a part each
    if not (grouped or isinstance(everything, Snapshots)) or grouped != (controllers is not None):
        return None
    if _learns_from_data(estimator):
        return None
    template = copy.copy(estimator)
    setup = (
        template.setup_fit(big_setup.trajectories)
        if not isinstance(template, ClosedLoopKoopman)
        else template.setup_fit(big_setup.trajectories, controllers)
    )
    setup = dataclasses.replace(setup, target_rows=template.relift_rows(setup))
    small, big = setup.lifting, big_setup.lifting
    fewer = small.n_delays_ < big.n_delays_
    if (
        small.n_delays_ > big.n_delays_
        or setup.target_rows != big_setup.target_rows
        or setup.n_feedforward != big_setup.n_feedforward
    ):
        return None
    names, big_names = small.feature_names_out_, big.feature_names_out_
    n_c = setup.target_rows - small.n_features_in_  # the controller's states lead the snapshots
    if columns is None:
        if any(n not in big_names for n in names) or names[: small.n_features_in_] != big_names[: small.n_features_in_]:
            return None
        columns = [big_names.index(n) for n in names]
    elif len(columns) != len(names) or list(columns[: small.n_features_in_]) != list(range(small.n_features_in_)):
        raise ValueError(f"columns must place the {len(names)} features, the states first, got {list(columns)}")
    if fewer and (heads is None or splits is None):  # their extra snapshots come from the heads, by the splits
        return None
    n_in = small.n_features_in_

    def take(stats):
        """The smaller lifting's columns (of each controller's part: its own controller states lead, its own map)."""
        if grouped:
            return _grouped_columns(stats, columns, len(big_names), setup)
        return _taken_columns(stats, n_c, columns, len(big_names), n_in)

    taken, whole = [take(s) for s in per_fold], take(everything)
    if not fewer:
        return setup, taken, whole
    assert heads is not None and splits is not None  # checked above
    # The snapshots from sample small.n_delays_ to big.n_delays_ - 1 of each episode, which the larger lifting lacks.
    extra = [template.episode_snapshots(setup, head) for head in heads]

    def add(stats, members):
        """``stats`` with the extra snapshots of the episodes ``members`` (into their controllers' parts)."""
        if grouped:
            return _with_extra_snapshots(stats, extra, members, setup)
        return Snapshots.total([stats] + [extra[int(j)] for j in members])

    return setup, [add(s, train) for s, (train, _) in zip(taken, splits)], add(whole, range(len(extra)))


def _taken_columns(stats: Snapshots, n_c: int, columns: Sequence[int], n_big: int, n_in: int) -> Snapshots:
    """The statistics of a smaller lifting from a larger one's (``n_big`` features): regressors ``[x^c; lifted;
    r; f]`` with the lifted features at ``columns``, targets ``[x^c; states]`` (``n_c`` controller states, ``n_in``
    states)."""
    n_v = stats.n_regressors - n_c - n_big  # references and feedforward follow the lifting
    regressors = list(range(n_c)) + [n_c + int(c) for c in columns] + [n_c + n_big + i for i in range(n_v)]
    return stats.columns(regressors, list(range(n_c + n_in)))


def _grouped_columns(stats: GroupedSnapshots, columns: Sequence[int], n_big: int, setup) -> GroupedSnapshots:
    """:func:`sub_statistics` of each controller's part: its regressors ``[x^c_g; lifted; r; f]`` and targets
    ``[x^c_g; states]`` taken at ``columns`` of the larger lifting's ``n_big`` features, each part's map
    (:func:`~qube_koopman.identify.estimators.structure.plant_input_map`) that of the smaller lifting."""
    groups = setup.controller_groups
    n_in = setup.lifting.n_features_in_
    parts, maps = [], []
    for part, ctrl in zip(stats.parts, stats.controllers):
        parts.append(_taken_columns(part, ctrl.n_states, columns, n_big, n_in))
        maps.append(next(m for c, m in zip(groups.controllers, groups.maps) if same_system(c, ctrl)))
    return GroupedSnapshots(tuple(parts), tuple(maps), stats.plant_rows, stats.controllers)


def _with_extra_snapshots(stats: GroupedSnapshots, extra: Sequence, members, setup) -> GroupedSnapshots:
    """``stats`` with the snapshots ``extra[j]`` of each episode ``j`` of ``members`` folded into its controller's
    part (a lifting with fewer delays has them from an earlier sample of each episode, :func:`sub_statistics`)."""
    groups = setup.controller_groups
    by_controller: dict[int, list] = {}
    for j in members:
        by_controller.setdefault(int(groups.labels[int(j)]), []).append(extra[int(j)])
    parts = []
    for part, ctrl in zip(stats.parts, stats.controllers):
        k = next(i for i, c in enumerate(groups.controllers) if same_system(c, ctrl))
        parts.append(Snapshots.total([part] + by_controller.pop(k, [])))
    if by_controller:
        raise ValueError("episodes of a controller the statistics have no part for")
    return GroupedSnapshots(tuple(parts), stats.maps, stats.plant_rows, stats.controllers)


def seconds_timer(seconds: dict):
    """``with timed(key):`` adds the block's wall time to ``seconds[key]``."""

    @contextmanager
    def timed(key: str):
        started = time.perf_counter()
        try:
            yield
        finally:
            seconds[key] = seconds.get(key, 0.0) + time.perf_counter() - started

    return timed


def _learns_from_data(estimator) -> bool:
    from qube_koopman.identify.estimators.base import resolve_lifting

    return any(getattr(step, "learns_from_data", True) for step in resolve_lifting(estimator.lifting).steps)


def _fold_controller(controllers, validation, default, fold: int):
    """The one controller a fold's validation episodes ran (``default`` when none are given)."""
    if controllers is None:
        return default
    distinct, _ = distinct_controllers([controllers[j] for j in validation])
    if len(distinct) != 1:
        raise ValueError(
            f"fold {fold + 1}'s validation episodes were recorded under {len(distinct)} controllers; "
            "a fold predicts one controller's loop: hold out one controller per fold "
            "(identify.model_selection.split.leave_one_controller_out)"
        )
    return distinct[0]


def _for_controller(estimator, controller):
    """``estimator``, or a copy whose closed loop is ``controller``'s (a closed-loop estimator's)."""
    if not isinstance(estimator, ClosedLoopKoopman) or same_system(estimator.controller, controller):
        return estimator
    return copy.copy(estimator).set_params(controller=controller)


def _statistics(
    estimator, trajectories, selections, partial: bool = False, controllers=None, elsewhere=None, indices=None
):
    """Setup, and the statistics of each selection of the episodes (index sequences; None: all).

    ``partial``: of the rows a re-lifted prediction uses only. ``controllers``: each episode's
    (a closed-loop estimator's episodes under several controllers). One pass over the episodes
    (:meth:`~qube_koopman.identify.estimators.base.SnapshotEstimator.selection_statistics`), their
    statistics computed ``elsewhere`` when given (``indices``: the episodes' among the sweep's).
    """
    template = copy.copy(estimator)
    if isinstance(template, ClosedLoopKoopman):
        setup = template.setup_fit(trajectories, controllers)
    else:
        setup = template.setup_fit(trajectories)
    if partial and template.relift_rows(setup) is not None:
        setup = dataclasses.replace(setup, target_rows=template.relift_rows(setup))
    return setup, template.selection_statistics(setup, selections, elsewhere, indices)
