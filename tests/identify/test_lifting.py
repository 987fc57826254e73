"""Lifting functions: values, names, order, episode boundaries, fitting on training data."""

import numpy as np
import pytest

from qube_koopman.identify import Delay, GaussianRbf, Lifting, Polynomial, ThinPlateRbf


@pytest.fixture
def episodes():
    rng = np.random.default_rng(0)
    return [rng.normal(size=(50, 2)), rng.normal(size=(30, 2))]


def test_polynomial_monomials_and_names(episodes):
    lift = Lifting([Polynomial(2)]).fit(episodes, ["theta", "alpha"])
    assert lift.feature_names_out_ == ("theta", "alpha", "theta^2", "theta*alpha", "alpha^2")
    X = np.array([[2.0, 3.0]])
    np.testing.assert_array_equal(lift.transform(X), [[2, 3, 4, 6, 9]])


def test_polynomial_order_three_counts(episodes):
    lift = Lifting([Polynomial(3)]).fit(episodes)
    # monomials of degree 1..3 in 2 variables: 2 + 3 + 4
    assert lift.n_features_out_ == 9
    assert lift.feature_names_out_[-1] == "x1^3"
    np.testing.assert_allclose(lift.transform(np.array([[2.0, 3.0]]))[0, -4:], [8, 12, 18, 27])


def test_delays_stack_the_past_and_consume_samples(episodes):
    lift = Lifting([Delay(2)]).fit(episodes, ["a", "b"])
    assert lift.n_delays_ == 2
    assert lift.feature_names_out_ == ("a", "b", "a[k-1]", "b[k-1]", "a[k-2]", "b[k-2]")
    X = np.arange(10.0).reshape(5, 2)
    out = lift.transform(X)
    assert out.shape == (3, 6)
    np.testing.assert_array_equal(out[0], [4, 5, 2, 3, 0, 1])


def test_paper_qube_lifting_has_55_states(episodes):
    lift = Lifting([Polynomial(2), Delay(10)]).fit(episodes, ["theta", "alpha"])
    assert lift.n_features_out_ == 55
    assert lift.feature_names_out_[:2] == ("theta", "alpha")


def test_thin_plate_formula_and_originals_first(episodes):
    centers = np.array([[0.0, 0.0], [1.0, 1.0]])
    lift = Lifting([ThinPlateRbf(shape=0.2, offset=1e-3, centers=centers)]).fit(episodes)
    X = np.array([[3.0, 4.0]])
    out = lift.transform(X)
    s = 0.2 * np.array([5.0, np.hypot(2, 3)]) + 1e-3
    np.testing.assert_allclose(out[0], [3, 4, *(s**2 * np.log(s))])
    assert lift.feature_names_out_ == ("x0", "x1", "tps0", "tps1")


def test_gaussian_formula(episodes):
    lift = Lifting([GaussianRbf(shape=0.5, centers=[[1.0, 0.0]])]).fit(episodes)
    np.testing.assert_allclose(lift.transform(np.array([[1.0, 2.0]]))[0, 2], np.exp(-1.0))


def test_latin_hypercube_centres_fill_the_training_box(episodes):
    lift = Lifting([ThinPlateRbf(n_centers=20, seed=4)]).fit(episodes)
    centers = lift.steps_[0].centers_
    data = np.vstack(episodes)
    assert centers.shape == (20, 2)
    assert np.all(centers >= data.min(axis=0)) and np.all(centers <= data.max(axis=0))
    # Latin hypercube: one centre per stratum in each dimension
    for j in range(2):
        strata = np.floor((centers[:, j] - data[:, j].min()) / np.ptp(data[:, j]) * 20).astype(int)
        assert sorted(strata) == list(range(20))
    again = Lifting([ThinPlateRbf(n_centers=20, seed=4)]).fit(episodes)
    np.testing.assert_array_equal(again.steps_[0].centers_, centers)


