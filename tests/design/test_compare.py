"""``qube-compare``: episodes run under a designed controller against what its design predicted.

- logs whose samples are the model's own prediction of the designed loop measure exactly the predicted
  figures, and on the design's excitation the comparison gives the controller file's predicted figures and
  interval again (the prediction is made again from the provenance, not copied from it);
- bad input is one line naming the file, exit 1: a log of another controller, a controller file
  qube-design did not write, a model file that is missing or not the one designed on.

The comparison on the twin (a design from a model identified on twin episodes, its episodes run by
``qube-run``) is in test_design.py, beside the runs it shares.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest
from test_design_uncertainty import _members, _plant, _save, _spectra

from qube_koopman.core.controller_file import load_controller
from qube_koopman.daq.episode import Episode, EpisodeMetadata
from qube_koopman.daq.log import write_episode
from qube_koopman.daq.session import excitation_record, excitation_settings, run_seeds
from qube_koopman.design.cli.compare import main as compare_main
from qube_koopman.design.cli.design import main as design_main
from qube_koopman.design.compare import compare_runs
from qube_koopman.design.predict import predict_loop, rig_excitations

SEED, EPISODES, DURATION = 3, 2, 4.0


@pytest.fixture(scope="module")
def designed(tmp_path_factory) -> Path:
    """A design on a small plant model with bootstrap plants and error spectra (an interval propagated through
    the loop), predicted on the excitation of ``qube-run --seed 3 --episodes 2 --duration 4``."""
    root = tmp_path_factory.mktemp("designed")
    plant = _plant()
    _save(root / "model.json", plant, _members(plant), _spectra())
    out = root / "designed.toml"
    argv = [
        str(root / "model.json"),
        "--out",
        str(out),
        "--seed",
        str(SEED),
        "--episodes",
        str(EPISODES),
        "--duration",
        str(DURATION),
        "-q",
    ]
    assert design_main(argv) == 0
    return out


def _logs_of_the_prediction(controller_file: Path, folder: Path, status: str = "complete") -> list[Path]:
    """Episode logs under the controller whose samples are the model's prediction of the loop (from upright) on
    the design's excitation: what the rig would measure were the model exact."""
    from qube_koopman.identify.models.model_file import load_model

    info = load_controller(controller_file)
    model = load_model(controller_file.parent / "model.json")
    loop = predict_loop(model.plant, info.system, rig_excitations(SEED, EPISODES, DURATION))
    seeds, _ = run_seeds(SEED, EPISODES)
    folder.mkdir()
    paths = []
    for i in range(EPISODES):
        n = loop.theta.shape[1]
        meta = EpisodeMetadata(
            info,
            500.0,
            "sim",
            "test",
            "2026-12-02T00:00:00+00:00",
            excitation=excitation_record(seeds[i], excitation_settings(DURATION)),
            status=status,
            status_reason="" if status == "complete" else "alpha limit",
        )
        zeros = np.zeros(n)
        episode = Episode(
            t=np.arange(n) / 500.0,
            theta=loop.theta[i],
            alpha=loop.alpha[i],
            target_theta=loop.target_theta[i],
            target_alpha=zeros,
            feedforward=zeros,
            controller_state=np.zeros((n, info.system.n_states)),
            control_output=loop.voltage[i],
            plant_input=loop.voltage[i],
            saturation=np.zeros(n, dtype=int),
            metadata=meta,
        )
        paths.append(write_episode(folder / f"qube_{i}.mcap", episode))
    return paths


