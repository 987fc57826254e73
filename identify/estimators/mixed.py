"""Training episodes recorded under several controllers: grouping, statistics, folds.

The plant is common to every episode; each episode's closed loop differs
only by its known controller. A closed-loop fit keeps the snapshot
statistics per controller (their regressors differ: the controller state's
width and the plant input map ``S_g``) and fits one plant to all of them
(:func:`~qube_koopman.identify.estimators.regression.grouped_plant_solve`).
Cross-validation then holds out one controller at a time
(:func:`~qube_koopman.identify.model_selection.split.leave_one_controller_out`): the question is whether the plant
predicts a loop it was not fitted on.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from qube_koopman.core.lti import same_system
from qube_koopman.identify.estimators.regression import GroupedSnapshots, SnapshotFold, Snapshots
from qube_koopman.identify.estimators.structure import plant_input_map
from qube_koopman.core.lti import DiscreteStateSpace

__all__ = [
    "ControllerGroups",
    "GroupedFold",
    "distinct_controllers",
    "majority_controller",
    "training_controllers_report",
]


def distinct_controllers(controllers: Sequence[DiscreteStateSpace]) -> tuple[list[DiscreteStateSpace], np.ndarray]:
    """The distinct controllers, in order of first appearance, and each episode's index among them.

    Two controllers are the same when :func:`~qube_koopman.core.lti.same_system` says so.
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
        return GroupedSnapshots(
            tuple(self._folds[k].total() for k in order),
            tuple(g.maps[k] for k in order),
            tuple(slice(g.controllers[k].n_states, None) for k in order),
            tuple(g.controllers[k] for k in order),
        )


def training_controllers_report(logs: Sequence, model_controller: DiscreteStateSpace) -> dict:
    """The training logs' controllers for a report: how many, episodes each, which one the model's loop is.

    ``logs`` are :class:`~qube_koopman.identify.data.logs.LoggedTrajectory`; controllers are numbered
    from 1 in order of first appearance.
    """
    distinct, labels = distinct_controllers([log.controller for log in logs])
    entries = []
    for g, ctrl in enumerate(distinct):
        mine = [log for log, label in zip(logs, labels) if label == g]
        entries.append(
            {
                "controller": g + 1,
                "n_episodes": len(mine),
                "gains": mine[0].gains,
                "model_closed_loop": same_system(ctrl, model_controller),
                "logs": [log.path.name for log in mine],
                "matrices": ctrl.as_dict(),
            }
        )
    note = (
        "one controller: the model's closed loop is its loop"
        if len(distinct) == 1
        else "one plant fitted to the episodes of all; the saved model's closed loop is that of the "
        "controller with the most training episodes (the first to appear among ties)"
    )
    return {"n_controllers": len(distinct), "controllers": entries, "note": note}
