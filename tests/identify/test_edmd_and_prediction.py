"""EDMD details, prediction behaviour, structure helpers."""

from dataclasses import replace

import numpy as np
import pytest

from qube_koopman.identify import (
    ClEdmd,
    Constant,
    CoulombFriction,
    Delay,
    Edmd,
    GaussianRbf,
    Lifting,
    Polynomial,
    ThinPlateRbf,
    Trajectory,
    Trigonometric,
    closed_loop_matrices,
    controller_states,
    output_selection,
    plant_input,
    plant_input_map,
    r2_score,
)
from linear_loops import closed_loop_trajectories, mass_spring_damper, pid_position_controller


@pytest.fixture(scope="module")
def loop():
    A_p, B_p = mass_spring_damper()
    controller = pid_position_controller()
    return A_p, B_p, controller, closed_loop_trajectories(A_p, B_p, controller, [0], n_episodes=3, seed=1)


def test_fit_returns_self_and_keeps_hyperparameters(loop):
    *_, trajs = loop
    lifting = [Polynomial(2)]
    est = Edmd(lifting=lifting, alpha=0.5)
    assert est.fit(trajs) is est
    assert est.get_params() == {"lifting": lifting, "alpha": 0.5, "input_lifting": None}
    assert lifting[0].__dict__.keys() == {"order"}  # fit did not touch the constructor's objects
    pipeline = Lifting([Polynomial(2)])
    Edmd(lifting=pipeline).fit(trajs)
    assert not hasattr(pipeline, "steps_")


def test_episodes_are_never_joined(loop):
    *_, trajs = loop
    a = Edmd(lifting=[Delay(2)]).fit(trajs[:2]).koopman_matrix_
    b = Edmd(lifting=[Delay(2)]).fit(trajs[1::-1]).koopman_matrix_
    joined = Trajectory(x=np.vstack([t.x for t in trajs[:2]]), u=np.vstack([t.u for t in trajs[:2]]))
    c = Edmd(lifting=[Delay(2)]).fit([joined]).koopman_matrix_
    np.testing.assert_allclose(a, b, atol=1e-9)
    assert np.abs(a - c).max() > 1e-6


def test_regularization_shrinks_the_koopman_matrix(loop):
    *_, trajs = loop
    norms = [np.linalg.norm(Edmd(alpha=a).fit(trajs).koopman_matrix_) for a in (0.0, 1.0, 100.0)]
    assert norms[0] > norms[1] > norms[2]


def test_ridge_convention_matches_normal_equations(loop):
    *_, trajs = loop
    est = Edmd(lifting=[Polynomial(2)], alpha=3.0).fit(trajs)
    G, H = est.snapshots_.G, est.snapshots_.H
    np.testing.assert_allclose(
        est.koopman_matrix_, G @ np.linalg.inv(H + 3.0 * np.eye(H.shape[0])), rtol=1e-8, atol=1e-10
    )


def test_closed_form_equals_generalized_ridge_formula(loop):
    """U^p = G_2 S^T (S H_alpha S^T)^-1: the paper's constrained problem in closed form."""
    A_p, B_p, controller, trajs = loop
    noisy = [
        Trajectory(x=t.x + 1e-3 * np.sin(np.arange(t.n_samples))[:, None], r=t.r, f=t.f, xc=t.xc, dt=t.dt)
        for t in trajs
    ]
    est = ClEdmd(controller, lifting=[Polynomial(2)], alpha=2.0, measured=[0]).fit(noisy)
    G, H, S = est.snapshots_.G, est.snapshots_.H, est.plant_input_map_
    n_c = controller.n_states
    H_alpha = H + 2.0 * np.eye(H.shape[0])
    expected = G[n_c:] @ S.T @ np.linalg.inv(S @ H_alpha @ S.T)
    np.testing.assert_allclose(est.plant_koopman_matrix_, expected, rtol=1e-7, atol=1e-9)


