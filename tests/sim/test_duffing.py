"""Paper section 4: the Duffing experiment and its reproduction."""

import json

import numpy as np
import pytest

from qube_koopman.core.controller import pi_controller
from qube_koopman.reproduce.cli.reproduce import main
from qube_koopman.reproduce.duffing_study import reproduce_duffing
from qube_koopman.sim.duffing import coloured_noise, duffing_experiment, duffing_pi_controller, random_dwell_prbs


def test_pi_controller_matches_the_zoh_discretization():
    ours = duffing_pi_controller(0.01)
    built = pi_controller(1.0, 1.0, 0.01, method="zoh")
    for a, b in zip((ours.A, ours.B, ours.C, ours.D), (built.A, built.B, built.C, built.D)):
        np.testing.assert_allclose(a, b, atol=1e-15)


def test_prbs_levels_and_dwell():
    rng = np.random.default_rng(0)
    r = random_dwell_prbs(1000, rng)
    assert set(np.unique(r)) == {-1.0, 1.0}
    edges = np.flatnonzero(np.diff(r)) + 1
    dwells = np.diff(edges)
    assert dwells.min() >= 29 and dwells.max() < 199


def test_coloured_noise_is_low_pass():
    rng = np.random.default_rng(0)
    n = coloured_noise(20000, rng)
    spectrum = np.abs(np.fft.rfft(n)) ** 2
    freqs = np.fft.rfftfreq(n.size, 0.01)
    # 12th order at 5 Hz: white noise would give a ratio near 1
    assert spectrum[freqs > 10].mean() < 1e-4 * spectrum[freqs < 4].mean()


def test_experiment_layout_is_seeded():
    a = duffing_experiment(seed=7)
    b = duffing_experiment(seed=7)
    assert len(a.train) == 10 and len(a.test) == 1
    assert all(e.noisy for e in a.train) and not a.test[0].noisy
    assert a.train[0].t.size == 1000 and a.train[0].t[1] == pytest.approx(0.01)
    np.testing.assert_array_equal(a.train[3].measured, b.train[3].measured)
    # the controller saw the noisy position: u = C xc + D (r - y)
    e = a.train[0]
    np.testing.assert_allclose(e.force, 0.01 * e.controller_state[:, 0] + (e.reference - e.measured))


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1234, 1, 2])
def test_reproduction_within_the_expected_bands(seed):
    """EDMD and CL EDMD plant NRMSE in [2.0, 4.5] %, ARX worse than both (the issue's targets)."""
    res = reproduce_duffing(seed)
    for key in ("edmd", "cl_edmd"):
        assert 2.0 <= res[key]["nrmse_pct"] <= 4.5
        assert abs(res[key]["nme_pct"]) < 1.0
    assert res["arx"]["nrmse_pct"] > max(res["edmd"]["nrmse_pct"], res["cl_edmd"]["nrmse_pct"])
    assert res["cl_arx"]["nrmse_pct"] > res["arx"]["nrmse_pct"]


def test_cli_writes_the_table_and_json(tmp_path, capsys):
    assert main(["duffing", "--out", str(tmp_path / "out"), "--seed", "3"]) == 0
    printed = capsys.readouterr().out
    assert "CL EDMD" in printed and "paper" in printed
    data = json.loads((tmp_path / "out" / "duffing.json").read_text())
    for key in ("edmd", "cl_edmd", "arx", "cl_arx"):
        assert set(data[key]) == {"nme_pct", "nrmse_pct"}
        assert np.isfinite(data[key]["nrmse_pct"])
    assert data["seed"] == 3


def test_cli_errors_are_clean(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main(["duffing", "--out", str(blocker / "sub")]) == 2
    assert "cannot create output folder" in capsys.readouterr().err
    assert main(["duffing", "--out", str(tmp_path), "--alpha", "-1"]) == 2
    assert "--alpha must be" in capsys.readouterr().err


@pytest.mark.slow
def test_cl_edmd_and_edmd_solve_different_problems_on_the_duffing_data():
    """Each estimator matches its own normal equations (built here from the raw snapshots,
    the generalized ridge of the paper's constrained problem for CL EDMD) and not the other's: with a
    real regularization the closed-loop penalty ||U^p S||^2 and EDMD's ||U^p||^2 give different plants."""
    from qube_koopman.identify import ClEdmd, Edmd
    from qube_koopman.reproduce.duffing_study import duffing_lifting, duffing_trajectory

    experiment = duffing_experiment(seed=5)
    dt, ctrl = experiment.controller.dt, experiment.controller
    train = [duffing_trajectory(e, f"train{i}", dt) for i, e in enumerate(experiment.train)]
    alpha = 10.0
    cl = ClEdmd(ctrl, lifting=duffing_lifting(5), alpha=alpha).fit(train)
    edmd = Edmd(lifting=duffing_lifting(5), alpha=alpha).fit(train)
    lifting, d = cl.plant_model_.lifting, cl.plant_model_.n_delays
    n = lifting.n_features_out_
    # Raw snapshots: theta^p_k, controller state, reference and plant input of every episode.
    z = [lifting.transform(t.x) for t in train]
    psi_p = np.vstack([np.hstack([zi[:-1], t.u[d:-1]]) for zi, t in zip(z, train)])  # [theta^p; u]
    psi_cl = np.vstack([np.hstack([t.xc[d:-1], zi[:-1], t.r[d:-1]]) for zi, t in zip(z, train)])
    target = np.vstack([zi[1:] for zi in z])
    # S maps [x^c; theta^p; r] to [theta^p; u] with u = C^c x^c + D^c (r - theta^p_0).
    S = np.zeros((n + 1, 1 + n + 1))
    S[:n, 1 : n + 1] = np.eye(n)
    S[n, 0], S[n, 1], S[n, n + 1] = ctrl.C[0, 0], -ctrl.D[0, 0], ctrl.D[0, 0]
    np.testing.assert_allclose(psi_cl @ S.T, psi_p, atol=1e-9)
    H = psi_cl.T @ psi_cl + alpha * np.eye(psi_cl.shape[1])
    U_cl = target.T @ psi_cl @ S.T @ np.linalg.inv(S @ H @ S.T)
    U_edmd = target.T @ psi_p @ np.linalg.inv(psi_p.T @ psi_p + alpha * np.eye(n + 1))
    scale = np.linalg.norm(U_cl)
    assert np.linalg.norm(cl.plant_koopman_matrix_ - U_cl) / scale < 1e-6
    assert np.linalg.norm(edmd.koopman_matrix_ - U_edmd) / scale < 1e-6
    assert np.linalg.norm(U_cl - U_edmd) / scale > 1e-3  # the two problems really differ