def test_composition_order_delay_then_rbf_matches_duffing_size():
    rng = np.random.default_rng(1)
    lift = Lifting([Delay(6), ThinPlateRbf(50, shape=0.2, seed=0)]).fit([rng.normal(size=(100, 1))])
    assert lift.n_features_out_ == 57


def test_fit_leaves_constructor_steps_untouched(episodes):
    step = ThinPlateRbf(n_centers=3, seed=0)
    Lifting([step]).fit(episodes)
    assert not hasattr(step, "centers_")


def test_episodes_are_lifted_separately(episodes):
    lift = Lifting([Delay(3)]).fit(episodes)
    joined = lift.transform(np.vstack(episodes))
    separate = [lift.transform(e) for e in episodes]
    assert sum(len(s) for s in separate) == len(joined) - 3
    np.testing.assert_array_equal(separate[1][0, 2:4], episodes[1][2])


def test_batched_transform_equals_per_episode(episodes):
    lift = Lifting([Polynomial(2), Delay(2), GaussianRbf(4, seed=0)]).fit(episodes)
    batch = np.stack([episodes[0][:30], episodes[1]])
    out = lift.transform(batch)
    np.testing.assert_allclose(out[1], lift.transform(episodes[1]))


@pytest.mark.parametrize(
    "make,match",
    [
        (lambda: Polynomial(0), "order"),
        (lambda: Delay(-1), "delays"),
        (lambda: Delay(1.5), "delays"),
        (lambda: ThinPlateRbf(shape=-1), "shape"),
        (lambda: ThinPlateRbf(offset=0), "offset"),
        (lambda: GaussianRbf(n_centers=0), "centres"),
    ],
)
def test_bad_hyperparameters(make, match, episodes):
    step = make()  # stored unchanged: the fit checks them
    with pytest.raises(ValueError, match=match):
        step.fit(episodes, ["x0", "x1"])
    with pytest.raises(ValueError, match=match):
        Lifting([step]).fit(episodes)
    with pytest.raises(ValueError, match=match):
        Lifting([step]).n_delays  # noqa: B018 (what a fit reads first, before the data)


def test_bad_explicit_centres(episodes):
    with pytest.raises(ValueError, match="centres"):
        Lifting([GaussianRbf(centers=[[1.0, 2.0, 3.0]])]).fit(episodes)


def test_wrong_width_and_too_short(episodes):
    lift = Lifting([Delay(5)]).fit(episodes)
    with pytest.raises(ValueError, match="expects 2 states"):
        lift.transform(np.zeros((10, 3)))
    with pytest.raises(ValueError, match="too few"):
        lift.transform(np.zeros((5, 2)))


def test_coulomb_friction_is_the_smoothed_sign_of_the_motion_over_its_lag(episodes):
    from qube_koopman.identify.lifting import CoulombFriction

    lifting = Lifting([Delay(4), CoulombFriction(0, lag=3, width=0.2)]).fit(episodes, ["theta", "alpha"])
    x = episodes[0]
    z = lifting.transform(x)
    assert lifting.feature_names_out_[-1] == "friction(theta)" and z.shape[1] == 2 * 5 + 1
    np.testing.assert_allclose(z[:, -1], np.tanh((x[4:, 0] - x[1:-3, 0]) / 0.2), rtol=1e-12)
    np.testing.assert_array_equal(z[:, :-1], Lifting([Delay(4)]).fit(episodes).transform(x))
    with pytest.raises(ValueError, match="needs a Delay step of at least 5"):
        Lifting([Delay(4), CoulombFriction(0, lag=5)]).fit(episodes)
    for bad in (dict(lag=0), dict(width=0.0), dict(feature=-1)):
        step = CoulombFriction(**bad)  # stored unchanged: the fit checks them
        with pytest.raises(ValueError, match="friction"):
            Lifting([Delay(4), step]).fit(episodes)
