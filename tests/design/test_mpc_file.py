"""The MPC's controller file (kind "mpc"): it round-trips through core's loader, qube-design --mpc writes it,
qube-run runs it on the twin within its voltage limit and logs the solver per tick."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from qube_koopman.core.controller_file import load_controller, registered_controller_kinds
from qube_koopman.daq.cli.run import main as run_main
from qube_koopman.daq.log import read_episode
from qube_koopman.design import Weights, linear_plant
from qube_koopman.design.cli.design import main as design_main
from qube_koopman.design.lq import augment
from qube_koopman.design.mpc import MpcSettings
from qube_koopman.design.mpc_file import mpc_controller, write_mpc_file
from qube_koopman.identify.cli.identify import main as identify_main

sys.path.insert(0, str(Path(__file__).parent))
from test_design import _pendulum_like  # noqa: E402


def _riccati(plant, weights):
    import control

    return np.asarray(control.dare(*augment(plant, weights))[0])


def test_the_mpc_kind_is_registered_through_its_entry_point():
    assert "mpc" in registered_controller_kinds()


def test_an_mpc_file_round_trips_through_load_controller(tmp_path):
    plant = linear_plant(_pendulum_like(3, False))
    weights = Weights(q_theta=4.0)
    settings = MpcSettings(horizon=12, voltage_limit=4.0, time_budget=10.0)  # no fallback on host luck
    P = _riccati(plant, weights)
    path = write_mpc_file(tmp_path / "mpc.toml", plant, weights, P, settings, {"model": "m.json", "n": 3})
    info = load_controller(path)
    expected = mpc_controller(plant, weights, P, settings, {"model": "m.json", "n": 3})
    assert info.kind == "mpc" and info.method == "given"
    assert info.settings == expected.settings and info.settings["horizon"] == 12 and info.settings["voltage_limit"] == 4
    assert info.provenance == {"model": "m.json", "n": 3} and info.tick_fields == expected.tick_fields
    for m in "ABCD":
        np.testing.assert_array_equal(getattr(info.system, m), getattr(expected.system, m))
    np.testing.assert_array_equal(info.runtime.problem.H, expected.runtime.problem.H)
    (out_a, upd_a), (out_b, upd_b) = info.runtime.step(), expected.runtime.step()
    rng = np.random.default_rng(0)
    for _ in range(50):
        e = 0.02 * rng.standard_normal(2)
        assert out_a(e[0], e[1], 0.0, 0.0) == out_b(e[0], e[1], 0.0, 0.0)
        upd_a(e[0], e[1], 0.0)
        upd_b(e[0], e[1], 0.0)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda t: t.replace("n_delays = 3", "n_delays = 4"), "plant_rows has shape 2 x 8, expected 2 x 10"),
        (lambda t: t.replace('kind = "mpc"', 'kind = "nmpc"'), "unknown controller kind 'nmpc'"),
        (lambda t: t.replace("horizon = 20", "horizon = 0"), "--horizon must be a whole number"),
        (lambda t: t.replace("dt = 0.002", "dt = 0.001"), "differs from the sample period"),
    ],
)
def test_a_bad_mpc_file_is_refused_naming_the_file(tmp_path, edit, message):
    plant = linear_plant(_pendulum_like(3, False))
    path = write_mpc_file(tmp_path / "mpc.toml", plant, Weights(), _riccati(plant, Weights()), MpcSettings())
    path.write_text(edit(path.read_text()))
    with pytest.raises(ValueError, match=message) as info:
        load_controller(path)
    assert str(info.value).startswith(str(path))


@pytest.fixture(scope="module")
def twin_model(tmp_path_factory) -> Path:
    """A plant identified on 4 rig-PD episodes of the twin (10 delays and a constant)."""
    root = tmp_path_factory.mktemp("mpc_twin")
    for out, n, seed in (("train", 4, 3), ("test", 1, 4)):
        argv = ["--episodes", str(n), "--duration", "10", "--seed", str(seed), "--out", str(root / out), "-q"]
        assert run_main([*argv, "--n-jobs", "1"]) == 0
    assert (
        identify_main(
            [
                "--train",
                *map(str, sorted((root / "train").glob("*.mcap"))),
                "--test",
                *map(str, (root / "test").glob("*.mcap")),
                "--poly",
                "1",
                "--delays",
                "10",
                "--const",
                "--out",
                str(root / "model"),
                "-q",
            ]
        )
        == 0
    )
    return root / "model"


def test_qube_design_mpc_writes_a_file_qube_run_runs_on_the_twin_within_its_voltage_limit(twin_model, tmp_path, capsys):
    out = tmp_path / "mpc.toml"
    argv = [str(twin_model), "--mpc", "--voltage-limit", "3", "--horizon", "15", "--out", str(out)]
    assert design_main([*argv, "--episodes", "2", "--duration", "4", "--interval", "0"]) == 0
    assert f"wrote {out}: qube-run --controller {out}" in capsys.readouterr().out
    info = load_controller(out)
    assert info.kind == "mpc" and info.settings["voltage_limit"] == 3.0 and info.settings["horizon"] == 15
    assert info.provenance["designed_by"].startswith("qube-design --mpc")
    runs = tmp_path / "runs"
    assert (
        run_main(
            [
                "--controller",
                str(out),
                "--episodes",
                "2",
                "--duration",
                "6",
                "--seed",
                "5",
                "--out",
                str(runs),
                "--n-jobs",
                "1",
                "-q",
            ]
        )
        == 0
    )
    episodes = [read_episode(p) for p in sorted(runs.glob("*.mcap"))]
    assert [e.metadata.status for e in episodes] == ["complete", "complete"]
    for e in episodes:
        c = e.metadata.controller
        assert c.kind == "mpc" and c.settings["horizon"] == 15 and c.settings["solver"] == "newton"
        assert c.tick_fields == ("solver_status", "solver_iterations", "solve_time", "constraint_active", "fallback")
        assert np.max(np.abs(e.plant_input)) <= 3.0 + 1e-12  # 0 ticks over the limit
        assert not e.saturation.any()  # the MPC kept it, not the supervisor's clamp
        record = dict(zip(c.tick_fields, e.controller_record.T))
        assert record["constraint_active"].sum() > 0  # the limit was reached, so it was held
        assert np.all(record["solve_time"] > 0) and np.all(record["solve_time"] <= e.compute_time)
        assert np.all(np.isin(record["solver_status"], (0, 1, 2, 3)))
        assert np.mean(record["solver_status"] == 0) > 0.9
    # a log keeps the MPC's settings, not its model: a replay needs the controller file
    log = str(sorted(runs.glob("*.mcap"))[0])
    assert run_main(["--replay", log, "--out", str(tmp_path / "replayed"), "-q"]) == 2
    assert "recorded under a controller of kind 'mpc'" in capsys.readouterr().err


def test_qube_design_refuses_mpc_settings_without_mpc(twin_model, tmp_path, capsys):
    assert design_main([str(twin_model), "--voltage-limit", "3", "--out", str(tmp_path / "x.toml")]) == 2
    assert "--voltage-limit is a setting of --mpc" in capsys.readouterr().err
    assert design_main([str(twin_model), "--mpc", "--voltage-limit", "12", "--out", str(tmp_path / "x.toml")]) == 2
    assert "--voltage-limit must be above 0 and at most the rig's 10 V" in capsys.readouterr().err


def test_the_episode_figure_shows_the_limit_the_active_ticks_and_one_ticks_horizon(twin_model, tmp_path):
    from PIL import Image

    from qube_koopman.design.mpc_figure import write_mpc_episode_figure

    out = tmp_path / "mpc.toml"
    argv = [str(twin_model), "--mpc", "--voltage-limit", "3", "--horizon", "15", "--out", str(out), "-q"]
    assert design_main([*argv, "--episodes", "1", "--duration", "2", "--interval", "0"]) == 0
    out.write_text(out.read_text().replace("time_budget = 0.001", "time_budget = 10.0"))  # no host luck
    runs = tmp_path / "runs"
    argv = ["--controller", str(out), "--episodes", "1", "--duration", "4", "--seed", "5", "--out", str(runs), "-q"]
    assert run_main([*argv, "--n-jobs", "1"]) == 0
    (log,) = sorted(runs.glob("*.mcap"))
    figure = write_mpc_episode_figure(log, out, tmp_path / "episode.png")
    episode = read_episode(log)
    record = dict(zip(episode.metadata.controller.tick_fields, episode.controller_record.T))
    k = figure.tick
    assert k >= 500 and record["constraint_active"][k] == 1 and not record["constraint_active"][500:k].any()
    assert figure.voltage_limit == 3.0 and figure.active_fraction == pytest.approx(record["constraint_active"].mean())
    # the replayed plan is the one the loop solved: its first input is the one applied, all within the limit
    assert figure.plan[0] == pytest.approx(episode.plant_input[k], abs=1e-9)
    assert len(figure.plan) == 15 and np.all(np.abs(figure.plan) <= 3.0 + 1e-9)
    # the model's prediction over the horizon follows the twin (0.03 s ahead, within a few encoder counts)
    assert np.max(np.abs(figure.predicted_theta - figure.measured_theta)) < 0.02
    assert abs(figure.predicted_theta[0] - figure.measured_theta[0]) < 0.006
    image = Image.open(figure.path)
    assert image.size[0] > 500 and "constraint active" in image.info["Title"]
