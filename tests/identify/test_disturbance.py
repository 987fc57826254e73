"""The disturbance model, its Kalman filter and K-step predictions (identify/models/disturbance.py).

Ground truth from a linear system with a known random-walk load at its input; the filter's gain
against python-control's ``dlqe``; the batched K-step predictions against a brute-force
re-simulation of each start; K = 0 against the filtered estimate; a zero gain against the
free-run prediction; a non-detectable augmentation refused.
"""

from __future__ import annotations

import numpy as np
import pytest

from qube_koopman.identify import Constant, Delay, KoopmanModel, Lifting, Polynomial, ThinPlateRbf, Trajectory
from qube_koopman.identify.models import disturbance as dm

#: A lightly damped, stable two-state plant (theta, alpha) driven by one input, sampled at 500 Hz.
A_TRUE = np.array([[0.999, 0.002], [-0.004, 0.995]])
B_TRUE = np.array([0.004, 0.002])


def _plant_model(lifting_steps=None) -> KoopmanModel:
    """The true plant as a Koopman model on the identity lifting (the states themselves)."""
    lifting = Lifting(lifting_steps or [Polynomial(1)]).fit([np.zeros((10, 2))], ["theta", "alpha"])
    return KoopmanModel(A_TRUE, B_TRUE[:, None], lifting, ("u",), dt=0.002)


