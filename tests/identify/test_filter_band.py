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
