"""The disturbance filter's prediction intervals (identify/uncertainty/filter_band.py).

The variance formula against a Monte-Carlo simulation of a linear plant with a known random-walk load at
its input, predicted K samples ahead by the module's Kalman filter; K = 1 against the innovations'
covariance; the calibrated band's coverage on held-out synthetic errors.
"""

from __future__ import annotations

import numpy as np
import pytest

from qube_koopman.identify import KoopmanModel, Lifting, Polynomial, Trajectory
from qube_koopman.identify.models import disturbance as dm
from qube_koopman.identify.uncertainty.filter_band import (
    FilterCalibration,
    filter_variance,
    innovation_covariance,
)

A_TRUE = np.array([[0.999, 0.002], [-0.004, 0.995]])
B_TRUE = np.array([0.004, 0.002])
SIGMA = np.array([2e-4, 1e-4])
Q = 1e-3


def _plant_model() -> KoopmanModel:
    lifting = Lifting([Polynomial(1)]).fit([np.zeros((10, 2))], ["theta", "alpha"])
    return KoopmanModel(A_TRUE, B_TRUE[:, None], lifting, ("u",), dt=0.002)


def _disturbance(model: KoopmanModel, q: float = Q) -> dm.DisturbanceModel:
    R = np.diag(SIGMA**2)
    G = model.C @ dm.disturbance_direction(model, "input")
    return dm.DisturbanceModel("input", 1.0, q, R, dm.steady_state_gain(G, 1.0, q, R)[0])


def _runs(n_runs: int, n: int, seed: int = 0) -> list[Trajectory]:
    """Independent episodes of the true plant under a random input, the random-walk load and white noise."""
    rng = np.random.default_rng(seed)
    u = rng.standard_normal((n_runs, n, 1))
    d = np.cumsum(rng.standard_normal((n_runs, n)) * np.sqrt(Q), axis=1)
    w = SIGMA * rng.standard_normal((n_runs, n, 2))
    x = np.zeros((n_runs, n, 2))
    for k in range(n - 1):  # x_{k+1} = A x_k + B (u_k + d_k) + w_k
        x[:, k + 1] = x[:, k] @ A_TRUE.T + B_TRUE * (u[:, k] + d[:, k, None]) + w[:, k]
    return [Trajectory(x=x[i], u=u[i], dt=0.002, name=f"run{i}") for i in range(n_runs)]


def test_the_k_step_variance_equals_a_monte_carlo_simulation_of_the_filter_s_predictions():
    model, dist = _plant_model(), _disturbance(_plant_model())
    horizons, start = [1, 10, 100], 300  # the filter has long converged at the start (its gain ~0.5 a sample)
    runs = _runs(2000, start + max(horizons) + 1)
    # One start per run at `start` (the stride skips every other sample): 2000 independent errors per horizon.
    ahead = dm.predict_ahead_many(model, dist, runs, horizons, [[start] * len(horizons)] * len(runs))
    variance = filter_variance(model, dist, n_steps=200)
    for K in horizons:
        errors = np.array([t.x[start + K] - a[K][start + K] for t, a in zip(runs, ahead)])
        assert np.all(np.isfinite(errors))
        np.testing.assert_allclose(errors.var(axis=0), variance(np.array(K)), rtol=0.1)
    # The load's response accumulates: the variance keeps growing after the plant's own response has settled.
    assert np.all(variance(np.array(100)) > 3 * variance(np.array(10)))


def test_one_step_ahead_the_variance_is_the_innovations_covariance():
    model = _plant_model()
    dist = _disturbance(model)
    variance = filter_variance(model, dist, n_steps=20)
    S = innovation_covariance(model, dist)
    np.testing.assert_allclose(variance(np.array(1)), np.diag(S), rtol=1e-6)
    assert np.all(np.diag(S) > np.diag(dist.R))  # the load's uncertainty adds to the noise's
    none = dm.DisturbanceModel("input", 1.0, 0.0, dist.R, np.zeros(2))
    np.testing.assert_allclose(filter_variance(model, none, n_steps=20)(np.array(1)), np.diag(dist.R), rtol=1e-6)
    np.testing.assert_array_equal(variance(np.array(0)), 0.0)
    # Beyond the simulated steps the variance grows at the last response's rate: once a loop has settled (a
    # fast plant here), as the sums themselves continue.
    lifting = Lifting([Polynomial(1)]).fit([np.zeros((10, 2))], ["theta", "alpha"])
    fast = KoopmanModel(np.diag([0.5, 0.6]), B_TRUE[:, None], lifting, ("u",), dt=0.002)
    fast_dist = _disturbance(fast)
    short, long = filter_variance(fast, fast_dist, n_steps=60), filter_variance(fast, fast_dist, n_steps=400)
    np.testing.assert_allclose(short(np.array(400)), long(np.array(400)), rtol=1e-6)
    assert np.all(long(np.array(400)) > 5 * long(np.array(60)))


