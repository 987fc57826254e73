"""End to end: qube-run collects on the simulator, CL EDMD identifies, closed-loop prediction scores.

The CI-size version of the issue's part 4 (the full 48-episode run is
bench/bench_end_to_end.py). Free-running simulation is deterministic, so
these numbers repeat exactly; measured: R^2 0.992 (20 delays), 0.838
(the paper's 10 delays), 0.993 across controllers.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from daq.cli.run import main
from identify import ClEdmd, Delay, Polynomial, r2_score
from identify.data import IncompleteLogSkipped, load_logs, paper_split
from identify.structure import close_loop

SKIP = 500  # the first second: the derivative kick (FACTS section 2)


def _r2(model, logs) -> float:
    # Samples 1.. of each episode, as the paper scores (the first is the initial condition).
    return float(np.mean([r2_score(log.trajectory.x[1:], model.predict(log.trajectory)[1:]) for log in logs]))


@pytest.fixture(scope="module")
def collected(tmp_path_factory):
    root = tmp_path_factory.mktemp("e2e")
    assert main(["--episodes", "8", "--duration", "10", "--seed", "1", "--out", str(root / "a"), "-q"]) == 0
    # A second set under other gains, to predict with the plant identified under the first.
    toml = root / "stiffer.toml"
    toml.write_text("kp_theta = 6.0\nkd_theta = 1.8\nkp_alpha = 35.0\nkd_alpha = 3.0\ntau = 50.0\n")
    assert main(["--episodes", "3", "--duration", "10", "--seed", "2", "--controller", str(toml),
                 "--out", str(root / "b"), "-q"]) == 0
    with warnings.catch_warnings():
        warnings.simplefilter("error", IncompleteLogSkipped)  # every episode must be complete
        train, test = paper_split(list((root / "a").glob("*.mcap")), n_train=5)
        return (load_logs(train, skip=SKIP), load_logs(test, skip=SKIP),
                load_logs(sorted((root / "b").glob("*.mcap")), skip=SKIP))


@pytest.mark.slow
def test_cl_edmd_predicts_held_out_simulated_episodes(collected):
    train, test, _ = collected
    assert len(train) == 5 and len(test) == 3
    controller = train[0].controller
    model = ClEdmd(controller, lifting=[Polynomial(2), Delay(20)], alpha=1e-3)
    model.fit([log.trajectory for log in train])
    r2 = _r2(model, test)
    print(f"CI-size end to end: closed-loop R^2 {r2:.4f} (Polynomial(2), Delay(20))")
    assert r2 >= 0.9
    # The paper's lifting (10 delays) does worse on the simulator's quantized angles: it
    # scores 0.84 here (0.85 on the full 48-episode run, 0.897 on the real dataset).
    paper = ClEdmd(controller, lifting=[Polynomial(2), Delay(10)], alpha=1e-3)
    paper_r2 = _r2(paper.fit([log.trajectory for log in train]), test)
    print(f"CI-size end to end: closed-loop R^2 {paper_r2:.4f} (Polynomial(2), Delay(10))")
    assert 0.75 <= paper_r2 < r2


@pytest.mark.slow
def test_plant_identified_under_one_controller_predicts_under_another(collected):
    train, _, other = collected
    first, second = train[0].controller, other[0].controller
    assert not np.allclose(first.D, second.D), "the second set must run other gains"
    model = ClEdmd(first, lifting=[Polynomial(2), Delay(20)], alpha=1e-3)
    model.fit([log.trajectory for log in train])
    wrapped = close_loop(model.plant_model_, second, measured=[0, 1])
    r2 = _r2(wrapped, other)
    print(f"cross-controller closed-loop R^2 {r2:.4f}")
    assert r2 >= 0.9
    # The identified plant is unstable (an inverted pendulum); both closed loops are not.
    assert model.plant_model_.spectral_radius() > 1.0
    assert wrapped.spectral_radius() < 1.0 + 1e-3
