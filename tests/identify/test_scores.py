"""Scores against values computed by hand."""

import numpy as np
import pytest

from qube_koopman.identify import normalized_mean_error, nrmse, r2_score, score_episodes


def test_r2_perfect_and_mean_predictor():
    y = np.column_stack([np.sin(np.linspace(0, 6, 100)), np.linspace(-1, 2, 100)])
    assert r2_score(y, y) == 1.0
    assert r2_score(y, np.broadcast_to(y.mean(axis=0), y.shape)) == pytest.approx(0.0)


def test_r2_is_averaged_over_states():
    y = np.column_stack([np.arange(10.0), np.arange(10.0)])
    pred = y.copy()
    pred[:, 1] = y[:, 1].mean()
    assert r2_score(y, pred) == pytest.approx(0.5)


def test_nrmse_and_nme_by_hand():
    y = np.array([[1.0, -4.0], [2.0, 0.0], [-2.0, 2.0]])
    pred = y + np.array([[0.1, 0.2], [0.1, -0.2], [0.1, 0.2]])
    # state 0: rmse 0.1, peak 2 -> 5 %; state 1: rmse 0.2, peak 4 -> 5 %
    assert nrmse(y, pred) == pytest.approx(5.0)
    # error = true - pred: state 0 mean -0.1 / 2 -> -5 %; state 1 mean -0.2/3 / 4 -> -1.667 %
    assert normalized_mean_error(y, pred) == pytest.approx((-5.0 - 100 * 0.2 / 3 / 4) / 2)


def test_non_finite_prediction_scores_minus_infinity():
    y = np.ones((5, 2)) * np.arange(5)[:, None]
    pred = y.copy()
    pred[3, 1] = np.nan
    assert r2_score(y, pred) == -np.inf
    assert nrmse(y, pred) == np.inf
    mean, std = score_episodes([y, y], [y, pred], "r2")
    assert mean == -np.inf


def test_score_episodes_mean_and_std():
    y = np.column_stack([np.arange(10.0)])
    preds = [y, y + 1.0]
    mean, std = score_episodes([y, y], preds, "nrmse")
    assert mean == pytest.approx(50 * 1 / 9)
    assert std == pytest.approx(50 * 1 / 9)


def test_bad_score_inputs():
    with pytest.raises(ValueError, match="unknown score"):
        score_episodes([np.zeros((3, 1))], [np.zeros((3, 1))], "mape")
    with pytest.raises(ValueError, match="shapes differ"):
        r2_score(np.zeros((3, 2)), np.zeros((3, 1)))


def test_a_constant_true_channel_is_left_out_with_a_warning():
    import warnings

    from qube_koopman.identify.metrics import ConstantChannelWarning, r2_scores

    t = np.linspace(0, 1, 50)
    truth = np.column_stack([np.sin(6 * t), np.full_like(t, 0.3)])
    pred = np.column_stack([np.sin(6 * t) + 0.01, np.full_like(t, 0.5)])
    expected = r2_score(truth[:, 0], pred[:, 0])
    with pytest.warns(ConstantChannelWarning, match=r"\[1\] are constant"):
        assert r2_score(truth, pred) == pytest.approx(expected)
    with pytest.warns(ConstantChannelWarning):
        assert np.isnan(r2_score(truth[:, 1:], pred[:, 1:]))  # nothing to explain at all
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert r2_scores(truth, pred) == pytest.approx(expected)  # the vectorized form agrees, silently
        bad = pred.copy()
        bad[10, 1] = np.nan
        assert r2_scores(truth, bad) == -np.inf  # divergence anywhere still counts


def test_a_huge_but_finite_r2_summarizes_without_an_overflow_warning():
    """A model that all but diverged (R^2 about -1e200, as ARX's plant scores can be): the spread is
    infinite, said without numpy's overflow warning on the user's terminal."""
    import warnings

    from qube_koopman.identify.metrics import EpisodeScore, summarize_scores

    scores = [EpisodeScore(-1e200, 1e99, None), EpisodeScore(0.9, 0.1, None)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        summary = summarize_scores(scores)
    assert summary["r2_mean"] == pytest.approx(-5e199) and summary["r2_std"] == np.inf
    assert summary["n_diverged"] == 0


def test_a_prediction_that_grows_beyond_a_thousand_times_the_data_has_diverged_finite_or_not():
    from qube_koopman.identify.metrics import DIVERGED_FACTOR, episode_score

    t = np.arange(400) * 0.002
    truth = np.column_stack([0.3 * np.sin(5 * t), 0.02 * np.cos(9 * t)])
    growing = truth + np.exp(40 * t)[:, None] * 1e-6  # finite throughout, 1e8 by the end
    score = episode_score(truth, growing)
    first = int(np.argmax(np.abs(growing).max(axis=1) > DIVERGED_FACTOR * 1.0))
    assert score.r2 == -np.inf and score.nrmse == np.inf and score.diverged_at == first
    close = truth + 0.01
    assert np.isfinite(episode_score(truth, close).r2) and episode_score(truth, close).diverged_at is None
