"""Paper section 4: the Duffing experiment and its reproduction."""

import json

import numpy as np
import pytest

from daq.controller import pi_controller
from identify.cli.reproduce import main
from identify.reproduce.duffing import reproduce_duffing
from sim.duffing import coloured_noise, duffing_experiment, duffing_pi_controller, random_dwell_prbs


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
