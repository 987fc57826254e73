"""Any discrete LTI controller end to end (issue 28): a state-space controller file runs in qube-run,
its log records it, identification reads it back and recomputes its state, and qube-identify's
what-if prediction takes it; a bad file is one error naming the file and the problem."""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from _episodes import assert_follows_controller

from qube_koopman.daq.backends.serial import SerialBackend
from qube_koopman.daq.cli.run import main as run_main
from qube_koopman.core.controller import load_pd_gains, pd_controller
from qube_koopman.core.controller_file import load_controller, write_controller_file
from qube_koopman.core.controller_file import ControllerInfo
from qube_koopman.daq.log import read_episode, write_episode
from qube_koopman.daq.loop import run_episode
from qube_koopman.daq.session import excitation_settings, plan_episodes, run_seeds
from qube_koopman.daq.sinks import McapSink
from qube_koopman.identify import controller_states
from qube_koopman.identify.cli.identify import main as identify_main
from qube_koopman.identify.data.logs import load_logs
from qube_koopman.core.lti import same_system
from qube_koopman.identify.models.model_file import load_model
from qube_koopman.sim.bridge import BridgeEmulator
from qube_koopman.core.lti import padded_realization, replay_controller

RIG_PD = pd_controller(load_pd_gains("rig"))
SOFT_PD = pd_controller(load_pd_gains("soft-theta"))
N_EXTRA = 50


def _qube_run(out: Path, *argv) -> None:
    assert run_main(["--episodes", "2", "--duration", "4", "--seed", "11", "--out", str(out), "-q", *argv]) == 0


def _episodes(folder: Path) -> list:
    """The run's episodes in episode order."""
    episodes = [read_episode(p) for p in folder.glob("*.mcap")]
    return sorted(episodes, key=lambda e: e.metadata.extra["episode_index"])


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The same 2 x 4 s twin run under the rig's gains, the equal state-space file and the
    52-state realization of the same controller."""
    root = tmp_path_factory.mktemp("ss")
    files = {
        "ss": write_controller_file(root / "rig_ss.toml", RIG_PD, {"designed_by": "test: pd_controller(rig)"}),
        "big": write_controller_file(root / "big.toml", padded_realization(RIG_PD, 2 + N_EXTRA, 3)),
    }
    _qube_run(root / "pd", "--controller", "rig")
    for name, path in files.items():
        _qube_run(root / name, "--controller", str(path))
    return root, files


def test_the_rigs_pd_as_a_state_space_file_runs_sample_for_sample_like_its_gains(runs):
    root, files = runs
    pd, ss = _episodes(root / "pd"), _episodes(root / "ss")
    assert len(pd) == len(ss) == 2
    for a, b in zip(pd, ss):
        assert a.is_complete and b.is_complete and len(a) == len(b) == 2000
        for name in ("theta", "alpha", "control_output", "plant_input", "controller_state"):
            np.testing.assert_array_equal(getattr(b, name), getattr(a, name), err_msg=name)
        info = b.metadata.controller
        assert (info.kind, info.method, dict(info.gains)) == ("state-space", "given", {})
        assert info.provenance == {"designed_by": "test: pd_controller(rig)"}
        assert a.metadata.controller.kind == "pd" and a.metadata.controller.provenance == {}
    for log in load_logs(sorted((root / "ss").glob("*.mcap"))):
        episode = read_episode(log.path)
        for m in "ABCD":  # the very matrices of the gains, back from the log
            np.testing.assert_array_equal(getattr(log.controller, m), getattr(RIG_PD, m))
        assert log.controller.dt == RIG_PD.dt and log.gains is None
        recomputed = controller_states(log.controller, episode.references, episode.states)
        np.testing.assert_allclose(log.trajectory.xc, recomputed, rtol=0, atol=1e-12)


def test_a_52_state_controller_runs_and_its_state_is_recomputed_from_the_log(runs):
    root, files = runs
    big = load_controller(files["big"]).system
    assert big.n_states == 2 + N_EXTRA and np.count_nonzero(big.C) == big.n_states
    for episode in _episodes(root / "big"):
        assert episode.is_complete and episode.controller_state.shape == (2000, 2 + N_EXTRA)
        assert same_system(episode.controller, big)
        recomputed = controller_states(episode.controller, episode.references, episode.states)
        np.testing.assert_allclose(episode.controller_state, recomputed, rtol=0, atol=1e-9)
        assert np.abs(recomputed[:, 2:]).max() > 1e-3  # every state moves: not a comparison of zeros
        u = episode.controller_state @ big.C[0] + episode.tracking_error @ big.D[0]
        np.testing.assert_allclose(episode.control_output, u, rtol=0, atol=1e-9)
        # The same transfer function as the rig's PD: on the logged errors the PD gives the same output.
        # (Not the PD run's samples: rounding differently, the quantized loop drifts a count apart.)
        _, pd_output = replay_controller(RIG_PD, episode.references, episode.states)
        np.testing.assert_allclose(episode.control_output, pd_output[:, 0], rtol=0, atol=1e-9)


def test_a_52_state_controller_runs_through_the_serial_bridge_too(core, runs, tmp_path):
    """The loop's one code path, paced by the emulated bridge (lockstep) instead of the simulator."""
    info = load_controller(runs[1]["big"])
    (plan,) = plan_episodes(info, run_seeds(1, 1)[0], excitation_settings(2.0), source="test")
    emu = BridgeEmulator(seed=9, core=core, lockstep=True, lockstep_timeout=0.1)
    backend, sink = SerialBackend(emu.start(), link_timeout=0.2), McapSink(tmp_path)
    try:
        result = run_episode(backend, plan, [sink])
    finally:
        backend.close()
        emu.stop()
    assert result.complete, result.reason
    episode = read_episode(sink.paths[0])
    assert episode.metadata.backend == "serial" and episode.metadata.controller.kind == "state-space"
    assert len(episode) == 1000 and np.abs(episode.alpha).max() < np.radians(20), "balanced"
    assert_follows_controller(episode, info.system)