def test_input_lifting(loop):
    *_, trajs = loop
    est = Edmd(input_lifting=[Polynomial(2)]).fit(trajs)
    assert est.model_.B.shape[1] == 2  # u, u^2
    assert np.all(np.isfinite(est.predict(trajs[0])))
    with pytest.raises(ValueError, match="pointwise"):
        Edmd(input_lifting=[Delay(1)]).fit(trajs)


def test_relift_and_linear_propagation_agree_for_linear_lifting(loop):
    *_, trajs = loop
    est = Edmd(lifting=[Delay(3)]).fit(trajs[:2])
    np.testing.assert_allclose(est.predict(trajs[2]), est.predict(trajs[2], relift=False), atol=1e-9)


def test_relift_differs_from_linear_propagation_for_nonlinear_lifting(loop):
    *_, trajs = loop
    est = Edmd(lifting=[Polynomial(3)], alpha=1e-3).fit(trajs[:2])
    a, b = est.predict(trajs[2]), est.predict(trajs[2], relift=False)
    assert np.all(np.isfinite(a)) and np.abs(a - b).max() > 1e-9


def test_initial_condition_samples_are_copied(loop):
    *_, trajs = loop
    est = Edmd(lifting=[Delay(4)]).fit(trajs[:2])
    pred = est.predict(trajs[2])
    np.testing.assert_array_equal(pred[:5], trajs[2].x[:5])


def test_batched_simulation_equals_per_episode(loop):
    *_, trajs = loop
    model = (
        ClEdmd(pid_position_controller(), lifting=[Polynomial(2), Delay(1)], alpha=1e-2, measured=[0])
        .fit(trajs[:2])
        .closed_loop_model_
    )
    d = model.n_delays
    x_init = np.stack([t.x[: d + 1] for t in trajs])
    v = np.stack([model.inputs_of(t) for t in trajs])
    p0 = np.stack([t.xc[d] for t in trajs])
    batched, _ = model.simulate(x_init, v, p0)
    for i, t in enumerate(trajs):
        np.testing.assert_allclose(batched[i], model.predict(t), rtol=1e-12, atol=1e-12)


def test_predict_many_equals_predict_for_episodes_of_any_length(loop):
    *_, trajs = loop
    model = (
        ClEdmd(pid_position_controller(), lifting=[Polynomial(2), Delay(1)], alpha=1e-2, measured=[0])
        .fit(trajs[:2])
        .closed_loop_model_
    )
    episodes = [trajs[0], trajs[1].skip(7), trajs[2]]  # two lengths
    many = model.predict_many(episodes)
    assert len(many) == 3
    for t, x in zip(episodes, many):
        assert x.shape == t.x.shape
        np.testing.assert_allclose(x, model.predict(t), rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="controller state"):
        model.predict_many([replace(trajs[0], xc=None)])


def test_diverging_prediction_is_non_finite_and_does_not_raise():
    rng = np.random.default_rng(0)
    n = 2000
    x = np.cumsum(rng.normal(size=(n, 1)), axis=0) * 0.01
    traj = Trajectory(x=x, u=rng.normal(size=(n, 1)))
    est = Edmd(lifting=[GaussianRbf(5, seed=0)]).fit([traj])
    unstable = replace(est.model_, A=3.0 * est.model_.A)
    pred = unstable.predict(traj)
    assert not np.all(np.isfinite(pred))
    assert r2_score(x, pred) == -np.inf


def test_structure_helpers_reproduce_simulated_signals(loop):
    A_p, B_p, controller, trajs = loop
    t = trajs[0]
    xc = controller_states(controller, t.r, t.x[:, [0]])
    np.testing.assert_allclose(xc, t.xc, atol=1e-12)
    np.testing.assert_allclose(plant_input(controller, t.xc, t.r, t.x[:, [0]], t.f), t.u, atol=1e-12)
    C_p = output_selection(2, [0])
    S = plant_input_map(controller, C_p, 1)
    psi = np.hstack([t.xc, t.x, t.r, t.f])
    np.testing.assert_allclose(psi @ S.T, np.hstack([t.x, t.u]), atol=1e-12)
    A_f, B_f = closed_loop_matrices(A_p, B_p, controller, C_p, 1)
    theta = np.hstack([t.xc, t.x])
    np.testing.assert_allclose(theta[:-1] @ A_f.T + np.hstack([t.r, t.f])[:-1] @ B_f.T, theta[1:], atol=1e-12)


