"""The bootstrap ensemble: a fit, its refits on resampled episodes and the calibration folds' ensembles, from
one pass over the episodes' statistics (the estimators' statistics protocol,
:class:`~qube_koopman.identify.estimators.base.SnapshotEstimator`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from qube_koopman.core.lti import DiscreteStateSpace
from qube_koopman.identify.data.trajectory import as_episodes
from qube_koopman.identify.estimators.base import episode_statistics

if TYPE_CHECKING:
    from qube_koopman.identify.estimators.base import SnapshotEstimator
    from qube_koopman.identify.models.model import KoopmanModel

__all__ = [
    "EnsembleFit",
    "FoldEnsemble",
    "INTERVAL_METHODS",
    "IntervalOptions",
    "bootstrap_counts",
    "ensemble_statistics",
    "episode_folds",
    "fit_ensemble",
]


#: How a band may be made (:class:`IntervalOptions`' ``method``).
INTERVAL_METHODS = ("bootstrap", "disturbance")


@dataclass(frozen=True)
class IntervalOptions:
    """How prediction intervals are made (see the module docstring).

    Parameters
    ----------
    level : float
        Coverage asked for, in (0, 1) (``qube-identify --interval``).
    n_members : int
        Bootstrap refits (at least 2).
    n_calibration_members : int
        Bootstrap refits of each calibration fold (at least 2): the calibration needs the spread's
        size on the held-out episodes, not the test band itself, and each member costs a
        prediction of every held-out episode. On the training loop the spread is a small part of
        the held-out error, so few do: with 4 instead of 10 the paper split's bands are the same to
        three decimals with the default lifting and within 0.005 in coverage with the search's, for
        a third less time in the calibration.
    n_probe_members : int
        Members of the fit predicting the twin's probe episodes, which calibrate the bands of loops
        the training never ran (at least 2). Under another loop the spread is a larger part of the
        error: with 4 instead of 10 the soft controller's theta band covered 0.908 instead of 0.919
        (worst episode 0.784 instead of 0.806) with the search's lifting.
    n_folds : int
        Groups of training episodes held out in turn for the calibration (at most one per episode).
    n_calibration_episodes : int
        Training episodes held out at most (drawn at random), so that the calibration's cost does not
        grow with the training set: its few parameters per channel are fitted on thousands of samples.
    seed : int
        Seed of the resampling and of the folds.
    stride : int
        Every ``stride``-th held-out sample enters the calibration (neighbouring samples at 500 Hz
        say nearly the same; this bounds its memory and time).
    other_loops : {"twin", "none"}
        How a test episode under a loop the training never ran is calibrated: on the twin's probe
        episodes under other controllers (``"twin"``), or as the training loop's held-out
        episodes (``"none"``, flagged in the report as a loop the calibration did not see).
    method : {"bootstrap", "disturbance"}
        The band's source of the prediction's uncertainty: the bootstrap refits' spread (and the
        twin's probes for other loops), or the disturbance model's Kalman filter variance
        (:mod:`~qube_koopman.identify.uncertainty.filter_band`: no bootstrap refits, one refit per
        calibration fold).
    """

    level: float = 0.95
    n_members: int = 20
    n_calibration_members: int = 4
    n_probe_members: int = 10
    n_folds: int = 5
    n_calibration_episodes: int = 16
    seed: int = 0
    stride: int = 5
    other_loops: str = "twin"
    method: str = "bootstrap"

    def __post_init__(self) -> None:
        if self.method not in INTERVAL_METHODS:
            raise ValueError(f"the interval method must be one of {', '.join(INTERVAL_METHODS)}, got {self.method!r}")
        if self.other_loops not in ("twin", "none"):
            raise ValueError(f"other_loops must be 'twin' or 'none', got {self.other_loops!r}")
        if not 0 < self.level < 1:
            raise ValueError(f"the interval's level must be between 0 and 1, got {self.level}")
        counts = (
            self.n_members,
            self.n_calibration_members,
            self.n_probe_members,
            self.n_folds,
            self.n_calibration_episodes,
        )
        if min(int(c) for c in counts) < 2 or int(self.stride) < 1:
            raise ValueError(
                f"intervals need at least 2 members, calibration members, probe members, folds and calibration "
                f"episodes and a stride of 1 or more, got {', '.join(str(c) for c in counts)} and {self.stride}"
            )


def bootstrap_counts(n_episodes: int, n_members: int, rng: np.random.Generator) -> np.ndarray:
    """How many times each episode is drawn in each resample of ``n_episodes`` with replacement.

    Returns
    -------
    ndarray of int of shape (n_members, n_episodes)
        Each row sums to ``n_episodes``.
    """
    return rng.multinomial(n_episodes, np.full(n_episodes, 1.0 / n_episodes), size=n_members)


def episode_folds(
    n_episodes: int, n_folds: int, rng: np.random.Generator, max_held_out: int | None = None
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Episodes drawn at random (``max_held_out`` at most, all by default) and split into ``n_folds`` groups
    (at most one per episode), each held out once; each fold trains on every other episode.

    Returns
    -------
    list of (train_indices, validation_indices)
    """
    held_out = rng.permutation(n_episodes)[: n_episodes if max_held_out is None else int(max_held_out)]
    groups = np.array_split(held_out, min(int(n_folds), held_out.size))
    return [(np.setdiff1d(np.arange(n_episodes), g), np.sort(g)) for g in groups]


