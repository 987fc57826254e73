"""scikit-learn style estimator plumbing without depending on scikit-learn."""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Self

import numpy as np

from qube_koopman.identify.lifting import Lifting
from qube_koopman.identify.params import Params
from qube_koopman.identify.data.trajectory import Trajectory

if TYPE_CHECKING:
    from qube_koopman.identify.estimators.mixed import ControllerGroups
    from qube_koopman.identify.models.model import KoopmanModel


class Estimator(Params):
    """Hyperparameters are constructor arguments, stored unchanged and checked by ``fit``; ``fit`` returns self.

    ``get_params``, ``set_params`` and :func:`~qube_koopman.identify.params.clone` as in scikit-learn
    (:class:`~qube_koopman.identify.params.Params`).
    """

    def _check_fitted(self) -> None:
        if not hasattr(self, "model_"):
            raise ValueError(f"this {type(self).__name__} is not fitted yet; call fit first")


class SnapshotEstimator(Estimator):
    """A least-squares Koopman estimator fitted from per-episode snapshot statistics.

    ``fit`` = ``_setup`` (validate, fit the lifting), ``_episode_snapshots``
    for each episode, ``_finish`` (solve for ``alpha``). Sweeps call the three
    steps themselves to reuse statistics across folds and alphas.
    """

    #: The fitted model, set by ``_finish`` (a closed-loop estimator's: its closed loop).
    model_: KoopmanModel

    def fit(self, trajectories) -> Self:
        """Fit on a list of :class:`~identify.Trajectory` (the class says which signals it needs).

        Returns
        -------
        self
        """
        return self._fit(self._setup(trajectories))

    def _fit(self, setup: "FitSetup", elsewhere=None) -> Self:
        """Solve from the statistics of all the setup's episodes (``elsewhere``: see :meth:`_selection_statistics`)."""
        # Folded as the episodes come, one at a time: never every episode's factor at once.
        return self._finish(setup, self._selection_statistics(setup, [None], elsewhere)[0])

    def _selection_statistics(self, setup: "FitSetup", selections, elsewhere=None, indices=None) -> list:
        """The statistics of several selections of the setup's episodes, from one pass over them.

        ``selections`` are index sequences (None: every episode), e.g. each cross-validation
        fold's training episodes. Each episode is read, lifted and factored once and folded into
        every selection holding it: memory grows with the selections, not with the episodes.
        An episode no selection holds is not read. Each total equals :meth:`_statistics` of its
        selection's per-episode statistics (bit for bit, the indices in increasing order).
        ``elsewhere(estimator, setup, ids)`` computes the episodes' statistics instead of this
        process, in order (on a dask cluster:
        :class:`~qube_koopman.identify.model_selection.distributed.ClusterStatistics`); ``ids`` are the
        episodes' places in ``indices`` (the setup's episodes among a larger list), or their own.
        """
        members = [None if s is None else {int(j) for j in s} for s in selections]
        folds = [self._statistics_fold(setup) for _ in selections]
        trajectories = setup.trajectories
        needed = [j for j in range(len(trajectories)) if any(m is None or j in m for m in members)]
        if elsewhere is None:
            parts = episode_statistics(self, setup, needed)
        else:
            parts = elsewhere(self, setup, [j if indices is None else int(indices[j]) for j in needed])
        for j, part in zip(needed, parts):
            for k, m in enumerate(members):
                if m is None or j in m:
                    folds[k].add(j, part)
        return [fold.total() for fold in folds]

    def _statistics_fold(self, setup: "FitSetup"):
        """A running total of episodes' statistics: ``add(episode_index, part)``, ``total()``."""
        return _EpisodeFold()

    def _setup(self, trajectories) -> "FitSetup":
        raise NotImplementedError

    def _statistics(self, setup: "FitSetup", per_episode, indices=None):
        """The statistics of the selected episodes (all by default), ready for ``_finish``.

        ``per_episode`` is a list when ``indices`` selects from it, else any iterable (a generator
        folds as it goes).
        """
        from qube_koopman.identify.estimators.regression import Snapshots

        return Snapshots.total(per_episode if indices is None else [per_episode[int(j)] for j in indices])

    def _episode_snapshots(self, setup: "FitSetup", trajectory: Trajectory):
        raise NotImplementedError

    def _finish(self, setup: "FitSetup", snapshots) -> Self:
        raise NotImplementedError

    def _relift_rows(self, setup: "FitSetup") -> int | None:
        """Leading lifted states a re-lifted prediction produces (it recomputes the rest), if known."""
        return None


