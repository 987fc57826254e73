"""The episode-grouped splits equal scikit-learn's GroupShuffleSplit (not a dependency)."""

import numpy as np
import pytest

from qube_koopman.identify.model_selection.split import group_shuffle_splits

# Written down from scikit-learn 1.9.1, GroupShuffleSplit(n_splits, test_size=..., random_state=...)
# with one group per episode: (n_groups, n_splits, test_size, seed) -> test indices of each split.
GOLDEN = {
    (28, 3, 0.2, 1234): [[1, 3, 4, 7, 8, 24], [5, 6, 9, 13, 15, 24], [0, 1, 10, 17, 21, 22]],
    (10, 2, 0.3, 7): [[0, 5, 8], [1, 2, 3]],
}


@pytest.mark.parametrize("config", sorted(GOLDEN))
def test_splits_match_the_values_scikit_learn_gave(config):
    n, k, test_size, seed = config
    splits = group_shuffle_splits(n, n_splits=k, test_size=test_size, seed=seed)
    assert [v.tolist() for _, v in splits] == GOLDEN[config]
    for train, validation in splits:
        assert sorted(np.concatenate([train, validation]).tolist()) == list(range(n))


@pytest.mark.parametrize("config", [(28, 3, 0.2, 1234), (10, 2, 0.3, 7), (48, 5, 0.25, 0), (7, 4, 0.5, 99)])
def test_splits_equal_scikit_learn_when_it_is_installed(config):
    model_selection = pytest.importorskip(
        "sklearn.model_selection", reason="scikit-learn is optional; the golden values cover CI"
    )
    n, k, test_size, seed = config
    groups = np.arange(n)
    expected = model_selection.GroupShuffleSplit(k, test_size=test_size, random_state=seed).split(groups, groups=groups)
    ours = group_shuffle_splits(n, n_splits=k, test_size=test_size, seed=seed)
    for (train, validation), (exp_train, exp_validation) in zip(ours, expected):
        np.testing.assert_array_equal(validation, np.sort(exp_validation))
        np.testing.assert_array_equal(train, np.sort(exp_train))


def test_per_controller_folds_hold_out_a_new_controller_whole_first_and_weigh_each_controller_the_same():
    """A search screens on the first fold: with a new controller's few episodes beside the rig's many,
    that fold holds out the few whole (the cheapest to predict, the new loop predicted by a plant fitted to
    the rest). The rig's whole would leave the few alone to train on: its folds hold out a part of it
    instead. Every controller has as many folds (the mean weighs them the same), each training on at least
    half of the episodes; equal counts keep the controllers' order."""
    from qube_koopman.core.controller import load_pd_gains, pd_controller
    from qube_koopman.identify.model_selection.split import cross_validation_folds

    rig, soft = pd_controller(load_pd_gains("rig")), pd_controller(load_pd_gains("soft-theta"))
    folds = cross_validation_folds([rig] * 5 + [soft] * 2)
    assert folds.kind == "per-controller"
    assert folds.held_out == [1, 0, 0, 0, 1, 1]  # the soft controller's whole fold first
    (train, validation), *rest = folds.splits
    assert validation.tolist() == [5, 6] and train.tolist() == [0, 1, 2, 3, 4]
    for (train, validation), held in zip(rest, folds.held_out[1:]):
        own = {0, 1, 2, 3, 4} if held == 0 else {5, 6}
        assert len(validation) == 1 and set(validation) <= own, "a part of its controller's episodes"
        assert sorted(set(train) | set(validation)) == list(range(7)), "trained on all the rest"
    assert all(2 * len(train) >= 7 for train, _ in folds.splits)
    tied = cross_validation_folds([soft, rig, soft, rig])
    assert tied.held_out == [0, 1, 0, 0, 1, 1]
    assert [v.tolist() for _, v in tied.splits[:2]] == [[0, 2], [1, 3]]


def test_a_fold_of_several_loops_becomes_a_fold_per_loop_with_the_same_training_episodes():
    """A controller's sessions with different command delays are several loops: folds are drawn by
    controller, then each fold's validation episodes split by loop (a fold predicts one loop)."""
    from qube_koopman.core.controller import load_pd_gains, pd_controller
    from qube_koopman.core.lti import with_output_delay
    from qube_koopman.identify.model_selection.split import cross_validation_folds, split_by_loop

    rig, soft = pd_controller(load_pd_gains("rig")), pd_controller(load_pd_gains("soft-theta"))
    late = with_output_delay(soft, 1.7)
    recorded = [rig] * 4 + [soft] * 4
    loops = [rig] * 4 + [soft, late, soft, late]
    folds = cross_validation_folds(recorded, loops=loops)
    assert folds.kind == "per-controller"
    assert [v.tolist() for _, v in folds.splits[:3]] == [[0, 1, 2, 3], [4, 6], [5, 7]]
    assert [t.tolist() for t, _ in folds.splits[:3]] == [[4, 5, 6, 7], [0, 1, 2, 3], [0, 1, 2, 3]]
    assert folds.held_out == [0, 1, 1, 0, 0, 1, 1]  # then each controller's folds holding out one episode
    assert all(len(v) == 1 and len(t) == 7 for t, v in folds.splits[3:])
    # Loops equal to the controllers change nothing; one controller's random splits split too.
    plain = cross_validation_folds(recorded)
    same = cross_validation_folds(recorded, loops=recorded)
    assert [(t.tolist(), v.tolist()) for t, v in same.splits] == [(t.tolist(), v.tolist()) for t, v in plain.splits]
    one = cross_validation_folds([soft] * 10, n_splits=2, seed=3, loops=[soft, late] * 5)
    drawn = cross_validation_folds([soft] * 10, n_splits=2, seed=3)
    assert one.kind == "episode-grouped" and len(one.splits) >= len(drawn.splits)
    assert [
        sorted(np.concatenate([v for t, v in one.splits if t.tolist() == t0.tolist()]).tolist())
        for t0, _ in drawn.splits
    ] == [sorted(v.tolist()) for _, v in drawn.splits]
    assert all(len({j % 2 for j in v}) == 1 for _, v in one.splits)  # each fold of one loop
    parts = split_by_loop([(np.array([0]), np.array([3, 1, 2]))], [0, 1, 0, 1])
    assert [(t.tolist(), v.tolist()) for t, v in parts] == [([0], [2]), ([0], [3, 1])]


def test_a_controller_of_one_episode_has_its_whole_fold_only():
    from qube_koopman.identify.model_selection.split import per_controller_splits

    folds = per_controller_splits([0, 0, 0, 0, 0, 1], n_splits=3)
    assert [g for _, _, g in folds] == [1, 0, 0, 0]
    train, validation, _ = folds[0]
    assert validation.tolist() == [5] and train.tolist() == [0, 1, 2, 3, 4]
    # the rig's five held out whole would leave one episode to train on: a part of them instead, 3 times
    assert all(len(v) == 1 and 5 not in v and len(t) == 5 for t, v, _ in folds[1:])