def ensemble_statistics(estimator, setup, selections: np.ndarray, elsewhere: Callable | None = None):
    """The statistics of all the setup's episodes and of weighted selections of them, in one pass.

    Each episode is lifted and factored once (here, or ``elsewhere``: see
    :meth:`~qube_koopman.identify.estimators.base.SnapshotEstimator.selection_statistics`), folded into the
    total of all episodes as a plain fit folds it (the same result, bit for bit), and into each
    selection that draws it, its factor scaled by the square root of its count. With a known
    set of rows that re-lifted predictions use (``estimator.relift_rows``), the selections keep
    only those targets (the factor's leading block: no new decomposition).

    Parameters
    ----------
    estimator : SnapshotEstimator
        The estimator, its setup made (``setup_fit``).
    setup : FitSetup
        The setup of all the episodes.
    selections : ndarray of int of shape (n_selections, n_episodes)
        How many times each selection counts each episode (0: left out).
    elsewhere : callable, optional
        Computes the episodes' statistics elsewhere (a dask cluster).

    Returns
    -------
    total : Snapshots or GroupedSnapshots
        Of all the episodes, once each.
    selected : list
        Of each selection.
    """
    selections = np.asarray(selections, dtype=int)
    trajectories = setup.trajectories
    n = len(trajectories)
    if selections.ndim != 2 or selections.shape[1] != n:
        raise ValueError(f"selections must count each of the {n} episodes, got shape {selections.shape}")
    partial = estimator.relift_rows(setup) is not None
    n_lifted, m = setup.lifting.n_features_out_, setup.lifting.n_features_in_
    total = estimator.statistics_fold(setup)
    folds = [estimator.statistics_fold(setup) for _ in selections]
    parts = (
        episode_statistics(estimator, setup, range(n))
        if elsewhere is None
        else elsewhere(estimator, setup, list(range(n)))
    )
    for j, part in enumerate(parts):
        total.add(j, part)
        # The targets are [controller states; lifted plant states]: keep the controller's and the plant's own.
        small = part.leading(part.R.shape[1] - part.n_regressors - n_lifted + m) if partial else part
        for fold, count in zip(folds, selections[:, j]):
            if count:
                fold.add(j, small.repeated(int(count)))
    return total.total(), [fold.total() for fold in folds]


