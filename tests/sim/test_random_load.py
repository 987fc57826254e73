"""The twin's random load on the arm: its process, its seeds, its place in the physics and the plant file."""

from __future__ import annotations

import math

import numpy as np
import pytest

from _episodes import QUBE_PD
from qube_koopman.sim.pendulum import (
    LoadStream,
    PendulumParameters,
    PendulumSimulator,
    RandomLoad,
    simulate_closed_loop,
)
from qube_koopman.sim.pendulum.params_file import PlantFile, PlantFileError, load_plant, plant_file, save_plant

DT = 1 / 500


def test_a_first_order_load_has_its_stationary_variance_and_correlation_time():
    load = RandomLoad(diffusion=0.1, time_constant=0.5)
    assert load.std == pytest.approx(0.1 * math.sqrt(0.25))
    d = load.sample(20000, DT, np.random.default_rng(1), (40,))
    assert d.std() == pytest.approx(load.std, rel=0.05)
    lag = int(0.5 / DT)  # one time constant: the correlation falls to 1/e
    corr = np.mean(d[lag:] * d[:-lag]) / np.mean(d * d)
    assert corr == pytest.approx(math.exp(-1), abs=0.05)


def test_a_random_walk_starts_at_zero_and_its_variance_grows_by_the_diffusion_squared_per_second():
    walk = RandomLoad(diffusion=0.2)
    assert walk.kind == "random-walk" and math.isinf(walk.std)
    d = walk.sample(1001, DT, np.random.default_rng(2), (4000,))
    assert np.all(d[0] == 0)
    assert d[-1].var() == pytest.approx(0.2**2 * 2.0, rel=0.06)  # 1000 steps: 2 s


def test_the_floor_is_a_faster_part_flat_up_to_its_corner():
    """Its variance is the flat level times (pi / 2) its corner; its spectrum below the corner is the level's
    first-order roll-off, ``floor / (1 + (f / corner)^2)``."""
    floor = RandomLoad(0.0, 1.0, floor=2e-4, floor_corner=1.0)
    d = floor.sample(40000, DT, np.random.default_rng(3), (20,))
    assert d.var() == pytest.approx(2e-4 * math.pi / 2, rel=0.05)
    from scipy.signal import welch

    f, p = welch(d, fs=1 / DT, nperseg=20000, axis=0)
    band = (f > 0.05) & (f < 0.5)  # ~1000 periodogram estimates: their mean within 0.1 of the level
    assert p[band].mean() == pytest.approx(np.mean(2e-4 / (1 + f[band] ** 2)), rel=0.1)


@pytest.mark.parametrize("load", [RandomLoad(0.05, 1.5), RandomLoad(0.05, 1.5, floor=2e-4), RandomLoad(0.1)])
def test_the_per_tick_stream_draws_the_samples_of_a_batch_of_one(load):
    batch = load.sample(9000, DT, np.random.default_rng(7))  # past two of the stream's blocks
    stream = LoadStream(load, DT, 7)
    ticks = [stream.value] + [stream.advance() for _ in range(8999)]
    np.testing.assert_allclose(ticks, batch, rtol=0, atol=1e-15)


def _run(load, seed):
    sim = PendulumSimulator(load=load, load_seed=seed)
    sim.reset((0.0, 0.01, 0.0, 0.0))
    out = []
    for _ in range(1500):
        theta, alpha = sim.step(-6 * sim.measurement[0] + 30 * sim.measurement[1])
        out.append(sim.state)
    return np.array(out)


def test_the_same_seed_gives_the_same_load_and_another_seed_another():
    load = RandomLoad(0.3, 1.0)
    a, b, c = _run(load, 3), _run(load, 3), _run(load, 4)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 1e-3


def test_no_load_is_the_arithmetic_of_a_twin_without_one_bit_for_bit():
    # The per-tick simulator and the batch closed loop, with and without the (absent) load.
    np.testing.assert_array_equal(_run(None, 3), _run(None, 99))
    rng = np.random.default_rng(0)
    refs = np.zeros((800, 3, 2))
    ff = rng.normal(0, 0.3, (800, 3))
    x0 = np.column_stack([np.zeros(3), [0.01, -0.01, 0.02], np.zeros((3, 2))])
    plain = simulate_closed_loop(x0, QUBE_PD, refs, ff)
    none = simulate_closed_loop(x0, QUBE_PD, refs, ff, load=None)
    np.testing.assert_array_equal(plain.states, none.states)


