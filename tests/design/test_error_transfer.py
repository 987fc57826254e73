"""The held-out error propagated through another loop (design.error_transfer), against a known answer.

A linear "rig" (the model plant with its input gain 10 % stronger, and white noise on both encoders)
runs under a gentle controller ``K0`` (the held-out episodes) and under a harder one ``K1`` (the
design). The model predicts both loops without the gain error or the noise. From the ``K0``
episodes alone (their band spectra, as a model file keeps them), the propagation must give the
``K1`` loop's measured J and voltage RMS; the training controller's ratio, which the design used
before, must miss the voltage (the harder loop turns more of the noise into voltage). Everything
is seeded: the answer is one number, checked against a simulation of the same rig.
"""

from __future__ import annotations

import numpy as np
import pytest

from qube_koopman.design import Weights, design_lq, linear_plant
from qube_koopman.design.error_transfer import loop_spectra, propagate_error
from qube_koopman.design.predict import rig_excitations
from qube_koopman.identify.uncertainty import loop_figures
from qube_koopman.identify.uncertainty.spectra import ErrorSpectra, band_sums, error_spectra

from test_design_uncertainty import _plant

SKIP = 500
NOISE = 1e-3  # rad RMS on each encoder: a few counts' quantization
#: The QUBE's references scaled to this plant (its input gain needs tens of volts for the QUBE's own).
REFERENCE_SCALE = 0.1
#: The rig's input gain over the model's.
GAIN = 1.1


def _run(plant, controller, excitations, gain: float = 1.0, noise: float = 0.0, seed: int = 0):
    """The plant (its input column times ``gain``) under ``controller`` on the excitations' references (their
    feedforward is the QUBE's, not this plant's: left out), the encoders ``noise`` rad RMS white: measured
    angles (E, T, 2), voltage (E, T), target theta (E, T)."""
    rng = np.random.default_rng(seed)
    m, n = plant.n_measured, plant.n_states
    r = REFERENCE_SCALE * np.stack([np.column_stack([e.target_theta, e.target_alpha]) for e in excitations])
    E, T = r.shape[:2]
    A, B, C, D = (np.asarray(getattr(controller, k)) for k in "ABCD")
    s, xc = np.zeros((E, n)), np.zeros((E, A.shape[0]))
    y, u = np.zeros((E, T, m)), np.zeros((E, T))
    for k in range(T):
        y[:, k] = s[:, :m] + noise * rng.standard_normal((E, m))
        e = r[:, k] - y[:, k]
        u[:, k] = (xc @ C.T + e @ D.T)[:, 0]
        xc = xc @ A.T + e @ B.T
        s = s @ plant.F.T + gain * u[:, k, None] * plant.G[:, 0] + plant.c
    return y, u, r[:, :, 0]


def _figures(y, u, target) -> np.ndarray:
    return np.array([loop_figures(y[i], target[i], u[i], SKIP) for i in range(len(y))])


@pytest.fixture(scope="module")
def loops():
    plant = linear_plant(_plant(d=3))
    gentle = design_lq(plant, Weights(r_voltage=1.0)).controller
    hard = design_lq(plant, Weights(r_voltage=0.01)).controller
    held_out, design = rig_excitations(3, 8, 12.0), rig_excitations(4, 8, 12.0)
    truth0 = _run(plant, gentle, held_out, gain=GAIN, noise=NOISE, seed=1)
    model0 = _run(plant, gentle, held_out)
    spectra = error_spectra(truth0[0], model0[0], model0[1], model0[2], [gentle] * 8, plant.dt, SKIP)
    figures = np.stack([_figures(*truth0), _figures(*model0)], axis=1)  # (n, [measured, predicted], 3)
    return plant, gentle, hard, design, spectra, figures