@dataclass
class FoldEnsemble:
    """One calibration fold: the episodes it holds out, its point fit and members on the others.

    Parameters
    ----------
    validation : ndarray of int
        The held-out episodes.
    point : (closed, plant)
        Fitted on the fold's other episodes once each.
    members : list of (closed, plant)
        Fitted on resamples of them.
    """

    validation: np.ndarray
    point: tuple[KoopmanModel | None, KoopmanModel]
    members: list[tuple[KoopmanModel | None, KoopmanModel]]


@dataclass
class EnsembleFit:
    """A fit on all the training episodes, its bootstrap members and the calibration folds' ensembles.

    Parameters
    ----------
    estimator : SnapshotEstimator
        Fitted on all the episodes, as a plain fit is.
    members : list of (closed, plant)
        The bootstrap refits (only the rows re-lifted predictions use; closed None for a plant
        fit without a controller).
    folds : list of FoldEnsemble
    counts : ndarray of int of shape (n_members, n_episodes)
        Each member's draw of the episodes.
    """

    estimator: SnapshotEstimator
    members: list[tuple[KoopmanModel | None, KoopmanModel]]
    folds: list[FoldEnsemble]
    counts: np.ndarray


def fit_ensemble(
    estimator,
    trajectories,
    options: IntervalOptions = IntervalOptions(),
    controllers: Sequence[DiscreteStateSpace] | None = None,
    controller: DiscreteStateSpace | None = None,
    measured: Sequence[int] | None = None,
    elsewhere: Callable | None = None,
) -> EnsembleFit:
    """Fit ``estimator`` on all the episodes, its bootstrap members and the folds' ensembles in one pass.

    Parameters
    ----------
    estimator : SnapshotEstimator
        Unfitted (:class:`~qube_koopman.identify.ClEdmd`, :class:`~qube_koopman.identify.Edmd`, ...);
        it is fitted in place, as :meth:`fit` would.
    trajectories : sequence of Trajectory
        The training episodes (a lazy sequence is read one episode at a time).
    options : IntervalOptions
        Members, folds, seed.
    controllers : sequence of DiscreteStateSpace, optional
        Each episode's controller (a closed-loop estimator's episodes under several).
    controller : DiscreteStateSpace, optional
        Wraps a plant estimator's (EDMD's) members for their closed loops.
    measured : sequence of int, optional
        The fed-back states, for that wrapping.
    elsewhere : callable, optional
        Computes the per-episode statistics elsewhere (a dask cluster).

    Returns
    -------
    EnsembleFit
    """
    from qube_koopman.identify.model_selection.sweep import fitted_models

    trajectories = as_episodes(trajectories)
    n = len(trajectories)
    if n < 2:
        raise ValueError(
            f"prediction intervals are calibrated on held-out training episodes: they need at least 2, got {n}"
        )
    rng = np.random.default_rng(options.seed)
    counts = bootstrap_counts(n, options.n_members, rng)
    splits = episode_folds(n, options.n_folds, rng, options.n_calibration_episodes)
    B, C = options.n_members, options.n_calibration_members
    selections = [counts]
    for train, _ in splits:
        fold = np.zeros((C + 1, n), dtype=int)
        fold[0, train] = 1
        fold[1:, train] = bootstrap_counts(len(train), C, rng)
        selections.append(fold)
    setup = estimator.setup_fit(trajectories) if controllers is None else estimator.setup_fit(trajectories, controllers)
    total, selected = ensemble_statistics(estimator, setup, np.vstack(selections), elsewhere)
    rows = estimator.relift_rows(setup)
    partial = setup if rows is None else dataclasses.replace(setup, target_rows=rows)

    def refit(snapshots) -> tuple:
        closed, plants = fitted_models(estimator, partial, snapshots, [estimator.alpha], controller, measured)
        return closed[0], plants[0]

    models = [refit(s) for s in selected]
    estimator.finish_fit(setup, total)
    folds = [
        FoldEnsemble(validation, models[B + i * (C + 1)], models[B + i * (C + 1) + 1 : B + (i + 1) * (C + 1)])
        for i, (_, validation) in enumerate(splits)
    ]
    return EnsembleFit(estimator, models[:B], folds, counts)
