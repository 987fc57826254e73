"""Training episodes recorded under several controllers: grouping, statistics, folds.

The plant is common to every episode; each episode's closed loop differs
only by its known controller. A closed-loop fit keeps the snapshot
statistics per controller (their regressors differ: the controller state's
width and the plant input map ``S_g``) and fits one plant to all of them
(:func:`~qube_koopman.identify.estimators.regression.grouped_plant_solve`).
Cross-validation then holds out one controller at a time
(:func:`leave_one_controller_out`): the question is whether the plant
predicts a loop it was not fitted on.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from qube_koopman.identify.data.logs import same_system
from qube_koopman.identify.estimators.regression import GroupedSnapshots, SnapshotFold, Snapshots
from qube_koopman.identify.estimators.structure import plant_input_map
from qube_koopman.core.lti import DiscreteStateSpace

__all__ = ["ControllerGroups", "distinct_controllers", "leave_one_controller_out", "within_controller_splits",
           "majority_controller"]


def distinct_controllers(controllers: Sequence[DiscreteStateSpace]) -> tuple[list[DiscreteStateSpace], np.ndarray]:
    """The distinct controllers, in order of first appearance, and each episode's index among them.

    Two controllers are the same when :func:`~qube_koopman.identify.data.logs.same_system` says so.
    """
    distinct: list[DiscreteStateSpace] = []
    labels = []
    for i, ctrl in enumerate(controllers):
        if not isinstance(ctrl, DiscreteStateSpace):
            raise ValueError(f"controller of episode {i} must be a DiscreteStateSpace, got {type(ctrl).__name__}")
        found = next((g for g, known in enumerate(distinct) if same_system(ctrl, known)), None)
        if found is None:
            distinct.append(ctrl)
            found = len(distinct) - 1
        labels.append(found)
    return distinct, np.array(labels, dtype=int)


def majority_controller(controllers: Sequence[DiscreteStateSpace]) -> DiscreteStateSpace:
    """The controller most episodes were recorded under (the first to appear among ties)."""
    distinct, labels = distinct_controllers(controllers)
    if not distinct:
        raise ValueError("no controllers")
    return distinct[int(np.argmax(np.bincount(labels)))]


def leave_one_controller_out(labels: Sequence[int]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Folds holding out all episodes of one controller each, in the order of the labels' values.

    Parameters
    ----------
    labels : sequence of int
        Each episode's controller (for example from :func:`distinct_controllers`).

    Returns
    -------
    list of (train_indices, validation_indices)
        One fold per distinct label.
    """
    labels = np.asarray(labels)
    groups = np.unique(labels)
    if groups.size < 2:
        raise ValueError(f"leave-one-controller-out needs episodes of at least two controllers, got {groups.size}")
    return [(np.flatnonzero(labels != g), np.flatnonzero(labels == g)) for g in groups]


def within_controller_splits(labels: Sequence[int], n_splits: int = 3, seed: int = 1234
                             ) -> list[tuple[np.ndarray, np.ndarray, int]]:
    """Folds that hold out some episodes of one controller and train on all the others.

    The complement of :func:`leave_one_controller_out`: each fold's validation
    episodes ran a controller the training episodes include, so its score is
    the same-controller one. For each controller with at least two episodes,
    :func:`~qube_koopman.identify.data.logs.group_shuffle_splits` (``n_splits``,
    ``seed``) over its episodes; the other controllers' episodes always train.

    Returns
    -------
    list of (train_indices, validation_indices, label)
    """
    from qube_koopman.identify.data.logs import group_shuffle_splits

    labels = np.asarray(labels)
    out = []
    for g in np.unique(labels):
        own, others = np.flatnonzero(labels == g), np.flatnonzero(labels != g)
        if own.size < 2:
            continue
        for train, validation in group_shuffle_splits(own.size, n_splits, seed=seed):
            out.append((np.sort(np.concatenate([others, own[train]])), own[validation], int(g)))
    return out


@dataclass(frozen=True, eq=False)
class ControllerGroups:
    """The controllers of a closed-loop fit's episodes, and each one's plant input map.

    Attributes
    ----------
    controllers : tuple of DiscreteStateSpace
        The distinct controllers, in order of first appearance.
    labels : ndarray of int
        Each episode's index into ``controllers``.
    maps : tuple of ndarray
        ``S_g`` of each controller (:func:`~qube_koopman.identify.estimators.structure.plant_input_map`).
    """

    controllers: tuple[DiscreteStateSpace, ...]
    labels: np.ndarray
    maps: tuple[np.ndarray, ...]

    @classmethod
    def of(cls, controllers: Sequence[DiscreteStateSpace], C_p: np.ndarray, n_feedforward: int) -> "ControllerGroups":
        """Group the episodes' controllers (one per episode)."""
        distinct, labels = distinct_controllers(controllers)
        return cls(tuple(distinct), labels, tuple(plant_input_map(c, C_p, n_feedforward) for c in distinct))

    def counts(self) -> list[int]:
        """Episodes per controller."""
        return np.bincount(self.labels, minlength=len(self.controllers)).tolist()

    def statistics(self, per_episode: Sequence[Snapshots], indices: Sequence[int] | None = None) -> GroupedSnapshots:
        """The selected episodes' statistics merged per controller (all episodes by default)."""
        fold = self.fold()
        for i in range(len(per_episode)) if indices is None else indices:
            fold.add(int(i), per_episode[int(i)])
        return fold.total()

    def fold(self) -> "GroupedFold":
        """A running total of episodes' statistics, per controller (see :class:`GroupedFold`)."""
        return GroupedFold(self)