def episode_statistics(estimator: SnapshotEstimator, setup: "FitSetup", indices: Sequence[int]) -> Iterator:
    """The statistics of the setup's episodes at ``indices``, in that order, computed side by side.

    As many episodes at a time as :func:`~qube_koopman.core.blas.episode_thread_count` gives
    (:func:`~qube_koopman.core.blas.episode_threads` inside one, else the threads the BLAS may use
    here), each read, lifted and factored with one BLAS thread: two tall QR factorizations at once
    on two cores take 0.6 times as long as one after the other on two BLAS threads each (measured
    on the search winner's lifting, 28 episodes: 3.5 against 5.5 s), and each gives the same
    factor bit for bit wherever it runs.
    Inside :func:`~qube_koopman.core.blas.limited_blas_threads` alone (a search's workers) they come
    one at a time. At most twice the threads' episodes are held ahead of the caller.
    """
    from concurrent.futures import ThreadPoolExecutor

    from qube_koopman.core.blas import episode_thread_count, limited_blas_threads

    trajectories = setup.trajectories

    def one(j: int):
        return estimator._episode_snapshots(setup, trajectories[j])

    n = min(episode_thread_count(), len(indices))
    if n <= 1:
        yield from map(one, indices)
        return
    with limited_blas_threads(1), ThreadPoolExecutor(n, thread_name_prefix="episode-statistics") as pool:
        pending: deque = deque()
        for j in indices:
            pending.append(pool.submit(one, j))
            if len(pending) >= 2 * n:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()


class _EpisodeFold:
    """:class:`~qube_koopman.identify.estimators.regression.SnapshotFold` taking the episode's index too."""

    def __init__(self) -> None:
        from qube_koopman.identify.estimators.regression import SnapshotFold

        self._fold = SnapshotFold()

    def add(self, episode: int, part) -> None:
        self._fold.add(part)

    def total(self):
        return self._fold.total()


def resolve_lifting(lifting) -> Lifting:
    """A Lifting from None (identity), a Lifting, or a sequence of lifting functions."""
    if lifting is None:
        return Lifting()
    # Always a new object: fitting must never mutate the estimator's parameters.
    steps = lifting.steps if isinstance(lifting, Lifting) else lifting
    return Lifting(list(steps))


@dataclass(frozen=True, eq=False)
class FitSetup:
    """What a fit learns before solving: validated data, fitted lifting, structure.

    Sweeps reuse one setup and per-episode snapshots across folds and alphas.
    """

    #: The validated episodes: a list, or a lazy sequence read one episode at a time.
    trajectories: Sequence[Trajectory]
    lifting: Lifting
    dt: float | None
    output_matrix: np.ndarray | None = None
    plant_input_map: np.ndarray | None = None
    n_feedforward: int = 0
    input_lifting: Lifting | None = None
    #: Fit only this many leading rows of the Koopman matrix, those a re-lifted prediction
    #: uses (a sweep that only scores re-lifted predictions); the other rows are NaN.
    target_rows: int | None = None
    #: Closed-loop fits of episodes under several controllers: who ran which episode
    #: (:class:`~qube_koopman.identify.estimators.mixed.ControllerGroups`); None when all ran the estimator's.
    controller_groups: ControllerGroups | None = None


def pad_rows(U: np.ndarray, n_rows: int) -> np.ndarray:
    """``U`` with NaN rows appended up to ``n_rows``: the rows a partial fit left out."""
    if U.shape[0] >= n_rows:
        return U
    return np.vstack([U, np.full((n_rows - U.shape[0], U.shape[1]), np.nan)])
