"""Prediction intervals (identify.uncertainty): the level on a loop whose predictive distribution is known,
the bootstrap's weighted factors against a direct fit, offsets, divergence."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from qube_koopman.identify import ClEdmd, Trajectory
from qube_koopman.identify.models.offsets import OffsetEstimate
from qube_koopman.identify.metrics import DivergedPrediction
from qube_koopman.identify.model_selection.sweep import fitted_models
from qube_koopman.identify.uncertainty import (
    CalibrationOptions,
    EpisodePrediction,
    IntervalCalibration,
    IntervalOptions,
    Loop,
    calibrate,
    ensemble_statistics,
    fit_ensemble,
    predict_episodes,
    prediction_band,
    summarize_bands,
)
from qube_koopman.core.lti import DiscreteStateSpace

DT = 0.01
A_P, B_P, GAIN = 1.0, 0.1, 0.5  # x+ = x + 0.1 u + w under u = 0.5 (r - x): x+ = 0.95 x + 0.05 r + w
RHO = A_P - B_P * GAIN
SIGMA = 0.01
# A proportional controller with a state that stays at zero (the closed-loop estimators need one).
P_CONTROLLER = DiscreteStateSpace([[0.0]], [[0.0]], [[0.0]], [[GAIN]], DT)


def ar1_loop(n_episodes: int, n_samples: int, seed: int) -> list[Trajectory]:
    """Episodes of a first-order loop driven by white process noise: x_k given x_0 and r is Gaussian with
    variance SIGMA^2 (1 - RHO^(2k)) / (1 - RHO^2), the band's form exactly."""
    return loop_episodes(n_episodes, GAIN, B_P, seed, n_samples, feedforward=False)