@pytest.mark.parametrize(
    "lifting",
    [
        [Polynomial(2), Delay(3)],  # pointwise head, one delay: the ring path
        [Polynomial(3), Delay(4), Constant()],  # the ring path with three factors and an affine term
        [Polynomial(1), Delay(1)],  # the ring path with the identity's features
        [Delay(2), GaussianRbf(6, shape=0.5, seed=1)],  # delays then RBF: the ring with a radial basis
        [Polynomial(2), Trigonometric([0, 1]), Delay(3)],  # the ring, a head applied as it is
        [Trigonometric([1]), Delay(2), ThinPlateRbf(5, seed=3), Constant()],  # ... with RBF and an affine term
        [Delay(2), Polynomial(2)],  # a step after the delays: the history path
        [Polynomial(2)],  # no delays
        [Polynomial(2), Delay(3), Constant()],  # the shift path with an affine term
        [Delay(2), Constant(), GaussianRbf(4, seed=2)],  # a constant inside the history path
        [Polynomial(2), Delay(3), CoulombFriction(0, 2, 0.05), Constant()],  # friction: the ring path
        [Delay(4), ThinPlateRbf(5, seed=3), CoulombFriction(0, 3, 0.05), CoulombFriction(1, 1, 0.1), Constant()],
        [Polynomial(2), Delay(3), Constant(), CoulombFriction(0, 2, 0.05)],  # friction after a constant: history
    ],
)
def test_fast_predictor_equals_naive_relifting(loop, lifting):
    from naive_reference import naive_predict

    *_, trajs = loop
    model = ClEdmd(pid_position_controller(), lifting=lifting, alpha=1e-3, measured=[0]).fit(trajs[:2])
    cl = model.closed_loop_model_
    t = trajs[2]
    d = cl.n_delays
    expected = naive_predict(cl, t.x[: d + 1], cl.inputs_of(t), t.xc[d])
    np.testing.assert_allclose(cl.predict(t), expected, rtol=1e-10, atol=1e-12)
    plant = model.plant_model_
    np.testing.assert_allclose(plant.predict(t), naive_predict(plant, t.x[: d + 1], t.u), rtol=1e-10, atol=1e-12)


def test_every_search_lifting_takes_the_ring(loop):
    # The ring is the fast path (about 10x the history loop on the search's liftings): a lifting the
    # search can choose that fell back to the history loop would still predict right, only slowly.
    from qube_koopman.identify.model_selection.search import LiftingSpec
    from qube_koopman.identify.models.simulate import _RingLayout

    *_, trajs = loop
    for spec in (
        LiftingSpec(delays=12, poly=3, friction=True, const=True),
        LiftingSpec(delays=12, poly=1, trig=True, rbf=5, friction=True, const=True),
    ):
        model = ClEdmd(pid_position_controller(), lifting=spec.steps(), alpha=1e-3, measured=[0]).fit(trajs[:2])
        plant = model.plant_model_
        At = np.ascontiguousarray(plant.A.T[None, :, :2])
        ring = _RingLayout.of(plant.lifting, 0, 2, At)
        assert ring is not None and len(ring.friction) == 1, spec.label()


