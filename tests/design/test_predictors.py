"""The plant's multi-step predictors (design.predictors): the model's re-lifted one, Korda & Mezić's, the MPC's.

- a linear lifting (order-1 monomials, delays, a constant) whose delay rows shift exactly: the lifted map
  propagated without re-lifting is the re-lifted prediction, and without the constant the MPC's plant on
  its history is too;
- a polynomial lifting: the two differ, and Korda & Mezić's prediction is ``C (A^k z_0 + sum A^j B u)``
  propagated by hand;
- the scores: a model predicting its own noise-free episodes scores R^2 1; a plant the design refuses
  (Coulomb friction) is scored without the MPC's predictor, saying why.
"""

from __future__ import annotations

import numpy as np
import pytest

from qube_koopman.design.predictors import PREDICTORS, lifted_condensed, predict_windows, score_predictors
from qube_koopman.identify import Constant, CoulombFriction, Delay, KoopmanModel, Lifting, Polynomial, Trajectory

DT = 0.002
NAMES = ("theta", "alpha")


def _linear_model(d: int, const: bool, seed: int = 0) -> KoopmanModel:
    """A pendulum-like plant over ``d`` delays of order-1 monomials; its delay rows shift and its constant stays 1."""
    rng = np.random.default_rng(seed)
    lifting = Lifting([Polynomial(1), Delay(d)] + ([Constant()] if const else [])).fit([np.zeros((50, 2))], NAMES)
    n = lifting.n_features_out_
    A = np.zeros((n, n))
    A[:2, :4] = [[1.9, 0.0, -0.9, 0.0], [0.0, 2.02, 0.0, -1.0]]
    A[:2, : 2 * (d + 1)] += 0.01 * rng.standard_normal((2, 2 * (d + 1)))
    A[2 : 2 * (d + 1), : 2 * d] = np.eye(2 * d)  # x[k-j] of the next sample is x[k-j+1] of this one
    if const:
        A[:2, -1] = [1e-3, -2e-3]
        A[-1, -1] = 1.0
    B = np.zeros((n, 1))
    B[:2, 0] = [2e-3, -2e-3]
    return KoopmanModel(A, B, lifting, ("u",), dt=DT)


def _polynomial_model(d: int, seed: int = 1) -> KoopmanModel:
    """Monomials to order 2 over ``d`` delays, every row of ``A`` fitted-looking (none an exact shift or square)."""
    rng = np.random.default_rng(seed)
    lifting = Lifting([Polynomial(2), Delay(d)]).fit([np.zeros((50, 2))], NAMES)
    n = lifting.n_features_out_
    A = 0.9 * np.eye(n, k=-5) + 0.05 * rng.standard_normal((n, n)) / np.sqrt(n)
    A[:2, :2] += [[1.0, 0.02], [0.0, 1.02]]
    B = 0.01 * rng.standard_normal((n, 1))
    return KoopmanModel(A, B, lifting, ("u",), dt=DT)


def _windows(model: KoopmanModel, n: int, K: int, scale: float, seed: int = 2):
    rng = np.random.default_rng(seed)
    return scale * rng.standard_normal((n, model.n_delays + 1, 2)), rng.standard_normal((n, K, 1))


@pytest.mark.parametrize("const", [False, True])
def test_for_a_linear_lifting_the_lifted_map_is_the_relifted_prediction(const):
    model = _linear_model(4, const)
    histories, inputs = _windows(model, 7, 40, 0.05)
    relifted = predict_windows(model, histories, inputs, "relifted")
    lifted = predict_windows(model, histories, inputs, "lifted")
    assert relifted.shape == (7, 40, 2) and np.abs(relifted).max() > 0.1  # the pendulum falls: a real test
    np.testing.assert_allclose(lifted, relifted, rtol=1e-9, atol=1e-12)
    upright = predict_windows(model, histories, inputs, "upright")
    if const:  # the MPC leaves the affine term out: it differs by the constant's response alone
        assert np.abs(upright - relifted).max() > 1e-3
    else:
        np.testing.assert_allclose(upright, relifted, rtol=1e-9, atol=1e-12)


