"""Offset-free MPC: a load at the plant input and a rate on the arm's angle filtered each tick with the model
file's covariances and used in the target; on the twin under a constant load, and on a twin with stiffer cables,
the arm stays at its reference where the MPC without them does not; without a disturbance model the MPC is the one
it was."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from qube_koopman.core.controller_file import load_controller
from qube_koopman.daq.cli.run import main as run_main
from qube_koopman.daq.log import read_episode
from qube_koopman.design import Weights, linear_plant
from qube_koopman.design.cli.design import main as design_main
from qube_koopman.design.mpc import MpcDisturbance, MpcRuntime, MpcSettings, build_problem
from qube_koopman.identify.cli.identify import main as identify_main
from qube_koopman.identify.models.disturbance import filter_disturbance
from qube_koopman.sim.pendulum import PendulumParameters
from qube_koopman.sim.pendulum.simulator import PendulumSimulator

sys.path.insert(0, str(Path(__file__).parent))
from test_design import _pendulum_like  # noqa: E402

DT = 0.002


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> dict[str, Path]:
    """A plant identified on 3 rig-PD episodes of the twin (10 delays and a constant), with a load at the plant
    input as its disturbance model (q and the pole set: the twin's episodes have no load to estimate them from), and
    without."""
    root = tmp_path_factory.mktemp("offset_free")
    for out, n, seed in (("train", 3, 3), ("test", 1, 4)):
        argv = ["--episodes", str(n), "--duration", "8", "--seed", str(seed), "--out", str(root / out), "-q"]
        assert run_main([*argv, "--n-jobs", "1"]) == 0
    logs = ["--train", *map(str, sorted((root / "train").glob("*.mcap"))), "--test", str(root / "test")]
    fit = ["--poly", "1", "--delays", "10", "--const", "--interval", "0", "-q"]
    horizon = ["--horizon", "0.1,1", "--disturbance", "input", "--disturbance-q", "1e-5", "--disturbance-pole", "1"]
    assert identify_main([*logs, *fit, *horizon, "--out", str(root / "with")]) == 0
    assert identify_main([*logs, *fit, "--out", str(root / "without")]) == 0
    return {"with": root / "with", "without": root / "without", "root": root}


def _design(model: Path, out: Path, *flags: str) -> Path:
    argv = [str(model), "--mpc", *flags, "--out", str(out), "--episodes", "1", "--duration", "2", "--interval", "0"]
    assert design_main(argv) == 0
    # the host's load must not decide a test: no tick falls back for being slow
    out.write_text(out.read_text().replace("time_budget = 0.001", "time_budget = 10.0"))
    return out


def _twin_loop(
    path: Path, load: float, seconds: float = 4.0, load_from: float = 0.5, params=PendulumParameters(), step=0.0
):
    """The controller file on the twin (``params``: its physics), ``load`` volts added at the plant input from
    ``load_from`` s on (the controller does not see it) and the arm's reference stepped to ``step`` there: theta,
    alpha, the controller's output and its disturbance estimates (one column per entry) per tick."""
    runtime = load_controller(path).runtime
    out, upd = runtime.step()
    sim = PendulumSimulator(params=params, seed=0)
    theta, alpha = sim.reset((0.0, 0.02, 0.0, 0.0))
    n = round(seconds / DT)
    rec = np.zeros((n, 3 + len(runtime.estimate)))
    for k in range(n):
        on = k * DT >= load_from
        r = step if on else 0.0
        e0, e1 = r - theta, -alpha
        u, _ = out(e0, e1, 0.0, r)
        rec[k] = theta - r, alpha, u, *runtime.estimate
        theta, alpha = sim.step(u + (load if on else 0.0))
        upd(e0, e1, 0.0)
    assert runtime.n_fallbacks == 0
    return rec


def test_under_a_constant_load_the_offset_free_mpc_holds_the_arm_at_its_reference(models, tmp_path, capsys):
    # without the arm's integral the MPC without a disturbance estimate has nothing to remove a load's offset
    on = _design(models["with"], tmp_path / "on.toml", "--no-integral")
    assert "offset-free: on" in capsys.readouterr().out
    off = _design(models["with"], tmp_path / "off.toml", "--no-integral", "--no-offset-free")
    assert "offset-free: off (--no-offset-free)" in capsys.readouterr().out
    load = 0.5
    # 10 s: the two estimates settle about 6 s after the load starts (one alone in about 3); without them the
    # offset is the load's from about 2 s on
    with_estimate, without = _twin_loop(on, load, seconds=10.0), _twin_loop(off, load, seconds=4.0)
    last = slice(-750, None)  # the last 1.5 s
    offset_off = abs(np.mean(without[last, 0]))
    offset_on = abs(np.mean(with_estimate[last, 0]))
    assert offset_off > 0.01  # rad: the load pushes the arm off
    assert offset_on < 0.1 * offset_off
    # the load's estimate converges to the load (both controllers estimate it; one uses it), the arm's rate to
    # next to nothing (rad per tick: under a tenth of what the load moves the arm by, b_theta rad per tick per volt)
    for rec in (with_estimate, without):
        assert np.mean(rec[last, 3]) == pytest.approx(load, rel=0.2)
    b_theta = load_controller(on).runtime.disturbance.input[0]
    assert abs(np.mean(with_estimate[last, 4])) < 0.1 * abs(b_theta) * load
    assert abs(np.mean(with_estimate[: round(0.5 / DT), 3])) < 0.1 * load  # no load yet: none estimated
    # the offset-free MPC's steady state cancels the load: its voltage is the load's opposite
    assert np.mean(with_estimate[last, 2]) == pytest.approx(-load, rel=0.2)


def _residuals(rec: np.ndarray, d: MpcDisturbance, n_delays: int) -> np.ndarray:
    """The one-step residuals of the plant the controller filters on, from a :func:`_twin_loop` record (reference 0)."""
    x = rec[:, :2]
    v = rec[:, 2]  # the plant input the controller applied (no feedforward; the load is not the controller's)
    residuals = np.full_like(x, np.nan)
    for k in range(n_delays + 1, len(x)):
        s = x[k - 1 - n_delays : k][::-1].ravel()
        residuals[k] = x[k] - (d.rows @ s + d.input * v[k - 1])
    return residuals


def test_one_estimate_is_identifys_kalman_filter_on_the_same_residuals(models, tmp_path):
    path = _design(models["with"], tmp_path / "on.toml", "--disturbances", "input")
    rec = _twin_loop(path, 0.3, seconds=2.0)
    info = load_controller(path)
    d = info.runtime.disturbance
    residuals = _residuals(rec, d, info.runtime.n_delays)
    filtered, _ = filter_disturbance(residuals, d.direction[:, 0], d.pole, d.gain[0])
    np.testing.assert_allclose(rec[:, 3], filtered, rtol=1e-9, atol=1e-12)
    assert info.settings["offset_free"] is True
    assert info.settings["disturbance"]["entries"] == ["input"]


def test_two_estimates_are_the_kalman_filter_of_dlqe_on_the_same_residuals(models, tmp_path):
    """The default offset-free MPC filters a load and the arm's rate: each tick's estimates are the steady-state
    Kalman filter's (python-control's dlqe on the model file's R and the equal-speed q's) run by hand."""
    import control

    from qube_koopman.identify.models.model_file import load_model

    path = _design(models["with"], tmp_path / "on.toml")
    rec = _twin_loop(path, 0.3, seconds=2.0)
    info = load_controller(path)
    d = info.runtime.disturbance
    assert d.entries == ("input", "theta") and info.settings["disturbance"]["entries"] == ["input", "theta"]
    model = load_model(models["with"] / "model.json").disturbance
    G = d.direction
    R = np.asarray(model.R)
    speed = model.q * G[:, 0] @ np.linalg.solve(R, G[:, 0])  # the model's load: its q and direction
    Q = np.diag([speed / (g @ np.linalg.solve(R, g)) for g in G.T])
    L, _, _ = control.dlqe(np.eye(2), np.eye(2), G, Q, R)
    np.testing.assert_allclose(d.gain, L, rtol=1e-6)
    residuals = _residuals(rec, d, info.runtime.n_delays)
    f, estimates = np.zeros(2), np.zeros((len(rec), 2))
    for k, r in enumerate(residuals):
        if np.all(np.isfinite(r)):
            f = f + L @ (r - G @ f)
        estimates[k] = f
    np.testing.assert_allclose(rec[:, 3:5], estimates, rtol=1e-7, atol=1e-12)


def test_on_stiffer_cables_than_the_models_the_arm_reaches_its_reference_with_two_estimates(models, tmp_path):
    """A plant the model did not see (the cables twice as stiff): one estimate per measured angle takes the arm's
    offset to under a third of the MPC's without an estimate, where a load alone leaves more."""
    from dataclasses import replace

    stiff = replace(PendulumParameters(), Kr=2 * PendulumParameters().Kr)
    offsets = {}
    for name, flags in (("none", ["--no-offset-free"]), ("load", ["--disturbances", "input"]), ("both", [])):
        path = _design(models["with"], tmp_path / f"{name}.toml", "--no-integral", *flags)
        rec = _twin_loop(path, 0.0, seconds=6.0, params=stiff, step=0.1)
        offsets[name] = abs(np.mean(rec[-1500:, 0]))  # the last 3 s
    assert offsets["both"] < offsets["none"] / 3
    assert offsets["both"] < offsets["load"]


def test_without_a_disturbance_model_the_mpc_is_unchanged(models, tmp_path, capsys):
    path = _design(models["without"], tmp_path / "plain.toml")
    assert "offset-free: off: the model file has no disturbance model" in capsys.readouterr().out
    text = path.read_text()
    assert "disturbance" not in text and "offset_free = false" in text
    info = load_controller(path)
    assert info.runtime.disturbance is None
    assert info.tick_fields == ("solver_status", "solver_iterations", "solve_time", "constraint_active", "fallback")
    # a file written before offset-free control existed (no offset_free setting) loads as the same controller
    old = tmp_path / "old.toml"
    old.write_text(text.replace(", offset_free = false", ""))
    assert load_controller(old).settings == info.settings


def test_without_a_disturbance_model_the_outputs_are_the_ones_before_offset_free_control(tmp_path):
    # recorded with the MPC as it was before the disturbance estimate (the voltage limit binds on half the ticks)
    plant = linear_plant(_pendulum_like(3, False))
    p = build_problem(plant, Weights(), MpcSettings(horizon=15, voltage_limit=2.0, time_budget=10.0))
    out, upd = MpcRuntime(p, plant.n_delays, True, plant.dt).step()
    rng = np.random.default_rng(3)
    us = []
    for k in range(200):
        e0, e1 = 0.05 * rng.standard_normal(2)
        f = 0.3 * np.sin(k / 20)
        us.append(out(e0, e1, f, 0.1)[0])
        upd(e0, e1, f)
    before = [2.0, -2.1028693422366356, -2.179541643231187, 2.083824649459678, 2.150421538453759]
    assert [us[k] for k in (0, 7, 50, 120, 199)] == pytest.approx(before, rel=1e-9)


def test_a_first_order_load_is_integrated_for_offset_free_control_with_its_covariances():
    """Offset-free control needs an integrating disturbance: a first-order one keeps its q and R, and the MPC
    filters it with the Kalman gain of pole 1 (python-control's dlqe on the same covariances), nothing refitted."""
    import control

    from qube_koopman.design.mpc import mpc_disturbance
    from qube_koopman.identify.models.disturbance import DisturbanceModel, steady_state_gain

    plant = linear_plant(_pendulum_like(3, False))
    R = np.diag([4e-8, 1e-8])
    model = DisturbanceModel("input", 0.99, 1e-4, R, np.array([5.0, -1.0]))
    kept = mpc_disturbance(plant, model)
    assert kept.pole == 0.99 and kept.gain.tolist() == [[5.0, -1.0]]
    walk = mpc_disturbance(plant, model, integrate=True)
    L, _, _ = control.dlqe(np.eye(1), np.eye(1), walk.direction, 1e-4, R)
    assert walk.pole == 1.0 and walk.gain[0] == pytest.approx(np.asarray(L).ravel(), rel=1e-6)
    assert walk.target_map().shape == (2, 2)  # the offset-free target exists for it
    # two disturbances: each alone filtered as fast as the model's (the scalar filter's speed L g), together dlqe's
    both = mpc_disturbance(plant, model, integrate=True, entries=("input", "theta"))
    G = both.direction
    assert both.entries == ("input", "theta") and both.target_map().shape == (2, 3)
    assert G[:, 0].tolist() == walk.direction[:, 0].tolist() and G[:, 1].tolist() == [1.0, 0.0]
    info = [g @ np.linalg.solve(R, g) for g in G.T]
    Q = np.diag([1e-4 * info[0] / i for i in info])
    speeds = [steady_state_gain(g, 1.0, q, R)[0] @ g for g, q in zip(G.T, np.diag(Q))]
    assert speeds[0] == pytest.approx(speeds[1], rel=1e-9) and speeds[0] == pytest.approx(walk.gain[0] @ G[:, 0])
    L, _, _ = control.dlqe(np.eye(2), np.eye(2), G, Q, R)
    np.testing.assert_allclose(both.gain, L, rtol=1e-6)


def test_the_estimate_does_not_change_the_mpc_without_offset_free_control():
    plant = linear_plant(_pendulum_like(3, False))
    p = build_problem(plant, Weights(), MpcSettings(horizon=15, voltage_limit=2.0, time_budget=10.0))
    m = plant.n_measured
    disturbance = MpcDisturbance("input", 1.0, np.array([3.0, -2.0]), plant.F[:m], plant.G[:m, 0])
    plain = MpcRuntime(p, plant.n_delays, True, plant.dt)
    estimating = MpcRuntime(p, plant.n_delays, True, plant.dt, disturbance=disturbance)
    assert estimating.tick_fields == plain.tick_fields + ("disturbance_input",)
    (out_a, upd_a), (out_b, upd_b) = plain.step(), estimating.step()
    rng = np.random.default_rng(4)
    for _ in range(100):
        e0, e1 = 0.05 * rng.standard_normal(2)
        assert out_a(e0, e1, 0.1, 0.0) == out_b(e0, e1, 0.1, 0.0)
        same = (0, 1, 3, 4)  # all but the solve time
        assert [estimating.tick_record[i] for i in same] == [plain.tick_record[i] for i in same]
        upd_a(e0, e1, 0.1)
        upd_b(e0, e1, 0.1)
    assert estimating.estimate.shape == (1,) and estimating.estimate[0] != 0.0


def test_a_bad_disturbance_table_or_offset_free_without_one_is_refused_naming_the_file(models, tmp_path):
    path = _design(models["with"], tmp_path / "on.toml")
    text = path.read_text()
    bad = tmp_path / "bad.toml"
    for edit, message in (
        (text.replace('entries = ["input", "theta"]', 'entries = ["torque", "theta"]'), "unknown disturbance entry"),
        (text.replace('entries = ["input", "theta"]', 'entries = ["input", "input"]'), "1 to 2 distinct"),
        (text.replace('entries = ["input", "theta"]', 'entries = ["input"]'), "disturbance.gain has shape 2 x 2"),
        (text.replace("pole = 1.0", "pole = 0.9"), "offset-free MPC needs a random-walk disturbance"),
        ("\n".join(line for line in text.splitlines() if not line.startswith("disturbance")), "needs a disturbance"),
    ):
        bad.write_text(edit)
        with pytest.raises(ValueError, match=message) as info:
            load_controller(bad)
        assert str(info.value).startswith(str(bad))


@pytest.mark.parametrize(
    "entry, pole, gain, wanted, on, says",
    [
        (
            "input",
            1.0,
            [1.0, -1.0],
            True,
            True,
            "offset-free: on: the MPC estimates a load at the plant input (V) and a rate on theta (rad per tick)",
        ),
        ("input", 1.0, [1.0, -1.0], False, False, "offset-free: off (--no-offset-free)"),
        ("input", 1.0, [0.0, 0.0], True, False, "has a zero gain"),
        (
            "input",
            0.99,
            [1.0, -1.0],
            True,
            True,
            "first-order (pole 0.99); nothing refitted",
        ),
        ("input", 0.99, [1.0, -1.0], False, False, "offset-free: off (--no-offset-free)"),
        ("theta", 1.0, [1.0, -1.0], True, True, "filter speed of its disturbance (a rate on theta (rad per tick)"),
        ("alpha", 1.0, [1.0, -1.0], True, True, "filter speed of its disturbance (a rate on alpha (rad per tick)"),
        (None, 1.0, [1.0, -1.0], True, False, "the model file has no disturbance model"),
    ],
)
def test_qube_design_turns_offset_free_control_on_for_a_disturbance_model_with_a_gain(
    entry, pole, gain, wanted, on, says
):
    from types import SimpleNamespace

    from qube_koopman.design.controller_design import offset_free_settings
    from qube_koopman.identify.models.disturbance import DisturbanceModel

    model = None if entry is None else DisturbanceModel(entry, pole, 1e-5, np.eye(2), np.array(gain))
    settings, line = offset_free_settings(
        SimpleNamespace(model=SimpleNamespace(disturbance=model)), MpcSettings(offset_free=wanted)
    )
    assert settings.offset_free is on and says in line


def test_no_offset_free_and_disturbances_are_settings_of_mpc_and_exclude_each_other(models, tmp_path, capsys):
    out = ["--out", str(tmp_path / "x.toml")]
    assert design_main([str(models["with"]), "--no-offset-free", *out]) == 2
    assert "--no-offset-free is a setting of --mpc" in capsys.readouterr().err
    assert design_main([str(models["with"]), "--disturbances", "input", *out]) == 2
    assert "--disturbances is a setting of --mpc" in capsys.readouterr().err
    assert design_main([str(models["with"]), "--mpc", "--disturbances", "input", "--no-offset-free", *out]) == 2
    assert "--no-offset-free turns it off" in capsys.readouterr().err
    for bad in ("input,input", "torque", "input,theta,alpha"):
        with pytest.raises(SystemExit):
            design_main([str(models["with"]), "--mpc", "--disturbances", bad, *out])
        assert "--disturbances" in capsys.readouterr().err
    assert not (tmp_path / "x.toml").exists()


def test_qube_run_logs_the_disturbance_estimate_per_tick(models, tmp_path):
    path = _design(models["with"], tmp_path / "on.toml")
    runs = tmp_path / "runs"
    argv = ["--controller", str(path), "--episodes", "1", "--duration", "3", "--seed", "5", "--out", str(runs)]
    assert run_main([*argv, "--n-jobs", "1", "-q"]) == 0
    (log,) = sorted(runs.glob("*.mcap"))
    e = read_episode(log)
    c = e.metadata.controller
    assert c.tick_fields[-2:] == ("disturbance_input", "disturbance_theta") and c.settings["offset_free"] is True
    estimate = e.controller_record[:, -2]
    assert np.all(np.isfinite(e.controller_record[:, -2:])) and np.any(estimate != 0.0)
    assert np.max(np.abs(estimate)) < 0.5  # V: the twin has no load; the estimate is the model's small error


def test_a_file_with_one_disturbance_entry_reads_as_the_same_controller(models, tmp_path):
    """A file written before the MPC estimated several disturbances (``entry`` and one gain row) loads as one entry."""
    import re

    path = _design(models["with"], tmp_path / "one.toml", "--disturbances", "input")
    text = path.read_text()
    one = r'entries = \["input"\], pole = 1.0, gain = \[(\[[^\]]*\])\]'
    old = re.sub(one, r'entry = "input", pole = 1.0, gain = \1', text)
    assert old != text
    (tmp_path / "old.toml").write_text(old)
    new, before = load_controller(path), load_controller(tmp_path / "old.toml")
    assert before.runtime.disturbance.entries == ("input",) and before.tick_fields == new.tick_fields
    np.testing.assert_array_equal(before.runtime.disturbance.gain, new.runtime.disturbance.gain)