def _propagated(loops, controller, excitations):
    plant, _, _, _, spectra, figures = loops
    y, u, target = _run(plant, controller, excitations)
    uu, eu = loop_spectra(y[:, :, 0], target, y[:, :, 1], u, spectra.edges, spectra.dt, SKIP)
    predicted = _figures(y, u, target)
    J, V = np.mean(predicted[:, 0]), np.sqrt(np.mean(predicted[:, 1] ** 2))
    found = propagate_error(spectra, figures, plant, controller, uu, eu, (J, V))
    return J, V, found


def test_the_bands_add_up_to_the_mean_squares_and_survive_the_model_file():
    rng = np.random.default_rng(0)
    a = rng.standard_normal((1001, 2)).cumsum(axis=0)
    b = rng.standard_normal((1001, 1))
    edges = np.array([0.0, 0.3, 2.0, 40.0, 250.0])
    np.testing.assert_allclose(band_sums(edges, 0.002, a, b).sum(axis=0).real, a.T @ b / len(a), rtol=1e-10)
    np.testing.assert_allclose(band_sums(edges, 0.002, a, a).sum(axis=0).real, a.T @ a / len(a), rtol=1e-10)


def test_no_spectra_of_a_diverged_or_too_short_held_out_prediction():
    x = np.zeros((600, 2))
    diverged = x.copy()
    diverged[550:] = np.nan
    args = ([np.zeros(600)], [np.zeros(600)])
    pd = design_lq(linear_plant(_plant(d=3)), Weights()).controller
    with pytest.raises(ValueError, match="held-out episode 0: its prediction diverged"):
        error_spectra([x], [diverged], *args, [pd], 0.002, SKIP)
    with pytest.raises(ValueError, match="2 samples or more past the first 500"):
        error_spectra([x[:501]], [x[:501]], [np.zeros(501)], [np.zeros(501)], [pd], 0.002, SKIP)


def test_the_spectra_come_back_from_the_model_file(loops):
    spectra = loops[4]
    again = ErrorSpectra.from_dict(spectra.as_dict())
    for name in ("edges", "centres", "controller", "error", "error_input", "input", "tracking_input"):
        np.testing.assert_allclose(getattr(again, name), getattr(spectra, name), rtol=1e-6, atol=0, err_msg=name)
    assert again.dt == spectra.dt and again.n_episodes == 8


def test_under_the_held_out_episodes_own_controller_the_propagation_gives_back_their_figures(loops):
    plant, gentle, _, excitations, spectra, figures = loops
    measured = _figures(*_run(plant, gentle, excitations, gain=GAIN, noise=NOISE, seed=2))
    J, V, found = _propagated(loops, gentle, excitations)
    assert J * np.exp(found.shift[0]) == pytest.approx(np.mean(measured[:, 0]), rel=0.01)
    assert V * np.exp(found.shift[1]) == pytest.approx(np.sqrt(np.mean(measured[:, 1] ** 2)), rel=0.01)
    assert np.all(np.abs(found.residuals) < 0.03), found.residuals  # each held-out episode given back too


def test_under_a_harder_controller_the_propagation_predicts_the_rigs_voltage_where_the_ratio_misses(loops):
    plant, _, hard, excitations, spectra, figures = loops
    measured = _figures(*_run(plant, hard, excitations, gain=GAIN, noise=NOISE, seed=3))
    J_true, V_true = np.mean(measured[:, 0]), np.sqrt(np.mean(measured[:, 1] ** 2))
    J, V, found = _propagated(loops, hard, excitations)
    assert J * np.exp(found.shift[0]) == pytest.approx(J_true, rel=0.01)
    assert V * np.exp(found.shift[1]) == pytest.approx(V_true, rel=0.01)
    ratio = np.exp(np.mean(np.log(figures[:, 0, 1] / figures[:, 1, 1])))  # the training controller's ratio
    assert abs(V * ratio / V_true - 1) > 0.05, (V * ratio, V_true)  # what the design said before misses
    assert V_true > 1.05 * V  # and the model alone would too
