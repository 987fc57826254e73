"""Shared command-line plumbing (core.cli, core.console, core.command): every command answers --version."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(
    "module, prog",
    [
        ("qube_koopman.daq.cli.run", "qube-run"),
        ("qube_koopman.daq.cli.import_csv", "qube-import"),
        ("qube_koopman.sim.cli.emulate", "qube-emulate"),
        ("qube_koopman.reproduce.cli.reproduce", "qube-reproduce"),
    ],
)
def test_version(module, prog):
    from qube_koopman.core.cli import package_version

    proc = subprocess.run(
        [sys.executable, "-m", module, "--version"], capture_output=True, text=True, cwd=REPO, timeout=60
    )
    assert proc.returncode == 0 and proc.stdout == f"{prog} {package_version()}\n", proc.stderr
    assert package_version() != ""


@pytest.mark.parametrize("terminal", [True, False])
def test_the_progress_callback_draws_on_a_terminal_only(terminal, capsys, monkeypatch):
    from qube_koopman.core.console import ProgressCallback

    monkeypatch.setattr(sys.stderr, "isatty", lambda: terminal)
    progress = ProgressCallback()
    for done in range(4):
        progress("cross-validation", done, 3)
    progress("alpha sweep", 1, 2)  # a new label: a new bar
    progress.close()
    err = capsys.readouterr().err
    if terminal:
        assert "cross-validation" in err and "3/3" in err and "alpha sweep" in err and "1/2" in err
    else:
        assert err == ""


# One error style for every command: `<command>: error: <file>: <problem>`, a non-zero exit, no traceback.
BAD_ARGUMENTS = [  # module, program, arguments, the file the error must name first
    (
        "qube_koopman.daq.cli.run",
        "qube-run",
        ["--controller", "{binary}", "--episodes", "1", "--duration", "1", "--out", "o", "-q"],
        "{binary}",
    ),
    (
        "qube_koopman.daq.cli.import_csv",
        "qube-import",
        ["{binary}", "--controller", "{binary}", "--out", "o", "-q"],
        "{binary}",
    ),
    ("qube_koopman.daq.cli.export", "qube-export", ["{binary}", "--format", "csv", "--out", "o", "-q"], "{binary}"),
    (
        "qube_koopman.identify.cli.identify",
        "qube-identify",
        ["--train", "{missing}", "--test", "{missing}", "--out", "o"],
        "{missing}",
    ),
    ("qube_koopman.reproduce.cli.reproduce", "qube-reproduce", ["duffing", "--out", "{binary}"], "{binary}"),
    ("qube_koopman.sim.cli.emulate", "qube-emulate", ["--record", "{missing}/x.csv", "-q"], "{missing}/x.csv"),
]


@pytest.mark.parametrize("module, prog, argv, named", BAD_ARGUMENTS, ids=[case[1] for case in BAD_ARGUMENTS])
def test_every_command_reports_a_bad_file_as_command_error_file_problem(module, prog, argv, named, tmp_path):
    paths = {"binary": tmp_path / "bin.dat", "missing": tmp_path / "missing"}
    paths["binary"].write_bytes(b"\x7fELF\x02\x01\x01" + bytes(500))
    proc = subprocess.run(
        [sys.executable, "-m", module, *(a.format(**paths) for a in argv)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=120,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    assert proc.returncode != 0 and "Traceback" not in proc.stderr, proc.stderr
    errors = [line for line in proc.stderr.splitlines() if ": error: " in line]
    assert errors and errors[0].startswith(f"{prog}: error: {named.format(**paths)}: "), proc.stderr


def test_qube_identify_refuses_a_rerun_file_in_a_missing_folder_before_any_work(tmp_path, capsys):
    pytest.importorskip("rerun")
    from qube_koopman.identify.cli.identify import main

    target = tmp_path / "no" / "such" / "id.rrd"
    status = main(
        [
            "--train",
            str(tmp_path),
            "--test",
            str(tmp_path),
            "--out",
            str(tmp_path / "model"),
            "--rerun-save",
            str(target),
        ]
    )
    assert status == 2
    assert capsys.readouterr().err == (
        f"qube-identify: error: {target}: folder {target.parent} does not exist (--rerun-save)\n"
    )
    assert not (tmp_path / "model").exists()  # refused before the output folder, the data or the fit


# A negative seed is a usage error naming the option (numpy refused it with a traceback before).
NEGATIVE_SEEDS = [
    ("qube_koopman.daq.cli.run", ["--seed", "-5", "--episodes", "1", "--duration", "0.2"], "--seed"),
    ("qube_koopman.sim.cli.emulate", ["--seed", "-5"], "--seed"),
    ("qube_koopman.reproduce.cli.reproduce", ["duffing", "--seed", "-5"], "--seed"),
    (
        "qube_koopman.identify.cli.identify",
        ["--train", "x", "--test", "y", "--rbf", "thin-plate", "--rbf-seed", "-5"],
        "--rbf-seed",
    ),
    ("qube_koopman.identify.cli.identify", ["--train", "x", "--test", "y", "--cv-seed", "-5"], "--cv-seed"),
]


@pytest.mark.parametrize(
    "module, argv, option", NEGATIVE_SEEDS, ids=[f"{c[0].rsplit('.')[-1]} {c[2]}" for c in NEGATIVE_SEEDS]
)
def test_a_negative_seed_is_a_usage_error_naming_the_option(module, argv, option, tmp_path, capsys, monkeypatch):
    import importlib

    monkeypatch.chdir(tmp_path)
    try:
        status = importlib.import_module(module).main(argv)
    except SystemExit as exc:  # the commands that leave usage errors to argparse
        status = exc.code
    err = capsys.readouterr().err
    assert status == 2 and "Traceback" not in err, err
    assert f"error: argument {option}: must be a whole number >= 0, got -5" in err, err
    assert list(tmp_path.iterdir()) == []  # refused before any work


@pytest.mark.parametrize(
    "option, value, minimum",
    [("--skip", "-1", 0), ("--delays", "-2", 0), ("--poly", "0", 1), ("--cv-splits", "0", 1), ("--arx-lags", "-3", 1)],
)
def test_qube_identify_names_the_option_and_value_out_of_range_before_loading(option, value, minimum, tmp_path, capsys):
    from qube_koopman.identify.cli.identify import main

    with pytest.raises(SystemExit) as exc:  # the logs do not exist: refused before looking for them
        main(["--train", str(tmp_path / "missing"), "--test", str(tmp_path / "missing"), option, value])
    err = capsys.readouterr().err
    assert exc.value.code == 2
    assert f"error: argument {option}: must be a whole number >= {minimum}, got {value}" in err, err
    assert "missing" not in err.splitlines()[-1]


@pytest.mark.parametrize(
    "module, prog, argv",
    [
        ("qube_koopman.daq.cli.import_csv", "qube-import", ["{missing}", "--out", "{tmp}/o"]),
        ("qube_koopman.daq.cli.export", "qube-export", ["{missing}", "--format", "csv", "--out", "{tmp}/o"]),
        ("qube_koopman.daq.cli.import_csv", "qube-import", ["{tmp}", "--out", "{tmp}/o"]),  # a folder without any
        ("qube_koopman.identify.cli.identify", "qube-identify", ["--train", "{missing}", "--test", "{missing}"]),
        ("qube_koopman.identify.cli.calibrate", "qube-calibrate", ["{missing}", "--out", "{tmp}/p.toml"]),
        ("qube_koopman.reproduce.cli.reproduce", "qube-reproduce", ["qube", "--data", "{missing}", "--out", "{tmp}/o"]),
    ],
    ids=["qube-import", "qube-export", "qube-import empty folder", "qube-identify", "qube-calibrate", "qube-reproduce"],
)
def test_a_missing_input_is_a_usage_error_in_every_command(module, prog, argv, tmp_path, capsys):
    import importlib

    status = importlib.import_module(module).main([a.format(missing=tmp_path / "nowhere", tmp=tmp_path) for a in argv])
    err = capsys.readouterr().err
    assert status == 2, err
    assert err.startswith(f"{prog}: error: ") and "Traceback" not in err, err


def _raises(exc):
    def command(args):
        raise exc

    return command


@pytest.mark.parametrize(
    "exc, status, line",
    [
        (None, 2, "qube-x: error: f.txt: bad value"),  # a user mistake
        (
            OSError(28, "No space left on device", "/out/model.json"),
            1,
            "qube-x: error: /out/model.json: No space left on device",
        ),  # a run-time failure
        (KeyboardInterrupt(), 130, "qube-x: error: interrupted"),
    ],
)
def test_run_command_exit_statuses_follow_the_readme_table(exc, status, line, capsys):
    import argparse

    from qube_koopman.core.command import CliError, run_command

    exc = exc if exc is not None else CliError("f.txt: bad value")
    assert run_command("qube-x", _raises(exc), argparse.Namespace(quiet=True, verbose=0)) == status
    assert capsys.readouterr().err == line + "\n"


def test_a_write_error_is_a_run_time_failure_naming_the_file(tmp_path, capsys, monkeypatch):
    import argparse
    import errno

    from qube_koopman.core.command import run_command, write_json

    def full(self, *args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(Path, "write_text", full)
    path = tmp_path / "report.json"
    assert run_command("qube-x", lambda a: write_json(path, {}), argparse.Namespace(quiet=True, verbose=0)) == 1
    assert capsys.readouterr().err == f"qube-x: error: {path}: cannot write: No space left on device\n"


def test_qube_emulate_names_an_output_it_cannot_write_at_exit(tmp_path):
    # /dev/full opens, then refuses every byte (ENOSPC): a full disk when the counters are written
    import argparse
    import types

    from qube_koopman.sim.cli.emulate import _write_outputs

    emulator = types.SimpleNamespace(
        stats=lambda: {"ticks": 1}, faults=types.SimpleNamespace(as_dict=dict), vanished_at=None, events=[]
    )
    errors = _write_outputs(emulator, argparse.Namespace(stats="/dev/full", record=None))
    assert errors == ["/dev/full: cannot write: No space left on device"]
    good = tmp_path / "stats.json"
    assert _write_outputs(emulator, argparse.Namespace(stats=str(good), record=None)) == []
    assert '"ticks": 1' in good.read_text()


@pytest.mark.parametrize(
    "module, argv, message",
    [
        (
            "qube_koopman.sim.cli.emulate",
            ["--hold-at", "1", "--hold-periods", "-3"],
            "argument --hold-periods: must be a whole number in [1, 100000], got -3",
        ),  # a traceback from Faults before
        (
            "qube_koopman.identify.cli.calibrate",
            ["x.mcap", "--out", "p.toml", "--delay", "-1"],
            "argument --delay: must be a whole number >= 0, got -1",
        ),
        (
            "qube_koopman.identify.cli.calibrate",
            ["x.mcap", "--out", "p.toml", "--max-nfev", "0"],
            "argument --max-nfev: must be a whole number >= 1, got 0",
        ),
    ],
    ids=["emulate --hold-periods", "calibrate --delay", "calibrate --max-nfev"],
)
def test_counts_out_of_range_are_usage_errors_naming_option_and_value(
    module, argv, message, tmp_path, capsys, monkeypatch
):
    import importlib

    monkeypatch.chdir(tmp_path)
    try:
        status = importlib.import_module(module).main(argv)
    except SystemExit as exc:
        status = exc.code
    err = capsys.readouterr().err
    assert status == 2 and message in err and "Traceback" not in err, err


@pytest.mark.parametrize(
    "module",
    [
        "daq.cli.import_csv",
        "daq.cli.export",
        "daq.cli.run",
        "identify.cli.identify",
        "reproduce.cli.reproduce",
        "identify.cli.calibrate",
        "design.cli.design",
        "sim.cli.emulate",
    ],
)
def test_help_is_plain_text_without_restructuredtext_markup(module, capsys):
    import importlib

    main = importlib.import_module(f"qube_koopman.{module}").main
    try:  # some commands return their status, others leave through argparse's SystemExit
        code = main(["--help"])
    except SystemExit as exc:
        code = exc.code
    assert code in (0, None)
    out = capsys.readouterr().out
    assert "usage:" in out and "``" not in out and ":func:" not in out and ":class:" not in out


@pytest.mark.parametrize(
    "module, argv",
    [
        ("daq.cli.import_csv", []),
        ("daq.cli.export", ["x.mcap", "--format", "xlsx", "--out", "d"]),
        ("daq.cli.run", ["--episodes", "-1"]),
        ("identify.cli.identify", ["--delays", "-1", "x.mcap"]),
        ("reproduce.cli.reproduce", ["bogus"]),
        ("identify.cli.calibrate", ["x.mcap", "--out", "p.toml", "--poly"]),
        ("design.cli.design", []),
        ("sim.cli.emulate", ["--drop-rate", "2"]),
    ],
)
def test_usage_errors_are_one_line_in_every_command(module, argv, capsys):
    import importlib

    main = importlib.import_module(f"qube_koopman.{module}").main
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and ": error: " in err[0] and "usage:" not in err[0], err


@pytest.mark.parametrize("prog", ["qube-identify", "qube-design"])
def test_the_earlier_rerun_file_option_names_its_new_name(prog, tmp_path, capsys):
    # --rerun streams to a viewer in qube-run; a recording written to a file is --rerun-save everywhere.
    from qube_koopman.design.cli.design import main as design_main
    from qube_koopman.identify.cli.identify import main as identify_main

    main = {"qube-identify": identify_main, "qube-design": design_main}[prog]
    with pytest.raises(SystemExit) as stopped:
        main([str(tmp_path), "--out", str(tmp_path / "x"), "--rerun", str(tmp_path / "r.rrd")])
    assert stopped.value.code == 2
    assert capsys.readouterr().err == (
        f"{prog}: error: --rerun is now --rerun-save FILE.rrd (a file; qube-run --rerun "
        f"streams to a viewer) (see {prog} --help)\n"
    )


def _every_help() -> dict:
    """Every console script's --help (and qube-reproduce's experiments'), by command line."""
    import importlib
    import tomllib
    from contextlib import redirect_stdout
    from io import StringIO
    from pathlib import Path

    scripts = tomllib.loads((Path(__file__).parents[2] / "pyproject.toml").read_text())["project"]["scripts"]
    out = {}
    for name, target in scripts.items():
        module, func = target.split(":")
        main = getattr(importlib.import_module(module), func)
        for argv in (
            (["--help"], ["qube", "--help"], ["duffing", "--help"]) if name == "qube-reproduce" else (["--help"],)
        ):
            text = StringIO()
            try:
                with redirect_stdout(text):
                    main(argv)
            except SystemExit:
                pass
            out[" ".join([name, *argv])] = text.getvalue()
    return out


def test_no_help_names_a_missing_section_or_a_development_path():
    """A user has neither the developers' folders nor a README section that is not there; and the examples import
    the real dataset into a folder of its own, not qube-run's default ./episodes."""
    import re
    from pathlib import Path

    root = Path(__file__).parents[2]
    headings = {
        line.lstrip("#").strip() for line in (root / "README.md").read_text().splitlines() if line.startswith("#")
    }
    helps = _every_help()
    assert len(helps) >= 10
    for command, text in helps.items():
        assert "usage:" in text, command
        flat = " ".join(text.split())
        for section in re.findall(r"README: ([^),;]+)", flat):
            assert section.strip() in headings, (command, section)
        for page in re.findall(r"docs/[\w-]+\.md", flat):
            assert (root / page).is_file(), (command, page)
        for dev in ("../shared", "shared/datasets", "/work/", "qube_servo_2023"):
            assert dev not in flat, (command, dev)
        for line in re.findall(r"qube-import [^\n]*", flat):
            assert not re.search(r"--out (\./)?episodes\b", line), (command, line)