def test_for_a_polynomial_lifting_the_lifted_map_is_a_k_z0_plus_the_inputs_and_not_the_relifted_one():
    model = _polynomial_model(3)
    K = 25
    histories, inputs = _windows(model, 5, K, 0.3)
    lifted = predict_windows(model, histories, inputs, "lifted")
    by_hand = np.empty_like(lifted)
    for w in range(len(histories)):
        z0 = model.lifting.transform(histories[w])[-1]
        for k in range(1, K + 1):  # x_{k} = C (A^k z_0 + sum_{j<k} A^(k-1-j) B u_j)
            z = np.linalg.matrix_power(model.A, k) @ z0
            for j in range(k):
                z += np.linalg.matrix_power(model.A, k - 1 - j) @ model.B @ inputs[w, j]
            by_hand[w, k - 1] = z[:2]
    np.testing.assert_allclose(lifted, by_hand, rtol=1e-10, atol=1e-13)
    relifted = predict_windows(model, histories, inputs, "relifted")
    np.testing.assert_allclose(relifted[:, 0], lifted[:, 0], rtol=1e-12)  # one step: the same rows of the same z_0
    assert np.abs(relifted[:, 1:] - lifted[:, 1:]).max() > 1e-3 * np.abs(lifted).max()
    Phi, Gamma = lifted_condensed(model, K)
    assert Phi.shape == (K, 2, model.A.shape[0]) and Gamma.shape == (K, 2, K)
    j, i = np.triu_indices(K, k=1)  # predicted sample j, input i > j: it acts on sample i, not before
    assert np.all(Gamma[j, :, i] == 0) and np.all(Gamma[i, :, j] != 0)


def _episodes(model: KoopmanModel, n: int, seed: int = 3) -> list[Trajectory]:
    """The model's own noise-free episodes under a small random input (short: the plant is unstable)."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        u = 0.2 * rng.standard_normal((160, 1))
        x0 = 1e-3 * rng.standard_normal((model.n_delays + 1, 2))
        x, _ = model.simulate(x0, u)
        x[: model.n_delays + 1] = x0
        out.append(Trajectory(x=x, u=u, name=f"e{i}", dt=DT))
    return out


def test_a_model_predicting_its_own_episodes_scores_one_with_every_predictor():
    model = _linear_model(3, False)
    scores = score_predictors(model, _episodes(model, 2), [1, 5, 20], n_starts=12)
    assert scores.predictors == PREDICTORS and scores.refused == "" and scores.n_windows == 24
    assert scores.r2.shape == scores.rms.shape == (3, 3, 2) and not scores.n_diverged.any()
    assert scores.episode_rms.shape == (2, 3, 3, 2)
    np.testing.assert_allclose(scores.r2, 1.0, atol=1e-9)
    assert np.all(scores.rms < 1e-9)


def test_a_plant_the_design_refuses_is_scored_without_the_mpcs_predictor_saying_why():
    lifting = Lifting([Delay(2), CoulombFriction(0, 2, 0.002)]).fit([np.zeros((50, 2))], NAMES)
    n = lifting.n_features_out_
    A = np.eye(n, k=-2)
    A[:2, :2] = np.eye(2)
    B = np.zeros((n, 1))
    B[:2, 0] = [1e-3, -1e-3]
    model = KoopmanModel(A, B, lifting, ("u",), dt=DT)
    scores = score_predictors(model, _episodes(model, 1), [1, 10], n_starts=5)
    assert scores.predictors == ("relifted", "lifted") and "Coulomb friction" in scores.refused
    assert scores.r2.shape == (2, 2, 2) and np.all(np.isfinite(scores.r2))
