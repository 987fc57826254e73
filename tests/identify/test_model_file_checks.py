"""A model file that cannot be used is one error naming the file and the entry, never a traceback."""

from __future__ import annotations

import json

import numpy as np
import pytest


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    from qube_koopman.daq.cli.run import main as run_main
    from qube_koopman.identify.cli.identify import main as identify_main

    root = tmp_path_factory.mktemp("model")
    assert run_main(["--episodes", "2", "--duration", "3", "--seed", "4", "--out", str(root / "logs"), "-q"]) == 0
    logs = sorted(map(str, (root / "logs").glob("*.mcap")))
    assert (
        identify_main(
            ["--train", logs[0], "--test", logs[1], "--delays", "5", "--poly", "1", "--out", str(root / "m"), "-q"]
        )
        == 0
    )
    return root / "m" / "model.json"


def _damaged(model_file, tmp_path, change) -> str:
    data = json.loads(model_file.read_text())
    change(data)
    path = tmp_path / "damaged.json"
    path.write_text(json.dumps(data))  # json writes NaN and Infinity, as a hand-edited file may hold
    return str(path)


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda d: d["plant"]["A"][2].__setitem__(3, float("nan")), "plant.A has a non-finite entry (nan) at [2, 3]"),
        (
            lambda d: d["closed_loop"]["B"][0].__setitem__(0, float("inf")),
            "closed_loop.B has a non-finite entry (inf) at [0, 0]",
        ),
        (lambda d: d["plant"]["B"].pop(), "plant: "),
        (
            lambda d: d["lifting"]["steps"][0].__setitem__("n_delays", 10**9),
            "lifting: number of delays 1000000000 is more than this reader takes (10000)",
        ),
        (
            lambda d: d["lifting"]["steps"][0].__setitem__("n_delays", 1e9),
            "lifting: number of delays must be an integer",
        ),
        (
            lambda d: d.__setitem__("dt", float("nan")),
            "dt must be a positive number of seconds (the sample period), got nan",
        ),
        (lambda d: d.__setitem__("dt", 0.01), "sample period 0.01 s, not the loop's 0.002 s"),
        (lambda d: d.__setitem__("plant", None), "the model file holds no plant model"),
    ],
    ids=["nan", "inf", "shape", "huge-delays", "float-delays", "dt-nan", "dt-other", "no-plant"],
)
def test_qube_design_refuses_an_unusable_model_in_one_line(model_file, tmp_path, capsys, change, message):
    from qube_koopman.design.cli.design import main as design_main

    path = _damaged(model_file, tmp_path, change)
    assert design_main([path, "--out", str(tmp_path / "c.toml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"qube-design: error: {path}: ") and message in err[0], err
    assert not (tmp_path / "c.toml").exists()


@pytest.mark.parametrize("command", ["design", "calibrate"])
@pytest.mark.parametrize(
    "out, message",
    [
        ("missing/x.toml", "folder {tmp}/missing does not exist (--out)"),
        ("afolder", "is a folder; --out names the file to write"),
    ],
)
def test_an_output_that_cannot_be_written_is_refused_before_any_work(
    command, out, message, model_file, tmp_path, capsys, monkeypatch
):
    from qube_koopman.design import controller_design
    from qube_koopman.design.cli.design import main as design_main
    from qube_koopman.identify.calibrate import PlantCalibration
    from qube_koopman.identify.cli.calibrate import main as calibrate_main

    def no_work(*args, **kwargs):
        raise AssertionError("the work started before the output was checked")

    monkeypatch.setattr(controller_design, "design_from_model", no_work)
    monkeypatch.setattr(PlantCalibration, "fit", no_work)
    (tmp_path / "afolder").mkdir()
    target = str(tmp_path / out)
    logs = str(model_file.parents[1] / "logs")
    status = (
        design_main([str(model_file), "--out", target])
        if command == "design"
        else calibrate_main([logs, "--out", target])
    )
    assert status == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].endswith(message.format(tmp=tmp_path)), err


def test_an_unstable_what_if_controller_is_named_with_its_spectral_radius(model_file, tmp_path, capsys):
    from qube_koopman.core.controller_file import write_controller_file
    from qube_koopman.identify.cli.identify import main as identify_main
    from qube_koopman.core.lti import DiscreteStateSpace

    logs = sorted(map(str, (model_file.parents[1] / "logs").glob("*.mcap")))
    bad = tmp_path / "unstable.toml"
    write_controller_file(bad, DiscreteStateSpace(1.5 * np.eye(2), np.eye(2), np.ones((1, 2)), np.zeros((1, 2)), 0.002))
    assert (
        identify_main(
            [
                "--train",
                logs[0],
                "--test",
                logs[1],
                "--delays",
                "5",
                "--controller",
                str(bad),
                "--out",
                str(tmp_path / "o"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{bad}: the controller is unstable on its own (spectral radius of A 1.5 > 1)" in err[0]
    assert not (tmp_path / "o").exists()
    # an integrator is a controller (a designed controller's integral action): accepted
    integrating = tmp_path / "integral.toml"
    write_controller_file(
        integrating, DiscreteStateSpace(np.eye(1), np.ones((1, 2)), np.ones((1, 1)), np.zeros((1, 2)), 0.002)
    )
    assert (
        identify_main(
            [
                "--train",
                logs[0],
                "--test",
                logs[1],
                "--delays",
                "5",
                "--controller",
                str(integrating),
                "--out",
                str(tmp_path / "i"),
                "-q",
            ]
        )
        == 0
    )


def test_the_designs_saturation_warning_names_the_peak_and_the_clamp():
    # qube-design prints it as a `qube-design: warning:` line on stderr, apart from the report on stdout
    from types import SimpleNamespace

    from qube_koopman.design.controller_design import saturation_warning

    def report(peak):
        return SimpleNamespace(predicted=SimpleNamespace(summary=lambda: {"voltage_peak": peak}))

    assert saturation_warning(report(6.0)) is None
    assert "peaks at 12.50 V, beyond the loop's 10 V clamp" in saturation_warning(report(12.5))


def test_the_model_file_writes_a_matrix_by_rows_and_leaves_text_as_it_is():
    """Each innermost list of numbers on one line; a string that reads like a list (a log's name, a note) is
    never rewritten, and the file loads back to the same data."""
    from qube_koopman.identify.models.model_file import _dumps

    data = {
        "A": [[1.0, -2e-05, 3], [4, 5, 6]],
        "note": "x [1,2] y",
        "logs": ["[3,4]", "b"],
        "n": [float("nan"), 1.0],
        "empty": [],
        "one": [0],
    }
    text = _dumps(data)
    assert "  [1.0, -2e-05, 3],\n  [4, 5, 6]\n" in text and '"one": [0]' in text
    back = json.loads(text)
    assert back["note"] == "x [1,2] y" and back["logs"] == ["[3,4]", "b"] and back["A"] == data["A"]
    assert np.isnan(back["n"][0]) and back["n"][1] == 1.0 and back["empty"] == []


def test_qube_design_refuses_a_deeply_nested_or_special_model_file_in_one_line(tmp_path, capsys):
    # A parser that recurses is never asked for 100000 levels; a named pipe is never waited on.
    import os

    from qube_koopman.design.cli.design import main as design_main

    deep = tmp_path / "deep.json"
    deep.write_text('{"format": "qube-koopman-model", "version": 1, "x": ' + "[" * 100_000 + "]" * 100_000 + "}")
    pipe = tmp_path / "pipe.json"
    os.mkfifo(pipe)
    for path, message in [
        (deep, "lists and tables nested more than 64 levels deep"),
        (pipe, "a named pipe, not a regular file: not read as the model file"),
    ]:
        assert design_main([str(path), "--out", str(tmp_path / "c.toml")]) == 2
        err = capsys.readouterr().err
        assert err == f"qube-design: error: {path}: {message}\n"


def test_a_write_error_names_the_file_and_leaves_the_folder_as_it_was(model_file, tmp_path, capsys, monkeypatch):
    # The disk fills while report.md is written: model.json and report.json, written before it, must
    # not be left without it (nor replace the previous run's files); the error names report.md.
    import errno
    import os
    import shutil

    import qube_koopman.identify.report.markdown as markdown
    from qube_koopman.identify.cli.identify import main as identify_main

    out = tmp_path / "m"
    shutil.copytree(model_file.parent, out)
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}

    def full_disk(path, report):
        tmp = path.with_name(f".{path.name}.0123.part.md")
        tmp.write_text("half a rep")
        tmp.unlink()
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp))

    monkeypatch.setattr(markdown, "write_markdown_report", full_disk)
    logs = sorted(map(str, (model_file.parent.parent / "logs").glob("*.mcap")))
    capsys.readouterr()
    assert (
        identify_main(
            ["--train", logs[0], "--test", logs[1], "--delays", "5", "--poly", "1", "--out", str(out), "--force", "-q"]
        )
        == 1
    )
    err = capsys.readouterr().err
    assert err == f"qube-identify: error: {out / 'report.md'}: cannot write: No space left on device; nothing written\n"
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before  # no staged file left either