def test_constant_lifting_appends_a_one_and_makes_the_model_affine(loop):
    *_, trajs = loop
    lifting = Lifting([Polynomial(2), Delay(2), Constant()]).fit([t.x for t in trajs])
    z = lifting.transform(trajs[0].x)
    assert lifting.feature_names_out_[-1] == "1"
    np.testing.assert_array_equal(z[:, -1], 1.0)
    # An offset on the data: the affine model fits it exactly where the linear one cannot.
    shifted = [replace(t, x=t.x + 0.5) for t in trajs]
    affine = Edmd(lifting=[Constant()], alpha=0.0).fit(shifted)
    linear = Edmd(alpha=0.0).fit(shifted)
    assert r2_score(shifted[0].x, affine.predict(shifted[0])) > 1 - 1e-8
    assert r2_score(shifted[0].x, linear.predict(shifted[0])) < 1 - 1e-4


def test_a_model_that_diverges_before_the_scored_samples_scores_minus_infinity(loop):
    # The simulator drops a model once all its predictions diverged; scoring from a later
    # sample must still see it as diverged, not as a perfect fit of samples it never produced.
    from qube_koopman.identify.model_selection.sweep import _score

    *_, trajs = loop
    model = (
        ClEdmd(pid_position_controller(), lifting=[Polynomial(2), Delay(2)], alpha=1e-3, measured=[0])
        .fit(trajs[:2])
        .closed_loop_model_
    )
    unstable = replace(model, A=model.A * 50.0)
    start = trajs[2].n_samples - 5
    scores = _score([model, unstable], [trajs[2]], "cl", relift=True, start=start)
    assert np.isfinite(scores[0]) and scores[1] == -np.inf
    x = unstable.predict(trajs[2])
    assert not np.isfinite(x[start:]).any() and np.isfinite(x[:3]).all()


def _random_models(n_models: int, n_lifted: int, n_inputs: int, n_p: int, seed: int, shared: bool):
    """Contracting random Koopman matrices; the first ``n_p`` rows the same in every model when ``shared``."""
    rng = np.random.default_rng(seed)
    A = rng.uniform(-1, 1, (n_models, n_lifted, n_lifted)) / n_lifted
    B = rng.uniform(-1, 1, (n_models, n_lifted, n_inputs)) / n_lifted
    if shared:
        A[:, :n_p], B[:, :n_p] = A[:1, :n_p], B[:1, :n_p]
    return A, B


@pytest.mark.parametrize(
    "lifting",
    [
        [Polynomial(2), Delay(3), Constant()],  # the ring
        [Delay(2), Polynomial(2)],
    ],
)  # the history loop
@pytest.mark.parametrize("n_p", [0, 9])  # 9 passthrough rows shared by every model: one product for all
def test_batched_paired_and_shared_row_predictions_are_each_models_own(loop, lifting, n_p):
    from qube_koopman.identify.models.simulate import simulate_batch, simulate_chunks

    *_, trajs = loop
    fitted = Lifting(lifting).fit([t.x for t in trajs])
    d, n_lifted, n_in = fitted.n_delays_, n_p + fitted.n_features_out_, 2
    A, B = _random_models(6, n_lifted, n_in, n_p, seed=4, shared=True)
    rng = np.random.default_rng(5)
    # Two groups of three models, each group on its own two episodes (the folds of a calibration).
    x_init = np.stack([np.stack([t.x[k : k + d + 1] for t in trajs[:2]]) for k in (0, 7)])
    v = rng.uniform(-1, 1, (2, 2, 120, n_in))
    p0 = rng.uniform(-1, 1, (2, 2, n_p)) if n_p else None
    chunks = []
    simulate_chunks(
        A,
        B,
        fitted,
        n_p,
        x_init,
        v,
        p0,
        True,
        lambda k0, chunk, models: chunks.append((k0, chunk.copy(), models.copy())),
        paired=True,
    )
    paired = np.concatenate([c for _, c, _ in chunks])  # (samples, models, episodes, n_p + states)
    assert all(m.tolist() == list(range(6)) for *_, m in chunks)
    for i in range(6):  # each model alone on its group's episodes: no shared rows, no pairing
        g = i // 3
        x, p = simulate_batch(A[i : i + 1], B[i : i + 1], fitted, n_p, x_init[g], v[g], None if p0 is None else p0[g])
        np.testing.assert_allclose(paired[:, i, :, n_p:], np.moveaxis(x[0, :, d + 1 :], 1, 0), rtol=1e-10, atol=1e-12)
        if n_p:
            np.testing.assert_allclose(
                paired[:, i, :, :n_p], np.moveaxis(p[0, :, d + 1 :], 1, 0), rtol=1e-10, atol=1e-12
            )
    # The shared rows' one product gives what the per-model products give (all six on one group's episodes).
    x_all, _ = simulate_batch(A, B, fitted, n_p, x_init[0], v[0], None if p0 is None else p0[0])
    x_one, _ = simulate_batch(A[4:5], B[4:5], fitted, n_p, x_init[0], v[0], None if p0 is None else p0[0])
    np.testing.assert_allclose(x_all[4], x_one[0], rtol=1e-10, atol=1e-12)