class GroupedFold:
    """Episodes' statistics folded one at a time into their controller's running total.

    Memory is that of a few factors per controller, whatever the number of episodes.
    """

    def __init__(self, groups: ControllerGroups) -> None:
        self.groups = groups
        self._folds: dict[int, SnapshotFold] = {}

    def add(self, episode: int, part: Snapshots) -> None:
        """Fold in the statistics of episode ``episode`` (its index: which controller ran it)."""
        self._folds.setdefault(int(self.groups.labels[episode]), SnapshotFold()).add(part)

    def total(self) -> GroupedSnapshots:
        """The statistics of every episode added, one part per controller (in the groups' order)."""
        order = sorted(self._folds)
        if not order:
            raise ValueError("no snapshot statistics to combine")
        g = self.groups
        return GroupedSnapshots(tuple(self._folds[k].total() for k in order), tuple(g.maps[k] for k in order),
                                tuple(slice(g.controllers[k].n_states, None) for k in order),
                                tuple(g.controllers[k] for k in order))


FOLD_KINDS = {
    "leave-one-controller-out": "each fold holds out all the training episodes of one controller and predicts its "
                                "loop with the plant fitted to the other controllers' episodes",
    "episode-grouped": "random splits holding out 20% of the training episodes (one controller: the paper's "
                       "protocol)",
}


@dataclass(frozen=True)
class CrossValidationFolds:
    """The folds of a cross-validation on training episodes, and what they hold out.

    Attributes
    ----------
    kind : {"leave-one-controller-out", "episode-grouped"}
    splits : list of (train_indices, validation_indices)
    held_out : list of int, optional
        Leave-one-controller-out: the controller each fold holds out (its
        index among the distinct training controllers, in order of appearance).
    """

    kind: str
    splits: list[tuple[np.ndarray, np.ndarray]]
    held_out: list[int] | None = None

    def report(self, names: Sequence[str], scores: Sequence[float] | None = None) -> list[dict]:
        """Each fold for a report: what it held out (log names) and its score (None: not finite)."""
        out = []
        for i, (train, validation) in enumerate(self.splits):
            fold = {"fold": i + 1, "n_train": len(train), "validation_logs": [names[j] for j in validation]}
            if self.held_out is not None:
                fold["held_out_controller"] = self.held_out[i] + 1
            if scores is not None:
                fold["cv_r2"] = float(scores[i]) if np.isfinite(scores[i]) else None
            out.append(fold)
        return out


def cross_validation_folds(controllers: Sequence[DiscreteStateSpace], n_splits: int = 3,
                           seed: int = 1234) -> CrossValidationFolds:
    """Leave one controller out when the episodes ran two or more controllers; else
    :func:`~qube_koopman.identify.data.logs.group_shuffle_splits` (``n_splits``, ``seed``)."""
    from qube_koopman.identify.data.logs import group_shuffle_splits

    distinct, labels = distinct_controllers(controllers)
    if len(distinct) >= 2:
        splits = leave_one_controller_out(labels)
        return CrossValidationFolds("leave-one-controller-out", splits, [int(labels[v[0]]) for _, v in splits])
    return CrossValidationFolds("episode-grouped", group_shuffle_splits(len(labels), n_splits, 0.2, seed))


def training_controllers_report(logs: Sequence, model_controller: DiscreteStateSpace) -> dict:
    """The training logs' controllers for a report: how many, episodes each, which one the model's loop is.

    ``logs`` are :class:`~qube_koopman.identify.data.logs.LoggedTrajectory`; controllers are numbered
    from 1 in order of first appearance.
    """
    distinct, labels = distinct_controllers([log.controller for log in logs])
    entries = []
    for g, ctrl in enumerate(distinct):
        mine = [log for log, label in zip(logs, labels) if label == g]
        entries.append({"controller": g + 1, "n_episodes": len(mine), "gains": mine[0].gains,
                        "model_closed_loop": same_system(ctrl, model_controller),
                        "logs": [log.path.name for log in mine], "matrices": ctrl.as_dict()})
    note = ("one controller: the model's closed loop is its loop" if len(distinct) == 1 else
            "one plant fitted to the episodes of all; the saved model's closed loop is that of the "
            "controller with the most training episodes (the first to appear among ties)")
    return {"n_controllers": len(distinct), "controllers": entries, "note": note}
