"""scikit-learn style estimator plumbing without depending on scikit-learn, and the public statistics
protocol of the least-squares estimators (:class:`SnapshotEstimator`)."""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Self

import numpy as np

from qube_koopman.identify.lifting import Lifting
from qube_koopman.identify.params import Params
from qube_koopman.identify.data.trajectory import Trajectory

__all__ = ["Estimator", "FitSetup", "SnapshotEstimator", "episode_statistics", "pad_rows", "resolve_lifting"]

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

    Besides ``fit``, its public statistics protocol fits from statistics computed one episode at a
    time, as scikit-learn's ``partial_fit`` fits from batches. The sweep, the search, the
    bootstrap of the prediction intervals and the dask runner use it to compute each episode's
    statistics once and reuse them across folds, alphas and refits; a caller keeping a running
    total adds an episode and refits without reading the others again:

    1. :meth:`setup_fit` validates the episodes and fits the lifting: a :class:`FitSetup`;
    2. :meth:`episode_snapshots` computes one episode's statistics (any episode of the same
       signals, also one the setup does not hold: the lifting stays the setup's);
    3. :meth:`statistics_fold` is a running total: ``add(episode_index, statistics)``, ``total()``;
    4. :meth:`finish_fit` solves from a total for the estimator's ``alpha`` and sets the fitted
       attributes; it may be called again after more episodes are added, or after ``set_params``
       changed ``alpha``.

    ``fit(trajectories)`` is ``finish_fit(setup, total)`` over every episode of
    ``setup_fit(trajectories)`` (:meth:`fit_setup`), bit for bit. :meth:`selection_statistics`
    folds several selections of the episodes (cross-validation folds) in one pass;
    :meth:`total_statistics` totals a list of per-episode statistics; :meth:`relift_rows` says
    which rows a sweep that scores re-lifted predictions needs.

    Examples
    --------
    >>> import numpy as np
    >>> from qube_koopman.identify import Edmd, Trajectory
    >>> rng = np.random.default_rng(0)
    >>> def episode():
    ...     u = rng.normal(size=(200, 1))
    ...     x = np.zeros((200, 1))
    ...     for k in range(199):
    ...         x[k + 1] = 0.9 * x[k] + 0.5 * u[k]
    ...     return Trajectory(x=x, u=u, dt=0.01)
    >>> first, second, third = episode(), episode(), episode()
    >>> est = Edmd(alpha=1e-6)
    >>> setup = est.setup_fit([first, second])
    >>> fold = est.statistics_fold(setup)
    >>> for j, t in enumerate(setup.trajectories):
    ...     fold.add(j, est.episode_snapshots(setup, t))
    >>> est = est.finish_fit(setup, fold.total())
    >>> fold.add(2, est.episode_snapshots(setup, third))  # an episode comes in: add it, refit
    >>> np.round(est.finish_fit(setup, fold.total()).koopman_matrix_, 3)
    array([[0.9, 0.5]])
    """

    #: The fitted model, set by ``finish_fit`` (a closed-loop estimator's: its closed loop).
    model_: KoopmanModel

    def fit(self, trajectories) -> Self:
        """Fit on a list of :class:`~identify.Trajectory` (the class says which signals it needs).

        Parameters
        ----------
        trajectories : sequence of Trajectory
            The episodes.

        Returns
        -------
        self
        """
        return self.fit_setup(self.setup_fit(trajectories))

    def setup_fit(self, trajectories) -> "FitSetup":
        """Validate the episodes and the hyperparameters, fit the lifting: the first step of a fit.

        Parameters
        ----------
        trajectories : sequence of Trajectory
            The episodes (a closed-loop estimator also takes ``controllers``, as its ``fit`` does).

        Returns
        -------
        FitSetup
            What every other step of the protocol takes.
        """
        raise NotImplementedError

    def episode_snapshots(self, setup: "FitSetup", trajectory: Trajectory):
        """The snapshot statistics of one episode, lifted with the setup's lifting.

        Parameters
        ----------
        setup : FitSetup
            From :meth:`setup_fit`.
        trajectory : Trajectory
            An episode with the signals the setup's episodes have (not necessarily one of them).

        Returns
        -------
        Snapshots
            Its statistics (a triangular factor), for a fold's ``add``.
        """
        raise NotImplementedError

    def statistics_fold(self, setup: "FitSetup"):
        """A running total of episodes' statistics, folded as they come.

        Parameters
        ----------
        setup : FitSetup
            From :meth:`setup_fit`.

        Returns
        -------
        fold
            ``add(episode_index, statistics)`` folds one episode in (the index is its place
            among the setup's episodes: with several controllers it says which one ran it);
            ``total()`` gives the statistics of every episode added so far, for
            :meth:`finish_fit`. Memory is that of a few factors whatever the episodes.
        """
        return _EpisodeFold()

    def total_statistics(self, setup: "FitSetup", per_episode, indices=None):
        """The statistics of the selected episodes (all by default), ready for :meth:`finish_fit`.

        Parameters
        ----------
        setup : FitSetup
            From :meth:`setup_fit`.
        per_episode : sequence or iterable
            Per-episode statistics (:meth:`episode_snapshots`) in the setup's order: a list when
            ``indices`` selects from it, else any iterable (a generator folds as it goes).
        indices : sequence of int, optional
            The episodes to total; None: all.

        Returns
        -------
        Snapshots
            Their total.
        """
        from qube_koopman.identify.estimators.regression import Snapshots

        return Snapshots.total(per_episode if indices is None else [per_episode[int(j)] for j in indices])

    def finish_fit(self, setup: "FitSetup", snapshots) -> Self:
        """Solve for ``alpha`` from totalled statistics and set the fitted attributes.

        Parameters
        ----------
        setup : FitSetup
            From :meth:`setup_fit`.
        snapshots : Snapshots
            A fold's ``total()`` (or :meth:`total_statistics`).

        Returns
        -------
        self
        """
        raise NotImplementedError

    def fit_setup(self, setup: "FitSetup", elsewhere=None) -> Self:
        """Fit on every episode of a setup: their statistics folded one at a time, then :meth:`finish_fit`.

        Parameters
        ----------
        setup : FitSetup
            From :meth:`setup_fit`.
        elsewhere : callable, optional
            Computes the episodes' statistics instead of this process (see
            :meth:`selection_statistics`).

        Returns
        -------
        self
        """
        # Folded as the episodes come, one at a time: never every episode's factor at once.
        return self.finish_fit(setup, self.selection_statistics(setup, [None], elsewhere)[0])

    def selection_statistics(self, setup: "FitSetup", selections, elsewhere=None, indices=None) -> list:
        """The statistics of several selections of the setup's episodes, from one pass over them.

        Each episode is read, lifted and factored once and folded into every selection holding it:
        memory grows with the selections, not with the episodes. An episode no selection holds is
        not read. Each total equals :meth:`total_statistics` of its selection's per-episode
        statistics (bit for bit, the indices in increasing order).

        Parameters
        ----------
        setup : FitSetup
            From :meth:`setup_fit`.
        selections : sequence of (sequence of int or None)
            Index sequences (None: every episode), e.g. each cross-validation fold's training
            episodes.
        elsewhere : callable, optional
            ``elsewhere(estimator, setup, ids)`` computes the episodes' statistics instead of this
            process, in order (on a dask cluster:
            :class:`~qube_koopman.identify.model_selection.distributed.ClusterStatistics`).
        indices : sequence of int, optional
            The setup's episodes' places in a larger list, which ``elsewhere`` receives as ``ids``;
            None: their own places.

        Returns
        -------
        list
            One total per selection, for :meth:`finish_fit`.
        """
        members = [None if s is None else {int(j) for j in s} for s in selections]
        folds = [self.statistics_fold(setup) for _ in selections]
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

    def relift_rows(self, setup: "FitSetup") -> int | None:
        """The leading lifted states a re-lifted prediction produces (it recomputes the rest), if known.

        Parameters
        ----------
        setup : FitSetup
            From :meth:`setup_fit`.

        Returns
        -------
        int or None
            A fit that only scores re-lifted predictions needs only these rows of the Koopman
            matrix (``dataclasses.replace(setup, target_rows=...)``); None: every row.
        """
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

    Parameters
    ----------
    estimator : SnapshotEstimator
        Computes each episode's statistics (:meth:`SnapshotEstimator.episode_snapshots`).
    setup : FitSetup
        Its setup, which holds the episodes.
    indices : sequence of int
        The episodes, by their places in ``setup.trajectories``.

    Yields
    ------
    Snapshots
        Each episode's statistics, in the order of ``indices``.
    """
    from concurrent.futures import ThreadPoolExecutor

    from qube_koopman.core.blas import episode_thread_count, limited_blas_threads

    trajectories = setup.trajectories

    def one(j: int):
        return estimator.episode_snapshots(setup, trajectories[j])

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

    Made by :meth:`SnapshotEstimator.setup_fit`, taken by every other step of the statistics
    protocol; sweeps reuse one setup and per-episode statistics across folds and alphas.

    Parameters
    ----------
    trajectories : sequence of Trajectory
        The validated episodes: a list, or a lazy sequence read one episode at a time.
    lifting : Lifting
        The fitted lifting of the plant states.
    dt : float or None
        The sample period (s).
    output_matrix : ndarray, optional
        ``C^p`` (closed-loop estimators).
    plant_input_map : ndarray, optional
        ``S`` (closed-loop estimators).
    n_feedforward : int
        Feedforward channels.
    input_lifting : Lifting, optional
        The fitted pointwise lifting of the inputs (EDMD).
    target_rows : int, optional
        Fit only this many leading rows of the Koopman matrix (see
        :meth:`SnapshotEstimator.relift_rows`); the other rows are NaN.
    controller_groups : ControllerGroups, optional
        Closed-loop fits of episodes under several controllers: who ran which episode; None
        when all ran the estimator's.
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