def test_the_ring_steps_shared_passthrough_rows_once_for_all_models():
    from qube_koopman.identify.models.simulate import _RingLayout

    fitted = Lifting([Polynomial(2), Delay(3)]).fit([np.random.default_rng(0).normal(size=(50, 2))])
    n_lifted = 9 + fitted.n_features_out_
    for shared in (True, False):
        A, _ = _random_models(4, n_lifted, 1, 9, seed=1, shared=shared)
        At = np.ascontiguousarray(A[:, :11, :].transpose(0, 2, 1))
        ring = _RingLayout.of(fitted, 9, 2, At)
        assert (ring.shared is not None) == shared
        assert ring.perms[0].shape[-1] == (2 if shared else 11)


@pytest.mark.parametrize(
    "lifting",
    [
        [Polynomial(2), Delay(3), CoulombFriction(0, 2, 0.05), Constant()],
        [Delay(4), ThinPlateRbf(5, seed=3), CoulombFriction(0, 3, 0.05), CoulombFriction(1, 1, 0.1), Constant()],
    ],
)
@pytest.mark.parametrize("shared", [False, True])
def test_a_loop_of_many_states_shifts_its_delayed_features_and_predicts_as_relifting_does(loop, lifting, shared):
    # A controller of many states (a designed one) makes the ring keep one copy of A^T and shift the
    # delayed features instead of rotating through a permuted copy per slot: the same predictions.
    from naive_reference import naive_predict
    from qube_koopman.identify.models.model import KoopmanModel
    from qube_koopman.identify.models.simulate import _SHIFT_FROM_ROWS, _RingLayout, simulate_batch

    *_, trajs = loop
    fitted = Lifting(lifting).fit([t.x for t in trajs])
    n_p, m, d = 9, fitted.n_features_in_, fitted.n_delays_
    assert n_p + m >= _SHIFT_FROM_ROWS
    A, B = _random_models(3, n_p + fitted.n_features_out_, 2, n_p, seed=6, shared=shared)
    A *= 0.5  # a thin-plate basis grows with the state: keep these random loops bounded
    At = np.ascontiguousarray(A[:, : n_p + m, :].transpose(0, 2, 1))
    ring = _RingLayout.of(fitted, n_p, m, At)
    assert ring is not None and ring.shift and len(ring.perms) == 1 and (ring.shared is not None) == shared
    assert not _RingLayout.of(fitted, 0, m, np.ascontiguousarray(At[:, n_p:, n_p:])).shift  # the rig's size: the ring
    rng = np.random.default_rng(7)
    x_init = np.stack([t.x[: d + 1] for t in trajs[:2]])
    v = rng.uniform(-0.2, 0.2, (2, 80, 2))
    p0 = rng.uniform(-0.2, 0.2, (2, n_p))
    x, _ = simulate_batch(A, B, fitted, n_p, x_init, v, p0)
    assert np.isfinite(x).all()
    for i in range(3):
        model = KoopmanModel(A[i], B[i], fitted, ("r", "f"), n_passthrough=n_p)
        for e in range(2):
            np.testing.assert_allclose(x[i, e], naive_predict(model, x_init[e], v[e], p0[e]), rtol=1e-10, atol=1e-12)