def test_the_load_is_a_torque_on_the_arm_past_the_dead_zone():
    """A constant load of d volts moves the arm as d volts more at the motor would, beyond the dead zone: the
    amplifier's dead zone swallows a command below it, not a torque."""
    p = PendulumParameters(dead_zone=0.1, Kr=0.0, Cr=0.0, delay=0.0)  # (a command is delayed, a torque not)
    x0 = np.array([[0.0, 0.0, 0.0, 0.0]])
    refs, ff = np.zeros((200, 1, 2)), np.zeros((200, 1))

    from qube_koopman.core.lti import DiscreteStateSpace

    zero = DiscreteStateSpace(np.zeros((1, 1)), np.zeros((1, 2)), np.zeros((1, 1)), np.zeros((1, 2)), DT)
    loaded = simulate_closed_loop(x0, zero, refs, ff, p, load=np.full((200, 1), 0.05))
    command = simulate_closed_loop(x0, zero, refs, ff + 0.15, p)  # 0.15 V command: 0.05 V past the dead zone
    np.testing.assert_allclose(loaded.states[:, 0, 0], command.states[:, 0, 0], rtol=1e-9, atol=1e-12)
    assert loaded.states[-1, 0, 0] != 0.0


def test_the_plant_files_load_round_trips_and_old_files_have_none(tmp_path):
    plant = plant_file(None)
    assert plant.load is None  # the shipped twin has no load table
    plant.load = RandomLoad(0.0312, 0.84)
    plant.load_standard_errors = {"diffusion": 0.004, "time_constant": 0.2}
    plant.load_setups = {"2023-09-15": RandomLoad(0.09, 0.55), "2023-08-28": RandomLoad(0.02)}
    plant.load_setup_standard_errors = {"2023-09-15": {"diffusion": 0.01}}
    save_plant(tmp_path / "p.toml", plant)
    back = load_plant(tmp_path / "p.toml")
    assert back.load == plant.load and back.load_standard_errors == plant.load_standard_errors
    assert back.load_setups == plant.load_setups
    assert back.load_setup_standard_errors == plant.load_setup_standard_errors
    assert back.loads_for_logs(["2023-09-15T15:00:00", "2023-08-28T16:00:00", "2024-01-01T00:00:00", None]) == [
        RandomLoad(0.09, 0.55),
        RandomLoad(0.02),
        plant.load,
        plant.load,
    ]
    assert back.params == plant.params and back.setups == plant.setups


@pytest.mark.parametrize(
    "table, problem",
    [
        ("[load]\ndiffusion = -1.0\n", "load diffusion must be between 0"),
        ("[load]\ndiffusion = 0.1\ntime_constant = 0.0\n", "time_constant must be positive"),
        ("[load]\ntime_constant = 2.0\n", "diffusion (V/sqrt(s)) is missing"),
        ("[load]\ndiffusion = 0.1\nstd = 0.2\n", "unknown key(s) std"),
        ('[load]\ndiffusion = "much"\n', "diffusion must be a number"),
        ("load = 3\n", "[load] must be a table"),
        ('[load_setups."2023-09-15"]\ndiffusion = 0.1\n', "needs a [load] table"),
    ],
)
def test_a_bad_load_table_is_one_error_naming_the_file(tmp_path, table, problem):
    path = tmp_path / "bad.toml"
    head = 'format = "qube-plant/2"\n'
    path.write_text(head + table if table.startswith("load =") else head + "\n" + table)
    with pytest.raises(PlantFileError) as err:
        load_plant(path)
    assert str(err.value).startswith(f"{path}: ") and problem in str(err.value)


