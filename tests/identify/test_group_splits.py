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
    model_selection = pytest.importorskip("sklearn.model_selection",
                                          reason="scikit-learn is optional; the golden values cover CI")
    n, k, test_size, seed = config
    groups = np.arange(n)
    expected = model_selection.GroupShuffleSplit(k, test_size=test_size, random_state=seed).split(groups, groups=groups)
    ours = group_shuffle_splits(n, n_splits=k, test_size=test_size, seed=seed)
    for (train, validation), (exp_train, exp_validation) in zip(ours, expected):
        np.testing.assert_array_equal(validation, np.sort(exp_validation))
        np.testing.assert_array_equal(train, np.sort(exp_train))


def test_leave_one_controller_out_folds_hold_out_the_fewest_episodes_first():
    """A search screens on the first fold: with a new controller's few episodes beside the rig's many,
    that fold holds out the few (the cheapest to predict); equal counts keep the controllers' order."""
    from qube_koopman.core.controller import load_pd_gains, pd_controller
    from qube_koopman.identify.model_selection.split import cross_validation_folds

    rig, soft = pd_controller(load_pd_gains("rig")), pd_controller(load_pd_gains("soft-theta"))
    folds = cross_validation_folds([rig] * 5 + [soft] * 2)
    assert folds.kind == "leave-one-controller-out"
    assert [v.tolist() for _, v in folds.splits] == [[5, 6], [0, 1, 2, 3, 4]]
    assert [t.tolist() for t, _ in folds.splits] == [[0, 1, 2, 3, 4], [5, 6]]
    assert folds.held_out == [1, 0]  # the soft controller's fold first
    tied = cross_validation_folds([soft, rig, soft, rig])
    assert tied.held_out == [0, 1] and [v.tolist() for _, v in tied.splits] == [[0, 2], [1, 3]]
