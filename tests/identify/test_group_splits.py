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