def test_cl_edmd_fits_the_same_plant_under_either_realization(runs, tmp_path, capsys):
    """The 52-state run's logs, identified with their controller, and the same samples with the
    2-state PD and its state recomputed: an orthogonal change of the controller's coordinates
    leaves the plant's regression data (lifted state, plant input) and its regularization
    unchanged, so the plant is the same."""
    root, _ = runs
    (tmp_path / "as_pd").mkdir()
    for path in sorted((root / "big").glob("*.mcap")):
        ep = read_episode(path)
        pd_info = ControllerInfo(RIG_PD, "backward-euler", load_pd_gains("rig").as_dict(), "pd")
        write_episode(
            tmp_path / "as_pd" / path.name,
            replace(
                ep,
                metadata=replace(ep.metadata, controller=pd_info),
                controller_state=controller_states(RIG_PD, ep.references, ep.states),
            ),
        )
    plants = {}
    for name, folder in (("big", root / "big"), ("pd", tmp_path / "as_pd")):
        logs = sorted(folder.glob("*.mcap"))
        argv = ["--train", str(logs[0]), "--test", str(logs[1]), "--delays", "2", "--out", str(tmp_path / name), "-q"]
        assert identify_main(argv) == 0, capsys.readouterr().err
        model = load_model(tmp_path / name / "model.json")
        assert model.controller.n_states == (2 if name == "pd" else 2 + N_EXTRA)
        plants[name] = model.plant
    np.testing.assert_allclose(plants["big"].A, plants["pd"].A, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(plants["big"].B, plants["pd"].B, rtol=1e-6, atol=1e-8)


def test_what_if_under_a_state_space_file_predicts_as_under_its_gains(runs, tmp_path, capsys):
    root, _ = runs
    soft_ss = write_controller_file(tmp_path / "soft_ss.toml", SOFT_PD)
    logs = sorted((root / "pd").glob("*.mcap"))
    reports = {}
    for name, controller in (
        ("gains", "rig"),
        ("ss", root / "rig_ss.toml"),
        ("soft", "soft-theta"),
        ("soft_ss", soft_ss),
    ):
        argv = [
            "--train",
            str(logs[0]),
            "--test",
            str(logs[1]),
            "--delays",
            "2",
            "--controller",
            str(controller),
            "--out",
            str(tmp_path / name),
            "-q",
        ]
        assert identify_main(argv) == 0, capsys.readouterr().err
        reports[name] = json.loads((tmp_path / name / "report.json").read_text())
    # Under the rig's controller (the logs' own): the same scored prediction.
    assert reports["ss"]["test"]["n_episodes"] == 1
    np.testing.assert_allclose(reports["ss"]["test"]["r2_mean"], reports["gains"]["test"]["r2_mean"], rtol=0, atol=1e-9)
    assert reports["soft_ss"]["what_if"]["controller"] == reports["soft"]["what_if"]["controller"]
    # Under another controller (the state recomputed from the log): the same predictions.
    from qube_koopman.identify.cli.identify import _what_if_controller
    from qube_koopman.identify.workflow import FitOptions, IdentifyOptions, ScoreOptions, identify_and_score
    from qube_koopman.identify import Delay

    train, test = load_logs(logs[:1]), load_logs(logs[1:])
    what_ifs = [_what_if_controller(str(f), 0.002) for f in ("soft-theta", soft_ss)]
    options = [IdentifyOptions(FitOptions("cl-edmd", [Delay(2)]), ScoreOptions(what_if=w)) for w in what_ifs]
    predictions = [identify_and_score(train, test, train[0].controller, o).test_predictions[0] for o in options]
    assert np.isfinite(predictions[0]).all()
    np.testing.assert_allclose(predictions[1], predictions[0], rtol=0, atol=1e-9)


# --- refusals ------------------------------------------------------------------------------------

GOOD = {
    "format": '"qube-controller/1"',
    "kind": '"state-space"',
    "dt": "0.002",
    "inputs": '["e_theta", "e_alpha"]',
    "A": "[[0.5, 0.0], [0.0, 0.5]]",
    "B": "[[1.0, 0.0], [0.0, 1.0]]",
    "C": "[[1.0, 2.0]]",
    "D": "[[-3.0, -4.0]]",
}

REFUSALS = {
    "B rows": ({"B": "[[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]]"}, "B has shape 3 x 2, expected 2 x 2"),
    "C columns": ({"C": "[[1.0, 2.0, 3.0]]"}, "C has shape 1 x 3, expected 1 x 2"),
    "D inputs": ({"D": "[[-3.0]]"}, "D has shape 1 x 1, expected 1 x 2"),
    "A square": ({"A": "[[0.5, 0.0, 0.1], [0.0, 0.5, 0.1]]"}, "A has shape 2 x 3, expected 2 x 2"),
    "ragged": ({"A": "[[0.5, 0.0], [0.5]]"}, "A has rows of different lengths"),
    "not numbers": ({"C": '[["1.0", 2.0]]'}, "C must be a matrix"),
    "nan": ({"A": "[[0.5, nan], [0.0, 0.5]]"}, "A has 1 non-finite entry (first: row 0, column 1: nan)"),
    "inf": ({"D": "[[-inf, 4.0]]"}, "D has 1 non-finite entry (first: row 0, column 0: -inf)"),
    "dt": ({"dt": "0.001"}, "dt 0.001 s differs from the sample period 0.002 s"),
    "dt not a number": ({"dt": '"2 ms"'}, "dt must be a positive number of seconds"),
    "missing C": ({"C": None}, "missing key C"),
    "missing dt": ({"dt": None}, "missing key dt"),
    "missing kind": ({"kind": None}, "missing key kind"),
    "unknown kind": ({"kind": '"lqr"'}, "unknown controller kind 'lqr'"),
    "format": ({"format": '"qube-controller/2"'}, "format 'qube-controller/2' is not supported"),
    "inputs": ({"inputs": '["e_alpha", "e_theta"]'}, 'inputs must be ["e_theta", "e_alpha"]'),
    "feedforward columns": (
        {"inputs": '["e_theta", "e_alpha", "feedforward"]'},
        "B has shape 2 x 2, expected 2 x 3 (A has 2 rows: 2 states; 3 inputs e_theta, e_alpha, "
        "feedforward; 1 output, the voltage)",
    ),
    "unknown key": ({"Q": "1"}, "unknown keys Q"),
    "npz missing": ({"matrices": '"nowhere.npz"', "A": None, "B": None, "C": None, "D": None}, "cannot read"),
    "npz and inline": ({"matrices": '"m.npz"'}, "A, B, C, D given both inline and in matrices"),
}


def _write(path: Path, changes: dict) -> Path:
    fields = {**GOOD, **changes}
    path.write_text("".join(f"{k} = {v}\n" for k, v in fields.items() if v is not None))
    return path


def test_the_documented_example_loads(tmp_path):
    info = load_controller(_write(tmp_path / "ok.toml", {}))
    assert info.kind == "state-space" and info.system.n_states == 2
    np.testing.assert_array_equal(info.system.D, [[-3.0, -4.0]])


@pytest.mark.parametrize("case", sorted(REFUSALS))
def test_each_refusal_names_the_file_and_the_problem(case, tmp_path):
    changes, message = REFUSALS[case]
    path = _write(tmp_path / "bad.toml", changes)
    with pytest.raises(ValueError) as info:
        load_controller(path)
    assert str(info.value).startswith(f"{path}: ") and message in str(info.value), str(info.value)


@pytest.mark.parametrize("case", ["B rows", "nan", "dt", "missing C", "unknown kind"])
def test_qube_run_refuses_a_bad_file_with_exit_2_and_one_line(case, tmp_path, capsys):
    changes, message = REFUSALS[case]
    path = _write(tmp_path / "bad.toml", changes)
    assert (
        run_main(["--controller", str(path), "--episodes", "1", "--duration", "1", "--out", str(tmp_path / "o")]) == 2
    )
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith(f"qube-run: error: {path}: ") and message in err and err.rstrip().endswith("(--controller)")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("case", ["D inputs", "inf", "dt"])
def test_qube_identify_refuses_a_bad_what_if_file_with_exit_2(case, runs, tmp_path, capsys):
    root, _ = runs
    changes, message = REFUSALS[case]
    path = _write(tmp_path / "bad.toml", changes)
    logs = sorted((root / "pd").glob("*.mcap"))
    argv = ["--train", str(logs[0]), "--test", str(logs[1]), "--controller", str(path), "--out", str(tmp_path / "o")]
    assert identify_main(argv) == 2
    err = capsys.readouterr().err
    assert re.fullmatch(rf"qube-identify: error: {re.escape(str(path))}: .*\n", err) and message in err
    assert not (tmp_path / "o").exists()


def test_matrices_in_a_sibling_npz_load_as_inline(tmp_path):
    big = padded_realization(RIG_PD, 12, 0)
    inline = load_controller(write_controller_file(tmp_path / "inline.toml", big))
    npz = load_controller(write_controller_file(tmp_path / "npz.toml", big, npz=True))
    assert 'matrices = "npz.npz"' in (tmp_path / "npz.toml").read_text()
    for m in "ABCD":
        np.testing.assert_array_equal(getattr(npz.system, m), getattr(big, m))
        np.testing.assert_array_equal(getattr(inline.system, m), getattr(big, m))
    np.savez(tmp_path / "npz.npz", A=big.A, B=big.B, C=big.C)
    with pytest.raises(ValueError, match=r"npz\.toml: .*npz\.npz holds no array D"):
        load_controller(tmp_path / "npz.toml")


def test_pd_gains_files_load_as_before(tmp_path):
    for name, gains in (("rig", RIG_PD), ("soft-theta", SOFT_PD)):
        info = load_controller(name)
        assert info.kind == "pd" and info.method == "backward-euler" and same_system(info.system, gains)
    with pytest.raises(ValueError, match="missing gains tau"):
        load_controller(_gains(tmp_path, "tau"))


def _gains(tmp_path: Path, drop: str) -> Path:
    path = tmp_path / "gains.toml"
    path.write_text(
        "".join(f"{k} = 1.0\n" for k in ("kp_theta", "kd_theta", "kp_alpha", "kd_alpha", "tau") if k != drop)
    )
    return path