def loop_episodes(
    n_episodes: int, gain: float, b_plant: float, seed: int, n_samples: int = 300, feedforward: bool = True
) -> list[Trajectory]:
    """Episodes of the first-order loop under ``u = gain (r - x)`` with the plant's input gain ``b_plant``
    (with a zero feedforward signal when ``feedforward``: a wrapped plant's loop takes one)."""
    rng = np.random.default_rng(seed)
    episodes = []
    for i in range(n_episodes):
        r = np.repeat(rng.uniform(-1, 1, n_samples // 50 + 1), 50)[:n_samples, None]
        x = np.zeros((n_samples, 1))
        x[0] = rng.uniform(-0.5, 0.5)
        for k in range(n_samples - 1):
            u = gain * (r[k, 0] - x[k, 0])
            x[k + 1] = A_P * x[k] + b_plant * u + SIGMA * rng.standard_normal()
        f = np.zeros((n_samples, 1)) if feedforward else None
        episodes.append(
            Trajectory(
                x=x, r=r, f=f, xc=np.zeros((n_samples, 1)), name=f"g{gain}-{i}" if feedforward else f"e{i}", dt=DT
            )
        )
    return episodes


@pytest.fixture(scope="module")
def ar1():
    return ar1_loop(60, 300, seed=1), ar1_loop(30, 300, seed=2)


def _bands(fit, calibration, episodes, measured=(0,)):
    models = [fit.estimator.closed_loop_model_] + [closed for closed, _ in fit.members]
    with warnings.catch_warnings():
        warnings.simplefilter("error", DivergedPrediction)
        return [
            prediction_band(t.name, t, p, calibration, 1, 0)
            for t, p in zip(episodes, predict_episodes(models, episodes))
        ]


def test_intervals_cover_a_first_order_loop_at_the_level_and_match_its_predictive_spread(ar1):
    train, test = ar1
    level = 0.9
    options = IntervalOptions(level, n_members=8, n_calibration_members=4, n_folds=5, stride=1)
    fit = fit_ensemble(ClEdmd(P_CONTROLLER, alpha=1e-8), train, options)
    calibration = calibrate(fit, train, [Loop("closed")] * len(train), CalibrationOptions(level))
    pooled = summarize_bands(_bands(fit, calibration, test), ["x"])["pooled"]
    assert abs(pooled["coverage"]["x"] - level) < 0.03
    # The band's growth is the loop's: tau = -1 / (2 ln rho) samples (loosely: each episode's first few tens of
    # samples tell it, the true model's own errors give 14 on 30 such episodes, 10.4 on 200), and at long
    # horizons the half-width is the normal quantile times the stationary standard deviation.
    assert calibration.timescale_[0] == pytest.approx(-1 / (2 * np.log(RHO)), rel=0.5)
    stationary = SIGMA / np.sqrt(1 - RHO**2)
    assert np.sqrt(calibration.scale_[0]) == pytest.approx(stationary, rel=0.1)
    assert calibration.factor_[0] == pytest.approx(1.645, rel=0.1)


def test_the_bootstrap_weighted_factors_are_a_fit_on_the_duplicated_episodes(ar1):
    train = ar1[0][:6]
    counts = np.array([[2, 0, 1, 3, 0, 0]])
    estimator = ClEdmd(P_CONTROLLER, alpha=1e-3)
    setup = estimator.setup_fit(train)
    total, (selected,) = ensemble_statistics(estimator, setup, counts)
    partial = dataclasses.replace(setup, target_rows=estimator.relift_rows(setup))
    closed, _ = fitted_models(estimator, partial, selected, [1e-3], None, None)
    duplicated = [t for t, c in zip(train, counts[0]) for _ in range(c)]
    direct = ClEdmd(P_CONTROLLER, alpha=1e-3).fit(duplicated).closed_loop_model_
    rows = estimator.relift_rows(setup)  # the members fit only the rows a re-lifted prediction uses
    np.testing.assert_allclose(closed[0].koopman_matrix[:rows], direct.koopman_matrix[:rows], rtol=1e-9, atol=1e-12)
    # The total of all the episodes is the plain fit's, bit for bit.
    estimator.finish_fit(setup, total)
    np.testing.assert_array_equal(
        estimator.koopman_matrix_, ClEdmd(P_CONTROLLER, alpha=1e-3).fit(train).koopman_matrix_
    )


def _estimate(std_error: float) -> OffsetEstimate:
    return OffsetEstimate((0,), np.array([0.002]), 50, 0.05, 0.01, 0.005, np.array([std_error]))


class _Window:
    """The offsets' protocol as predict_episodes reads it."""

    channels, bound = (0,), 0.05

    def window(self, dt: float) -> int:
        return 50


def test_an_offset_the_window_cannot_see_widens_the_interval_within_its_bound(ar1, monkeypatch):
    from qube_koopman.identify.uncertainty import prediction

    train, test = ar1
    fit = fit_ensemble(ClEdmd(P_CONTROLLER, alpha=1e-8), train[:10], IntervalOptions(n_members=4))
    models = [fit.estimator.closed_loop_model_] + [closed for closed, _ in fit.members]
    variance = {}
    for std_error in (1e-4, np.inf):  # a sharp estimate, and a flat cost (the status says so)
        assert _estimate(std_error).status == ("flat" if std_error == np.inf else "ok")
        monkeypatch.setattr(prediction, "estimate_offsets_many", lambda *a, se=std_error, **k: [_estimate(se)])
        variance[std_error] = predict_episodes(models, test[:1], _Window())[0].variance[100:]
    assert np.all(variance[np.inf] > variance[1e-4]) and np.all(np.isfinite(variance[np.inf]))
    # A feedback loop carries an offset of the fed-back channel to the prediction: at most the bound's worth.
    assert np.sqrt(variance[np.inf].max()) < 2 * 0.05


def _calibration() -> IntervalCalibration:
    rng = np.random.default_rng(0)
    errors = 0.01 * rng.standard_normal((1000, 2))
    return IntervalCalibration(0.95).fit(errors, np.zeros((1000, 2)), np.arange(1, 1001) * 10)


@pytest.mark.parametrize("what", ["prediction", "member"])
def test_a_diverged_prediction_gets_an_infinite_band_and_a_warning(what):
    x = np.zeros((200, 2))
    trajectory = Trajectory(x=x, name="e", dt=DT)
    prediction, variance = np.zeros((200, 2)), np.full((200, 2), 1e-6)
    if what == "prediction":
        prediction[120:] = np.inf
    else:
        variance[120:, 1] = np.inf
    with pytest.warns(DivergedPrediction, match="infinite from sample 120"):
        band = prediction_band("e", trajectory, EpisodePrediction(prediction, variance), _calibration(), 1, 0)
    assert np.all(np.isinf(band.lower[band.t >= 120 * DT])) and np.all(np.isinf(band.upper[band.t >= 120 * DT]))
    assert np.all(np.isfinite(band.upper[:118])) and band.diverged_at == 120
    summary = summarize_bands([band], ["theta", "alpha"])
    assert summary["pooled"]["mean_half_width"]["theta"] == np.inf and summary["pooled"]["n_infinite"] == 1


def test_a_loop_the_training_never_ran_is_calibrated_on_probes_of_other_loops(ar1):
    """The training loop (gain 0.5) cannot show a plant error that only another controller brings out
    (the probes' and the test's plant has input gain 0.16, not 0.1): its held-out calibration undercovers
    the test episodes under gain 1.5, while the calibration on probe episodes under gains 1.2 and 1.8
    (predicted by the wrapped fit, :func:`calibrate_on_probes`) covers them at about the level."""
    from qube_koopman.identify.model_selection.transfer import ProbeSet
    from qube_koopman.identify.uncertainty import calibrate_on_probe_sets, calibrate_on_probes

    train, _ = ar1
    level = 0.9
    options = IntervalOptions(level, n_members=8, n_calibration_members=4, n_folds=5, stride=1)
    fit = fit_ensemble(ClEdmd(P_CONTROLLER, alpha=1e-8), train, options)
    held_out = calibrate(fit, train, [Loop("closed")] * len(train), CalibrationOptions(level))

    def controller(gain):
        return DiscreteStateSpace([[0.0]], [[0.0]], [[0.0]], [[gain]], DT)

    probes = ProbeSet(
        [controller(1.2), controller(1.8)],
        [loop_episodes(20, 1.2, 0.16, seed=3), loop_episodes(20, 1.8, 0.16, seed=4)],
        [],
    )
    on_probes = calibrate_on_probes(fit, probes, CalibrationOptions(level, stride=1))
    # Its members' spread is the same sort as the held-out one; the model error is larger.
    assert on_probes.scale_[0] > 1.3 * held_out.scale_[0]
    # Independently: the same numbers from calibrate() on one fold holding out every probe episode.
    episodes = probes.episodes[0] + probes.episodes[1]
    loops = [Loop("wrapped", c) for c, group in zip(probes.controllers, probes.episodes) for _ in group]
    point = (fit.estimator.closed_loop_model_, fit.estimator.plant_model_)
    one_fold = dataclasses.replace(
        fit, folds=[dataclasses.replace(fit.folds[0], validation=np.arange(40), point=point, members=fit.members)]
    )
    again = calibrate(one_fold, episodes, loops, CalibrationOptions(level, stride=1))
    np.testing.assert_allclose(on_probes.scale_, again.scale_, rtol=1e-12)
    np.testing.assert_allclose(on_probes.factor_, again.factor_, rtol=1e-12)
    # Two probe sets calibrated in one simulation: each is its own calibration.
    other = ProbeSet([controller(1.5)], [loop_episodes(10, 1.5, 0.16, seed=6)], [])
    first, second = calibrate_on_probe_sets(fit, [probes, other], CalibrationOptions(level, stride=1))
    assert calibrate_on_probe_sets(fit, [], CalibrationOptions(level)) == []
    np.testing.assert_allclose(first.factor_, on_probes.factor_, rtol=1e-12)
    np.testing.assert_allclose(first.scale_, on_probes.scale_, rtol=1e-12)
    alone = calibrate(
        dataclasses.replace(one_fold, folds=[dataclasses.replace(one_fold.folds[0], validation=np.arange(10))]),
        other.episodes[0],
        [Loop("wrapped", controller(1.5))] * 10,
        CalibrationOptions(level, stride=1),
    )
    assert second.n_samples_ == alone.n_samples_ and not np.allclose(second.scale_, first.scale_)
    np.testing.assert_allclose(second.scale_, alone.scale_, rtol=1e-12)
    np.testing.assert_allclose(second.factor_, alone.factor_, rtol=1e-12)

    test = loop_episodes(30, 1.5, 0.16, seed=5)
    wrapped = Loop("wrapped", controller(1.5))
    models = [wrapped.model(*point, [0])] + [wrapped.model(*member, [0]) for member in fit.members]
    predictions = predict_episodes(models, test)

    def coverage(calibration):
        bands = [prediction_band(t.name, t, p, calibration, 1, 0) for t, p in zip(test, predictions)]
        return summarize_bands(bands, ["x"])["pooled"]["coverage"]["x"]

    assert coverage(held_out) < level - 0.1  # 0.79 measured
    assert abs(coverage(on_probes) - level) < 0.05  # 0.92 measured


def test_the_probes_take_their_own_number_of_members_and_the_calibration_folds_theirs(ar1, monkeypatch):
    """The folds' ensembles have ``n_calibration_members`` refits each; the probes are predicted by the
    first ``n_probe_members`` of the fit's members (a loop the training never ran needs more of them);
    the fit's own members do not depend on either."""
    import qube_koopman.identify.uncertainty.calibration as calibration

    train = ar1[0][:12]
    options = IntervalOptions(0.9, n_members=6, n_calibration_members=2, n_probe_members=5, n_folds=3)
    fit = fit_ensemble(ClEdmd(P_CONTROLLER, alpha=1e-6), train, options)
    assert len(fit.members) == 6 and all(len(fold.members) == 2 for fold in fit.folds)
    more = fit_ensemble(ClEdmd(P_CONTROLLER, alpha=1e-6), train, dataclasses.replace(options, n_calibration_members=3))
    np.testing.assert_array_equal(more.counts, fit.counts)
    seen = []

    class Seen(Exception):
        pass

    def predict_group_sets(group_sets, offsets=None):
        seen.extend(models for groups in group_sets for models, _ in groups)
        raise Seen

    monkeypatch.setattr(calibration, "predict_group_sets", predict_group_sets)
    probes = dataclasses.make_dataclass("Probes", ["controllers", "episodes"])([P_CONTROLLER], [train[:2]])
    with pytest.raises(Seen):
        calibration.calibrate_on_probes(fit, probes, CalibrationOptions(0.9), n_members=options.n_probe_members)
    wrapped = Loop("wrapped", P_CONTROLLER)
    expected = [wrapped.model(*member, None) for member in fit.members[:5]]
    assert len(seen) == 1 and len(seen[0]) == 6  # the point fit and the first 5 members
    for got, want in zip(seen[0][1:], expected):
        np.testing.assert_array_equal(got.A, want.A)
    with pytest.raises(ValueError, match="probe members"):
        IntervalOptions(n_probe_members=1)


def test_the_widest_calibration_takes_each_channel_from_the_wider_band():
    from qube_koopman.identify.uncertainty import widest

    def fitted(scale, timescale, factor):
        c = IntervalCalibration(0.95)
        c.scale_, c.timescale_, c.factor_ = np.array(scale), np.array(timescale), np.array(factor)
        c.coverage_, c.n_samples_, c.n_diverged_ = np.array([0.95, 0.95]), 100, 1
        return c

    # Channel 0: 2 sqrt(0.04) = 0.4 against 1 sqrt(0.09) = 0.3; channel 1: 2 sqrt(0.01) = 0.2 against 3 sqrt(0.01).
    a, b = fitted([0.04, 0.01], [10.0, 20.0], [2.0, 2.0]), fitted([0.09, 0.01], [30.0, 40.0], [1.0, 3.0])
    w = widest([a, b])
    np.testing.assert_array_equal(w.scale_, [0.04, 0.01])
    np.testing.assert_array_equal(w.timescale_, [10.0, 40.0])
    np.testing.assert_array_equal(w.factor_, [2.0, 3.0])
    assert (w.n_samples_, w.n_diverged_) == (200, 2)
    variances, horizons = np.zeros((5, 2)), np.array([1, 10, 100, 1_000, 10_000])
    np.testing.assert_allclose(
        w.half_width(variances, horizons),
        np.maximum(a.half_width(variances, horizons), b.half_width(variances, horizons)),
    )
    # A band that grows slowly to the wider limit (c: 2 sqrt(0.04) = 0.4 after 1000 samples) is the narrower
    # one at short horizons (d: 1.2 sqrt(0.09) = 0.36 after 10): the widest band is d's there, c's far out.
    c, d = fitted([0.04, 0.01], [1000.0, 20.0], [2.0, 2.0]), fitted([0.09, 0.01], [10.0, 20.0], [1.2, 1.0])
    w = widest([c, d])
    assert w.factor_[0] == 2.0 and w.timescale_[0] == 1000.0  # the report's numbers: widest far out
    near, far = w.half_width(np.zeros((2, 2)), np.array([100, 100_000]))
    assert near[0] == pytest.approx(d.half_width(np.zeros(2), np.array(100))[0]) and near[0] > 0.35
    assert far[0] == pytest.approx(0.4)
    assert len(widest([w, a]).parts_) == 3  # nested: the parts, not the combination


def test_a_random_walk_error_is_reported_by_the_bands_width_at_the_horizons_not_its_parameters():
    # An error whose variance grows as sigma^2 h over every horizon seen never levels off: the fit pushes
    # q and tau to their largest (only q / tau is known). The report still says what the band is: at
    # h samples, k sigma sqrt(h), k the 95 % quantile (1.96 for a Gaussian), within the sampling noise.
    rng = np.random.default_rng(3)
    sigma, n = 1e-3, 20_000
    horizons = rng.integers(1, 10_001, n)
    errors = sigma * np.sqrt(horizons)[:, None] * rng.standard_normal((n, 2))
    calibration = IntervalCalibration(0.95).fit(errors, np.zeros((n, 2)), horizons)
    assert calibration.timescale_[0] > 1e5  # far beyond the horizons: the random-walk limit
    report = calibration.as_dict(["theta", "alpha"])["theta"]
    assert report["scale"] > 10 * sigma * np.sqrt(10_000)  # alone, a scale far beyond any error seen
    for h, width in report["model_error_half_width"].items():
        assert width == pytest.approx(1.96 * sigma * np.sqrt(int(h)), rel=0.08), h
    # A widest combination reports its own band at each horizon (the wider part there).
    from qube_koopman.identify.uncertainty import REPORTED_HORIZONS, widest

    short = IntervalCalibration(0.95).fit(0.05 * rng.standard_normal((n, 2)), np.zeros((n, 2)), horizons)
    both = widest([calibration, short]).as_dict(["theta", "alpha"])["theta"]["model_error_half_width"]
    for h in REPORTED_HORIZONS:
        parts = [c.as_dict(["theta", "alpha"])["theta"]["model_error_half_width"][str(h)] for c in (calibration, short)]
        assert both[str(h)] == max(parts)
    walk = report["model_error_half_width"]
    assert both["100"] > walk["100"] and both["10000"] == walk["10000"]


@pytest.mark.parametrize("offsets", [None, _Window()], ids=["plain", "offsets"])
def test_the_folds_predicted_together_are_each_folds_own_predictions(ar1, offsets):
    from qube_koopman.identify.uncertainty import predict_groups

    train = ar1[0][:12]
    fit = fit_ensemble(
        ClEdmd(P_CONTROLLER, alpha=1e-3), train, IntervalOptions(n_members=3, n_calibration_members=3, n_folds=3)
    )
    shorter = dataclasses.replace(train[0], x=train[0].x[:200], r=train[0].r[:200], xc=train[0].xc[:200], name="short")
    groups = []
    for i, fold in enumerate(fit.folds):  # unequal groups: one more episode (a shorter one) in the first
        episodes = [train[j] for j in fold.validation] + ([shorter] if i == 0 else [])
        models = [fold.point[0]] + [closed for closed, _ in fold.members]
        groups.append((models, episodes))
    together = predict_groups(groups, offsets)
    for (models, episodes), predicted in zip(groups, together):
        alone = predict_episodes(models, episodes, offsets)
        assert len(predicted) == len(episodes)
        for a, b, t in zip(predicted, alone, episodes):
            assert a.prediction.shape == (t.n_samples, 1)
            np.testing.assert_allclose(a.prediction, b.prediction, rtol=1e-10, atol=1e-13)
            np.testing.assert_allclose(a.variance, b.variance, rtol=1e-8, atol=1e-16)
            if offsets is None:
                assert a.plain is None and a.estimate is None
            else:
                np.testing.assert_allclose(a.plain, b.plain, rtol=1e-10, atol=1e-13)
                np.testing.assert_allclose(a.estimate.values, b.estimate.values, rtol=1e-9)  # batch shapes: rounding
                assert a.estimate.channels == (0,)


def _two_state_loop(n_episodes: int, n_samples: int, seed: int) -> list[Trajectory]:
    """An arm (integrator, fed back) and a stable second state it drives, with feedforward and input logged:
    what held_out_figures' J and voltage need."""
    rng = np.random.default_rng(seed)
    episodes = []
    for i in range(n_episodes):
        r = np.repeat(rng.uniform(-1, 1, n_samples // 50 + 1), 50)[:n_samples, None]
        f = 0.05 * rng.standard_normal((n_samples, 1))
        x, u = np.zeros((n_samples, 2)), np.zeros((n_samples, 1))
        for k in range(n_samples - 1):
            u[k] = GAIN * (r[k, 0] - x[k, 0]) + f[k, 0]
            x[k + 1] = [x[k, 0] + B_P * u[k, 0], 0.9 * x[k, 1] + 0.05 * u[k, 0]] + SIGMA * rng.standard_normal(2)
        u[-1] = GAIN * (r[-1, 0] - x[-1, 0]) + f[-1, 0]
        episodes.append(Trajectory(x=x, u=u, r=r, f=f, xc=np.zeros((n_samples, 1)), name=f"two-{i}", dt=DT))
    return episodes


@pytest.mark.parametrize("offsets", [None, _Window()], ids=["plain", "offsets"])
def test_the_design_figures_reuse_the_calibrations_held_out_predictions(offsets):
    """calibrate() hands its held-out closed-loop predictions (without offsets) to held_out_figures, which then
    predicts nothing again: the same figures as its own predictions by the plant wrapped with each episode's
    controller, to the rounding between the fitted closed loop and that wrapping. Under a "plant" loop
    calibrate's predictions are not closed-loop ones and are not handed on."""
    from qube_koopman.identify.uncertainty import held_out

    train = _two_state_loop(12, 300, seed=7)
    controllers = [P_CONTROLLER] * len(train)
    fit = fit_ensemble(
        ClEdmd(P_CONTROLLER, alpha=1e-3, measured=[0]),
        train,
        IntervalOptions(n_members=3, n_calibration_members=3, n_folds=3),
    )
    expected = held_out.held_out_figures(fit, train, controllers, [0], 20)
    points: dict = {}
    calibrate(fit, train, [Loop("closed")] * len(train), CalibrationOptions(0.9, 60, offsets, [0]), points=points)
    held_out_episodes = sorted(int(j) for fold in fit.folds for j in fold.validation)
    assert sorted(points) == held_out_episodes
    original = held_out.predict_groups
    try:
        held_out.predict_groups = None  # nothing left to predict: calling it would fail
        reused = held_out.held_out_figures(fit, train, controllers, [0], 20, points)
    finally:
        held_out.predict_groups = original
    assert np.all(np.isfinite(expected))
    np.testing.assert_allclose(reused, expected, rtol=1e-6)
    plant_points: dict = {}
    calibrate(fit, train, [Loop("plant")] * len(train), CalibrationOptions(0.9, 60, None, [0]), points=plant_points)
    assert plant_points == {}