def _episodes(q: float, sigma: np.ndarray, n_episodes: int = 4, n: int = 10000, seed: int = 0):
    """Episodes of the true plant under a random input, a random-walk load of variance ``q`` per sample at
    the input and white innovations of standard deviations ``sigma``; each episode's load too."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_episodes):
        u = rng.standard_normal((n, 1))
        d = np.cumsum(rng.standard_normal(n) * np.sqrt(q))
        w = B_TRUE[None, :] * (u + d[:, None]) + sigma * rng.standard_normal((n, 2))
        x = np.zeros((n, 2))
        for k in range(n - 1):  # x_{k+1} = A x_k + B (u_k + d_k) + w_k
            x[k + 1] = A_TRUE @ x[k] + w[k]
        out.append((Trajectory(x=x, u=u, dt=0.002, name=f"ep{i}"), d))
    return out


def test_a_random_walk_load_s_covariances_and_gain_are_recovered():
    q, sigma = 1e-3, np.array([2e-4, 1e-4])
    model = _plant_model()
    episodes = _episodes(q, sigma)
    fitted = dm.fit_disturbance(model, [t for t, _ in episodes], "input", method="likelihood")
    assert fitted.q == pytest.approx(q, rel=0.25)
    assert np.sqrt(np.diag(fitted.R)) == pytest.approx(sigma, rel=0.02)
    # The gain is the steady-state Kalman filter's of the scalar load seen through G = C E, as python-control's
    # dlqe (solve_discrete_are) gives it for the fitted covariances.
    import control

    G = (model.C @ dm.disturbance_direction(model, "input"))[:, None]  # (n_outputs, 1)
    L_pred, P, _ = control.dlqe(np.eye(1), np.eye(1), G, fitted.q, fitted.R)
    # dlqe's gain is the filtered one: x_{k|k} = x_{k|k-1} + L (y - C x_{k|k-1}).
    assert fitted.gain == pytest.approx(np.asarray(L_pred).ravel(), rel=1e-6)
    # The filter tracks the true load: most of its variance explained.
    t, d = episodes[0]
    r, _ = dm.one_step_residuals(model, t)
    dhat, _ = dm.filter_disturbance(r, G.ravel(), 1.0, fitted.gain)
    err = d[1000:-1] - dhat[1000:-1]
    assert np.var(err) < 0.2 * np.var(d[1000:-1] - d[1000:-1].mean())


def test_the_prediction_criterion_finds_a_load_and_predicts_better_than_without():
    model = _plant_model()
    episodes = [t for t, _ in _episodes(1e-3, np.array([2e-4, 1e-4]), n_episodes=3, n=6000)]
    fitted = dm.fit_disturbance(model, episodes, "input", horizons=(25, 250))
    assert fitted.q > 0
    data = dm.KStepData.of(model, episodes, (25, 250))
    none = fitted.with_gain(np.zeros(2))
    with_load, without = dm.prediction_errors(model, data, [fitted, none]).sum(axis=(1, 2))
    assert with_load < 0.5 * without
    # Its costs are those of the K-step predictions themselves (the load's response is linear here).
    pred = dm.predict_ahead(model, fitted, episodes[0], [250], stride=25)[250]
    ok = np.all(np.isfinite(pred), axis=1)
    assert np.sum(ok) > 100


def _loop_model():
    """A closed loop of a nonlinear lifting (poly 2, 3 delays) with a controller state: the batched predictions
    take the ring loop a real model takes."""
    rng = np.random.default_rng(3)
    lifting = Lifting([Polynomial(2), Delay(3)]).fit([rng.standard_normal((50, 2)) * 0.1], ["theta", "alpha"])
    n_z = 1 + lifting.n_features_out_
    A = 0.02 * rng.standard_normal((n_z, n_z))
    A[:3, :3] += np.diag([0.9, 0.95, 0.97])
    B = 0.05 * rng.standard_normal((n_z, 2))
    return KoopmanModel(A, B, lifting, ("r", "f"), n_passthrough=1, dt=0.002)


def _loop_episode(model, n=400, seed=5):
    rng = np.random.default_rng(seed)
    return Trajectory(
        x=0.1 * rng.standard_normal((n, 2)),
        r=0.1 * rng.standard_normal((n, 1)),
        f=0.1 * rng.standard_normal((n, 1)),
        xc=0.1 * rng.standard_normal((n, 1)),
        dt=0.002,
        name="loop",
    )


def test_k_step_predictions_equal_a_re_simulation_from_each_filtered_state():
    model = _loop_model()
    t = _loop_episode(model)
    dist = dm.DisturbanceModel("input", 0.98, 1e-3, np.eye(2) * 1e-2, np.array([0.3, -0.2]))
    K = 7
    ahead = dm.predict_ahead(model, dist, t, [K], stride=3)[K]
    r, _ = dm.one_step_residuals(model, t)
    dhat, _ = dm.filter_disturbance(r, model.C @ dm.disturbance_direction(model, "input"), dist.pole, dist.gain)
    d = model.n_delays
    checked = 0
    for k in range(d, t.n_samples - K, 3):
        v = model.inputs_of(t)[k - d : k + K + 1].copy()
        v[d:, 1] += dhat[k] * dist.pole ** np.arange(K + 1)
        x, _ = model.simulate(t.x[k - d : k + 1], v, t.xc[k])
        np.testing.assert_allclose(ahead[k + K], x[d + K], rtol=1e-10, atol=1e-12)
        checked += 1
    assert checked > 100
    # Between strided starts nothing is predicted.
    assert np.all(np.isnan(ahead[d + K + 1]))


def test_a_rate_on_an_angle_is_re_simulated_the_same_way():
    model = _loop_model()
    t = _loop_episode(model, seed=8)
    dist = dm.DisturbanceModel("alpha", 1.0, 1e-6, np.eye(2) * 1e-2, np.array([0.01, 0.05]))
    K, d = 5, model.n_delays
    ahead = dm.predict_ahead(model, dist, t, [K])[K]
    r, _ = dm.one_step_residuals(model, t)
    dhat, _ = dm.filter_disturbance(r, model.C @ dm.disturbance_direction(model, "alpha"), 1.0, dist.gain)
    E = dm.disturbance_direction(model, "alpha")
    augmented = KoopmanModel(model.A, np.hstack([model.B, E[:, None]]), model.lifting, ("r", "f"), 1, dt=0.002)
    k = 100
    v = np.hstack([model.inputs_of(t)[k - d : k + K + 1], np.full((K + d + 1, 1), dhat[k])])
    x, _ = augmented.simulate(t.x[k - d : k + 1], v, t.xc[k])
    np.testing.assert_allclose(ahead[k + K], x[d + K], rtol=1e-10)


def _affine_loop_model():
    """A closed loop on an affine lifting (3 delays and a constant) with a controller state."""
    rng = np.random.default_rng(4)
    lifting = Lifting([Polynomial(1), Delay(3), Constant()]).fit([rng.standard_normal((50, 2))], ["theta", "alpha"])
    n_z = 1 + lifting.n_features_out_
    A = 0.05 * rng.standard_normal((n_z, n_z))
    A[:3, :3] += np.diag([0.9, 0.95, 0.97])
    A[-2, :] = 0.0
    A[-2, -2] = 1.0  # the constant stays 1
    B = 0.05 * rng.standard_normal((n_z, 2))
    B[-2] = 0.0
    return KoopmanModel(A, B, lifting, ("r", "f"), n_passthrough=1, dt=0.002)


@pytest.mark.parametrize("entry", ["input", "alpha"])
def test_an_affine_loops_k_step_predictions_are_a_filter_equal_to_re_simulating_every_start(entry, monkeypatch):
    model = _affine_loop_model()
    assert model.lifting.affine and not _loop_model().lifting.affine
    t = _loop_episode(model, n=600, seed=9)
    dist = dm.DisturbanceModel(entry, 0.99, 1e-4, np.eye(2) * 1e-2, np.array([0.2, 0.1]))
    horizons = [1, 8, 60]
    filtered = dm.predict_ahead(model, dist, t, horizons, stride=2)
    # the same predictions with the filter refused: every start re-simulated
    simulated_calls = []
    original = KoopmanModel.simulate

    def counting(self, x_init, v, p0=None, relift=True):
        simulated_calls.append(np.asarray(x_init).shape[0] if np.asarray(x_init).ndim == 3 else 1)
        return original(self, x_init, v, p0, relift)

    monkeypatch.setattr(KoopmanModel, "simulate", counting)
    dm.predict_ahead(model, dist, t, horizons, stride=2)
    filter_windows = sum(simulated_calls)
    n_starts = sum(len(range(model.n_delays, t.n_samples - K, 2)) for K in horizons)
    assert filter_windows < n_starts / 2  # probes and checks, not one simulation per start
    monkeypatch.setattr(type(model.lifting), "affine", property(lambda self: False))
    resimulated = dm.predict_ahead(model, dist, t, horizons, stride=2)
    for K in horizons:
        ok = np.isfinite(resimulated[K][:, 0])
        assert ok.sum() > 200
        np.testing.assert_array_equal(np.isfinite(filtered[K][:, 0]), ok)
        np.testing.assert_allclose(filtered[K][ok], resimulated[K][ok], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("beta", [1.0, 0.99995, 0.98, 0.3, 0.0])
def test_the_filters_recursion_is_lfilters_without_importing_scipy_signal(beta):
    from scipy.signal import lfilter

    u = np.random.default_rng(2).standard_normal(5000) * 1e-3
    expected = lfilter([1.0], [1.0, -beta], u)
    # the same recursion, rounded apart by an ulp or two (a fused multiply-add): relative to the signal's size
    np.testing.assert_allclose(dm.first_order_filter(beta, u), expected, rtol=0, atol=1e-13 * np.max(np.abs(expected)))
    assert dm.first_order_filter(beta, np.zeros(0)).shape == (0,)


def test_a_horizon_fit_does_not_import_scipy_signal_or_stats(tmp_path):
    """scipy.signal and scipy.stats took 0.4-0.8 s and 0.3 s to import; ``--horizon`` needs only the filter's
    recursion and a binomial tail."""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent(
        """
        import sys, numpy as np
        from qube_koopman.identify import Delay, KoopmanModel, Lifting, Polynomial, Trajectory
        from qube_koopman.identify.models.kstep import AheadOptions, fit_training_disturbance
        rng = np.random.default_rng(0)
        lifting = Lifting([Polynomial(1), Delay(2)]).fit([rng.standard_normal((20, 2))], ["theta", "alpha"])
        A = np.zeros((6, 6))
        A[:2, :2] = [[0.999, 0.002], [-0.004, 0.995]]
        A[2:4, :2] = A[4:, 2:4] = np.eye(2)
        model = KoopmanModel(A, rng.standard_normal((6, 1)) * 1e-3, lifting, ("u",), dt=0.002)
        x, u = 0.01 * rng.standard_normal((3000, 2)), rng.standard_normal((3000, 1))
        t = Trajectory(x=x, u=u, dt=0.002, name="e")
        fit_training_disturbance(model, [t, t], AheadOptions((0.1, 1.0)))
        print("scipy.signal" in sys.modules, "scipy.stats" in sys.modules)
        """
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "False False"


def test_a_lifting_is_affine_only_when_every_step_is():
    assert Lifting([Delay(2), Constant()]).affine and Lifting([Polynomial(1), Delay(1)]).affine
    assert not Lifting([Polynomial(2), Delay(1)]).affine
    assert not Lifting([Delay(1), ThinPlateRbf()]).affine


def test_zero_steps_ahead_is_the_filtered_estimate():
    model = _loop_model()
    t = _loop_episode(model)
    dist = dm.DisturbanceModel("input", 1.0, 1e-3, np.eye(2) * 1e-2, np.array([0.3, -0.2]))
    zero = dm.predict_ahead(model, dist, t, [0])[0]
    d = model.n_delays
    # In innovations form the filtered estimate of the measured states is the measurement.
    np.testing.assert_array_equal(zero[d:], t.x[d:])
    assert np.all(np.isnan(zero[:d]))


def test_with_a_zero_gain_the_prediction_from_the_first_window_is_the_free_run():
    model = _loop_model()
    t = _loop_episode(model)
    dist = dm.DisturbanceModel("input", 1.0, 1e-3, np.eye(2) * 1e-2, np.zeros(2))
    free = model.predict(t)
    d = model.n_delays
    for K in (1, 10, 60):
        ahead = dm.predict_ahead(model, dist, t, [K], stride=1000)[K]
        np.testing.assert_allclose(ahead[d + K], free[d + K], rtol=1e-12)
    # Not only at the first window: a gain that is not zero changes later starts' predictions.
    moved = dm.predict_ahead(model, dist.with_gain(np.array([0.5, 0.5])), t, [10], stride=1)[10]
    still = dm.predict_ahead(model, dist, t, [10], stride=1)[10]
    assert not np.allclose(moved[d + 50 :], still[d + 50 :])


def test_a_non_detectable_augmentation_is_refused():
    model = _plant_model()
    blind = KoopmanModel(model.A, np.zeros((2, 1)), model.lifting, ("u",), dt=0.002)  # the input moves nothing
    t = _episodes(1e-3, np.array([2e-4, 1e-4]), n_episodes=1, n=500)[0][0]
    with pytest.raises(dm.NotDetectable, match="not detectable"):
        dm.fit_disturbance(blind, [t], "input")
    # A random walk entering an integrating controller state that no measured state sees cannot be told from
    # that state: the rank condition fails although the disturbance moves the lifted state.
    loop = _loop_model()
    A = loop.A.copy()
    A[0, :], A[:, 0], A[0, 0] = 0.0, 0.0, 1.0
    hidden = KoopmanModel(A, loop.B, loop.lifting, ("r", "f"), n_passthrough=1, dt=0.002)
    E = np.zeros(A.shape[0])
    E[0] = 1.0
    assert not dm.augmented_detectable(hidden, E)
    assert not dm.disturbance_detectable(hidden, E)
    assert dm.augmented_detectable(model, dm.disturbance_direction(model, "input"))
    assert dm.augmented_detectable(model, dm.disturbance_direction(model, "theta"))
    # A lifting with a constant feature has a mode at 1 the outputs never see: a filter of the whole lifted
    # state fails the rank condition, the innovations form (the lifted state measured) does not.
    constant = _loop_model()
    A = constant.A.copy()
    A[:, -1], A[-1, :], A[-1, -1] = 0.0, 0.0, 1.0
    constant = KoopmanModel(A, constant.B, constant.lifting, ("r", "f"), n_passthrough=1, dt=0.002)
    E = dm.disturbance_direction(constant, "input")
    assert not dm.augmented_detectable(constant, E)
    assert dm.disturbance_detectable(constant, E)


def test_the_model_round_trips_through_its_dict_and_damage_is_named():
    dist = dm.DisturbanceModel("input", 1.0, 2e-7, np.array([[1e-6, 1e-8], [1e-8, 2e-6]]), np.array([0.5, -0.3]))
    back = dm.DisturbanceModel.from_dict(dist.as_dict())
    assert back.entry == "input" and back.q == dist.q and back.pole == 1.0
    np.testing.assert_array_equal(back.R, dist.R)
    np.testing.assert_array_equal(back.gain, dist.gain)
    with pytest.raises(ValueError, match="unknown disturbance entry"):
        dm.DisturbanceModel.from_dict({**dist.as_dict(), "entry": "wind"})
    with pytest.raises(ValueError, match="do not fit"):
        dm.DisturbanceModel.from_dict({**dist.as_dict(), "gain": [1.0, 2.0, 3.0]})


def _coloured_episodes(pole: float, q: float, n_episodes: int = 3, n: int = 6000, seed: int = 11):
    """Episodes of the true plant under a random input and a first-order load ``d_{k+1} = pole d_k + w_k``."""
    from scipy.signal import lfilter

    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_episodes):
        u = rng.standard_normal((n, 1))
        d = lfilter([1.0], [1.0, -pole], rng.standard_normal(n) * np.sqrt(q))
        w = B_TRUE[None, :] * (u + d[:, None]) + np.array([2e-4, 1e-4]) * rng.standard_normal((n, 2))
        x = np.zeros((n, 2))
        for k in range(n - 1):
            x[k + 1] = A_TRUE @ x[k] + w[k]
        out.append(Trajectory(x=x, u=u, dt=0.002, name=f"ep{i}"))
    return out


@pytest.mark.parametrize("pole, expected", [(1.0, {1.0, 0.999}), (0.98, {0.99, 0.98, 0.95})])
def test_the_pole_the_training_episodes_support_is_chosen(pole, expected):
    """A random-walk load is kept a random walk (or nearly: a 2 s time constant, indistinguishable in 12 s); a
    first-order load of time constant 0.1 s gets a pole near its own, and predicts better than the random walk."""
    from qube_koopman.identify.models.kstep import AheadOptions, fit_training_disturbance

    model = _plant_model()
    episodes = _coloured_episodes(pole, 1e-3 if pole == 1.0 else 2e-2)
    fitted, report = fit_training_disturbance(model, episodes, AheadOptions((0.05, 0.5), entry="input"))
    assert fitted is not None and fitted.pole in expected
    costs = report["training_cost_by_pole"]["input"]
    assert set(costs) == {f"{p:g}" for p in dm.POLES}
    assert costs[f"{fitted.pole:g}"] == min(costs.values())
    if pole < 1.0:
        assert costs[f"{fitted.pole:g}"] < 0.95 * costs["1"]
        assert "first-order" in report["why"]
    # set by hand, the pole is obeyed
    forced, _ = fit_training_disturbance(model, episodes, AheadOptions((0.05, 0.5), entry="input", pole=0.995))
    assert forced is not None and forced.pole == 0.995
    with pytest.raises(ValueError, match="pole is in"):
        AheadOptions((0.1,), pole=1.5)


def test_a_first_order_disturbance_integrated_keeps_its_covariances_with_the_random_walks_gain():
    import control

    model = _plant_model()
    G = model.C @ dm.disturbance_direction(model, "input")
    R = np.diag([4e-8, 1e-8])
    first_order = dm.DisturbanceModel("input", 0.99, 1e-4, R, dm.steady_state_gain(G, 0.99, 1e-4, R)[0])
    walk = first_order.integrated(G)
    assert (walk.pole, walk.q, walk.entry) == (1.0, 1e-4, "input") and walk.R is R
    L, _, _ = control.dlqe(np.eye(1), np.eye(1), G[:, None], 1e-4, R)
    assert walk.gain == pytest.approx(np.asarray(L).ravel(), rel=1e-6)
    assert walk.integrated(G) is walk


def test_several_disturbances_gain_is_dlqes_and_one_is_the_scalar_closed_form():
    import control

    rng = np.random.default_rng(5)
    R = np.array([[4e-8, 1e-9], [1e-9, 1e-8]])
    G = np.column_stack([B_TRUE, [1.0, 0.0]])
    Q = np.diag([1e-6, 2e-9])
    for pole in (1.0, 0.99):
        L, P = dm.steady_state_gains(G, pole, Q, R)
        L_ref, P_ref, _ = control.dlqe(pole * np.eye(2), np.eye(2), G, Q, R)
        np.testing.assert_allclose(pole * L, L_ref, rtol=1e-6)  # dlqe's gain is the predictor's, A P C' S^-1
        np.testing.assert_allclose(P, P_ref, rtol=1e-6)
    g, q = rng.standard_normal(2), 1e-5
    L1, P1 = dm.steady_state_gains(g[:, None], 0.995, np.array([[q]]), R)
    L0, P0 = dm.steady_state_gain(g, 0.995, q, R)
    np.testing.assert_allclose(L1[0], L0, rtol=1e-8)
    assert P1[0, 0] == pytest.approx(P0, rel=1e-8)
