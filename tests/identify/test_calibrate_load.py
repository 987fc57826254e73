"""The arm's random load estimated from logs: reconstructed by the arm's equation, its statistics by a spectral fit."""

from __future__ import annotations

import math

import numpy as np
import pytest

from _episodes import QUBE_PD
from qube_koopman.identify.calibrate.load_fit import fit_load, load_fit_check, reconstruct_load
from qube_koopman.sim.pendulum import PendulumParameters, RandomLoad, SensorModel, simulate_closed_loop

DT = 1 / 500


def twin_logs(load: RandomLoad, n: int = 12, seconds: float = 16.0, seed: int = 0):
    """Closed-loop twin episodes under the rig's PD with a known load: a small random feedforward, no reference."""
    rng = np.random.default_rng(seed)
    steps = int(seconds / DT)
    ff = np.repeat(rng.choice([-0.3, 0.3], (steps // 50 + 1, n)), 50, axis=0)[:steps]
    x0 = np.column_stack([np.zeros(n), rng.uniform(-0.01, 0.01, n), np.zeros((n, 2))])
    run = simulate_closed_loop(
        x0,
        QUBE_PD,
        np.zeros((steps, n, 2)),
        ff,
        PendulumParameters(),
        SensorModel(),
        load=load.sample(steps, DT, rng, (n,)),
    )
    return [run.measurements[:, i] for i in range(n)], [run.plant_input[:, i] for i in range(n)]


@pytest.mark.parametrize("truth", [RandomLoad(0.1, 0.5), RandomLoad(0.03, 1.5)])
def test_a_known_load_is_recovered_from_twin_episodes(truth):
    """Twin episodes with a soft day's load (0.05 V, 0.5 s) and a rig's day's (0.026 V, 1.5 s): the fit gets its
    standard deviation back within 15 %, its time constant within 40 %, each within three standard errors."""
    ys, us = twin_logs(truth)
    fit = fit_load([reconstruct_load(y, u, PendulumParameters(), DT) for y, u in zip(ys, us)], DT)
    assert fit.load.kind == "first-order"
    assert fit.load.std == pytest.approx(truth.std, rel=0.15)
    assert fit.load.time_constant == pytest.approx(truth.time_constant, rel=0.4)
    assert abs(fit.load.diffusion - truth.diffusion) < 3 * fit.standard_errors["diffusion"]
    assert abs(fit.load.time_constant - truth.time_constant) < 3 * fit.standard_errors["time_constant"]
    assert fit.log_likelihood["first-order"] > fit.log_likelihood["random-walk"]


def test_without_a_load_the_reconstruction_has_no_slow_torque():
    """The twin without a load: the fitted load is under a twentieth of the soft day's (0.05 V), what the arm's
    equation leaves is the white floor of the differentiated encoders."""
    ys, us = twin_logs(RandomLoad(0.0, 1.0), n=4)
    fit = fit_load([reconstruct_load(y, u, PendulumParameters(), DT) for y, u in zip(ys, us)], DT)
    assert fit.load.std < 0.05 / 20


def test_the_fit_check_is_1_in_every_band_for_a_load_of_the_fitted_kind_and_not_for_another():
    """Loads drawn from a first-order process (0.1 V, 0.5 s, a floor): the fitted spectrum has their power in
    every band within a fifth. The same with a 0.45 Hz oscillation of 0.05 V added, which no first-order
    spectrum has: the data have twice the fitted power in its band, and less than two thirds of it
    either side."""
    rng = np.random.default_rng(4)
    steps = int(18.0 / DT)
    drawn = RandomLoad(0.1, 0.5, floor=1e-4).sample(steps, DT, rng, (60,))
    fitted = dict(load_fit_check(list(drawn.T), DT))
    assert list(fitted) == ["0-0.1 Hz", "0.1-0.3 Hz", "0.3-0.6 Hz", "0.6-1 Hz"]
    assert all(0.8 < ratio < 1.25 for ratio in fitted.values()), fitted
    t = np.arange(steps)[:, None] * DT
    line = 0.05 * np.sin(2 * np.pi * 0.45 * t + rng.uniform(0, 2 * np.pi, drawn.shape[1]))
    off = dict(load_fit_check(list((drawn + line).T), DT))
    assert off["0.3-0.6 Hz"] > 1.8 and off["0.1-0.3 Hz"] < 0.67 and off["0.6-1 Hz"] < 0.67, off


def test_qube_calibrate_load_writes_the_load_tables_and_the_reports_band_table(tmp_path):
    from qube_koopman.daq.cli.run import main as run_main
    from qube_koopman.identify.cli.calibrate import main
    from qube_koopman.sim.pendulum.params_file import PlantFile, load_plant, save_plant

    save_plant(tmp_path / "truth.toml", PlantFile(PendulumParameters(), load=RandomLoad(0.1, 0.5)))
    assert (
        run_main(
            [
                "--episodes",
                "3",
                "--duration",
                "4",
                "--seed",
                "5",
                "--plant",
                str(tmp_path / "truth.toml"),
                "--out",
                str(tmp_path / "logs"),
                "-q",
            ]
        )
        == 0
    )
    logs = sorted(map(str, (tmp_path / "logs").glob("*.mcap")))
    assert (
        main(
            [
                *logs[:2],
                "--validate",
                logs[2],
                "--out",
                str(tmp_path / "plant.toml"),
                "--max-nfev",
                "4",
                "--load",
                "--report",
                str(tmp_path / "report"),
                "-q",
            ]
        )
        == 0
    )
    plant = load_plant(tmp_path / "plant.toml")
    assert plant.load is not None and math.isfinite(plant.load.diffusion) and plant.load.diffusion > 0
    assert set(plant.load_standard_errors) >= {"diffusion"}
    assert plant.load_setups == {}  # one recording day: the central load is that day's
    report = (tmp_path / "report" / "report.md").read_text()
    assert "## The arm's random load" in report and "## Replay with the arm's random load" in report
    assert "| on |" in report and "| off |" in report