@pytest.mark.parametrize("model_error", [False, True])
def test_the_calibrated_band_covers_the_level_on_held_out_errors(model_error):
    model = _plant_model()
    dist = _disturbance(model)
    variance = filter_variance(model, dist, n_steps=300)
    rng = np.random.default_rng(1)

    def draw(n):
        h = rng.integers(1, 3000, n)
        # errors 1.7 times the filter's size plus a slower model error: the factor and the term must absorb both
        sd = np.sqrt(1.7**2 * variance(h) + 1e-4 * (1 - np.exp(-h / 500.0))[:, None])
        return h, sd * rng.standard_normal((n, 2))

    h, e = draw(20000)
    cal = FilterCalibration(0.9, model_error).fit_filter(e, np.zeros_like(e), h, variance)
    h2, e2 = draw(20000)
    coverage = (np.abs(e2) <= cal.half_width(np.zeros_like(e2), h2)).mean(axis=0)
    np.testing.assert_allclose(coverage, 0.9, atol=0.01)
    assert np.all(cal.factor_ > 1.0)  # wider than the filter alone says


def test_probe_sets_calibrated_together_are_each_calibrated_alone():
    """calibrate_filter_on_probe_sets predicts every set's probe episodes in one simulation: each set's
    calibration is the one calibrate_filter makes of that set's episodes alone (as a held-out fold)."""
    from _episodes import probe_sources
    from qube_koopman.core.controller import PdGains, pd_controller
    from qube_koopman.identify import ClEdmd
    from qube_koopman.identify.model_selection.search import LiftingSpec
    from qube_koopman.identify.model_selection.transfer import DEFAULT_PROBE_GAINS, twin_probe_sets
    from qube_koopman.identify.uncertainty.calibration import CalibrationOptions
    from qube_koopman.identify.uncertainty.ensemble import FoldEnsemble
    from qube_koopman.identify.uncertainty.filter_band import (
        calibrate_filter,
        calibrate_filter_on_probe_sets,
        residual_model,
    )
    from qube_koopman.identify.uncertainty.loops import Loop

    sources = probe_sources(3)
    rig = (6.0, 2.0, 35.0, 3.0, 50.0)  # the rig's gains' form: kp_theta, kd_theta, kp_alpha, kd_alpha, filter
    soft = [(2.0, 2.0, 35.0, 3.0, 50.0)]
    train, default, own = twin_probe_sets(sources, [[rig], DEFAULT_PROBE_GAINS, soft], per_controller=2, skip=100)
    fit = ClEdmd(pd_controller(PdGains(*rig)), lifting=LiftingSpec(delays=5, poly=1).steps(), alpha=1e-3)
    fit.fit(train.episodes[0])
    closed, plant = fit.closed_loop_model_, fit.plant_model_
    disturbance = residual_model(closed, train.episodes[0])
    options = CalibrationOptions(0.95, start=50, measured=[0, 1])

    def variance_of(model):
        return filter_variance(model, disturbance)

    together = calibrate_filter_on_probe_sets(
        (closed, plant), [default, own], options, disturbance, closed, variance_of
    )
    assert len(together) == 2
    assert calibrate_filter_on_probe_sets((closed, plant), [], options, disturbance, closed, variance_of) == []
    first, second = (c.as_dict(["theta", "alpha"])["theta"]["factor"] for c in together)
    assert first != second  # the sets' calibrations differ: each must be its own
    for probes, joint in zip([default, own], together):
        episodes = [e for group in probes.episodes for e in group]
        loops = [Loop("wrapped", c) for c, group in zip(probes.controllers, probes.episodes) for _ in group]
        fold = FoldEnsemble(np.arange(len(episodes)), (closed, plant), [])
        alone = calibrate_filter([fold], episodes, loops, options, disturbance, closed, variance_of=variance_of)
        a, b = joint.as_dict(["theta", "alpha"]), alone.as_dict(["theta", "alpha"])
        assert a.keys() == b.keys() and joint.n_samples_ == alone.n_samples_ > 0
        for name in a:
            assert a[name].keys() == b[name].keys()
            numbers = [key for key, value in b[name].items() if not isinstance(value, dict)]
            assert {"factor", "scale", "timescale_samples", "held_out_coverage"} <= set(numbers), numbers
            for key in numbers:
                np.testing.assert_allclose(a[name][key], b[name][key], rtol=1e-12, err_msg=f"{name} {key}")
