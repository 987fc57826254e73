"""A controller that takes the feedforward as a third input (issue 28 section 1): the loop still adds
the feedforward to its output, and the controller also sees it. The file format, the loop's step, the
log, the state recomputed from the log, CL EDMD's closed-loop structure and the what-if prediction
all carry the extra input; with zero feedforward columns everything equals the two-input controller.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from _episodes import assert_follows_controller
from linear_loops import closed_loop_trajectories, mass_spring_damper, pid_position_controller

from qube_koopman.daq.cli.run import main as run_main
from qube_koopman.core.controller import load_pd_gains, pd_controller
from qube_koopman.core.controller_file import load_controller, write_controller_file
from qube_koopman.daq.controller_step import controller_step
from qube_koopman.daq.log import read_episode
from qube_koopman.identify import (
    ClEdmd,
    close_loop,
    closed_loop_matrices,
    controller_states,
    extract_plant_lstsq,
    output_selection,
)
from qube_koopman.identify.cli.identify import main as identify_main
from qube_koopman.identify.data.logs import load_logs
from qube_koopman.core.lti import same_system
from qube_koopman.identify.models.model_file import load_model
from qube_koopman.identify.metrics import r2_score
from qube_koopman.core.qube import MEASURED
from qube_koopman.core.lti import DiscreteStateSpace, controller_inputs, padded_realization

RIG_PD = pd_controller(load_pd_gains("rig"))


def with_feedforward(controller: DiscreteStateSpace, b_f, d_f: float) -> DiscreteStateSpace:
    """``controller`` with a feedforward input: B gains the column ``b_f``, D the entry ``d_f``."""
    B = np.hstack([controller.B, np.asarray(b_f, dtype=float).reshape(-1, 1)])
    D = np.hstack([controller.D, [[d_f]]])
    return DiscreteStateSpace(controller.A, B, controller.C, D, controller.dt)


# --- the closed-loop structure, on a linear plant (ground truth) ---------------------------------------


@pytest.fixture(scope="module")
def linear():
    A_p, B_p = mass_spring_damper()
    controller = with_feedforward(pid_position_controller(), [0.2, 0.1], -0.5)
    return A_p, B_p, controller, closed_loop_trajectories(A_p, B_p, controller, measured=[0], n_episodes=4, seed=5)


def test_cl_edmd_recovers_the_plant_under_a_controller_that_sees_the_feedforward(linear):
    A_p, B_p, controller, trajs = linear
    model = ClEdmd(controller, measured=[0]).fit(trajs)
    np.testing.assert_allclose(model.plant_model_.A, A_p, atol=1e-8)
    np.testing.assert_allclose(model.plant_model_.B, B_p, atol=1e-8)
    A_f, B_f = closed_loop_matrices(A_p, B_p, controller, output_selection(2, [0]), 1)
    np.testing.assert_allclose(model.koopman_matrix_, np.hstack([A_f, B_f]), atol=1e-8)
    # The feedforward's column of the closed loop is [B^c_f; B^p (1 + D^c_f)], not the paper's [0; B^p].
    np.testing.assert_allclose(B_f[:2, 1], controller.B[:, 1], rtol=0, atol=1e-15)
    np.testing.assert_allclose(B_f[2:, 1], B_p[:, 0] * (1 + controller.D[0, 1]), rtol=0, atol=1e-15)
    # The paper's least-squares extraction inverts the same structure.
    A_x, B_x = extract_plant_lstsq(np.hstack([A_f, B_f]), controller, output_selection(2, [0]), 1)
    np.testing.assert_allclose(A_x, A_p, atol=1e-12)
    np.testing.assert_allclose(B_x, B_p, atol=1e-12)
    # And the controller's state, recomputed from the data with the feedforward, is the simulated one.
    for t in trajs:
        np.testing.assert_allclose(controller_states(controller, t.r, t.x[:, [0]], t.f), t.xc, rtol=0, atol=1e-12)


def test_the_sdp_built_apart_agrees_with_the_closed_form(linear):
    from qube_koopman.identify import ClEdmdSdp

    A_p, B_p, controller, trajs = linear
    sdp = ClEdmdSdp(controller, measured=[0]).fit(trajs)
    np.testing.assert_allclose(sdp.plant_model_.A, A_p, atol=1e-5)
    np.testing.assert_allclose(sdp.plant_model_.B, B_p, atol=1e-5)


def test_zero_feedforward_columns_are_the_two_input_controller(linear):
    A_p, B_p, _, _ = linear
    plain = pid_position_controller()
    C_p = output_selection(2, [0])
    wide = with_feedforward(plain, [0.0, 0.0], 0.0)
    for a, b in zip(closed_loop_matrices(A_p, B_p, wide, C_p, 1), closed_loop_matrices(A_p, B_p, plain, C_p, 1)):
        np.testing.assert_array_equal(a, b)


def test_a_feedforward_input_without_feedforward_data_is_refused(linear):
    A_p, B_p, controller, trajs = linear
    bare = [t.__class__(x=t.x, u=t.u, r=t.r, xc=t.xc, dt=t.dt, name=t.name) for t in trajs]
    with pytest.raises(ValueError, match="no feedforward"):
        ClEdmd(controller, measured=[0]).fit(bare)
    with pytest.raises(ValueError, match="no feedforward is given"):
        controller_inputs(controller, trajs[0].r, trajs[0].x[:, [0]])


# --- the loop's step ---------------------------------------------------------------------------------


@pytest.mark.parametrize("n_states", [2, 12], ids=["plain floats", "numpy"])
def test_the_loops_step_runs_the_third_input_as_the_state_space_system_does(n_states):
    controller = with_feedforward(padded_realization(RIG_PD, n_states, 4), np.linspace(-1, 1, n_states), -0.5)
    inputs = np.random.default_rng(3).standard_normal((200, 3)) * [0.1, 0.05, 0.5]
    states, outputs = controller.simulate(inputs)
    output, update = controller_step(controller)
    for k, (e0, e1, f) in enumerate(inputs.tolist()):
        u, x = output(e0, e1, f)
        np.testing.assert_allclose(x, states[k], rtol=0, atol=1e-12)
        assert abs(u - outputs[k, 0]) <= 1e-12
        update(e0, e1, f)


def test_the_loops_step_of_a_two_input_controller_ignores_the_feedforward():
    output, update = controller_step(RIG_PD)
    other_output, other_update = controller_step(RIG_PD)
    for e0, e1, f in np.random.default_rng(4).standard_normal((50, 3)).tolist():
        assert output(e0, e1, f) == other_output(e0, e1, 0.0)
        update(e0, e1, f)
        other_update(e0, e1, 0.0)


# --- on the twin, end to end -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    """2 x 4 s twin episodes under the rig's PD and under the PD that also halves the feedforward and
    feeds it to its theta filter."""
    root = tmp_path_factory.mktemp("ff")
    controller = with_feedforward(RIG_PD, [0.01, 0.0], -0.5)
    path = write_controller_file(root / "ff.toml", controller, {"designed_by": "test: PD seeing the feedforward"})
    for name, choice in (("pd", "rig"), ("ff", str(path))):
        argv = [
            "--episodes",
            "2",
            "--duration",
            "4",
            "--seed",
            "11",
            "--out",
            str(root / name),
            "-q",
            "--controller",
            choice,
        ]
        assert run_main(argv) == 0
    return root, path, controller


#: A lifting that identifies the twin's plant from one 4 s episode (R^2 about 0.98 on another).
FLAGS = ["--delays", "20", "--const"]


def _logs(folder: Path) -> list[Path]:
    return sorted(folder.glob("*.mcap"), key=lambda p: read_episode(p).metadata.extra["episode_index"])


def test_the_file_reads_back_and_the_twin_runs_it_as_written(twin):
    root, path, controller = twin
    assert 'inputs = ["e_theta", "e_alpha", "feedforward"]' in path.read_text()
    loaded = load_controller(path).system
    for m in "ABCD":
        np.testing.assert_array_equal(getattr(loaded, m), getattr(controller, m))
    for log in _logs(root / "ff"):
        episode = read_episode(log)
        assert episode.is_complete and len(episode) == 2000
        assert same_system(episode.metadata.controller.system, controller)
        assert episode.metadata.controller.provenance == {"designed_by": "test: PD seeing the feedforward"}
        # State recomputed from the log with the feedforward; output C x + D [e; f]; input clip(u + f).
        assert_follows_controller(episode, controller)
        # The third input matters: without it the output would differ by far more than round-off.
        without = episode.controller_state @ RIG_PD.C[0] + episode.tracking_error @ RIG_PD.D[0]
        assert np.abs(episode.control_output - without).max() > 0.05


def test_a_plant_identified_under_the_pd_predicts_the_loop_under_the_feedforward_controller(twin, tmp_path, capsys):
    """A test log is predicted under its own recorded controller: here the one that sees the feedforward.
    Closing the same plant with the PD alone (the third input dropped) leaves 3 times the residual."""
    root, path, controller = twin
    pd, ff = _logs(root / "pd"), _logs(root / "ff")
    argv = ["--train", str(pd[0]), "--test", str(ff[1]), *FLAGS, "--out", str(tmp_path / "m"), "-q"]
    assert identify_main(argv) == 0, capsys.readouterr().err
    scored = json.loads((tmp_path / "m" / "report.json").read_text())["test"]["r2_mean"]
    assert scored > 0.95
    plant = load_model(tmp_path / "m" / "model.json").plant
    (log,) = load_logs([ff[1]])
    t = log.trajectory
    right = r2_score(t.x, close_loop(plant, controller, MEASURED).predict(t))
    dropped = replace(t, xc=controller_states(RIG_PD, t.r, t.x[:, MEASURED]))
    wrong = r2_score(t.x, close_loop(plant, RIG_PD, MEASURED).predict(dropped))
    assert right > 0.95
    assert 1 - wrong > 2 * (1 - right), (right, wrong)  # measured: 0.976 vs 0.922, 3.2x the residual
    # The what-if path: the PD's test log predicted under the feedforward controller's file.
    argv = [
        "--train",
        str(pd[0]),
        "--test",
        str(pd[1]),
        *FLAGS,
        "--controller",
        str(path),
        "--out",
        str(tmp_path / "what_if"),
        "-q",
    ]
    assert identify_main(argv) == 0, capsys.readouterr().err
    assert json.loads((tmp_path / "what_if" / "report.json").read_text())["what_if"]


def test_cl_edmd_on_the_feedforward_controllers_logs_records_its_three_inputs(twin, tmp_path, capsys):
    root, _, controller = twin
    ff = _logs(root / "ff")
    argv = ["--train", str(ff[0]), "--test", str(ff[1]), *FLAGS, "--out", str(tmp_path / "m"), "-q"]
    assert identify_main(argv) == 0, capsys.readouterr().err
    model = load_model(tmp_path / "m" / "model.json")
    assert same_system(model.controller, controller)
    report = json.loads((tmp_path / "m" / "report.json").read_text())
    assert report["test"]["r2_mean"] > 0.95
