"""End to end: qube-run collects on the simulator, qube-identify fits CL EDMD and scores in closed loop.

The CI-size version of the issue's part 4 (the full 48-episode run is
bench/bench_end_to_end.py). Free-running simulation is deterministic, so
these numbers repeat; measured: R^2 0.992 with 20 delays, 0.838 with the
paper's 10 delays, 0.993 across controllers.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from qube_koopman.daq.cli.run import main as qube_run
from qube_koopman.daq.log import read_episode_metadata
from qube_koopman.identify.cli.identify import main as qube_identify


@pytest.fixture(scope="module")
def collected(tmp_path_factory):
    root = tmp_path_factory.mktemp("e2e")
    assert qube_run(["--episodes", "8", "--duration", "10", "--seed", "1", "--out", str(root / "a"), "-q"]) == 0
    # A second set under other gains, to predict with the plant identified under the first.
    toml = root / "stiffer.toml"
    toml.write_text("kp_theta = 6.0\nkd_theta = 1.8\nkp_alpha = 35.0\nkd_alpha = 3.0\ntau = 50.0\n")
    assert (
        qube_run(
            [
                "--episodes",
                "3",
                "--duration",
                "10",
                "--seed",
                "2",
                "--controller",
                str(toml),
                "--out",
                str(root / "b"),
                "-q",
            ]
        )
        == 0
    )
    logs = sorted((root / "a").glob("*.mcap"))  # by name: the order they ran
    return root, [str(p) for p in logs[:5]], [str(p) for p in logs[5:]], str(root / "b")


def _identify(root, name: str, train, test, delays: int) -> dict:
    out = root / name
    assert qube_identify(["--train", *train, "--test", *test, "--delays", str(delays), "--out", str(out)]) == 0
    return json.loads((out / "report.json").read_text())


@pytest.mark.slow
def test_cl_edmd_predicts_held_out_simulated_episodes(collected):
    root, train, test, _ = collected
    report = _identify(root, "d20", train, test, delays=20)
    assert report["method"] == "cl-edmd" and report["score"] == "cl" and report["test"]["n_episodes"] == 3
    r2 = report["test"]["r2_mean"]
    print(f"CI-size end to end: closed-loop R^2 {r2:.4f} (Polynomial(2), Delay(20))")
    assert r2 >= 0.9
    # The logged controller is the rig's, as identification read it back from the logs.
    np.testing.assert_allclose(report["controller"]["D"], [[-87.8181818181818, -143.636363636364]], rtol=1e-12)
    # The paper's lifting (10 delays) does worse on the simulator's quantized angles: 0.84
    # here, 0.85 on the full 48-episode run (0.897 on the real dataset).
    paper_r2 = _identify(root, "d10", train, test, delays=10)["test"]["r2_mean"]
    print(f"CI-size end to end: closed-loop R^2 {paper_r2:.4f} (Polynomial(2), Delay(10))")
    assert 0.75 <= paper_r2 < r2


@pytest.mark.slow
def test_plant_identified_under_one_controller_predicts_under_another(collected):
    root, train, _, other = collected
    report = _identify(root, "cross", train, [other], delays=20)
    r2 = report["test"]["r2_mean"]
    print(f"cross-controller closed-loop R^2 {r2:.4f}")
    assert r2 >= 0.9
    # The identified plant is unstable (an inverted pendulum); its closed loop is not.
    assert report["spectral_radius"]["plant"] > 1.0 > report["spectral_radius"]["closed_loop"] - 1e-3


@pytest.mark.slow
def test_second_set_really_ran_other_gains(collected):
    root, train, _, other = collected
    first = read_episode_metadata(train[0]).controller.gains
    second = read_episode_metadata(next(Path(other).glob("*.mcap"))).controller.gains
    assert (first["kp_alpha"], first["kd_alpha"]) == (30.0, 2.5)
    assert (second["kp_alpha"], second["kd_alpha"]) == (35.0, 3.0)