def test_qube_run_refuses_a_bad_load_table_in_one_line(tmp_path, capsys):
    from qube_koopman.daq.cli.run import main

    path = tmp_path / "bad.toml"
    path.write_text('format = "qube-plant/2"\n[load]\ndiffusion = -1\n')
    assert main(["--episodes", "1", "--duration", "1", "--plant", str(path), "--out", str(tmp_path / "e"), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0] and "diffusion" in err[0]


def _states(folder):
    from qube_koopman.daq.log import read_episode

    episodes = [read_episode(p) for p in sorted(folder.glob("*.mcap"))]
    return [np.asarray(e.states) for e in episodes], [e.metadata.extra["backend"].get("load") for e in episodes]


def test_qube_run_no_load_is_a_plant_file_without_the_table_and_the_log_records_the_loads_seed(tmp_path):
    from qube_koopman.daq.cli.run import main

    plant = PlantFile(PendulumParameters(), load=RandomLoad(0.2, 1.0))
    save_plant(tmp_path / "load.toml", plant)
    save_plant(tmp_path / "none.toml", PlantFile(PendulumParameters()))
    argv = ["--episodes", "2", "--duration", "1", "--seed", "5", "--n-jobs", "1", "-q"]
    for name, extra in (
        ("a", ["--plant", "load.toml"]),
        ("b", ["--plant", "load.toml"]),
        ("off", ["--plant", "load.toml", "--no-load"]),
        ("none", ["--plant", "none.toml"]),
    ):
        assert (
            main(
                [
                    *argv,
                    *[str(tmp_path / x) if x.endswith(".toml") else x for x in extra],
                    "--out",
                    str(tmp_path / name),
                ]
            )
            == 0
        )
    a, loads = _states(tmp_path / "a")
    b, _ = _states(tmp_path / "b")
    off, off_loads = _states(tmp_path / "off")
    none, _ = _states(tmp_path / "none")
    for x, y, z, w in zip(a, b, off, none):
        np.testing.assert_array_equal(x, y)  # the same run seed: the same loads
        np.testing.assert_array_equal(z, w)  # --no-load: the plant file without its table, bit for bit
        assert np.abs(x - w).max() > 0  # the load moved the arm
    assert off_loads == [None, None]
    assert loads[0]["kind"] == "first-order" and loads[0]["diffusion"] == 0.2 and loads[0]["seed"] != loads[1]["seed"]


def test_qube_run_no_load_is_for_the_simulator(tmp_path, capsys):
    from qube_koopman.daq.cli.run import main

    assert main(["--backend", "serial", "--port", "/dev/null", "--no-load", "--out", str(tmp_path)]) == 2
    assert "--no-load is for --backend sim" in capsys.readouterr().err


def test_a_replay_runs_each_log_with_its_days_load(tmp_path):
    from qube_koopman.daq.cli.run import main

    assert main(["--episodes", "1", "--duration", "1", "--seed", "8", "--out", str(tmp_path / "orig"), "-q"]) == 0
    day = next((tmp_path / "orig").glob("*.mcap")).name[5:13]
    plant = PlantFile(
        PendulumParameters(),
        load=RandomLoad(0.2, 1.0),
        load_setups={f"{day[:4]}-{day[4:6]}-{day[6:]}": RandomLoad(0.5, 2.0)},
    )
    save_plant(tmp_path / "p.toml", plant)
    log = str(next((tmp_path / "orig").glob("*.mcap")))
    assert main(["--replay", log, "--plant", str(tmp_path / "p.toml"), "--out", str(tmp_path / "r"), "-q"]) == 0
    assert (
        main(["--replay", log, "--plant", str(tmp_path / "p.toml"), "--no-load", "--out", str(tmp_path / "n"), "-q"])
        == 0
    )
    _, loads = _states(tmp_path / "r")
    _, none = _states(tmp_path / "n")
    assert loads[0]["diffusion"] == 0.5 and loads[0]["time_constant"] == 2.0 and none == [None]


def test_qube_run_on_the_named_twin_with_the_load_draws_its_central_load(tmp_path):
    from qube_koopman.daq.cli.run import main
    from qube_koopman.sim.pendulum.params_file import plant_file

    central = plant_file("calibrated-with-load").load
    argv = ["--episodes", "1", "--duration", "1", "--seed", "5", "--plant", "calibrated-with-load", "-q"]
    assert main([*argv, "--out", str(tmp_path / "on")]) == 0
    assert main([*argv, "--no-load", "--out", str(tmp_path / "off")]) == 0
    (on,), (recorded,) = _states(tmp_path / "on")
    (off,), (none,) = _states(tmp_path / "off")
    assert recorded["diffusion"] == central.diffusion and recorded["time_constant"] == central.time_constant
    assert none is None and np.abs(on - off).max() > 0