def test_the_models_own_loop_measures_the_prediction_and_the_design_excitation_gives_the_files_figures(
    designed, tmp_path, capsys
):
    logs = _logs_of_the_prediction(designed, tmp_path / "runs")
    comparison = compare_runs(designed, logs)
    provenance = tomllib.loads(designed.read_text())["provenance"]
    assert comparison.design_excitation and comparison.model_path == designed.parent / "model.json"
    for name in ("J", "tracking_rms", "voltage_rms"):
        # measured with the same definition as predicted: the model's own loop measures its prediction
        assert comparison.measured[name] == pytest.approx(comparison.predicted[name], rel=1e-9), name
        # made again from the provenance (model, weights), on the logs' excitations: the file's figures
        assert comparison.predicted[name] == pytest.approx(provenance["predicted"][name], rel=1e-9), name
    iv = comparison.interval
    for name in ("J", "voltage_rms"):
        written = provenance["interval"][name]
        assert (iv.lower[name], iv.upper[name]) == pytest.approx((written["lower"], written["upper"]), rel=1e-9)
        assert comparison.inside(name) == (written["lower"] <= comparison.measured[name] <= written["upper"])
    assert iv.propagated and comparison.inside("tracking_rms") is None  # no interval is made for it

    assert compare_main([str(designed), str(tmp_path / "runs")]) == 0
    out = capsys.readouterr().out.splitlines()
    assert (
        out[1] == "2 episodes compared, after the first second, predicted by the model on the excitation it was "
        "designed on"
    )
    row = next(line for line in out if line.lstrip().startswith("J (rad^2)"))
    J = provenance["interval"]["J"]
    assert row.split()[2:] == [
        f"{comparison.measured['J']:.3e}",
        f"{provenance['predicted']['J']:.3e}",
        f"{J['expected']:.3e}",
        f"{J['lower']:.3e}",
        "to",
        f"{J['upper']:.3e}",
        "yes" if comparison.inside("J") else "no",
    ]
    assert out[-1] == "measured J +0.0 % against the prediction"


def test_a_subset_of_the_run_is_predicted_on_its_own_excitations_and_stopped_episodes_are_left_out(
    designed, tmp_path, capsys
):
    logs = _logs_of_the_prediction(designed, tmp_path / "runs")
    one = compare_runs(designed, logs[1:])
    assert not one.design_excitation and one.measured["J"] == pytest.approx(one.predicted["J"], rel=1e-9)
    stopped = _logs_of_the_prediction(designed, tmp_path / "stopped", status="aborted")
    both = compare_runs(designed, [stopped[0], logs[1]])
    assert both.logs == (logs[1],) and both.skipped == ((stopped[0], "aborted"),)
    assert both.predicted["J"] == pytest.approx(one.predicted["J"], rel=1e-12)
    assert compare_main([str(designed), *map(str, stopped)]) == 1
    assert capsys.readouterr().err == "qube-compare: error: no complete episode among the 2 logs: nothing to compare\n"


def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err.removeprefix("qube-compare: error: ").rstrip("\n")


def test_bad_input_is_one_line_naming_the_file(designed, tmp_path, capsys):
    from qube_koopman.daq.cli.run import main as run_main

    pd_runs = tmp_path / "pd"
    assert run_main(["--episodes", "1", "--duration", "2", "--seed", "1", "--out", str(pd_runs), "-q"]) == 0
    (pd_log,) = pd_runs.glob("*.mcap")
    assert compare_main([str(designed), str(pd_log)]) == 1
    assert _one_line(capsys) == f"{pd_log}: recorded under another controller (pd, 2 states), not {designed}"

    gains = tmp_path / "gains.toml"
    gains.write_text("kp_theta = 6.0\nkd_theta = 1.8\nkp_alpha = 30.0\nkd_alpha = 2.5\ntau = 50.0\n")
    assert compare_main([str(gains), str(pd_log)]) == 1
    assert (
        _one_line(capsys) == f"{gains}: PD gains; the comparison predicts an LQ design qube-design wrote "
        "(kind 'state-space')"
    )

    logs = _logs_of_the_prediction(designed, tmp_path / "runs")
    moved = tmp_path / "elsewhere" / "designed.toml"
    moved.parent.mkdir()
    moved.write_text(designed.read_text().replace(str(designed.parent / "model.json"), "gone/model.json"))
    assert compare_main([str(moved), *map(str, logs)]) == 1
    assert (
        _one_line(capsys) == f"{moved}: its model file gone/model.json is not there (nor beside the controller "
        "file); give it with --model"
    )
    other = _save(tmp_path / "other.json", _plant(seed=1))
    assert compare_main([str(moved), *map(str, logs), "--model", str(other)]) == 1
    assert (
        _one_line(capsys) == f"{moved}: designed again from {other} with its weights, it is another controller: "
        "the model file is not the one it was designed on"
    )
    assert compare_main([str(moved), *map(str, logs), "--model", str(tmp_path / "none.json")]) == 2
    assert _one_line(capsys) == f"{tmp_path / 'none.json'}: no such model file (--model)"
    assert compare_main([str(moved), *map(str, logs), "--model", str(designed.parent / "model.json")]) == 0
    assert compare_main([str(designed), str(tmp_path / "nothing")]) == 2  # a usage error, as in every command
    assert _one_line(capsys) == f"{tmp_path / 'nothing'}: no such file or folder"
