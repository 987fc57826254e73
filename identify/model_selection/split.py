"""Cross-validation splits of training episodes: by episode, by controller, and the paper's split.

Every split holds out whole episodes (an episode's samples are never split between
training and validation). With one training controller the folds are random
episode-grouped splits, identical to scikit-learn's ``GroupShuffleSplit``; with two or
more, each fold holds out one controller (:func:`leave_one_controller_out`), the
question a plant model answers: does it predict a loop it was not fitted on?
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from qube_koopman.core.lti import DiscreteStateSpace
from qube_koopman.identify.estimators.mixed import distinct_controllers

__all__ = [
    "paper_split",
    "PaperSplitWarning",
    "PAPER_LOGS",
    "group_shuffle_splits",
    "leave_one_controller_out",
    "within_controller_splits",
    "per_controller_splits",
    "cross_validation_folds",
    "split_by_loop",
    "CrossValidationFolds",
    "FOLD_KINDS",
]


#: The paper's logs: its split trains on the first 28 of them, sorted by name, and tests on the other 20.
PAPER_LOGS = 48


class PaperSplitWarning(UserWarning):
    """The paper's split given other than the paper's 48 logs: it still splits them, and says how."""


def paper_split(paths: Sequence[str | Path], n_train: int = 28) -> tuple[list[Path], list[Path]]:
    """The paper's split: names sorted, the first ``n_train`` train, the rest test.

    Warns (:class:`PaperSplitWarning`) when given other than the paper's 48 logs: the split is then
    not the paper's, though it is made the same way.
    """
    ordered = sorted((Path(p) for p in paths), key=lambda p: p.name)
    if len(ordered) <= n_train:
        raise ValueError(f"the paper's split needs more than {n_train} logs, got {len(ordered)}")
    if len(ordered) != PAPER_LOGS:
        warnings.warn(
            f"the paper's split is for its {PAPER_LOGS} logs, got {len(ordered)}: the first {n_train} names "
            f"sorted train, the other {len(ordered) - n_train} test",
            PaperSplitWarning,
            stacklevel=2,
        )
    return ordered[:n_train], ordered[n_train:]


def group_shuffle_splits(
    n_groups: int, n_splits: int = 3, test_size: float = 0.2, seed: int = 1234
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Random episode-grouped splits, identical to scikit-learn's GroupShuffleSplit.

    Each split holds out ``ceil(test_size * n_groups)`` episodes (6 of 28 for
    the paper's protocol) drawn by the same ``RandomState`` permutations as
    ``GroupShuffleSplit(n_splits, test_size=test_size, random_state=seed)``.

    Returns
    -------
    list of (train_indices, validation_indices)
    """
    n_test = int(np.ceil(test_size * n_groups))
    n_train = n_groups - n_test
    if n_test < 1 or n_train < 1 or n_splits < 1:
        raise ValueError(f"cannot make {n_splits} splits holding out {test_size:g} of {n_groups} episodes")
    rng = np.random.RandomState(seed)
    splits = []
    for _ in range(n_splits):
        permutation = rng.permutation(n_groups)
        splits.append((np.sort(permutation[n_test : n_test + n_train]), np.sort(permutation[:n_test])))
    return splits


def leave_one_controller_out(labels: Sequence[int] | np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
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
    ids = np.asarray(labels)
    groups = np.unique(ids)
    if groups.size < 2:
        raise ValueError(f"leave-one-controller-out needs episodes of at least two controllers, got {groups.size}")
    return [(np.flatnonzero(ids != g), np.flatnonzero(ids == g)) for g in groups]


def per_controller_splits(
    labels: Sequence[int] | np.ndarray, n_splits: int = 3, seed: int = 1234
) -> list[tuple[np.ndarray, np.ndarray, int]]:
    """``n_splits`` folds per controller, each scored on that controller's episodes.

    A controller's first fold holds out all its episodes when the other controllers' are at least half
    of the training episodes: its loop predicted by a plant fitted to the rest, the question of a loop
    the training never ran. Its other folds (all of them when the others are fewer) are
    :func:`within_controller_splits`' for it: 20% of its episodes held out, all the rest trained on.

    Why not :func:`leave_one_controller_out` alone: with a new controller's few episodes beside the
    rig's many, its fold that holds out the rig's trains on the few alone, a fit nothing like the one
    the search recommends (on the rig's 28 and 6 soft episodes, that fold scored the rig-only winner's
    lifting 0.85 where every fold trained on 28 or more scored it 0.96-0.99, and below zero at larger
    alphas, which dropped that lifting from the ranking), and no fold asks how well the rig's own loop
    is still predicted. Every fold here trains on at least half of the episodes, and each controller
    weighs the same (as many folds each), whatever its share of the episodes; a controller of a
    single episode has only its whole fold (none when the others are fewer), since no part of one
    episode can be held out.

    Returns
    -------
    list of (train_indices, validation_indices, label)
        The folds holding out whole controllers first (in the labels' order), then each
        controller's others in the labels' order.
    """
    ids = np.asarray(labels)
    parts = within_controller_splits(ids, n_splits, seed)
    whole, within = [], []
    for g in np.unique(ids):
        own, others = np.flatnonzero(ids == g), np.flatnonzero(ids != g)
        alone = 2 * others.size >= ids.size
        if alone:
            whole.append((others, own, int(g)))
        within += [p for p in parts if p[2] == g][: n_splits - int(alone)]
    return whole + within


def within_controller_splits(
    labels: Sequence[int] | np.ndarray, n_splits: int = 3, seed: int = 1234
) -> list[tuple[np.ndarray, np.ndarray, int]]:
    """Folds that hold out some episodes of one controller and train on all the others.

    The complement of :func:`leave_one_controller_out`: each fold's validation
    episodes ran a controller the training episodes include, so its score is
    the same-controller one. For each controller with at least two episodes,
    :func:`group_shuffle_splits` (``n_splits``,
    ``seed``) over its episodes; the other controllers' episodes always train.

    Returns
    -------
    list of (train_indices, validation_indices, label)
    """
    ids = np.asarray(labels)
    out = []
    for g in np.unique(ids):
        own, others = np.flatnonzero(ids == g), np.flatnonzero(ids != g)
        if own.size < 2:
            continue
        for train, validation in group_shuffle_splits(own.size, n_splits, seed=seed):
            out.append((np.sort(np.concatenate([others, own[train]])), own[validation], int(g)))
    return out


FOLD_KINDS = {
    "leave-one-controller-out": "each fold holds out all the training episodes of one controller and predicts its "
    "loop with the plant fitted to the other controllers' episodes",
    "per-controller": "as many folds per training controller: one holding out all its episodes when the others "
    "are at least half of the training episodes (its loop predicted by a plant fitted to the rest), the others "
    "holding out 20% of its episodes, trained on all the rest",
    "episode-grouped": "random splits holding out 20% of the training episodes (one controller: the paper's protocol)",
}


@dataclass(frozen=True)
class CrossValidationFolds:
    """The folds of a cross-validation on training episodes, and what they hold out.

    Attributes
    ----------
    kind : {"per-controller", "leave-one-controller-out", "episode-grouped"}
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


def cross_validation_folds(
    controllers: Sequence[DiscreteStateSpace],
    n_splits: int = 3,
    seed: int = 1234,
    loops: Sequence[DiscreteStateSpace] | None = None,
) -> CrossValidationFolds:
    """:func:`per_controller_splits` when the episodes ran two or more controllers; else
    :func:`group_shuffle_splits` (``n_splits``, ``seed``).

    The folds holding out a whole controller come first, the fewest held-out episodes first (ties in
    the controllers' order): a search screens its candidates on the first fold, which is then the
    cheapest to predict, and with a new controller's few episodes beside many of the rig's, the one
    that asks the question the user has, the new loop predicted by a plant fitted to the others.

    ``loops``: each episode's loop, when it is not its controller alone (a recording session's
    command delay after it: :func:`~qube_koopman.identify.estimators.structure.with_command_delay`).
    The folds are drawn from ``controllers`` as above; a fold whose validation episodes ran several
    loops becomes one fold per loop (:func:`split_by_loop`), since a fold predicts one loop.
    """
    distinct, labels = distinct_controllers(controllers)
    if len(distinct) >= 2:
        parts = per_controller_splits(labels, n_splits, seed)
        # The folds holding out a whole controller first, the fewest held-out episodes first among them (stable:
        # ties keep the controllers' order): a search screens on the first.
        ids = np.asarray(labels)
        trains_on_its_own = [bool(np.any(ids[t] == g)) for t, _, g in parts]
        whole = sorted((p for p, own in zip(parts, trains_on_its_own) if not own), key=lambda p: len(p[1]))
        ordered = whole + [p for p, own in zip(parts, trains_on_its_own) if own]
        folds = CrossValidationFolds("per-controller", [(t, v) for t, v, _ in ordered], [g for _, _, g in ordered])
    else:
        folds = CrossValidationFolds("episode-grouped", group_shuffle_splits(len(labels), n_splits, 0.2, seed))
    if loops is None:
        return folds
    loop_labels = distinct_controllers(loops)[1]
    by_loop = [split_by_loop([split], loop_labels) for split in folds.splits]
    held_out = None if folds.held_out is None else [c for c, p in zip(folds.held_out, by_loop) for _ in p]
    return CrossValidationFolds(folds.kind, [s for p in by_loop for s in p], held_out)


def split_by_loop(
    splits: Sequence[tuple[np.ndarray, np.ndarray]], loop_labels: Sequence[int] | np.ndarray
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each split whose validation episodes ran several loops as one split per loop, the training the same.

    Parameters
    ----------
    splits : sequence of (train_indices, validation_indices)
    loop_labels : sequence of int
        Each episode's loop (for example from :func:`distinct_controllers` of the loops).

    Returns
    -------
    list of (train_indices, validation_indices)
        In the splits' order; a split's loops in the order of their labels.
    """
    ids = np.asarray(loop_labels)
    out = []
    for train, validation in splits:
        validation = np.asarray(validation)
        for loop in np.unique(ids[validation]):
            out.append((np.asarray(train), validation[ids[validation] == loop]))
    return out
